"""The bending term (bend triples with kb, kbd) against independent references: a NumPy loop of
the turning angle with finite differences in float64, the internal-force laws, and scene-file errors."""

import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.errors import InputError
from jaxspring.sim.forces import TERMS

jax.config.update("jax_enable_x64", True)

RNG = np.random.default_rng(7)
X = np.cumsum(RNG.normal(0.0, 0.1, size=(6, 3)), axis=0)
TRIPLES = [[0, 1, 2], [1, 2, 3], [2, 3, 4], [3, 4, 5], [5, 1, 3]]  # the last is not along the chain
REST = np.array([0.0, 0.3, 0.1, 0.5, 0.2])
KB = np.array([0.02, 0.01, 0.03, 0.015, 0.005])
KBD = np.array([1e-3, 2e-3, 5e-4, 1e-3, 3e-3])


def _doc(x=X, triples=TRIPLES, rest=REST, kb=KB, kbd=KBD, **extra):
    doc = {
        "dt": 1e-3,
        "physics": {
            "kb": list(np.broadcast_to(kb, (len(triples),))),
            "kbd": list(np.broadcast_to(kbd, (len(triples),))),
            "gravity": [0.0, 0.0, 0.0],
        },
        "particles": {"x": np.asarray(x).tolist(), "mass": 0.05},
        "bending": {"triples": triples, "rest_curvature": np.asarray(rest).tolist()},
    }
    doc.update(extra)
    return doc


def _numpy_energy(x, rest_x, triples, rest, kb):
    """Sum over triples of kb / (2 l) (2 tan(theta / 2) - kappa_0)^2, theta the turning angle, by a loop."""
    total = 0.0
    for (a, b, c), k0, k in zip(triples, rest, kb):
        e1, e2 = x[b] - x[a], x[c] - x[b]
        cos = np.dot(e1, e2) / (np.linalg.norm(e1) * np.linalg.norm(e2))
        theta = math.acos(min(1.0, max(-1.0, cos)))
        length = 0.5 * (np.linalg.norm(rest_x[b] - rest_x[a]) + np.linalg.norm(rest_x[c] - rest_x[b]))
        total += k / (2 * length) * (2 * math.tan(theta / 2) - k0) ** 2
    return total


def _numpy_binormal(x, a, b, c):
    e1, e2 = x[b] - x[a], x[c] - x[b]
    theta = math.acos(np.dot(e1, e2) / (np.linalg.norm(e1) * np.linalg.norm(e2)))
    axis = np.cross(e1, e2)
    return 2 * math.tan(theta / 2) * axis / np.linalg.norm(axis)


def _central(f, x, h=1e-6):
    """Central differences of f (a scalar or array of x) with respect to every coordinate of x."""
    columns = []
    for i in np.ndindex(x.shape):
        up, down = x.copy(), x.copy()
        up[i] += h
        down[i] -= h
        columns.append((np.asarray(f(up)) - np.asarray(f(down))) / (2 * h))
    return np.stack(columns, axis=-1)  # (..., x.size)


def test_elastic_force_is_minus_the_gradient_of_the_turning_angle_energy():
    scene = js.scene_from_dict(_doc())
    x = X + RNG.normal(0.0, 0.02, size=X.shape)  # away from the rest shape
    params = scene.params.replace(kbd=jnp.zeros(len(TRIPLES)))
    force = np.asarray(TERMS["bending"].force(scene.model, params, jnp.asarray(x), jnp.zeros_like(jnp.asarray(x))))
    expected = -_central(lambda y: _numpy_energy(y, X, TRIPLES, REST, KB), x).reshape(x.shape)
    np.testing.assert_allclose(force, expected, rtol=1e-6, atol=1e-9)
    energy = float(TERMS["bending"].energy(scene.model, params, jnp.asarray(x)))
    assert energy == pytest.approx(_numpy_energy(x, X, TRIPLES, REST, KB), rel=1e-12)


def test_damping_force_is_rayleigh_on_the_rate_of_the_bend():
    scene = js.scene_from_dict(_doc())
    x, v = X + RNG.normal(0.0, 0.02, size=X.shape), RNG.normal(0.0, 0.5, size=X.shape)
    params = scene.params.replace(kb=jnp.zeros(len(TRIPLES)))
    force = np.asarray(TERMS["bending"].force(scene.model, params, jnp.asarray(x), jnp.asarray(v)))
    expected = np.zeros_like(x)
    for (a, b, c), kbd in zip(TRIPLES, KBD):
        gradient = _central(lambda y, t=(a, b, c): np.linalg.norm(_numpy_binormal(y, *t)), x)  # (N * 3,)
        rate = gradient @ v.reshape(-1)  # d|kappa|/dt
        length = 0.5 * (np.linalg.norm(X[b] - X[a]) + np.linalg.norm(X[c] - X[b]))
        expected -= (kbd / length * rate * gradient).reshape(x.shape)
    np.testing.assert_allclose(force, expected, rtol=1e-6, atol=1e-9)
    # Rayleigh damping only takes energy out: the power f . v is -sum kbd / l rate^2 <= 0
    assert float(np.sum(force * v)) < 0


def test_bending_is_an_internal_force_without_net_force_or_torque():
    scene = js.scene_from_dict(_doc())
    x, v = X + RNG.normal(0.0, 0.03, size=X.shape), RNG.normal(0.0, 0.5, size=X.shape)
    force = np.asarray(TERMS["bending"].force(scene.model, scene.params, jnp.asarray(x), jnp.asarray(v)))
    scale = np.abs(force).max()
    np.testing.assert_allclose(force.sum(axis=0), 0.0, atol=1e-12 * scale)
    torque = np.cross(x, force).sum(axis=0)
    np.testing.assert_allclose(torque, 0.0, atol=1e-11 * scale)


def test_the_default_rest_curvature_is_that_of_the_rest_shape_and_a_rest_shape_feels_no_force():
    doc = _doc()
    del doc["bending"]["rest_curvature"]
    scene = js.scene_from_dict(doc)
    expected = [np.linalg.norm(_numpy_binormal(X, *t)) for t in TRIPLES]
    np.testing.assert_allclose(np.asarray(scene.model.rest_curvature), expected, rtol=1e-10)
    force = TERMS["bending"].force(scene.model, scene.params, jnp.asarray(X), jnp.zeros((6, 3)))
    np.testing.assert_allclose(np.asarray(force), 0.0, atol=1e-12)


@pytest.mark.slow
def test_a_straight_chain_has_finite_gradients_and_a_bent_one_swings_back_conserving_energy():
    """At kappa = 0 the norm's gradient is the trap; without damping, energy is kept to O(dt)."""
    x = np.stack([np.linspace(0.0, 0.4, 5), np.zeros(5), np.zeros(5)], axis=1)
    doc = _doc(x=x, triples=[[0, 1, 2], [1, 2, 3], [2, 3, 4]], rest=0.0, kb=0.02, kbd=0.0)
    doc["physics"].update(ks=500.0, kd=0.0)
    doc["particles"]["v"] = [[0, 0, 0], [0, 0, 0], [0, 0.2, 0], [0, 0, 0], [0, -0.1, 0.05]]
    doc["springs"] = {"pairs": [[0, 1], [1, 2], [2, 3], [3, 4]]}
    scene = js.scene_from_dict(doc)
    model, params = scene.model, scene.params

    @jax.jit
    def final_bend(kb):
        trajectory = js.rollout(model, params.replace(kb=kb), scene.state, 100, save_every=100)
        return jnp.sum(trajectory.x[-1, :, 1] ** 2)

    gradient = float(jax.grad(final_bend)(jnp.asarray(0.02)))
    step = 1e-6
    expected = (float(final_bend(jnp.asarray(0.02 + step))) - float(final_bend(jnp.asarray(0.02 - step)))) / (2 * step)
    assert np.isfinite(gradient) and gradient == pytest.approx(expected, rel=1e-5)

    trajectory = jax.jit(lambda: js.rollout(model, params, scene.state, 1500, save_every=10))()
    energies = jax.vmap(lambda x, v: model.energy(params, js.State(x=x, v=v)))(trajectory.x, trajectory.v)
    energies = np.asarray(energies)
    assert np.abs(np.asarray(trajectory.x)[-1, :, 1:]).max() > 1e-3  # it moved
    assert np.abs(energies - energies[0]).max() < 0.02 * energies[0]


@pytest.mark.parametrize(
    "change, field",
    [
        (lambda d: d["bending"].update(triples=[[0, 1, 1]], rest_curvature=0.0), "bending.triples"),
        (lambda d: d["bending"].update(triples=[[0, 1, 9]], rest_curvature=0.0), "bending.triples"),
        (lambda d: d["bending"].update(rest_curvature=[0.1, 0.2]), "bending.rest_curvature"),
        (lambda d: d["bending"].update(rest_curvature=-1.0), "bending.rest_curvature"),
        (lambda d: d.pop("bending"), "physics.kb"),
        (lambda d: d["physics"].pop("kbd"), "physics.kbd"),
        (lambda d: d["physics"].update(kb=[0.1, 0.2]), "kb"),
    ],
)
def test_bad_bending_tables_are_one_line_errors_naming_the_field(change, field):
    doc = _doc()
    change(doc)
    with pytest.raises(InputError) as error:
        js.scene_from_dict(doc)
    assert error.value.field.endswith(field), (error.value.field, str(error.value))
    assert "\n" not in str(error.value)


@pytest.mark.slow
def test_the_stability_estimate_of_a_straight_chain_sees_the_bending_stiffness():
    """A straight chain's zig-zag mode: kappa_i = (u_i-1 - 2 u_i + u_i+1) / l, K = kb / l^3 D^T D with
    |D^T D| <= 16, so omega^2 -> 16 kb / (l^3 m); a long chain comes close to the bound from below."""
    n, length, mass, kb = 41, 0.025, 0.02, 1.0
    x = np.stack([np.arange(n) * length, np.zeros(n), np.zeros(n)], axis=1)
    doc = _doc(x=x, triples=[[i, i + 1, i + 2] for i in range(n - 2)], rest=0.0, kb=kb, kbd=0.0)
    doc["particles"]["mass"] = mass
    doc["physics"].update(ks=1e-3, kd=0.0)  # stretching far softer than bending
    doc["springs"] = {"pairs": [[i, i + 1] for i in range(n - 1)]}
    scene = js.scene_from_dict(doc)
    estimate = js.sim.estimate_stability(scene.model, scene.params, scene.state, iterations=400)
    bound = math.sqrt(16 * kb / (length**3 * mass))
    assert 0.97 * bound < estimate.omega_max <= 1.0001 * bound


def _native_or_skip():
    from jaxspring.steppers import native_kernels

    if not native_kernels.available():
        if os.environ.get("CI"):
            raise AssertionError("the native kernel was not built by the install")
        pytest.skip("native kernel not built here")


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_the_native_bending_kernel_matches_finite_differences_and_the_jax_force(dtype):
    """The C++ kernel (the default stepper of a bending model on CPU): its force equals the JAX
    term's, and its reverse pass (dual numbers through the curvature's Hessians) the JAX
    term's VJP and central differences of its own force, batched with vmap too."""
    _native_or_skip()
    scene = js.scene_from_dict(_doc())
    native, plain = scene.model, scene.model.replace(backend="jax")
    assert native.stepper.name == "native_springs" and plain.stepper.name == "generic"
    x = jnp.asarray(X * 1.3 + RNG.normal(0.0, 0.02, X.shape), dtype)
    v = jnp.asarray(RNG.normal(0.0, 0.5, X.shape), dtype)
    ct = jnp.asarray(RNG.normal(0.0, 1.0, X.shape), dtype)
    params = scene.params

    def force(model):
        return lambda x, v, kb, kbd: model.force(params.replace(kb=kb, kbd=kbd), x, v)

    tol = 1e-12 if dtype == jnp.float64 else 2e-5
    args = (x, v, jnp.asarray(KB, dtype), jnp.asarray(KBD, dtype))
    reference = np.asarray(force(plain)(*args))
    assert np.abs(np.asarray(force(native)(*args)) - reference).max() < tol * np.abs(reference).max()
    mine = jax.vjp(force(native), *args)[1](ct)
    theirs = jax.vjp(force(plain), *args)[1](ct)
    for a, b in zip(mine, theirs):
        assert np.abs(np.asarray(a) - np.asarray(b)).max() < 10 * tol * np.abs(np.asarray(b)).max()
    if dtype == jnp.float64:  # the kernel's VJP against its own force's central differences
        for i, arg in enumerate(args):

            def along(value, i=i):
                moved = list(args)
                moved[i] = jnp.asarray(value)
                return float(jnp.sum(ct * force(native)(*moved)))

            expected = _central(along, np.asarray(arg), h=1e-7)
            assert np.asarray(mine[i]).ravel() == pytest.approx(expected, rel=1e-5, abs=1e-6 * np.abs(expected).max())
    # a batch of states (vmap) and one scalar kb, kbd shared by every triple
    xs = x[None] + jnp.asarray(RNG.normal(0.0, 0.01, (3,) + X.shape), dtype)
    vs = v[None] * jnp.asarray([1.0, -0.5, 2.0], dtype)[:, None, None]

    def batch(model):
        return lambda xs, kb, kbd: jnp.sum(ct * jax.vmap(lambda x, v: force(model)(x, v, kb, kbd))(xs, vs))

    scalars = (xs, jnp.asarray(0.02, dtype), jnp.asarray(1e-3, dtype))
    mine, theirs = jax.grad(batch(native), (0, 1, 2))(*scalars), jax.grad(batch(plain), (0, 1, 2))(*scalars)
    for a, b in zip(mine, theirs):
        assert np.abs(np.asarray(a) - np.asarray(b)).max() < 10 * tol * np.abs(np.asarray(b)).max()
