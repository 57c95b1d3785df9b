"""The objective's horizon: the nonlinearity measure against a loop over rollouts written
here, and a chaotic target whose final stage is cut to that horizon, checked against the
misfit itself evaluated on a line of parameter values."""

import dataclasses
import importlib
import tomllib
from pathlib import Path

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.cli import main
from jaxspring.fit.horizon import round_off_loss, smooth_horizon
from jaxspring.fit.objective import loss_function, target_data
from jaxspring.fit.plan import horizon_stage, needs_horizon, over_horizon
from jaxspring.fit.progress import FitProgress
from jaxspring.fit.settings import Stage
from jaxspring.io.fit_file import load_fit_progress, save_fit

jax.config.update("jax_enable_x64", True)
SCENES = Path(__file__).parents[1] / "scenes"
CHAIN_TRUTH = {"ks": 1000.0, "kd": 5.0, "cd": 0.05}
JELLY_TRUTH = {"ks": 250.0, "kd": 0.05}


def reference_nonlinearity(scene, obs, names, values, cloud, start, length):
    """sqrt(unexplained / explained) of a least-squares fit, with an intercept, of the
    positions over frames start+1 .. start+length against the cloud's offsets: every
    member simulated on its own."""
    rows = []
    for offset in cloud:
        params = scene.model.params_with(scene.params, {n: values[n] * np.exp(offset[i]) for i, n in enumerate(names)})
        state = js.State(x=obs.states.x[start], v=obs.states.v[start])
        x = js.rollout(scene.model, params, state, steps=length * obs.save_every, save_every=obs.save_every).x
        rows.append(np.asarray(x[1:, obs.particles]).reshape(-1))
    y = np.array(rows)
    design = np.column_stack([np.ones(len(cloud)), cloud])
    coefficients = np.linalg.lstsq(design, y, rcond=None)[0]
    fitted = design @ coefficients
    left = y - fitted
    explained = fitted - y.mean(axis=0)
    return np.sqrt(np.sum(left**2) / np.sum(explained**2))


def test_the_nonlinearity_matches_a_loop_over_rollouts(scenes):
    chain = scenes["chain"]
    obs = js.synthetic_observations(chain, CHAIN_TRUTH, steps=400, save_every=40)  # 10 frames after frame 0
    names = ["ks", "kd", "cd"]
    rng = np.random.default_rng(3)
    cloud = rng.normal(0.0, 0.6, size=(7, 3)) + 0.05  # not symmetric, not centred
    horizon = smooth_horizon(chain, obs, names, CHAIN_TRUTH, cloud=cloud, starts=3, limit=0.2)
    np.testing.assert_array_equal(horizon.starts, [0, 3, 6])
    crossing = horizon.total
    for row, start in enumerate(horizon.starts):
        for length in range(1, horizon.total - start + 1):
            expected = reference_nonlinearity(chain, obs, names, CHAIN_TRUTH, cloud, start, length)
            np.testing.assert_allclose(horizon.nonlinearity[row, length - 1], expected, rtol=1e-7)
            if expected > 0.2:
                crossing = min(crossing, max(length - 1, 1))
                break
        assert np.all(np.isnan(horizon.nonlinearity[row, horizon.total - start :]))  # past the target's end
    assert crossing < horizon.total  # the limit is crossed somewhere: the horizon is the first crossing
    assert horizon.frames == crossing


def test_a_smooth_target_keeps_its_whole_horizon(scenes):
    obs = js.synthetic_observations(scenes["chain"], CHAIN_TRUTH, steps=3000, save_every=30)
    horizon = smooth_horizon(scenes["chain"], obs, list(CHAIN_TRUTH), CHAIN_TRUTH)
    assert horizon.whole and horizon.frames == 100
    assert "over all 100 frames" in horizon.describe()


@pytest.fixture(scope="module")
def spinning_jelly():
    """A 3 x 3 x 3 jelly with the jelly scene's springs, ground and spin, dropped 0.3 m: it
    lands, bounces and tumbles for 1.5 s (full states recorded, no noise)."""
    data = tomllib.loads((SCENES / "jelly.toml").read_text())
    data["lattice"]["shape"], data["lattice"]["origin"] = [3, 3, 3], [0.0, 0.3, 0.0]
    scene = js.scene_from_dict(data)
    return scene, js.synthetic_observations(scene, JELLY_TRUTH, steps=1500, save_every=10)


def local_minima(scene, obs, stage, name):
    """Local minima of a stage's misfit along log(name) within +-10% of the truth (41 points)."""
    offsets = np.linspace(-0.1, 0.1, 41)
    theta = {n: jnp.full(offsets.size, np.log(v)) for n, v in JELLY_TRUTH.items()}
    theta[name] = theta[name] + offsets
    loss = jax.jit(jax.vmap(loss_function(scene, obs, list(JELLY_TRUTH), stage), in_axes=(0, None)))
    values = np.asarray(loss(theta, target_data(obs)))
    return [offsets[i] for i in range(1, offsets.size - 1) if values[i] < min(values[i - 1], values[i + 1])]


@pytest.mark.slow
def test_a_chaotic_target_is_fitted_over_the_horizon_its_misfit_is_smooth_over(spinning_jelly):
    scene, obs = spinning_jelly
    result = js.fit(scene, obs, ["ks", "kd"], init={"ks": 600.0, "kd": 0.02})  # auto: shooting, then the horizon
    for n, true in JELLY_TRUTH.items():
        assert abs(float(result.final[n]) / true - 1) < 1e-7, (n, result.final[n])
    first, final = result.stages
    assert first == Stage("shooting", 10)
    assert final.kind == "shooting" and 10 < final.frames < 150  # segments, longer than the warm-up's
    objective = result.identifiability.objective
    assert objective.startswith(f"the misfit over {150 // final.frames} segments of {final.frames} frames")
    assert "not over all 150" in objective and f"minimised: {objective}" in result.table()
    # the misfit itself, on a line of ks values within 10% of the truth: over the whole horizon it
    # has dips all along (a polish there can stop anywhere); over the final stage's segments one
    assert len(local_minima(scene, obs, Stage("direct", 150), "ks")) > 2
    assert local_minima(scene, obs, final, "ks") == [0.0]


def test_the_measured_horizon_is_kept_for_a_resumed_fit(tmp_path):
    progress = FitProgress(1, 3, {"ks": jnp.zeros(1)}, None, [np.zeros(1)] * 3, {"ks": [np.ones(1)] * 3}, [0, 0, 1])
    progress.horizon = 37
    save_fit(tmp_path / "f.h5", {"a": 1}, ["ks"], {"ks": 1.0}, progress)
    assert load_fit_progress(tmp_path / "f.h5", {"a": 1}, ["ks"]).horizon == 37
    with h5py.File(tmp_path / "f.h5", "a") as f:  # a fit that never measured one
        del f["fit/optimizer"].attrs["horizon"]
    assert load_fit_progress(tmp_path / "f.h5", {"a": 1}, ["ks"]).horizon is None
    with h5py.File(tmp_path / "f.h5", "a") as f:  # written before the plan's rules changed
        del f["fit/optimizer"].attrs["plan_version"]
    with pytest.raises(js.InputError, match="planned a fit's stages otherwise"):
        load_fit_progress(tmp_path / "f.h5", {"a": 1}, ["ks"])


def test_positions_only_targets_start_from_the_initial_state(scenes):
    obs = dataclasses.replace(js.synthetic_observations(scenes["chain"], CHAIN_TRUTH, 300, 30), states=None)
    horizon = smooth_horizon(scenes["chain"], obs, ["ks"], {"ks": 1000.0})
    np.testing.assert_array_equal(horizon.starts, [0])
    assert horizon.nonlinearity.shape == (1, 10) and horizon.whole


def test_the_final_stage_for_a_horizon():
    whole = Stage("ensemble", 150)
    assert over_horizon(whole, 150) == whole and over_horizon(whole, 400, recorded=False) == whole
    assert over_horizon(whole, 62) == Stage("shooting", 50)  # 3 equal segments, none longer than 62
    assert over_horizon(Stage("direct", 250), 62) == Stage("shooting", 50)  # 5 x 50
    assert over_horizon(Stage("direct", 200), 89) == Stage("shooting", 66)  # 3 x 66, 2 frames left out
    assert over_horizon(whole, 136, recorded=False, segment_frames=10) == Stage("free_shooting", 10)
    assert over_horizon(whole, 6, recorded=False, segment_frames=10) == Stage("free_shooting", 6)
    target = js.fitting.Observations(
        x=np.zeros((151, 1, 3)), particles=np.ones(1, int), save_every=1, initial_state=None
    )
    assert needs_horizon([Stage("shooting", 10), whole], target)
    assert needs_horizon([Stage("direct", 19), Stage("direct", 150)], target)
    assert not needs_horizon([whole], target) and not needs_horizon([Stage("free_shooting", 10)], target)
    recordings = dataclasses.make_dataclass("Recordings", [("shootable", bool, True)])()
    assert not needs_horizon([Stage("shooting", 10), whole], recordings)  # takes are fitted whole


def test_free_shooting_ends_a_positions_only_fit_only_where_it_can():
    """From positions alone the final stage would be free shooting, which leaves out segments
    that touch the ground and fits every particle's state per segment: a jelly resting on the
    plane, or seen at one corner, keeps its whole-horizon stage."""
    data = tomllib.loads((SCENES / "jelly.toml").read_text())
    data["lattice"]["shape"], data["lattice"]["origin"] = [2, 2, 2], [0.0, 0.0, 0.0]
    scene = js.scene_from_dict(data)
    obs = dataclasses.replace(js.synthetic_observations(scene, JELLY_TRUTH, 100, 10), states=None)
    whole = Stage("ensemble", 10)
    settings = js.FitSettings(segment_frames=5)
    assert horizon_stage(scene, [obs], ["ks"], settings, whole, 4) == whole
    # smooth throughout: the whole horizon, its first cloud no wider than the one measured smooth
    spread = min(settings.horizon_spread, settings.ensemble_spread)
    assert horizon_stage(scene, [obs], ["ks"], settings, whole, 10) == Stage("ensemble", 10, spread)
    up = np.array([0.0, 1.0, 0.0])  # the same motion 1 m up
    lifted = dataclasses.replace(
        obs, x=obs.x + up, initial_state=js.State(x=obs.initial_state.x + up, v=obs.initial_state.v)
    )
    assert horizon_stage(scene, [lifted], ["ks"], settings, whole, 4) == Stage("free_shooting", 4)
    assert horizon_stage(scene, [lifted, obs], ["ks"], settings, whole, 4) == whole  # one target on the ground
    corner = js.synthetic_observations(scene, JELLY_TRUTH, 100, 10, particles=[0])
    corner = dataclasses.replace(corner, x=corner.x + up, initial_state=lifted.initial_state)
    assert horizon_stage(scene, [corner], ["ks"], settings, whole, 4) == whole  # one of 8 particles seen


def test_a_cloud_member_that_blows_up_ends_the_smooth_stretch(scenes):
    obs = js.synthetic_observations(scenes["chain"], CHAIN_TRUTH, steps=400, save_every=40)
    cloud = np.array([[0.1], [-0.1], [0.05], [-0.05], [14.0]])  # ks e^14 times too stiff: unstable at dt
    horizon = smooth_horizon(scenes["chain"], obs, ["ks"], CHAIN_TRUTH, cloud=cloud, starts=1)
    assert np.isinf(horizon.nonlinearity[0, -1]) and horizon.frames < horizon.total
    still = smooth_horizon(scenes["chain"], obs, ["ks"], CHAIN_TRUTH, cloud=cloud[:4], starts=1)
    assert still.whole  # the same cloud without it


@pytest.mark.slow
def test_a_fit_cut_to_its_horizon_resumes_with_the_saved_one(scenes, monkeypatch):
    """The horizon is measured once; a fit resumed in its final stage reads it back and never
    measures again (a new measurement at other values could cut other segments)."""
    scene = scenes["mass_spring"]
    obs = js.synthetic_observations(scene, {"ks": 2.0}, steps=600, save_every=20)  # 30 frames
    settings = js.FitSettings(strategy="shooting", segment_frames=5)

    def unexpected(*args, **kwargs):
        raise AssertionError("the horizon was measured again")

    monkeypatch.setattr(importlib.import_module("jaxspring.fit.horizon"), "smooth_horizon", unexpected)
    theta = {"ks": jnp.log(jnp.array([2.2]))}
    progress = FitProgress(1, 0, theta, None, [], {"ks": []}, [], horizon=12)  # at the final stage's start
    resumed = js.fit_batch(scene, [obs], ["ks"], [{"ks": 3.0}], settings, progress=progress, identify=False)[0]
    assert resumed.stages == (Stage("shooting", 5), Stage("shooting", 10))  # 3 segments of at most 12 frames
    assert abs(float(resumed.final["ks"]) / 2.0 - 1) < 1e-8


def test_an_ensemble_stage_that_fits_to_round_off_stops(scenes):
    """Without noise the ensemble stage would shrink its cloud towards standard errors of
    zero for all its iterations; a loss at round-off ends it. A gradient stage there goes on
    to its own stopping rules (L-BFGS reaches far below that floor in float32)."""
    stop_rules = importlib.import_module("jaxspring.fit.gradient").converged
    obs = js.synthetic_observations(scenes["chain"], CHAIN_TRUTH, steps=100, save_every=10)
    floor = round_off_loss(scenes["chain"], obs)
    size = np.abs(obs.x).max()  # the chain reaches 19 m from its pin
    assert floor == pytest.approx((64 * np.finfo(np.float64).eps * size) ** 2)
    progress = FitProgress(1, 2, {}, None, [np.array([1.0]), np.array([floor / 2])], {}, [1, 1])
    ensemble = {"done": np.zeros(1)}  # an ensemble stage that has not finished
    assert stop_rules(progress, js.FitSettings(), True, ensemble, floor)
    progress.loss[-1] = np.array([floor * 2])
    assert not stop_rules(progress, js.FitSettings(), True, ensemble, floor)
    progress.stage = 2  # a new stage: the last stage's loss does not count
    progress.loss[-1] = np.array([floor / 2])
    assert not stop_rules(progress, js.FitSettings(), True, ensemble, floor)
    gradient = {"lbfgs": np.zeros(1)}  # a gradient stage's optimizer state
    progress.stage = 1
    progress.loss = [np.array([floor]), np.array([floor / 2])]  # still falling fast
    assert not stop_rules(progress, js.FitSettings(), True, gradient, floor)
    progress.last_step = np.array([1e-10])  # no value moved over its last two iterations
    assert stop_rules(progress, js.FitSettings(), True, gradient, floor)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["chain", "jelly"])
def test_a_float32_fit_without_noise_reaches_the_truth(tmp_path, capsys, name):
    """Measured: with the round-off loss (64 units of float32's precision of the chain's
    size) ending every stage, the float32 chain stopped at kd 2.6e-3 off; L-BFGS left to its
    own rules reaches 1.5e-4. The jelly's shooting stage (L-BFGS) stalled with kd 13% off, at
    a loss its line search could not resolve; Levenberg-Marquardt on the segments' residuals
    finishes it (kd 1.4e-5)."""
    experiment = Path(__file__).parents[1] / "fitting" / f"{name}.toml"
    # in-process, as a fresh `jaxspring fit --dtype float32` process runs it: without 64-bit types
    jax.config.update("jax_enable_x64", False)
    try:
        code = main(["fit", str(experiment), "--dtype", "float32", "--out", str(tmp_path / "c.fit.h5"), "--quiet"])
    finally:
        jax.config.update("jax_enable_x64", True)
    assert code == 0, capsys.readouterr().err
    truth = tomllib.loads(experiment.read_text())["target"]["true"]
    with h5py.File(tmp_path / "c.fit.h5", "r") as f:
        final = {n: float(np.asarray(v)) for n, v in f["fit"]["final"].attrs.items()}
    assert set(final) == set(truth)
    for parameter, value in truth.items():
        assert abs(final[parameter] / value - 1) < 1e-3, (parameter, final[parameter])


def test_an_ensemble_cloud_is_never_narrower_than_round_off_along_any_axis(scenes):
    """At a noise-free truth the standard errors vanish; the first cloud (3 standard errors)
    is held at the square root of the precision on every axis, not only on its widest: the
    residuals of a narrower axis differ by round-off and its slope measures nothing."""
    scene = scenes["chain"]
    names = ("ks", "kd", "cd")
    obs = js.synthetic_observations(scene, CHAIN_TRUTH, steps=100, save_every=10)
    theta = {n: jnp.log(jnp.array([CHAIN_TRUTH[n]])) for n in names}
    stage = Stage("ensemble", obs.frame_count - 1, spread=0.1)
    step, init = importlib.import_module("jaxspring.fit.ensemble").ensemble_step_function(
        scene, obs, names, stage, js.FitSettings(), False, theta
    )
    _, state, _ = step(theta, init(theta), target_data(obs))
    sizes = np.linalg.svd(np.asarray(state["spread"][0]), compute_uv=False)
    floor = np.sqrt(np.finfo(np.float64).eps)
    np.testing.assert_allclose(sizes, floor, rtol=1e-6)  # 3 standard errors of zero, lifted on each axis
