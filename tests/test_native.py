"""The native C++ spring kernel (jax.ffi) against the pure-JAX path: values, gradients, batches, fallback."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.bench.speed import cloth_of_size
from jaxspring.steppers import native_kernels as _native

if not _native.available():
    if os.environ.get("CI"):
        raise AssertionError("the native kernel was not built by the install")  # CI must exercise it
    pytest.skip("native kernel not built here", allow_module_level=True)

SCENES = ["mass_spring", "chain", "jelly", "cloth"]


@pytest.fixture(scope="module")
def scenes():
    """The seed scenes on the pure-JAX backend: the reference every native result is held to."""
    return {name: js.load_scene(name).with_backend("jax") for name in js.builtin_scenes()}


def in_float32(tree):
    """Every floating-point leaf of a model, params or state in float32 (the kernel's 16-lane path)."""
    cast = lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a  # noqa: E731
    return jax.tree_util.tree_map(cast, tree)


def random_topology(seed=0, count=30, springs=80):
    rng = np.random.default_rng(seed)
    pairs = set()
    while len(pairs) < springs:
        a, b = rng.integers(0, count, 2)
        if a != b:
            pairs.add((min(a, b), max(a, b)))
    positions = rng.normal(size=(count, 3))
    pairs = np.array(sorted(pairs))
    rest = rng.uniform(0.0, 2.0, len(pairs))
    rest[:5] = 0.0  # zero-length springs too
    model = js.sim.make_model(pairs, rng.uniform(0.5, 2.0, count), rest_length=rest, pinned=[0, 1], drag=True, dt=1e-3)
    params = js.Params(ks=jnp.asarray(rng.uniform(50, 150, len(pairs))), kd=0.3, cd=0.02, gravity=[0.0, -9.81, 0.0])
    state = js.State(x=jnp.asarray(positions), v=jnp.asarray(rng.normal(size=(count, 3)) * 0.1).at[:2].set(0.0))
    return model, params, state


def cases(scenes):
    for name in SCENES:
        s = scenes[name]
        yield name, s.model, s.params, s.state
    yield ("random",) + random_topology()


def generic(model):
    """The pure-JAX reference of a 3-D lattice (the jelly) on the generic (scatter) stepper, not
    the grid one: the grid's numbers are the generic one's (tests/test_fast_paths.py holds them to
    1e-12), but XLA compiles the jelly's grid rollout gradient for minutes (the generic: ~15 s).
    The 2-D cloth stays on the grid: the kernel sums in its order (1e-19 apart), and its gradient
    to 1e-11 needs that (against the generic path: 4.6e-11, measured)."""
    return model.replace(lattice=None) if model.lattice is not None and len(model.lattice[0]) == 3 else model


def relative(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


@jax.jit
def force_and_vjp(model, params, x, v, ct):
    """The force at (x, v) and the VJP of ct through it wrt x, v and params, as one compiled
    program (op by op, the pure-JAX force alone compiles for seconds)."""
    pull = jax.vjp(lambda x, v, p: model.force(p, x, v), x, v, params)[1]
    return model.force(params, x, v), pull(ct)


@pytest.mark.slow
def test_forces_and_their_vjp_match(scenes):
    for name, model, params, state in cases(scenes):
        native = model.replace(backend="native", lattice=None)  # the spring kernel of any topology
        key = jax.random.PRNGKey(1)
        x = state.x + 0.05 * jax.random.normal(key, state.x.shape)
        v = jax.random.normal(jax.random.PRNGKey(2), state.x.shape)
        plain = model.replace(lattice=None)
        ct = jax.random.normal(jax.random.PRNGKey(3), x.shape)
        f_native, vjp_native = force_and_vjp(native, params, x, v, ct)
        f_plain, vjp_plain = force_and_vjp(plain, params, x, v, ct)
        assert relative(f_native, f_plain) < 1e-12, name
        for a, b in zip(vjp_native, vjp_plain):
            for la, lb in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
                assert relative(la, lb) < 1e-12, name


def fit_loss(p, s, m, target):
    return jnp.mean((js.rollout(m, p, s, 60, 20).x - target) ** 2)


fit_loss_grad = jax.jit(jax.grad(fit_loss, argnums=(0, 1)))  # one compiled program a model


@pytest.mark.slow
def test_rollouts_and_gradients_match(scenes):
    for name, model, params, state in cases(scenes):
        native, model = model.replace(backend="native"), generic(model)
        target = js.rollout(model, params.replace(ks=params.ks * 1.2), state, 60, 20).x
        assert relative(js.rollout(native, params, state, 60, 20).x, js.rollout(model, params, state, 60, 20).x) < 1e-12
        g_native = fit_loss_grad(params, state, native, target)
        g_plain = fit_loss_grad(params, state, model, target)
        leaves = list(zip(jax.tree_util.tree_leaves(g_native), jax.tree_util.tree_leaves(g_plain)))
        scale = max(float(np.max(np.abs(np.asarray(b)))) for _, b in leaves)
        for a, b in leaves:  # to 1e-11 of the largest gradient component (max-norm; round-off of reordered sums)
            assert float(np.max(np.abs(np.asarray(a) - np.asarray(b)))) <= 1e-11 * scale, name


@pytest.mark.slow
def test_vmap_and_forward_mode_fallbacks(scenes):
    scene = scenes["chain"].with_backend("native")
    assert scene.model.backend == "native"
    ks = jnp.array([500.0, 1000.0, 2000.0])
    run = lambda k: js.rollout(scene.model, scene.params.replace(ks=k), scene.state, 40, 20).x  # noqa: E731
    batched = jax.vmap(run)(ks)
    for i in range(3):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(run(ks[i])), rtol=1e-12, atol=1e-12)
    # jaxspring's own forward-mode users switch to the pure-JAX force
    assert js.sim.estimate_stability(scene.model, scene.params, scene.state).omega_max > 60
    implicit = scene.with_integrator("backward_euler")
    x = js.rollout(implicit.model, implicit.params, implicit.state, 20, 20).x
    y = js.rollout(implicit.model.replace(backend="jax"), implicit.params, implicit.state, 20, 20).x
    assert relative(x, y) < 1e-12


@pytest.mark.slow
def test_fit_with_the_native_backend(scenes):
    chain = scenes["chain"]
    obs = js.synthetic_observations(chain, {"ks": 1000.0, "kd": 5.0}, 200, 20)
    init = {"ks": 600.0, "kd": 9.0}
    native = js.fit(chain.with_backend("native"), obs, ["ks", "kd"], init, iterations=30)
    plain = js.fit(chain, obs, ["ks", "kd"], init, iterations=30)
    for n in ("ks", "kd"):
        assert abs(float(native.final[n]) - float(plain.final[n])) <= 1e-6 * float(plain.final[n])
    assert max(native.relative_errors().values()) < 1e-6


def test_missing_kernel_falls_back_with_one_notice(monkeypatch, capsys):
    monkeypatch.setattr(_native, "library_path", lambda: None)
    monkeypatch.setattr(_native, "_NOTICED", [])
    _native.available.cache_clear()
    try:
        scene = js.load_scene("chain")
        assert scene.with_backend("native").model.backend == "jax"
        assert scene.with_backend("native").model.backend == "jax"
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "native kernel is not built" in err[0]
    finally:
        _native.available.cache_clear()  # found again once the patch is undone


# --- the lattice kernel: whole semi-implicit Euler steps of lattice scenes ---------------


def lattice_case(scene, seed=0, drop=0.0):
    """A lattice scene with per-spring ks, per-particle cd (and kg), moving, optionally lowered."""
    rng = np.random.default_rng(seed)
    model, params, state = scene.model, scene.params, scene.state
    changes = {"ks": params.ks * jnp.asarray(rng.uniform(0.7, 1.3, model.spring_count))}
    changes["cd"] = params.cd * jnp.asarray(rng.uniform(0.5, 1.5, model.particle_count))
    if params.kg is not None:
        changes["kg"] = params.kg * jnp.asarray(rng.uniform(0.8, 1.2, model.particle_count))
    v = state.v + 0.3 * jnp.asarray(rng.normal(size=state.v.shape)) * (~model.pinned)[:, None]
    state = js.State(x=state.x - jnp.array([0.0, drop, 0.0]), v=v)
    return model, params.replace(**changes), state


def assert_gradients_match(loss, native, plain, args, name):
    """Gradients of loss(model, *args) wrt args and the model's float leaves, to 1e-11 of the largest."""
    grad = jax.jit(jax.grad(loss, argnums=tuple(range(len(args) + 1)), allow_int=True))  # one program a model
    g_native = grad(native, *args)
    g_plain = grad(plain, *args)
    pairs = []
    for a, b in zip(jax.tree_util.tree_leaves(g_native), jax.tree_util.tree_leaves(g_plain)):
        if np.asarray(b).dtype.kind == "f":
            pairs.append((np.asarray(a), np.asarray(b)))
    scale = max(float(np.max(np.abs(b))) for _, b in pairs)
    assert scale > 0
    for a, b in pairs:
        assert float(np.max(np.abs(a - b))) <= 1e-11 * scale, name


@pytest.mark.slow
def test_lattice_kernel_matches_jax_through_ground_contact(scenes):
    """Jelly lowered onto the ground (contact from the first steps) and the pinned cloth:
    trajectories to 1e-12, gradients wrt every parameter, the initial state and the
    model's masses and rest lengths to 1e-11 (float64)."""
    for name, drop, steps in (("jelly", 1.97, 150), ("cloth", 0.0, 60)):
        model, params, state = lattice_case(scenes[name], drop=drop)
        native, model = model.replace(backend="native"), generic(model)
        assert native.stepper.name == "native_lattice"
        a = js.rollout(native, params, state, steps, steps // 5)
        b = js.rollout(model, params, state, steps, steps // 5)
        assert relative(a.x, b.x) < 1e-12 and relative(a.v, b.v) < 1e-12, name
        if name == "jelly":  # the ground is in play
            assert float(jnp.min(a.x[..., 1])) < 0.0

        def loss(m, p, s, steps=steps):
            t = js.rollout(m, p, s, steps, steps // 5)
            return jnp.sum(jnp.sin(3.0 * t.x)) + jnp.sum(t.v[-1] ** 2)

        assert_gradients_match(loss, native, model, (params, state), name)


@pytest.mark.slow
def test_lattice_kernel_batches_segments_and_checkpoints(scenes):
    model, params, state = lattice_case(scenes["chain"], seed=1)
    native = model.replace(backend="native")
    ks = params.ks[None] * jnp.array([0.8, 1.0, 1.3])[:, None]

    def final(m, k, x0):
        return js.rollout(m, params.replace(ks=k), state.replace(x=x0), 37, 37).x[-1]

    x0 = state.x[None] + 0.01 * jnp.arange(3.0)[:, None, None]
    batched = jax.vmap(lambda k, x: final(native, k, x))(ks, x0)
    for i in range(3):
        assert relative(batched[i], final(model, ks[i], x0[i])) < 1e-12
    # 37 steps: segments of 7 with a shorter last one, in every backward variant
    loss = lambda k, m: jnp.sum(final(m, k, state.x) ** 2)  # noqa: E731
    g_batched = jax.vmap(jax.grad(loss), in_axes=(0, None))(ks, native)
    for i in range(3):
        assert relative(g_batched[i], jax.grad(loss)(ks[i], model)) < 1e-11
    for checkpoint in ("sqrt", 5):
        g = jax.grad(lambda k, c=checkpoint: jnp.sum(js.rollout(native, params.replace(ks=k), state, 37, 1, c).x ** 2))
        h = jax.grad(lambda k: jnp.sum(js.rollout(model, params.replace(ks=k), state, 37, 1).x ** 2))
        assert relative(g(params.ks), h(params.ks)) < 1e-11


@pytest.mark.slow
def test_lattice_backward_replays_alone_when_its_second_thread_is_late(scenes, monkeypatch):
    """On two threads, the backward call's first thread replays what the second has not
    begun, and all that is left once the second is late (here forced by a test hook, from
    its first replay): into buffers of its own, with the same gradients. One call of 80
    steps: 9 segments."""
    model, params, state = lattice_case(scenes["cloth"], seed=3)
    native = model.replace(backend="native")

    def loss(m, p, s):
        return jnp.sum(js.rollout(m, p, s, 80, 80).x[-1] ** 2)

    monkeypatch.setattr(_native, "_test_hooks", _native._TEST_IMPATIENT)
    jax.clear_caches()  # the hook is an attribute of the traced call
    try:
        assert_gradients_match(loss, native, model, (params, state), "impatient")
    finally:
        monkeypatch.undo()
        jax.clear_caches()


OUT_OF_MEMORY = """
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import jaxspring as js
from jaxspring.steppers import native_kernels
scene = js.load_scene("cloth")
native = scene.model.replace(backend="native")
def loss(x):
    return jnp.sum(js.rollout(native, scene.params, scene.state.replace(x=x), 30, 30).x ** 2)
native_kernels._test_hooks = native_kernels._TEST_OUT_OF_MEMORY
try:
    jax.grad(loss)(scene.state.x)
except Exception as error:
    print("raised:", type(error).__name__, str(error).splitlines()[0][:200])
else:
    print("no error")
native_kernels._test_hooks = 0
jax.clear_caches()
print("after:", " ".join(repr(float(g)) for g in np.ravel(jax.grad(loss)(scene.state.x))))
"""


@pytest.mark.slow
def test_lattice_backward_out_of_memory_raises_and_the_process_lives(scenes):
    """The backward call's buffers cannot be allocated (forced by a test hook, in a process
    of its own): the call raises a Python exception saying so instead of ending the
    process, which then computes the same gradient as the pure-JAX path."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", OUT_OF_MEMORY], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    lines = run.stdout.splitlines()
    assert lines[0].startswith("raised:") and "out of memory" in lines[0], run.stdout
    scene = scenes["cloth"]
    expected = jax.grad(
        lambda x: jnp.sum(js.rollout(scene.model, scene.params, scene.state.replace(x=x), 30, 30).x ** 2)
    )(scene.state.x)
    after = np.array([float(g) for g in lines[1].split(":", 1)[1].split()]).reshape(expected.shape)
    assert relative(after, expected) < 1e-11


def test_lattice_batches_of_members_side_by_side(scenes):
    """Batched forward rollouts of the cloth (several particle blocks) run members side by
    side; what the members share (rest lengths and uniform ks, kd; particle parameters) is
    kept once. Every combination equals the pure-JAX rollouts member by member (float64)."""
    scene = scenes["cloth"]
    model, params, state = scene.model, scene.params, scene.state
    native = model.replace(backend="native")
    assert native.stepper.name == "native_lattice" and len(native.lattice[0]) == 2
    steps = 25
    rng = np.random.default_rng(3)
    per_spring = params.ks * jnp.asarray(rng.uniform(0.7, 1.3, (3, model.spring_count)))
    batches = {  # what varies: ks as one value a member (all shared), per spring, cd (particles differ)
        "ks": dict(ks=params.ks * jnp.array([0.8, 1.0, 1.25])),
        "ks per spring": dict(ks=per_spring),
        "cd": dict(cd=params.cd * jnp.array([0.0, 1.0, 3.0])),
    }
    x0 = state.x[None] + 0.01 * jnp.asarray(rng.normal(size=(3,) + state.x.shape)) * (~model.pinned)[None, :, None]
    for name, changes in batches.items():

        def final(m, x, **values):
            return js.rollout(m, params.replace(**values), state.replace(x=x), steps, steps).x[-1]

        batched = jax.vmap(lambda x, values: final(native, x, **values))(x0, changes)
        for i in range(3):
            member = {key: value[i] for key, value in changes.items()}
            assert relative(batched[i], final(model, x0[i], **member)) < 1e-12, name


@pytest.mark.slow
def test_lattice_kernel_threads_on_a_large_lattice():
    """A 100 x 100 cloth (39k springs) splits over threads: same numbers, float64 and float32."""
    scene = cloth_of_size((100, 100)).with_backend("jax")
    model, params, state = scene.model, scene.params, scene.state
    native = model.replace(backend="native")
    state = state.replace(v=0.1 * jnp.asarray(np.random.default_rng(2).normal(size=state.v.shape)))
    assert relative(js.rollout(native, params, state, 6, 3).x, js.rollout(model, params, state, 6, 3).x) < 1e-12

    def loss(m, p, s):
        return jnp.sum(js.rollout(m, p, s, 6, 6).x[-1] ** 2)

    assert_gradients_match(loss, native, model, (params, state), "100x100")
    by_params = jax.grad(lambda p, m: loss(m, p, state))  # the lean spring pass on two threads
    leaves = [jax.tree_util.tree_leaves(by_params(params, m)) for m in (native, model)]
    for a, b in zip(*leaves):
        assert relative(a, b) < 1e-11
    a = js.rollout(in_float32(native), in_float32(params), in_float32(state), 20, 20).x
    b = js.rollout(model, params, state, 20, 20).x
    assert a.dtype == jnp.float32 and float(jnp.max(jnp.abs(a - b))) < 1e-4


@pytest.mark.slow
def test_lattice_gradients_of_only_what_is_asked_for(scenes):
    """The backward call computes only the cotangents asked for: with scalar ks and kd and
    no model gradient it sums their cotangents per lane (the lean spring pass); a scalar
    ks beside a per-spring kd, and masses without rest lengths, take the other branches.
    Every one against the pure-JAX gradient (float64), batched too; the lean pass also on
    a 3 x 3 cloth (family runs shorter than a vector) and in float32."""
    steps = 30

    def problem(scene):
        model, params, state = scene.model, scene.params, scene.state
        state = state.replace(v=0.2 * jnp.asarray(np.random.default_rng(4).normal(size=state.v.shape)))
        assert jnp.ndim(params.ks) == 0 and jnp.ndim(params.kd) == 0

        def loss(m, p, s=state):
            t = js.rollout(m, p, s, steps, steps // 3)
            return jnp.sum(jnp.sin(3.0 * t.x)) + jnp.sum(t.v[-1] ** 2)

        return model, params, state, loss

    cloth = problem(scenes["cloth"])
    by_params = {}  # one compiled gradient wrt the params per problem, for either model and every params shape
    for model, params, _, loss in (cloth, problem(cloth_of_size((3, 3)).with_backend("jax"))):
        native = model.replace(backend="native")
        grad = by_params[model.particle_count] = jax.jit(jax.grad(loss, argnums=1))
        kd_per_spring = params.kd * jnp.asarray(np.random.default_rng(5).uniform(0.5, 1.5, model.spring_count))
        for name, p in (("scalar ks, kd", params), ("scalar ks, kd per spring", params.replace(kd=kd_per_spring))):
            a, b = grad(native, p), grad(model, p)
            for key in ("ks", "kd", "cd"):
                where = (model.particle_count, name, key)
                assert jnp.shape(getattr(a, key)) == jnp.shape(getattr(b, key)), where
                assert relative(getattr(a, key), getattr(b, key)) < 1e-11, where
    # float32 (16 lanes a vector): near the float64 gradient (measured 3e-4, 2e-5, 2e-6)
    model, params, state, loss = cloth
    native = model.replace(backend="native")
    grad = by_params[model.particle_count]
    exact = grad(model, params)  # the float64 pure-JAX gradient (compiled above)
    approx = jax.jit(jax.grad(lambda p: loss(in_float32(native), in_float32(p), in_float32(state))))(params)
    for key, tolerance in (("ks", 2e-3), ("kd", 2e-4), ("cd", 2e-4)):
        assert relative(getattr(approx, key), getattr(exact, key)) < tolerance, key
    # the masses' cotangent without the rest lengths'
    by_mass = jax.jit(jax.grad(lambda mass, m: loss(m.replace(mass=mass), params)))
    assert relative(by_mass(model.mass, native), by_mass(model.mass, model)) < 1e-11
    # a batch of scalar ks: one lean backward per member, each against the pure-JAX gradient wrt ks there
    ks = params.ks * jnp.array([0.8, 1.0, 1.3])
    by_ks = lambda k, m: loss(m, params.replace(ks=k))  # noqa: E731
    batched = jax.jit(jax.vmap(jax.grad(by_ks), in_axes=(0, None)))(ks, native)
    for i in range(3):
        assert relative(batched[i], grad(model, params.replace(ks=ks[i])).ks) < 1e-11
