"""The hard cases in scenes/hard/ behave as their files document."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.cli import main

EXPLICIT = ["semi_implicit_euler", "verlet", "rk4"]


def hard(name):
    return js.load_scene(f"hard/{name}")


def off_grid(model):
    """An explicit integrator's model on the generic (scatter) stepper where it would take the
    pure-JAX grid stepper: the same numbers (tests/test_fast_paths.py holds the two paths to
    1e-12), but XLA compiles a grid step of a 2-D or 3-D lattice several times slower (fast
    jelly, RK4: ~90 s against ~8 s). Lattice semi-implicit Euler keeps its native kernel."""
    explicit = model.integrator.explicit
    return model.replace(lattice=None) if explicit and model.stepper.name == "grid" else model


def run(scene, integrator, steps, every, dt=None):
    model = off_grid(scene.model.replace(integrator=integrator, dt=dt or scene.model.dt))
    traj = js.rollout(model, scene.params, scene.state, steps=steps, save_every=every)
    return model, traj, js.sim.find_blowup(model, scene.params, traj)


@pytest.fixture(scope="module")
def stiff_cloth():
    return hard("stiff_cloth")


@pytest.fixture(scope="module")
def damped_chain():
    return hard("damped_chain")


@pytest.mark.slow
@pytest.mark.parametrize("case", ["stiff_cloth", "damped_chain"])
@pytest.mark.parametrize("integrator", EXPLICIT)
def test_explicit_integrators_blow_up_where_predicted(request, case, integrator):
    scene = request.getfixturevalue(case)
    # the analyser linearises the force: on the generic stepper, not the slow-to-compile grid one
    estimate = js.sim.estimate_stability(scene.model.replace(lattice=None), scene.params, scene.state)
    bound = estimate.bounds[integrator]
    assert bound < scene.model.dt  # the analyser predicts the blow-up at the scene's dt
    _, _, problem = run(scene, integrator, 400, 10)
    assert problem is not None and 0 < problem.step <= 400
    # and the prediction is sharp: 20% below the bound runs clean, 20% above blows up
    # (within tens of steps, so 1,000 steps tell them apart)
    assert run(scene, integrator, 1000, 10, dt=0.8 * bound)[2] is None
    assert run(scene, integrator, 1000, 10, dt=1.2 * bound)[2] is not None


@pytest.mark.slow
@pytest.mark.parametrize("case, steps", [("stiff_cloth", 40), ("damped_chain", 400)])
def test_backward_euler_stays_bounded(request, case, steps):
    scene = request.getfixturevalue(case)
    model, traj, problem = run(scene, "backward_euler", steps, steps // 4)
    assert problem is None
    e = np.asarray(js.sim.energy(model, scene.params, traj))
    assert np.all(np.isfinite(np.asarray(traj.x)))
    assert np.all(e <= e[0] + 1e-9 * abs(e[0]))  # nothing adds energy; backward Euler only removes it


@pytest.mark.slow
def test_run_reports_the_blowup_step(tmp_path, capsys):
    out = tmp_path / "stiff.h5"
    code = main(["run", "hard/stiff_cloth", "--steps", "400", "--save-every", "10", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not out.exists()
    assert "warning" in err[0] and "backward_euler" in err[0]
    assert "blew up at step" in err[-1]
    assert main(["check", "hard/stiff_cloth"]) == 1
    assert main(["check", "hard/stiff_cloth", "--integrator", "backward_euler"]) == 0
    assert "unconditional" in capsys.readouterr().out


@pytest.mark.slow
def test_fast_jelly_stays_stable_and_loses_energy():
    scene = hard("fast_jelly")
    for integrator in EXPLICIT:
        model, traj, problem = run(scene, integrator, 300, 10)
        assert problem is None
        e = np.asarray(js.sim.energy(model, scene.params, traj))
        assert e[-1] < 0.7 * e[0]  # the impact dissipates (contact and spring damping)
        y = np.asarray(traj.x[..., 1])
        assert -0.2 < y.min() < -0.05  # sinks ~0.1 m into the penalty ground, not through it


def test_undamped_chain_conserves_energy_and_is_chaotic():
    scene = hard("undamped_chain")
    assert "drag" not in scene.model.terms
    model, traj, _ = run(scene, "verlet", 15000, 500)
    e = np.asarray(js.sim.energy(model, scene.params, traj))
    weight_scale = 20 * 9.81 * 10  # total weight times half the chain's length [J]
    assert np.max(np.abs(e - e[0])) < 1e-3 * weight_scale
    nudged = scene.with_state(js.State(x=scene.state.x.at[-1, 1].add(1e-9), v=scene.state.v))
    _, other, _ = run(nudged, "verlet", 15000, 500)
    separation = np.sqrt(np.mean((np.asarray(traj.x) - np.asarray(other.x)) ** 2, axis=(1, 2)))
    assert separation[-1] > 1e6 * separation[1]  # 1e-10 m at 0.5 s grows past 1e-4 m by 15 s


@pytest.mark.slow
def test_fine_cloth_is_a_100_by_100_lattice_and_runs():
    scene = hard("fine_cloth")
    assert scene.model.particle_count == 10_000 and scene.lattice_shape == (100, 100)
    estimate = js.sim.estimate_stability(scene.model, scene.params, scene.state)
    assert estimate.margin > 1
    _, traj, problem = run(scene, "semi_implicit_euler", 20, 10)
    assert problem is None and np.all(np.isfinite(np.asarray(traj.x)))


@pytest.mark.parametrize(
    "integrator",
    # < 5 s each from an empty compile cache but RK4 and backward Euler
    [pytest.param(name, marks=[pytest.mark.slow] * (name in ("rk4", "backward_euler"))) for name in js.sim.INTEGRATORS],
)
def test_coincident_particles_finite_forces_and_gradients(integrator):
    scene = hard("coincident").with_integrator(integrator)
    x = np.asarray(scene.state.x)
    assert np.array_equal(x[1], x[2]) and np.array_equal(x[3], x[4])  # zero-length springs at the start
    force = jax.jit(lambda model, params, x, v: model.force(params, x, v))  # one program, not op by op
    assert np.all(np.isfinite(np.asarray(force(scene.model, scene.params, scene.state.x, scene.state.v))))

    def loss(ks, kd, state):
        traj = js.rollout(scene.model, scene.params.replace(ks=ks, kd=kd), state, steps=30, save_every=30)
        return jnp.sum(traj.x[-1] ** 2) + jnp.sum(traj.v[-1] ** 2)

    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(scene.params.ks, scene.params.kd, scene.state)
    for leaf in jax.tree_util.tree_leaves(grads):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert float(grads[0]) != 0.0
