"""Steppers: one interface, four implementations; each runs what it claims and refuses the rest.

A force term added here (linear drag f = -c v, not one of jaxspring's) must run on every
stepper that claims it, with the numbers of a NumPy loop written in this file, and be
refused with a message naming it by the stepper that does not (the native lattice kernel).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.steppers import Generic, Grid, select_stepper
from jaxspring.steppers import native_kernels as native
from jaxspring.steppers.layout import to_grid

SHAPE = (4, 3)
STEPS = 60


@dataclasses.dataclass(frozen=True)
class LinearDrag:
    """f = -cd v on every particle (reads the `cd` parameter)."""

    name = "linear_drag"

    def force(self, model, params, x, v):
        return -params.cd * v

    def grid_force(self, model, params, x, v):
        return -params.cd * v

    def energy(self, model, params, x):
        return jnp.zeros((), x.dtype)


@dataclasses.dataclass(frozen=True)
class LinearDragWithoutGrid:
    name = "linear_drag_no_grid"

    def force(self, model, params, x, v):
        return -params.cd * v

    def energy(self, model, params, x):
        return jnp.zeros((), x.dtype)


js.sim.register_term(LinearDrag(), parameters=("cd",))
js.sim.register_term(LinearDragWithoutGrid(), parameters=("cd",))


def sheet(term="linear_drag", backend="auto"):
    positions = js.sim.lattice_positions(SHAPE, 0.5, (0.0, 0.0, 0.0), (0, 2))
    springs = js.sim.lattice_springs(SHAPE, ["structural", "shear"])
    model = js.sim.make_model(springs, 0.2, positions=positions, pinned=[0, 2], lattice_shape=SHAPE, backend=backend)
    model = model.replace(terms=model.terms + (term,))
    params = js.Params(ks=80.0, kd=0.3, cd=0.7, gravity=[0.0, -9.81, 0.0])
    state = js.State(x=jnp.asarray(positions), v=jnp.zeros_like(jnp.asarray(positions)))
    return model, params, state


def numpy_reference(model, params, state, steps):
    """Semi-implicit Euler with springs, gravity and linear drag, one loop over steps and springs."""
    x, v = np.array(state.x, float), np.array(state.v, float)
    springs, rest = np.asarray(model.springs), np.asarray(model.rest_length)
    mass, free = np.asarray(model.mass), ~np.asarray(model.pinned)
    ks, kd, cd, g = float(params.ks), float(params.kd), float(params.cd), np.asarray(params.gravity)
    for _ in range(steps):
        force = mass[:, None] * g - cd * v
        for (a, b), length0 in zip(springs, rest):
            d = x[b] - x[a]
            length = np.sqrt(d @ d)
            u = d / length
            f = (ks * (length - length0) + kd * (v[b] - v[a]) @ u) * u
            force[a] += f
            force[b] -= f
        v = np.where(free[:, None], v + model.dt * force / mass[:, None], 0.0)
        x = x + model.dt * v
    return x


def claimed_steppers():
    steppers = [Generic(), Grid()]
    if native.available():
        from jaxspring.steppers.native_springs import NativeSprings

        steppers.append(NativeSprings())
    return steppers


@pytest.mark.parametrize("stepper", claimed_steppers(), ids=lambda s: s.name)
def test_added_force_term_runs_on_every_stepper_that_claims_it(stepper):
    model, params, state = sheet()
    model = model.replace(stepper=stepper)
    assert model.stepper == stepper and "linear_drag" in model.terms
    got = js.rollout(model, params, state, steps=STEPS, save_every=STEPS).x[-1]
    want = numpy_reference(model, params, state, STEPS)
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-12)
    # and the term matters: without it the motion differs by far more than the tolerance
    plain = js.rollout(
        model.replace(terms=model.terms[:-1], stepper=stepper), params.replace(cd=None), state, STEPS, STEPS
    ).x[-1]
    assert np.abs(np.asarray(plain) - want).max() > 1e-6


@pytest.mark.skipif(not native.available(), reason="the native kernel is not built")
def test_added_force_term_is_refused_by_the_native_lattice_stepper():
    from jaxspring.steppers.native_lattice import NativeLattice

    model, _, _ = sheet()
    with pytest.raises(js.InputError, match="native_lattice stepper does not run the force term 'linear_drag'"):
        model.replace(stepper=NativeLattice())
    # auto never picks a stepper that would skip the term; plain lattices do get the native one on CPU
    assert model.stepper.name == "grid"
    plain = model.replace(terms=model.terms[:-1])
    assert plain.stepper.name == ("native_lattice" if jax.default_backend() == "cpu" else "grid")


def test_a_term_without_a_grid_force_runs_on_the_generic_stepper():
    model, params, state = sheet("linear_drag_no_grid")
    assert model.stepper.name in ("generic", "native_springs")
    with pytest.raises(js.InputError, match="grid stepper does not run the force term 'linear_drag_no_grid'"):
        model.replace(stepper=Grid())
    got = js.rollout(model, params, state, steps=STEPS, save_every=STEPS).x[-1]
    np.testing.assert_allclose(np.asarray(got), numpy_reference(model, params, state, STEPS), rtol=0, atol=1e-12)


def test_selection_by_backend_and_integrator(scenes):
    cloth = scenes["cloth"]
    assert cloth.with_backend("jax").model.stepper.name == "grid"
    assert cloth.with_backend("jax").with_integrator("rk4").model.stepper.name == "grid"
    assert scenes["mass_spring"].model.stepper.name == "generic"
    if native.available():
        assert cloth.with_backend("native").model.stepper.name == "native_lattice"
        # the lattice kernel steps semi-implicit Euler only: other integrators take the springs kernel
        assert cloth.with_backend("native").with_integrator(js.sim.RK4()).model.stepper.name == "native_springs"
        assert cloth.with_integrator(js.sim.Verlet()).model.stepper.name == "grid"  # auto: pure JAX
    # forward mode: every model has a pure-JAX twin; a 2-D lattice's keeps the grid layout, a 3-D
    # lattice's is the generic stepper (its Jacobian programs compile 5x faster: Model.forward_mode)
    twin = cloth.model.forward_mode()
    assert twin.stepper.forward_mode and twin.stepper.array_to_internal(twin, cloth.state.x).shape == (3, 31, 41)
    jelly = scenes["jelly"]
    if native.available():
        assert jelly.model.stepper.name == "native_lattice" and jelly.model.forward_mode().stepper.name == "generic"
    assert jelly.with_backend("jax").model.forward_mode().stepper.name == "grid"  # already forward mode: itself
    assert scenes["chain"].model.forward_mode().stepper.forward_mode
    assert select_stepper(cloth.model.replace(backend="jax")).name == "grid"
    with pytest.raises(js.InputError, match="backend"):
        cloth.with_backend("cuda")


@pytest.mark.slow
def test_integrators_are_configured_objects(scenes):
    chain = scenes["chain"]
    guess_only = js.sim.BackwardEuler(newton=js.sim.NewtonSettings(max_newton=0))
    configured = chain.with_integrator(guess_only)
    assert configured.model.integrator == guess_only and configured.model.integrator.name == "backward_euler"
    assert chain.with_integrator("backward_euler").model.integrator == js.sim.INTEGRATORS["backward_euler"]
    assert chain.with_integrator("backward_euler").model.integrator != guess_only
    start = chain.state.replace(v=chain.state.v.at[5].set(jnp.array([0.0, 3.0, 0.0])))

    def end(scene):
        return np.asarray(js.rollout(scene.model, chain.params, start, steps=20, save_every=20).x[-1])

    # no Newton iteration leaves Newton's starting guess, the explicit semi-implicit Euler
    # step: the settings reach the solver
    explicit = end(chain.with_backend("jax"))
    np.testing.assert_allclose(end(configured), explicit, rtol=0, atol=1e-14)
    assert np.abs(end(chain.with_integrator("backward_euler")) - explicit).max() > 1e-7
    with pytest.raises(js.InputError, match="unknown integrator"):
        chain.with_integrator("magic")


def test_grid_layout_round_trip():
    values = jnp.arange(12 * 3, dtype=float).reshape(12, 3)
    grid = to_grid(SHAPE, values)
    assert grid.shape == (3,) + SHAPE and float(grid[1, 2, 1]) == float(values[2 * 3 + 1, 1])
