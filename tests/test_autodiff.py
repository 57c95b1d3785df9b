"""Gradients against float64 central finite differences; vmap against separate rollouts."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js


def position_loss(scene, steps, every):
    """Mean squared distance of all saved frames to a target made with other parameters."""
    target_params = scene.params.replace(ks=scene.params.ks * 1.3, kd=scene.params.kd * 0.7, cd=scene.params.cd * 2)
    target = js.rollout(scene.model, target_params, scene.state, steps=steps, save_every=every).x

    def loss(values):
        params = scene.params.replace(**values)
        x = js.rollout(scene.model, params, scene.state, steps=steps, save_every=every).x
        return jnp.mean((x - target) ** 2)

    return jax.jit(loss)


@pytest.mark.parametrize("name, steps", [("chain", 300), ("cloth", 300)])
def test_gradient_matches_central_differences(scenes, name, steps):
    scene = scenes[name]
    loss = position_loss(scene, steps, steps // 6)
    values = {k: scene.params.to_dict()[k] for k in ("ks", "kd", "cd")}
    grads = jax.grad(loss)(values)
    for key, value in values.items():
        h = 1e-5 * float(value)
        plus = float(loss({**values, key: value + h}))
        minus = float(loss({**values, key: value - h}))
        fd = (plus - minus) / (2 * h)
        assert abs(float(grads[key]) - fd) <= 1e-6 * abs(fd), (key, float(grads[key]), fd)
        assert fd != 0.0


def test_gradient_with_respect_to_initial_state_is_finite_at_rest(scenes):
    scene = scenes["chain"]  # starts at rest with drag: |v| at v = 0

    def loss(state):
        return jnp.sum(js.rollout(scene.model, scene.params, state, steps=50, save_every=50).x[-1, :, 1])

    grads = jax.grad(loss)(scene.state)
    assert np.all(np.isfinite(np.asarray(grads.x))) and np.all(np.isfinite(np.asarray(grads.v)))
    assert np.any(np.asarray(grads.v) != 0)


@pytest.mark.parametrize("backend", ["jax", "auto"])
def test_vmap_over_parameters_equals_separate_rollouts(scenes, backend):
    # pure JAX: bit for bit; the default (the native lattice kernel here) batches members
    # side by side in vector lanes, whose sums may round in another order
    scene = scenes["chain"].with_backend(backend)
    ks = jnp.linspace(500.0, 1500.0, 8)
    kd = jnp.linspace(1.0, 8.0, 8)
    cd = jnp.linspace(0.01, 0.1, 8)
    batch = scene.params.replace(ks=ks, kd=kd, cd=cd)
    axes = js.Params(ks=0, kd=0, cd=0, gravity=None)

    def run(params):
        return js.rollout(scene.model, params, scene.state, steps=400, save_every=40).x

    batched = jax.vmap(run, in_axes=(axes,))(batch)
    assert batched.shape == (8, 11, 20, 3)
    for i in range(8):
        single = run(scene.params.replace(ks=ks[i], kd=kd[i], cd=cd[i]))
        if backend == "jax":
            np.testing.assert_array_equal(np.asarray(batched[i]), np.asarray(single))
        else:
            np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(single), rtol=1e-13, atol=1e-14)
    assert not np.array_equal(np.asarray(batched[0]), np.asarray(batched[-1]))


def test_vmap_over_initial_states_equals_separate_rollouts(scenes):
    scene = scenes["cloth"]
    kicks = jnp.linspace(0.0, 2.0, 8)
    states = js.State(
        x=jnp.broadcast_to(scene.state.x, (8,) + scene.state.x.shape),
        v=scene.state.v[None] + kicks[:, None, None] * jnp.array([0.0, 1.0, 0.0]),
    )
    states = states.replace(v=states.v * (~scene.model.pinned)[None, :, None])

    def run(state):
        return js.rollout(scene.model, scene.params, state, steps=40, save_every=20).x

    batched = jax.vmap(run)(states)
    for i in (0, 3, 7):
        single = run(js.State(x=states.x[i], v=states.v[i]))
        # the batched lattice step fuses differently: round-off (1e-14 m), not bitwise
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(single), rtol=1e-12, atol=1e-12)
