"""Multiple shooting with the segments' start states fitted: positions only, against the truth;
continuity checked by simulating each fitted segment again; the objective's gradient
against finite differences."""

import dataclasses
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.fit.block_lm import _costs, _normal_pieces
from jaxspring.fit.shooting import CONTINUITY_WEIGHTS, shooting_problem

jax.config.update("jax_enable_x64", True)
SCENES = Path(__file__).parents[1] / "scenes"
CHAIN_TRUTH = {"ks": 1000.0, "kd": 5.0, "cd": 0.05}


def positions_only(scene, truth, steps, save_every):
    obs = js.synthetic_observations(scene, truth, steps=steps, save_every=save_every)
    return dataclasses.replace(obs, states=None)  # no recorded states: velocities unknown


@pytest.fixture(scope="module")
def chain():
    return js.load_scene(SCENES / "chain.toml")


@pytest.mark.slow
def test_positions_only_multiple_shooting_recovers_a_1s_chain(chain):
    # 1 s in segments of 10 frames: the shapes of the noisy fit's 10-frame segments below (compiled once)
    obs = positions_only(chain, CHAIN_TRUTH, 1000, 20)
    init = {"ks": 400.0, "kd": 12.0, "cd": 0.15}  # 2.5 to 3 times away
    result = js.fit(chain, obs, list(CHAIN_TRUTH), init=init, strategy="free_shooting", segment_frames=10)
    for n, true in CHAIN_TRUTH.items():
        assert abs(float(result.final[n]) / true - 1) < 1e-8, (n, result.final[n])
    assert result.identifiability.objective.startswith("multiple shooting: the misfit of 5 segments of 10 frames")
    assert "minimised: multiple shooting" in result.table()
    # continuity: every fitted segment, simulated again from its fitted start, ends on the next one's start
    x, v = result.estimated["segment_x"], result.estimated["segment_v"]
    params = chain.model.params_with(chain.params, result.final)
    for j in range(len(x) - 1):
        end = js.sim.final_state(chain.model, params, js.State(x=jnp.asarray(x[j]), v=jnp.asarray(v[j])), steps=200)
        np.testing.assert_allclose(end.x, x[j + 1], atol=1e-10)
        np.testing.assert_allclose(end.v, v[j + 1], atol=1e-8)
    np.testing.assert_allclose(x[:, obs.particles], obs.x[::10][: len(x)], atol=1e-10)  # and on the observations


@pytest.mark.slow
def test_with_noise_the_segment_length_does_not_change_the_answer(chain):
    """1 s, 1% noise, positions only: with continuity raised to a constraint the answer is the
    maximum-likelihood fit of one continuous motion, whatever the segments (a fixed penalty's
    answer moves with them: its states take up noise as gaps), and within 3 standard errors."""
    obs = dataclasses.replace(
        js.synthetic_observations(chain, CHAIN_TRUTH, 1000, 20, noise_relative=0.01, seed=1), states=None
    )
    init = {"ks": 400.0, "kd": 12.0, "cd": 0.15}
    short, long = (
        js.fit(chain, obs, list(CHAIN_TRUTH), init=init, strategy="free_shooting", segment_frames=k) for k in (10, 25)
    )
    for n, true in CHAIN_TRUTH.items():
        se = float(short.identifiability.relative_standard_error[n])
        assert abs(float(long.identifiability.relative_standard_error[n]) / se - 1) < 0.01
        assert abs(np.log(float(short.final[n]) / float(long.final[n]))) < 0.05 * se, n
        assert abs(np.log(float(short.final[n]) / true)) < 3 * se, n


@pytest.mark.slow
def test_multiple_shooting_recovers_a_chain_seen_at_a_third_of_its_particles(chain):
    """6 of 19 free particles observed, positions only: the others' segment states are guessed
    by the start rule and fitted like the rest."""
    obs = js.synthetic_observations(chain, CHAIN_TRUTH, steps=1000, save_every=20, particles=list(range(2, 20, 3)))
    assert obs.states is None
    init = {"ks": 400.0, "kd": 12.0, "cd": 0.15}
    result = js.fit(chain, obs, list(CHAIN_TRUTH), init=init, strategy="free_shooting", segment_frames=10)
    for n, true in CHAIN_TRUTH.items():
        assert abs(float(result.final[n]) / true - 1) < 1e-8, (n, result.final[n])
    se = result.identifiability.relative_standard_error
    assert all(float(se[n]) < 1e-6 for n in CHAIN_TRUTH)  # exact data: the residual variance is round-off


@pytest.mark.slow
def test_positions_only_multiple_shooting_recovers_a_jelly_through_its_impacts():
    """A 3 x 3 x 3 jelly (all springs of the jelly scene) spinning as it falls 0.3 m, lands and
    bounces, for 1 s: the segments that touch the ground are left out (contact switches on at
    a discrete step), the flight before the impact and the bounce after it are fitted."""
    data = tomllib.loads((SCENES / "jelly.toml").read_text())
    data["lattice"]["shape"], data["lattice"]["origin"] = [3, 3, 3], [0.0, 0.3, 0.0]
    scene = js.scene_from_dict(data)
    truth = {"ks": 250.0, "kd": 0.05}
    recorded = js.synthetic_observations(scene, truth, steps=1000, save_every=10)
    obs = dataclasses.replace(recorded, states=None)
    result = js.fit(
        scene, obs, ["ks", "kd"], init={"ks": 600.0, "kd": 0.02}, strategy="free_shooting", segment_frames=10
    )
    for n, true in truth.items():
        assert abs(float(result.final[n]) / true - 1) < 1e-8, (n, result.final[n])
    firsts = result.estimated["segment_frame"]
    np.testing.assert_array_equal(firsts, [0, 60])  # before the landing, and in the air after the bounce
    y = recorded.states.x[:, :, 1]  # every particle at every frame
    fall = max(abs(y[i + 1, j] - y[i, j]) for i in range(len(y) - 1) for j in range(y.shape[1]))
    for f in range(0, 100, 10):  # kept: clear of the ground by a frame's fall; left out: within it, or in contact
        assert (y[f : f + 11].min() > fall) == (f in firsts), f
    assert any(y[f : f + 11].min() < 0.0 for f in range(0, 100, 10))  # contact: below the plane
    assert "8 touching the ground left out" in result.identifiability.objective
    np.testing.assert_allclose(result.estimated["segment_x"][:, obs.particles], obs.x[firsts], atol=1e-10)


@pytest.mark.slow
def test_the_shooting_objective_gradient_matches_finite_differences(chain):
    obs = positions_only(chain, CHAIN_TRUTH, 300, 20)
    problem = shooting_problem(chain, obs, list(CHAIN_TRUTH), CHAIN_TRUTH, 5, CONTINUITY_WEIGHTS[0])
    p0, s0, residual, data = problem.p0, problem.s0, problem.residual, problem.data
    rng = np.random.default_rng(0)
    p = jnp.asarray(p0) + 0.1 * rng.normal(size=p0.shape)
    s = jnp.asarray(1e-2 * rng.normal(size=s0.shape))
    cost = jax.jit(lambda p, s: _costs(residual, p, s, data, linked=True).sum())
    grad_p, grad_s = jax.grad(cost, argnums=(0, 1))(p, s)
    h = 1e-6
    for i in range(p.shape[0]):
        step = jnp.zeros_like(p).at[i].set(h)
        np.testing.assert_allclose(grad_p[i], (cost(p + step, s) - cost(p - step, s)) / (2 * h), rtol=1e-4)
    for index in [(0, 0), (0, 40), (1, 7), (2, s.shape[1] - 1)]:  # a state's gap to the next segment counts too
        step = jnp.zeros_like(s).at[index].set(h)
        np.testing.assert_allclose(grad_s[index], (cost(p, s + step) - cost(p, s - step)) / (2 * h), rtol=1e-4)
    # the Levenberg-Marquardt normal equations' gradient, assembled from the blocks and their links
    pieces = _normal_pieces(residual, p, s, data, linked=True)
    gp, gs, defect = pieces[4].sum(axis=0), pieces[5], pieces[8]
    gs = gs.at[1:].add(-defect[:-1])  # block b + 1's state also sits in block b's continuity gap
    np.testing.assert_allclose(2 * gp, grad_p, rtol=1e-9)
    np.testing.assert_allclose(2 * gs, grad_s, rtol=1e-9, atol=1e-12 * float(jnp.abs(grad_s).max()))


def test_a_target_always_on_the_ground_is_refused_with_the_way_out():
    data = tomllib.loads((SCENES / "jelly.toml").read_text())
    data["lattice"]["shape"], data["lattice"]["origin"] = [2, 2, 2], [0.0, 0.0, 0.0]  # resting on the plane
    scene = js.scene_from_dict(data)
    obs = positions_only(scene, {"ks": 250.0, "kd": 0.05}, 100, 10)
    with pytest.raises(js.InputError, match="every segment touches the ground.*strategy shooting"):
        js.fit(scene, obs, ["ks"], init={"ks": 300.0}, strategy="free_shooting", segment_frames=5)
