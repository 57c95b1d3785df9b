"""Integrators: convergence orders, energy behaviour, gradients, stable-dt bounds against observed blow-ups."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js

ORDERS = {"semi_implicit_euler": 1, "verlet": 2, "rk4": 4, "backward_euler": 1}
# horizon [s] and dt sweep per scene: small enough to be in the asymptotic regime
SWEEPS = {
    "mass_spring": (2.0, {1: [0.04, 0.02, 0.01, 0.005], 2: [0.04, 0.02, 0.01, 0.005], 4: [0.1, 0.05, 0.025, 0.0125]}),
    "chain": (
        0.2,
        {1: [0.004, 0.002, 0.001, 0.0005], 2: [0.004, 0.002, 0.001, 0.0005], 4: [0.008, 0.004, 0.002, 0.001]},
    ),
}


def final_positions(scene, integrator, dt, horizon):
    model = scene.model.replace(integrator=integrator, dt=dt)
    return np.asarray(js.sim.final_state(model, scene.params, scene.state, int(round(horizon / dt))).x)


@pytest.fixture(scope="module")
def references(scenes):
    """RK4 at 1/16 of the smallest swept step: its error is < 1e-4 of any measured one."""
    out = {}
    for name, (horizon, dts) in SWEEPS.items():
        out[name] = final_positions(scenes[name], "rk4", min(min(d) for d in dts.values()) / 16, horizon)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("scene_name", list(SWEEPS))
@pytest.mark.parametrize("integrator", list(ORDERS))
def test_convergence_order(scenes, references, scene_name, integrator):
    horizon, sweeps = SWEEPS[scene_name]
    order = ORDERS[integrator]
    dts = sweeps[order]
    errors = [
        np.sqrt(np.mean((final_positions(scenes[scene_name], integrator, dt, horizon) - references[scene_name]) ** 2))
        for dt in dts
    ]
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert abs(slope - order) <= 0.15, (errors, slope)


def radial_oscillator(integrator, dt, kd=0.0):
    """A particle on a spring to a pinned anchor, moving only along the spring: x'' = -(ks/m) x."""
    model = js.sim.make_model(
        [[0, 1]], [1.0, 1.0], positions=[[0, 0, 0], [1, 0, 0]], pinned=[0], gravity=False, dt=dt, integrator=integrator
    )
    params = js.Params(ks=4.0, kd=kd)  # omega = 2 rad/s
    state = js.State(x=jnp.array([[0.0, 0, 0], [1.2, 0, 0]]), v=jnp.zeros((2, 3)))
    return model, params, state


@pytest.mark.parametrize("integrator", ["semi_implicit_euler", "verlet"])
def test_symplectic_energy_bounded_without_drift(integrator):
    model, params, state = radial_oscillator(integrator, 1e-3)
    traj = js.rollout(model, params, state, steps=100_000, save_every=10)
    e = np.asarray(js.sim.energy(model, params, traj))
    error = (e - e[0]) / e[0]
    bound = {"semi_implicit_euler": 2e-3, "verlet": 1e-6}[integrator]  # O(omega dt) and O((omega dt)^2)
    assert np.max(np.abs(error)) < bound
    trend = np.polyfit(np.asarray(traj.t), error, 1)[0] * float(traj.t[-1])
    assert abs(trend) < 0.1 * np.max(np.abs(error))


@pytest.mark.slow
@pytest.mark.parametrize("integrator", ["rk4", "backward_euler"])
def test_energy_loss_matches_amplification_factor(integrator):
    # On x'' = -w^2 x one step multiplies the amplitude by |R(i w dt)|, so energy by |R|^2:
    # RK4: |R|^2 = 1 - y^6/72 + y^8/576 (y = w dt); backward Euler: 1 / (1 + y^2).
    dt, steps, omega = 0.05, 2000, 2.0
    y = omega * dt
    factor = {"rk4": 1 - y**6 / 72 + y**8 / 576, "backward_euler": 1 / (1 + y**2)}[integrator]
    model, params, state = radial_oscillator(integrator, dt)
    traj = js.rollout(model, params, state, steps=steps, save_every=steps)
    e = np.asarray(js.sim.energy(model, params, traj))
    assert e[-1] / e[0] == pytest.approx(factor**steps, rel=1e-6)
    assert e[-1] < e[0]


def loss_grad_and_positions(scene, steps, every):
    """One compiled program a scene: (loss, frames), d loss / d values at `values` for the
    position loss against `target`. The frames at the target's values give the target; the
    loss values at values +- h the central differences; the gradient the reverse pass."""

    def loss(values, target):
        x = js.rollout(scene.model, scene.params.replace(**values), scene.state, steps=steps, save_every=every).x
        return jnp.mean((x - target) ** 2), x

    return jax.jit(jax.value_and_grad(loss, has_aux=True))


@pytest.mark.slow
@pytest.mark.parametrize("integrator", ["verlet", "rk4", "backward_euler"])
def test_gradient_matches_central_differences(scenes, integrator):
    scene = scenes["chain"].with_integrator(integrator)
    program = loss_grad_and_positions(scene, 120, 20)
    values = {k: scene.params.to_dict()[k] for k in ("ks", "kd", "cd")}
    target_values = {"ks": values["ks"] * 1.3, "kd": values["kd"] * 0.7, "cd": values["cd"] * 2}
    (_, target), _ = program(target_values, jnp.zeros((120 // 20 + 1,) + scene.state.x.shape))
    (_, _), grads = program(values, target)

    def loss(v):
        return float(program(v, target)[0][0])

    for key, value in values.items():
        h = 1e-5 * float(value)
        fd = (loss({**values, key: value + h}) - loss({**values, key: value - h})) / (2 * h)
        assert fd != 0.0
        assert abs(float(grads[key]) - fd) <= 1e-5 * abs(fd), (key, float(grads[key]), fd)


def test_backward_euler_under_vmap_matches_single_rollouts(scenes):
    scene = scenes["chain"].with_integrator("backward_euler")
    ks = jnp.array([500.0, 1000.0, 2000.0])

    def run(k):
        return js.rollout(scene.model, scene.params.replace(ks=k), scene.state, steps=60, save_every=20).x

    batched = jax.vmap(run)(ks)
    for i in range(3):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(run(ks[i])), rtol=0, atol=1e-10)


def test_stable_dt_test_equation():
    # undamped: semi-implicit Euler and Verlet 2/w, RK4 2 sqrt(2)/w; backward Euler unconditional
    assert js.sim.stable_dt("semi_implicit_euler", 100.0) == pytest.approx(0.02, rel=1e-6)
    assert js.sim.stable_dt("verlet", 100.0) == pytest.approx(0.02, rel=1e-6)
    assert js.sim.stable_dt("rk4", 100.0) == pytest.approx(2 * math.sqrt(2) / 100, rel=1e-6)
    assert math.isinf(js.sim.stable_dt("backward_euler", 100.0, 50.0))
    # damped semi-implicit Euler: (w dt)^2 + 2 c dt = 4
    assert js.sim.stable_dt("semi_implicit_euler", 100.0, 20.0) == pytest.approx(
        (-20 + math.sqrt(400 + 4e4)) / 1e4, rel=1e-6
    )
    # pure damping: explicit Euler on v' = -c v needs c dt <= 2
    assert js.sim.stable_dt("semi_implicit_euler", 0.0, 100.0) == pytest.approx(0.02, rel=1e-5)


def on_the_ground(scene):
    """The jelly at rest with its bottom face on the ground: sustained contact."""
    x = scene.state.x - jnp.array([0.0, float(jnp.min(scene.state.x[:, 1])), 0.0])
    return scene.with_state(js.State(x=x, v=jnp.zeros_like(x)))


def off_grid(model):
    """An explicit integrator's model on the generic (scatter) stepper where it would take the
    pure-JAX grid stepper: the same numbers (tests/test_fast_paths.py holds the two paths to
    1e-12), but XLA compiles a grid step of a 2-D or 3-D lattice several times slower (cloth,
    RK4: ~20 s against ~5 s). Lattice semi-implicit Euler keeps its native kernel."""
    explicit = model.integrator.explicit
    return model.replace(lattice=None) if explicit and model.stepper.name == "grid" else model


def blows_up(scene, integrator, dt, steps=2000):
    model = off_grid(scene.model.replace(integrator=integrator, dt=dt))
    traj = js.rollout(model, scene.params, scene.state, steps=steps, save_every=10)
    return js.sim.find_blowup(model, scene.params, traj)


CASES = [("chain", "semi_implicit_euler"), ("chain", "verlet"), ("chain", "rk4")]
CASES += [("cloth", "semi_implicit_euler"), ("cloth", "verlet"), ("cloth", "rk4"), ("jelly", "semi_implicit_euler")]


@pytest.mark.slow
@pytest.mark.parametrize("name, integrator", CASES)
def test_analyser_bound_matches_observed_stability_limit(scenes, name, integrator):
    scene = on_the_ground(scenes["jelly"]) if name == "jelly" else scenes[name]
    # the analyser linearises the force: on the generic stepper (jelly: 12 s to compile, the grid one 33 s)
    bound = js.sim.estimate_stability(scene.model.replace(lattice=None), scene.params, scene.state).bounds[integrator]
    assert blows_up(scene, integrator, 0.8 * bound) is None
    problem = blows_up(scene, integrator, 1.2 * bound)
    assert problem is not None and problem.step > 0
