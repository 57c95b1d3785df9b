"""Driven particles: moved along given paths, checked against a NumPy loop, Galilean
invariance for every integrator, finite differences, vmap over drives, and bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy_reference import reference_rollout

import jaxspring as js
from jaxspring.sim.driven import make_drive

ROPE = {
    "name": "driven rope",
    "dt": 0.002,
    "physics": {"ks": {"stretch": 300.0, "bend": 4.0}, "kd": {"stretch": 0.5, "bend": 0.05}, "cd": 0.03},
    "particles": {"x": [[0.2 * i, 0.0, 0.0] for i in range(5)], "mass": 0.05, "drag": True},
    "springs": [
        {"name": "stretch", "pairs": [[i, i + 1] for i in range(4)]},
        {"name": "bend", "pairs": [[i, i + 2] for i in range(3)]},
    ],
}


def path(t):
    """The driven end's path: a circle in the x-y plane, 0.1 m radius, 2 rad/s."""
    return np.stack([0.1 * np.sin(2.0 * t), 0.1 - 0.1 * np.cos(2.0 * t), 0.05 * t], axis=-1)


@pytest.fixture(scope="module")
def rope():
    return js.scene_from_dict(ROPE)


def knots(times):
    """A drive of particle 0 along `path` with knots at `times` (linear in between)."""
    return js.sim.Drive(particles=(0,), t=jnp.asarray(times), x=jnp.asarray(path(np.asarray(times)))[:, None, :])


def test_driven_rope_matches_numpy_loop(rope):
    times = np.arange(0.0, 0.5, 0.01)  # knots every 5 steps: the path is linear between them
    drive = knots(times)
    traj = js.rollout(rope.model, rope.params, rope.state, steps=200, save_every=10, drive=drive)
    m = rope.model
    flat = {
        "ks": np.asarray(m.per_spring(rope.params.ks)),
        "kd": np.asarray(m.per_spring(rope.params.kd)),
        "cd": 0.03,
        "gravity": np.asarray(rope.params.gravity),
    }

    def linear(t):
        return np.array([np.interp(t, times, path(times)[:, k]) for k in range(3)])

    x, v = reference_rollout(
        rope.state.x, rope.state.v, m.springs, m.rest_length, m.mass, m.pinned, m.drag, flat, m.dt, 200, 10, {0: linear}
    )
    np.testing.assert_allclose(np.asarray(traj.x), x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(traj.v), v, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(traj.x[1:, 0]), [linear(t) for t in np.asarray(traj.t[1:])], atol=1e-14)
    assert np.abs(x[-1, 1:] - x[0, 1:]).max() > 0.05  # the rest of the rope moved


@pytest.mark.slow
@pytest.mark.parametrize("integrator", ["semi_implicit_euler", "verlet", "rk4", "backward_euler"])
def test_galilean_invariance_for_every_integrator(integrator):
    """Without drag, an end dragged at constant velocity u moves the rope exactly like the
    pinned rope seen from a frame moving at u (springs see only relative motion)."""
    spec = dict(ROPE, physics={"ks": 300.0, "kd": 0.5})
    scene = js.scene_from_dict(dict(spec, particles=dict(spec["particles"], drag=False))).with_integrator(integrator)
    pinned = js.scene_from_dict(dict(spec, particles=dict(spec["particles"], drag=False, pinned=[0])))
    pinned = pinned.with_integrator(integrator)
    u = np.array([0.3, -0.2, 0.1])
    drive = js.sim.Drive(particles=(0,), t=jnp.array([0.0, 1.0]), x=jnp.asarray([[[0.0, 0, 0]], [u]]))
    moving = js.State(x=scene.state.x, v=scene.state.v + jnp.asarray(u))
    driven = js.rollout(scene.model, scene.params, moving, steps=100, save_every=10, drive=drive)
    still = js.rollout(pinned.model, pinned.params, pinned.state, steps=100, save_every=10)
    t = np.asarray(driven.t)[:, None, None]
    np.testing.assert_allclose(np.asarray(driven.x), np.asarray(still.x) + u * t, rtol=0, atol=1e-11)
    np.testing.assert_allclose(np.asarray(driven.v[1:]), np.asarray(still.v[1:]) + u, rtol=0, atol=1e-9)
    assert np.abs(np.asarray(still.x[-1] - still.x[0])).max() > 1e-3  # gravity moved it


@pytest.mark.slow
def test_gradient_through_driven_rollout_matches_finite_differences(rope):
    drive = knots(np.linspace(0.0, 0.3, 7))
    target = js.rollout(rope.model, rope.params, rope.state, steps=120, save_every=20, drive=drive).x

    def loss(stretch):
        params = rope.model.params_with(rope.params, {"ks.stretch": stretch})
        x = js.rollout(rope.model, params, rope.state, steps=120, save_every=20, drive=drive).x
        return jnp.sum((x - target * 1.01) ** 2)

    grad = jax.grad(loss)(250.0)
    h = 1e-3
    fd = (loss(250.0 + h) - loss(250.0 - h)) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_vmap_over_drives_equals_one_by_one(rope):
    base = np.linspace(0.0, 0.3, 7)
    drives = [knots(base), knots(base + 0.4)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *drives)
    run = lambda d: js.rollout(rope.model, rope.params, rope.state, steps=100, save_every=10, drive=d).x  # noqa: E731
    batched = jax.vmap(run)(stacked)
    for i, drive in enumerate(drives):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(run(drive)), rtol=0, atol=1e-13)


def test_native_lattice_drives_on_the_pure_jax_stepper_with_one_notice():
    scene = js.scene_from_dict(_chain_dict()).with_backend("native")
    if scene.model.stepper.name != "native_lattice":
        pytest.skip("native kernels not built")
    drive = js.sim.Drive(particles=(0,), t=jnp.array([0.0, 1.0]), x=jnp.asarray([[[0.0, 0, 0]], [[0.0, 0.5, 0]]]))
    with pytest.warns(UserWarning, match="generic pure-JAX stepper"):
        native = js.rollout(scene.model, scene.params, scene.state, steps=50, save_every=10, drive=drive)
    plain = scene.with_backend("jax")
    expected = js.rollout(plain.model, plain.params, plain.state, steps=50, save_every=10, drive=drive)
    np.testing.assert_allclose(np.asarray(native.x), np.asarray(expected.x), atol=1e-12)
    assert np.abs(np.asarray(native.x[-1, 1:, 1])).max() > 1e-3


def _chain_dict():
    return {
        "name": "chain",
        "dt": 0.001,
        "physics": {"ks": 1000.0, "kd": 5.0},
        "lattice": {"shape": [6], "axes": ["x"], "spacing": 1.0, "springs": ["structural"], "mass": 1.0},
    }


@pytest.mark.parametrize(
    "particles, t, x, message",
    [
        ([7], [0.0, 1.0], np.zeros((2, 1, 3)), "out of range"),
        ([0, 0], [0.0, 1.0], np.zeros((2, 2, 3)), "twice"),
        ([0], [0.0, 0.0], np.zeros((2, 1, 3)), "strictly increasing"),
        ([0], [0.0, 1.0], np.zeros((2, 2, 3)), "shape"),
        ([0], [0.0, 1.0], np.full((2, 1, 3), np.nan), "NaN"),
        ([], [0.0, 1.0], np.zeros((2, 0, 3)), "no particle"),
    ],
)
def test_bad_drives_are_refused_in_one_line(particles, t, x, message):
    with pytest.raises(js.InputError, match=message) as error:
        make_drive(particles, t, x, particle_count=5)
    assert "\n" not in str(error.value)


def test_a_pinned_particle_cannot_be_driven():
    with pytest.raises(js.InputError, match="pinned"):
        make_drive([0], [0.0, 1.0], np.zeros((2, 1, 3)), 5, pinned=np.array([True, False, False, False, False]))
