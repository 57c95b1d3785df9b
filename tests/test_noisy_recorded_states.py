"""Recorded states whose positions are noisy: their noise measured with segments' starts
fitted, against the variance drawn; fitting the starts removing the damping's bias; "auto"
going on to fit the starts where its answer leaves more than that noise, and not where it
does not; the decision kept in fit files."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.fit.plan import plan_stages
from jaxspring.fit.position_shooting import start_fitted_noise
from jaxspring.fit.progress import FitProgress
from jaxspring.io.fit_file import load_fit_progress, save_fit

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def noisy_small_jelly():
    """The small spinning jelly landing over 0.5 s, positions and velocities recorded, 1% noise
    on the positions (seed 1), and its truth."""
    experiment = js.load_experiment(Path(__file__).parents[1] / "fitting" / "cases" / "small_jelly_1s.toml")
    truth = {"ks": 250.0, "kd": 0.05}
    obs = js.synthetic_observations(experiment.scene, truth, steps=500, save_every=10, noise_relative=0.01, seed=1)
    return experiment.scene, obs, truth


@pytest.mark.slow
def test_the_noise_of_recorded_positions_is_measured_with_their_starts_fitted(noisy_small_jelly):
    """`start_fitted_noise` against the variance the noise was drawn with: within 10% at the
    truth and at kd 5x its truth (a short segment with fitted starts hardly sees kd), its
    degrees of freedom the data values less the fitted start values; on exact data, round-off;
    in float32 within 10% too."""
    scene, obs, truth = noisy_small_jelly
    for values in (truth, {**truth, "kd": 5 * truth["kd"]}):
        variance, freedom = start_fitted_noise(scene, obs, ["ks", "kd"], values)
        assert abs(variance / obs.noise_std**2 - 1) < 0.1, (values, variance / obs.noise_std**2)
        # segments 0, 2 and 4 of 5: 10, 10 and 11 frames (the last owns the end) of 27 free particles
        assert freedom == (10 + 10 + 11) * 27 * 3 - 3 * 27 * 3
    exact = js.synthetic_observations(scene, truth, steps=500, save_every=10)
    motion = np.sqrt(np.mean((np.asarray(exact.x) - np.asarray(exact.x)[:1]) ** 2))
    assert start_fitted_noise(scene, exact, ["ks", "kd"], truth)[0] < (1e-10 * motion) ** 2
    with jax.enable_x64(False):  # float32: central differences and solves to its precision
        scene32 = js.load_experiment(Path(__file__).parents[1] / "fitting" / "cases" / "small_jelly_1s.toml").scene
        obs32 = js.synthetic_observations(scene32, truth, steps=500, save_every=10, noise_relative=0.01, seed=1)
        assert np.asarray(obs32.x).dtype == np.float32
        variance, _ = start_fitted_noise(scene32, obs32, ["ks", "kd"], truth)
        assert abs(variance / obs32.noise_std**2 - 1) < 0.1, variance / obs32.noise_std**2


@pytest.fixture(scope="module")
def dense_segment_fit(noisy_small_jelly):
    """Segment 2's residual sum of squares with its start positions fitted by Gauss-Newton with
    the dense forward-mode Jacobian solved by NumPy's least squares, iterated to convergence,
    and before any step: the reference of both backends' fast fits (computed once)."""
    from jaxspring.fit.position_shooting import _recorded_segments, _segment_misfit

    scene, obs, truth = noisy_small_jelly
    seg = _recorded_segments(scene, obs, ["ks", "kd"], truth, 10)
    data = {key: value[2] for key, value in seg.data.items()}
    forward = scene.model.forward_mode()
    dense_params = forward.params_with(scene.params, {n: jnp.asarray(v) for n, v in truth.items()})
    particles, free = jnp.asarray(obs.particles), jnp.asarray(seg.free)

    def residual(s):
        return _segment_misfit(forward, dense_params, particles, free, s, data, 10, obs.save_every)

    s = np.zeros(free.size * 3)
    for _ in range(6):
        jac = np.asarray(jax.jacfwd(residual)(jnp.asarray(s)))
        s = s - np.linalg.lstsq(jac, np.asarray(residual(jnp.asarray(s))), rcond=None)[0]
    dense = float(np.sum(np.asarray(residual(jnp.asarray(s))) ** 2))
    before = float(np.sum(np.asarray(residual(jnp.zeros(free.size * 3))) ** 2))
    return dense, before


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["native", "jax"])
def test_a_segment_with_its_starts_fitted_matches_a_dense_least_squares_fit(
    noisy_small_jelly, dense_segment_fit, backend
):
    """One segment's residual sum of squares with its start positions fitted, solved without
    a Jacobian (central differences and reverse passes, conjugate gradients) on either
    backend, against Gauss-Newton with the dense forward-mode Jacobian solved by NumPy's
    least squares, iterated to convergence (`dense_segment_fit`)."""
    from jaxspring.fit.position_shooting import _recorded_segments, _start_fitted_squares

    scene, obs, truth = noisy_small_jelly
    scene = scene.with_backend(backend)
    if backend == "native" and not scene.model.stepper.name.startswith("native"):
        pytest.skip("native kernel not built here")  # CI builds it (tests/test_native.py)
    seg = _recorded_segments(scene, obs, ["ks", "kd"], truth, 10)
    data = {key: value[2] for key, value in seg.data.items()}
    model = scene.model
    params = model.params_with(scene.params, {n: jnp.asarray(v) for n, v in truth.items()})
    particles, free = jnp.asarray(obs.particles), jnp.asarray(seg.free)
    fast = float(_start_fitted_squares(model, params, particles, free, data, frames=10, every=obs.save_every))
    dense, before = dense_segment_fit
    assert dense < 0.9 * before  # the starts' noise was there to remove
    assert fast == pytest.approx(dense, rel=1e-6), (fast, dense, before)


@pytest.mark.slow
def test_fitting_noisy_recorded_start_positions_removes_their_bias(noisy_small_jelly):
    """The small spinning jelly landing over 0.5 s, positions and velocities recorded, 1% noise on
    the positions. Shooting from the recorded states as they are fits kd well above its truth
    (their noise sets off oscillations the damping is fitted to hide: measured +210% to +380%
    over seeds 0-2 at its least-squares minimum; the plan's shooting stage stops at 2.0x on
    this seed). Fitting the segments' start positions too ("position_shooting") brings every
    value within 2 of its reported standard errors of the truth (measured: ks 1.3, kd 0.3),
    the standard errors counting the starts as estimated, and the fitted starts nearer the
    clean states than the recorded ones (measured: 0.40 of their error)."""
    scene, obs, truth = noisy_small_jelly  # the same target (seed 1): its compiled stages are shared
    start = {"ks": 400.0, "kd": 0.1}
    result = js.fit(scene, obs, ["ks", "kd"], start, strategy="position_shooting")
    assert [s.kind for s in result.stages] == ["shooting", "position_shooting"]
    biased = result.value_history["kd"][int(np.sum(result.stage_of_iteration == 0))]  # where shooting ended
    assert biased > 1.5 * truth["kd"], biased
    report = result.identifiability
    assert report.objective.startswith(
        "multiple shooting: the misfit of 5 segments of 10 frames, each from its recorded"
    )
    for n in truth:
        z = np.log(float(result.final[n]) / truth[n]) / float(report.relative_standard_error[n])
        assert abs(z) < 2, (n, result.final[n], report.relative_standard_error[n])
    starts = result.estimated["segment_x"]  # fitted start positions: nearer the truth than the recorded ones
    clean = js.rollout(scene.model, scene.with_params(**truth).params, scene.state, steps=500, save_every=10).x
    frames = result.estimated["segment_frame"]
    # (segment 0 starts at the exact first frame)
    noisy_error = np.abs(np.asarray(obs.states.x)[frames] - np.asarray(clean)[frames])[1:].mean()
    fitted_error = np.abs(starts - np.asarray(clean)[frames])[1:].mean()
    assert fitted_error < 0.7 * noisy_error, (fitted_error, noisy_error)


def stopped_at_the_final_stage(scene, obs, values, on_iteration=None, identify=True, **settings):
    """A fit stopped at the start of the plan's final stage with `values`, its iterations
    spent, so that stage returns `values` and the fit decides what comes next; and the plan.
    `on_iteration` sees every checkpoint too; `identify=False` skips the identifiability
    report (for fits whose report is not looked at)."""
    settings = js.FitSettings(iterations=100, **settings)
    planned = plan_stages(obs, settings, scene, values=2)
    theta = {n: jnp.log(jnp.asarray([float(v)])) for n, v in values.items()}
    progress = FitProgress(1, settings.iterations, theta, None, [], {n: [] for n in values}, [])
    saved = []

    def checkpoint(p, stages):
        saved.append(p)
        if on_iteration:
            on_iteration(p, stages)

    result = js.fit_batch(
        scene, [obs], list(values), [values], settings, progress=progress, on_iteration=checkpoint, identify=identify
    )[0]
    return result, planned, saved[-1]


@pytest.mark.slow
def test_auto_fits_the_starts_when_the_answer_leaves_more_than_the_noise(noisy_small_jelly, tmp_path):
    """From kd 7x its truth (the whole horizon's misfit there exceeds the noise), "auto" adds a
    "position_shooting" stage and its answer comes within 3 standard errors of the truth; the
    fit file keeps the decision, so the finished fit read back has the same stages and answer.
    From the truth (the misfit is the noise), or with the strategy "shooting" named, the plan
    ends as planned."""
    scene, obs, truth = noisy_small_jelly
    wrong = {**truth, "kd": 7 * truth["kd"]}
    result, planned, progress = stopped_at_the_final_stage(scene, obs, wrong)
    assert [s.kind for s in planned] == ["shooting", "ensemble"]
    # the whole horizon measured smooth: the final stage runs over it, its answer is tested after
    assert [s.kind for s in result.stages] == ["shooting", "ensemble", "position_shooting"]
    report = result.identifiability
    assert report.objective.endswith(
        "left more misfit than the recorded positions' noise: their starts were fitted too)"
    )
    for n in truth:
        z = np.log(float(result.final[n]) / truth[n]) / float(report.relative_standard_error[n])
        assert abs(z) < 3, (n, result.final[n], report.relative_standard_error[n])
    assert progress.done and progress.refit_frames == 10
    save_fit(tmp_path / "fit.h5", {"a": 1}, list(truth), wrong, progress)
    loaded = load_fit_progress(tmp_path / "fit.h5", {"a": 1}, list(truth))
    again = js.fit_batch(scene, [obs], list(truth), [wrong], progress=loaded, identify=False)[0]
    assert again.stages[: len(result.stages)] == result.stages
    for n in truth:  # settled again from the recorded starts: the same answer, to a small part of its error
        shift = np.log(float(again.final[n]) / float(result.final[n]))
        assert abs(shift) < 0.1 * float(report.relative_standard_error[n]), (n, shift)
    for values, strategy in ((truth, "auto"), (wrong, "shooting")):
        result, planned, progress = stopped_at_the_final_stage(scene, obs, values, identify=False, strategy=strategy)
        assert [s.kind for s in result.stages] == [s.kind for s in planned[:1]] + [result.stages[1].kind]
        assert progress.refit_frames is None


@pytest.mark.slow
def test_auto_fits_the_starts_in_place_of_longer_segments_from_noisy_states(noisy_small_jelly, tmp_path):
    """Where the measured horizon is shorter than the target (a wide spread: 8 frames of 50),
    the final stage would be longer segments from the noisy recorded states, which leave
    their starts' noise whatever the answer: "auto" decides at the shooting answer and fits
    the starts in their place, from the truth as from kd 7x it, within 3 standard errors of
    the truth; a fit resumed from its file runs the same stages."""
    scene, obs, truth = noisy_small_jelly
    for values in (truth, {**truth, "kd": 7 * truth["kd"]}):
        decided = tmp_path / "decided.h5"  # the checkpoint written when the decision was taken

        def on_decision(p, _, decided=decided, values=values):
            if p.refit_frames and not p.done:
                save_fit(decided, {"a": 1}, list(truth), values, p)

        result, planned, progress = stopped_at_the_final_stage(
            scene, obs, values, horizon_spread=0.6, on_iteration=on_decision
        )
        assert [s.kind for s in planned] == ["shooting", "ensemble"]
        assert progress.horizon < 50 and progress.refit_frames == 10
        assert [(s.kind, s.frames) for s in result.stages] == [("shooting", 10), ("position_shooting", 10)]
        report = result.identifiability
        assert "the answer of the shooting stage over 10 frames left more misfit" in report.objective
        for n in truth:
            z = np.log(float(result.final[n]) / truth[n]) / float(report.relative_standard_error[n])
            assert abs(z) < 3, (n, values, result.final[n], report.relative_standard_error[n])
    for name in ("fit.h5", "decided.h5"):  # resumed finished, and from the decision
        if name == "fit.h5":
            save_fit(tmp_path / name, {"a": 1}, list(truth), values, progress)
        loaded = load_fit_progress(tmp_path / name, {"a": 1}, list(truth))
        assert loaded.refit_frames == 10 and loaded.done == (name == "fit.h5")
        settings = js.FitSettings(horizon_spread=0.6)
        again = js.fit_batch(scene, [obs], list(truth), [values], settings, progress=loaded, identify=False)[0]
        assert again.stages == result.stages
        for n in truth:  # the same answer, to a small part of its error
            shift = np.log(float(again.final[n]) / float(result.final[n]))
            assert abs(shift) < 0.1 * float(report.relative_standard_error[n]), (name, n, shift)
