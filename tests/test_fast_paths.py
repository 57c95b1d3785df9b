"""The structured lattice path gives the generic (scatter) path's numbers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js


def perturbed(scene, seed=0):
    key1, key2 = jax.random.split(jax.random.PRNGKey(seed))
    x = scene.state.x + 0.05 * jax.random.normal(key1, scene.state.x.shape)
    v = jax.random.normal(key2, scene.state.x.shape) * (~scene.model.pinned)[:, None]
    return js.State(x=x, v=v)


@pytest.mark.parametrize("name", ["chain", "cloth", "jelly", "hard/fine_cloth"])
def test_lattice_scenes_take_the_structured_path(name):
    scene = js.load_scene(name)
    shape, offsets = scene.model.lattice
    assert shape == scene.lattice_shape and len(offsets) >= 1


def test_explicit_topologies_take_the_generic_path():
    assert js.load_scene("mass_spring").model.lattice is None
    # a lattice whose springs are not whole neighbour families (one removed) falls back
    springs = js.sim.lattice_springs((4, 3), ["structural"])[1:]
    model = js.sim.make_model(springs, 1.0, positions=np.zeros((12, 3)) + np.arange(12)[:, None], lattice_shape=(4, 3))
    assert model.lattice is None


@jax.jit
def force(model, params, x, v):
    """model.force as one compiled program (op by op, the grid force of the jelly compiles for seconds)."""
    return model.force(params, x, v)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["cloth", "jelly"])
@pytest.mark.parametrize("per_spring", [False, True])
def test_structured_force_rollout_and_gradient_equal_generic(scenes, name, per_spring):
    scene = scenes[name].with_backend("jax")  # the grid stepper (the native one: tests/test_native.py)
    params = scene.params
    if per_spring:
        count = scene.model.spring_count
        params = params.replace(ks=params.ks * jnp.linspace(0.5, 1.5, count), kd=params.kd * jnp.linspace(2, 1, count))
    fast, generic = scene.model, scene.model.replace(lattice=None)
    assert (fast.stepper.name, generic.stepper.name) == ("grid", "generic")
    state = perturbed(scene)
    a, b = force(fast, params, state.x, state.v), force(generic, params, state.x, state.v)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12 * float(jnp.abs(b).max()))

    def loss(values, model):
        x = js.rollout(model, params.replace(**values), scene.state, steps=100, save_every=50).x
        return jnp.sum(x[-1] ** 2)

    # the loss and its gradient wrt ks and kd (those compared) from one compiled program a path
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    values = {"ks": params.ks, "kd": params.kd}
    (fa, ga), (fb, gb) = value_and_grad(values, fast), value_and_grad(values, generic)
    assert abs(float(fa) - float(fb)) <= 1e-12 * abs(float(fb))
    for key in ("ks", "kd"):
        x, y = np.asarray(ga[key]), np.asarray(gb[key])
        np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-12 * np.abs(y).max())


def test_trajectory_files_keep_the_lattice(tmp_path, scenes):
    scene = scenes["cloth"]
    traj = js.rollout(scene.model, scene.params, scene.state, steps=10, save_every=10)
    js.save_trajectory(tmp_path / "c.h5", scene, traj)
    loaded, _ = js.load_trajectory(tmp_path / "c.h5")
    assert loaded.model.lattice == scene.model.lattice


def cloth_loss(scene, steps, every, checkpoint):
    def loss(ks, kd):
        params = scene.params.replace(ks=ks, kd=kd)
        x = js.rollout(scene.model, params, scene.state, steps, every, checkpoint=checkpoint).x
        return jnp.mean(x[-1] ** 2) + jnp.mean(x[:, 5] ** 2)

    return loss


@pytest.mark.slow
@pytest.mark.parametrize("steps, every, checkpoint", [(200, 200, "sqrt"), (200, 10, 7), (210, 3, 50)])
def test_checkpointed_gradient_equals_plain(scenes, steps, every, checkpoint):
    scene = scenes["cloth"]
    plain = jax.grad(cloth_loss(scene, steps, every, None), argnums=(0, 1))(5000.0, 0.5)
    saved = jax.grad(cloth_loss(scene, steps, every, checkpoint), argnums=(0, 1))(5000.0, 0.5)
    for a, b in zip(plain, saved):
        assert abs(float(a) - float(b)) <= 1e-9 * abs(float(a))
    x0 = js.rollout(scene.model, scene.params, scene.state, steps, every).x
    x1 = js.rollout(scene.model, scene.params, scene.state, steps, every, checkpoint=checkpoint).x
    np.testing.assert_array_equal(np.asarray(x0), np.asarray(x1))


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["jax", "auto"])
def test_hundred_thousand_step_gradient_fits_in_one_gib(scenes, backend):
    scene = scenes["cloth"].with_backend(backend)
    grad = jax.jit(jax.value_and_grad(cloth_loss(scene, 100_000, 100_000, "sqrt"), argnums=(0, 1)))
    memory = grad.lower(5000.0, 0.5).compile().memory_analysis()
    total = memory.temp_size_in_bytes + memory.argument_size_in_bytes + memory.output_size_in_bytes
    assert total < 2**30, total / 2**20
    if scene.model.stepper.fused:  # the native kernel keeps its own checkpoints either way
        return
    plain = jax.jit(jax.value_and_grad(cloth_loss(scene, 100_000, 100_000, None), argnums=(0, 1)))
    assert plain.lower(5000.0, 0.5).compile().memory_analysis().temp_size_in_bytes > 2**30  # why it is needed


def test_checkpoint_argument_is_checked(scenes):
    scene = scenes["chain"]
    with pytest.raises(js.InputError, match="checkpoint"):
        js.rollout(scene.model, scene.params, scene.state, 10, 10, checkpoint=0)
