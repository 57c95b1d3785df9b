"""Physics against independent references: a loop-based NumPy simulator, hand calculations, conservation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy_reference import reference_for_scene

import jaxspring as js

SCENES = ["mass_spring", "chain", "jelly", "cloth"]


def relative_error(a, b):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b))))


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENES)
def test_scene_matches_loop_reference_float64(scenes, name):
    scene = scenes[name]
    steps, every = 500, 50
    traj = js.rollout(scene.model, scene.params, scene.state, steps=steps, save_every=every)
    x_ref, v_ref = reference_for_scene(scene, steps, every)
    assert traj.x.dtype == jnp.float64
    assert relative_error(traj.x, x_ref) < 1e-9
    assert relative_error(traj.v, v_ref) < 1e-9
    # the scene really moved, so the comparison is not trivially between two rest states
    assert np.max(np.abs(x_ref[-1] - x_ref[0])) > 1e-3


@pytest.mark.slow
def test_jelly_reference_covers_ground_contact(scenes):
    """Compare through the impact: the ground term must be exercised."""
    scene = scenes["jelly"]
    traj = js.rollout(scene.model, scene.params, scene.state, steps=900, save_every=30)
    x_ref, v_ref = reference_for_scene(scene, 900, 30)
    assert np.min(x_ref[:, :, 1]) < -0.01, "the window must include contact"
    assert relative_error(traj.x, x_ref) < 1e-9
    assert relative_error(traj.v, v_ref) < 1e-9


@pytest.mark.parametrize("name", SCENES)
def test_float32_stays_close_to_float64(scenes, name):
    scene = scenes[name]
    to32 = lambda tree: jax.tree_util.tree_map(  # noqa: E731
        lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree
    )
    x64 = js.rollout(scene.model, scene.params, scene.state, steps=200, save_every=20).x
    x32 = js.rollout(to32(scene.model), to32(scene.params), to32(scene.state), steps=200, save_every=20).x
    assert x32.dtype == jnp.float32
    assert relative_error(x32, x64) < 1e-4


def two_particles(x_b, v_b, ks=10.0, kd=2.0, rest=4.0):
    model = js.sim.make_model([[0, 1]], [1.0, 1.0], rest_length=[rest], gravity=False)
    params = js.Params(ks=ks, kd=kd)
    x = jnp.array([[0.0, 0.0, 0.0], x_b])
    v = jnp.array([[0.0, 0.0, 0.0], v_b])
    return model, params, x, v


def test_spring_force_hand_calculation():
    # d = (3, 4, 0): L = 5, u = (0.6, 0.8, 0); extension 1; closing speed (1,0,0).u = 0.6
    # magnitude = 10 * 1 + 2 * 0.6 = 11.2; force on a = 11.2 u = (6.72, 8.96, 0)
    model, params, x, v = two_particles([3.0, 4.0, 0.0], [1.0, 0.0, 0.0])
    force = np.asarray(model.force(params, x, v))
    np.testing.assert_allclose(force[0], [6.72, 8.96, 0.0], rtol=1e-14)
    np.testing.assert_allclose(force[1], [-6.72, -8.96, 0.0], rtol=1e-14)


def test_drag_gravity_ground_hand_calculation():
    model = js.sim.make_model(np.zeros((0, 2)), [2.0], rest_length=[], drag=True, ground=True)
    params = js.Params(cd=0.1, gravity=[0.0, -9.81, 0.0], kg=1000.0, kgd=2.0, ground_height=0.0)
    x = jnp.array([[0.0, -0.1, 0.0]])
    v = jnp.array([[3.0, -4.0, 0.0]])
    # drag: -0.1 * 5 * (3, -4, 0) = (-1.5, 2, 0); gravity: 2 * (0, -9.81, 0)
    # ground: 1000 * 0.1 - 2 * (-4) = 108 upward
    expected = [-1.5, 2.0 - 19.62 + 108.0, 0.0]
    np.testing.assert_allclose(np.asarray(model.force(params, x, v))[0], expected, rtol=1e-14)
    assert model.terms == ("drag", "gravity", "ground")


def test_zero_length_spring_finite_force_and_gradients():
    for rest in (0.0, 1.0):
        model, params, x, v = two_particles([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], rest=rest)
        force = model.force(params, x, v)
        assert np.all(np.isfinite(np.asarray(force)))

        def loss(p, x0, model=model, v=v):
            state = js.State(x=x0, v=v)
            traj = js.rollout(model, p, state, steps=20, save_every=20)
            return jnp.sum(traj.x[-1] ** 2) + jnp.sum(traj.v[-1] ** 2)

        grads = jax.grad(loss, argnums=(0, 1))(params, x)
        for leaf in jax.tree_util.tree_leaves(grads):
            assert np.all(np.isfinite(np.asarray(leaf)))


def test_safe_norm_gradient_at_zero():
    assert np.all(np.asarray(jax.grad(lambda d: js.sim.safe_norm(d))(jnp.zeros(3))) == 0.0)
    assert np.all(np.isfinite(np.asarray(jax.grad(lambda v: jnp.sum(js.sim.safe_norm(v) * v))(jnp.zeros(3)))))


def test_undamped_spring_energy_bounded_without_drift():
    # mass_spring geometry, kd = 0, no drag; float64; 1e5 steps of 1e-3 s
    model = js.sim.make_model([[0, 1]], [1.0, 1.0], positions=[[0, 0, 0], [0, -1, 0]], pinned=[0], dt=1e-3)
    params = js.Params(ks=2.0, kd=0.0, gravity=[0.0, -9.81, 0.0])
    state = js.State(x=jnp.array([[0.0, 0, 0], [0, -1, 0]]), v=jnp.array([[0.0, 0, 0], [1.0, 0, 0]]))
    traj = js.rollout(model, params, state, steps=100_000, save_every=10)
    e = np.asarray(js.sim.energy(model, params, traj))
    # the potential's zero is arbitrary: measure relative to the peak kinetic energy
    scale = np.max(0.5 * np.sum(np.asarray(traj.v) ** 2, axis=(1, 2)))
    assert np.max(np.abs(e - e[0])) / scale < 1e-3
    # no secular drift: a linear trend over the whole run explains < 10% of the error band
    # (a drifting integrator, e.g. explicit Euler, has a trend as large as its error)
    error = (e - e[0]) / scale
    trend = np.polyfit(np.asarray(traj.t), error, 1)[0] * float(traj.t[-1])
    assert abs(trend) < 0.1 * np.max(np.abs(error))


def jaxpr_scopes(fn, *args):
    names = set()

    def visit(jaxpr):
        for eqn in jaxpr.eqns:
            names.add(str(eqn.source_info.name_stack))
            for value in eqn.params.values():
                for sub in value if isinstance(value, (list, tuple)) else (value,):
                    if hasattr(sub, "jaxpr") and hasattr(sub.jaxpr, "eqns"):
                        visit(sub.jaxpr)
                    elif hasattr(sub, "eqns"):
                        visit(sub)

    visit(jax.make_jaxpr(fn)(*args).jaxpr)
    return " ".join(names)


@pytest.mark.parametrize(
    "name, present, absent",
    [
        ("mass_spring", {"springs", "gravity"}, {"drag", "ground"}),
        ("chain", {"springs", "drag", "gravity"}, {"ground"}),
        ("cloth", {"springs", "drag", "gravity"}, {"ground"}),
        ("jelly", {"springs", "drag", "gravity", "ground"}, set()),
    ],
)
def test_compiled_step_holds_only_the_scene_terms(scenes, name, present, absent):
    # the pure-JAX step (the native lattice kernel is specialised on the same terms by its flags)
    scene = scenes[name].with_backend("jax")
    scopes = jaxpr_scopes(lambda p, s: js.rollout(scene.model, p, s, steps=4, save_every=2), scene.params, scene.state)
    for term in present:
        assert term in scopes
    for term in absent:
        assert term not in scopes
