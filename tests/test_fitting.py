"""Parameter identification: recovery on every fitting/ experiment, uncertainty, batches, the CLI, resume."""

import copy
import importlib.util
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.cli import main
from jaxspring.fit.identifiability import identifiability_report
from jaxspring.fit.objective import misfit_function, target_data

ROOT = Path(__file__).resolve().parent.parent
EXPERIMENTS = sorted(p.stem for p in (ROOT / "fitting").glob("*.toml"))


def test_every_seed_scene_has_an_experiment():
    assert EXPERIMENTS == ["chain", "cloth", "jelly", "mass_spring"]


def test_success_map_cases_are_experiments_with_a_possible_draw():
    """Each success-map case is an experiment file (users run any case with `jaxspring fit`): its
    truth lies in the range the benchmark draws from, its start is 1/3-3x away, and only the
    `_velocities` cases record velocities."""
    spec = importlib.util.spec_from_file_location("success_map", ROOT / "benchmarks" / "success_map.py")
    success_map = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(success_map)
    cases = ROOT / "fitting" / "cases"
    assert sorted(success_map.RANGES) == sorted(p.stem for p in cases.glob("*.toml"))
    for name, ranges in success_map.RANGES.items():
        experiment = js.load_experiment(cases / f"{name}.toml")
        assert sorted(experiment.params) == sorted(ranges), name
        assert experiment.velocities == name.endswith("_velocities"), name
        for n, (low, high) in ranges.items():
            assert low <= experiment.true_values[n] <= high, (name, n)
            assert 1 / 3 <= experiment.init[n] / experiment.true_values[n] <= 3, (name, n)


# With 1% observation noise the cloth's spring damping is not determined by its positions:
# the Gauss-Newton (Cramer-Rao) standard error of kd is several times kd itself (damping
# ratio kd / (2 sqrt(ks m)) = 0.0035). No estimator can reach 5% there; the fit must say so.
POORLY_DETERMINED_WITH_NOISE = {("cloth", "kd")}


@pytest.fixture(scope="module")
def experiments():
    return {name: js.load_experiment(ROOT / "fitting" / f"{name}.toml") for name in EXPERIMENTS}


@pytest.mark.slow
@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_recovers_parameters_without_noise(experiments, name):
    experiment = experiments[name]
    truth = experiment.true_values
    for n in experiment.params:  # the start is a factor >= 2 away from the truth
        ratio = experiment.init[n] / truth[n]
        assert ratio >= 2 or ratio <= 0.5
    result = js.fit(  # judged on its answer alone: no identifiability report needed
        experiment.scene,
        experiment.observations(),
        experiment.params,
        experiment.init,
        experiment.settings,
        identify=False,
    )
    assert set(result.relative_errors()) == set(experiment.params)
    for n, error in result.relative_errors().items():
        assert error < 0.01, (n, error)


@pytest.mark.slow
@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_with_one_percent_noise(experiments, name):
    experiment = experiments[name].replace(noise=0.01)
    truth = experiment.true_values
    target = experiment.observations()
    result = js.fit(experiment.scene, target, experiment.params, experiment.init, experiment.settings)
    # each plan's answer explains the data to their noise: none goes on to fit the starts
    assert "position_shooting" not in [s.kind for s in result.stages], result.stages
    report = result.identifiability
    for n, error in result.relative_errors().items():
        se = float(report.standard_error[n])
        assert abs(float(result.final[n]) - truth[n]) <= 3 * se, (n, result.final[n], truth[n], se)  # covered
        if (name, n) in POORLY_DETERMINED_WITH_NOISE:
            assert any(w.startswith(f"{n} is poorly determined") for w in report.warnings), report.warnings
        else:  # within 5%, or within one standard error where the data do not determine 5%
            assert error < max(0.05, se / truth[n]), (n, error, se / truth[n])
    # the answer is not rejected against the truth by a likelihood-ratio test at three standard
    # deviations: its misfit exceeds the truth's by at most 9 noise variances (contact terraces
    # keep a fit from the exact least-squares minimum; that is all they may cost)
    misfit = misfit_function(experiment.scene, target, list(experiment.params), target.frame_count - 1)
    data = target_data(target)

    def squares(values):
        return float(jnp.sum(misfit({n: jnp.log(jnp.asarray(float(values[n]))) for n in experiment.params}, data) ** 2))

    excess = (squares(result.final) - squares(truth)) / target.noise_std**2
    assert excess <= 9.0, excess


@pytest.mark.slow
def test_ensemble_stage_finds_the_least_squares_fit_of_a_smooth_loss():
    """On a smooth loss the smoothed Gauss-Newton stage must land where the gradient fit does.

    Mass on a spring, 5 s, 2% noise: both fits start from the experiment's guess;
    the ensemble stage's answer (no gradients, loss smoothed at the standard errors)
    must agree with L-BFGS's least-squares minimum to a small fraction of a standard error.
    """
    experiment = js.load_experiment(ROOT / "fitting" / "mass_spring.toml")
    obs = experiment.replace(noise=0.02).observations()
    fits = {  # only the gradient fit's standard errors are used
        kind: js.fit(
            experiment.scene, obs, ["ks", "kd"], experiment.init, strategy="direct", ensemble=kind, identify=identify
        )
        for kind, identify in (("gradient", True), ("ensemble", False))
    }
    assert [s.kind for s in fits["ensemble"].stages] == ["ensemble"]
    se = fits["gradient"].identifiability.standard_error
    for n in ("ks", "kd"):
        gap = abs(float(fits["ensemble"].final[n]) - float(fits["gradient"].final[n]))
        assert gap < 0.1 * float(se[n]), (n, fits["ensemble"].final[n], fits["gradient"].final[n], se[n])
    assert fits["ensemble"].final_loss <= fits["gradient"].final_loss * (1 + 1e-3)


def test_ensemble_stage_started_near_an_exact_answer_finds_it_in_a_few_steps():
    """A small spinning jelly landing over 0.5 s, exact data, a start 1e-8 from the truth: the
    first cloud is a few standard errors wide, so the stage comes to the truth in a few
    steps. (With the 30% default cloud it spent all 60 iterations and never moved: the
    smoothed loss of motions the data rule out has its minimum elsewhere.)"""
    experiment = js.load_experiment(ROOT / "fitting" / "cases" / "small_jelly_1s.toml").replace(steps=500)
    truth = experiment.true_values
    start = {n: truth[n] * (1 + 1e-8) for n in ("ks", "kd")}
    settings = js.FitSettings(strategy="direct", ensemble="ensemble", iterations=60)
    result = js.fit(experiment.scene, experiment.observations(), ["ks", "kd"], start, settings, identify=False)
    assert [s.kind for s in result.stages] == ["ensemble"]
    assert result.iterations <= 15, result.iterations
    for n, error in result.relative_errors().items():
        assert abs(error) < 1e-10, (n, error)


def test_ensemble_stage_resumes_exactly():
    """An ensemble stage interrupted mid-way continues from its saved state to the same numbers."""
    experiment = js.load_experiment(ROOT / "fitting" / "mass_spring.toml").replace(steps=1000, save_every=20)
    obs = experiment.replace(noise=0.02).observations()
    args = (experiment.scene, [obs], ["ks", "kd"], [experiment.init])
    options = dict(strategy="direct", ensemble="ensemble", identify=False)
    whole = js.fit_batch(*args, **options)[0]
    assert whole.iterations > 6
    saved = []

    class Stop(Exception):
        pass

    def interrupt(progress, stages):
        if progress.iteration == 5:
            saved.append(copy.deepcopy(progress))
            raise Stop

    with pytest.raises(Stop):
        js.fit_batch(*args, on_iteration=interrupt, **options)
    resumed = js.fit_batch(*args, progress=saved[0], **options)[0]
    np.testing.assert_array_equal(resumed.loss_history, whole.loss_history)
    for n in ("ks", "kd"):
        assert float(resumed.final[n]) == float(whole.final[n])


def test_gauss_newton_standard_error_matches_hand_calculation():
    """One particle on a spring, no gravity, only ks fitted: check s^2 (J^T J)^-1 against finite differences."""
    scene = js.scene_from_dict(
        {
            "dt": 0.001,
            "physics": {"ks": 20.0, "kd": 0.3, "gravity": [0.0, 0.0, 0.0]},
            "particles": {"x": [[0, 0, 0], [1.5, 0, 0]], "pinned": [0]},
            "springs": {"pairs": [[0, 1]], "rest_length": [1.0]},
        }
    )
    model = scene.model
    obs = js.synthetic_observations(scene, {"ks": 20.0}, steps=400, save_every=20, noise_relative=0.02, seed=3)
    report = js.identifiability(scene, obs, ["ks"], {"ks": 20.0})

    def residuals(ks):
        x = js.rollout(model, scene.params.replace(ks=ks), obs.initial_state, steps=400, save_every=20).x
        return (np.asarray(x)[1:, obs.particles] - obs.x[1:]).reshape(-1)

    h = 1e-6
    jac = (residuals(20.0 * np.exp(h)) - residuals(20.0 * np.exp(-h))) / (2 * h)  # d r / d log ks
    r = residuals(20.0)
    sigma2 = r @ r / (r.size - 1)
    expected = 20.0 * np.sqrt(sigma2 / (jac @ jac))
    assert float(report.standard_error["ks"]) == pytest.approx(expected, rel=1e-5)


@pytest.mark.slow
def test_standard_error_counts_the_noise_of_recorded_segment_starts():
    """Segments from noisy recorded states: s^2 (J^T J)^-1 plus the starts' noise carried to the
    answer, s_x^2 (J^T J)^-2 (J^T J_x)^2, both Jacobians by finite differences of rollouts."""
    scene = js.scene_from_dict(
        {
            "dt": 0.001,
            "physics": {"ks": 20.0, "kd": 0.3, "gravity": [0.0, 0.0, 0.0]},
            "particles": {"x": [[0, 0, 0], [1.5, 0.2, 0]], "pinned": [0]},
            "springs": {"pairs": [[0, 1]], "rest_length": [1.0]},
        }
    )
    obs = js.synthetic_observations(scene, {"ks": 20.0}, steps=400, save_every=20, noise_relative=0.02, seed=3)
    report = identifiability_report(scene, obs, ["ks"], {"ks": 20.0}, segment=5)  # 4 segments of 5 frames
    states = np.asarray(obs.states.x)

    def residuals(ks, starts):
        out = []
        for k, x0 in enumerate(starts):
            start = js.State(x=x0, v=obs.states.v[5 * k])
            x = js.rollout(scene.model, scene.params.replace(ks=ks), start, steps=100, save_every=20).x
            out.append(np.asarray(x)[1:, obs.particles] - obs.x[5 * k + 1 : 5 * k + 6])
        return np.concatenate(out).reshape(-1)

    starts = states[0:20:5]
    h = 1e-6
    jac = (residuals(20.0 * np.exp(h), starts) - residuals(20.0 * np.exp(-h), starts)) / (2 * h)
    columns = []
    for k in range(4):
        for axis in range(3):  # the free particle's start position; the pinned one is known
            step = np.zeros_like(starts)
            step[k, 1, axis] = h
            columns.append((residuals(20.0, starts + step) - residuals(20.0, starts - step)) / (2 * h))
    cross = jac @ np.stack(columns, axis=1)  # J^T J_x
    r = residuals(20.0, starts)
    plain = (r @ r / (r.size - 1)) / (jac @ jac)
    extra = obs.noise_std**2 * (cross @ cross) / (jac @ jac) ** 2
    assert extra > 0.1 * plain  # the starts' noise matters here
    assert float(report.relative_standard_error["ks"]) == pytest.approx(np.sqrt(plain + extra), rel=1e-4)


def test_warns_when_a_parameter_does_not_affect_the_data():
    # drag only on the pinned particle: cd changes nothing that moves
    doc = {
        "dt": 0.001,
        "steps": 200,
        "save_every": 20,
        "physics": {"ks": 50.0, "kd": 0.5, "cd": 0.1},
        "particles": {"x": [[0, 0, 0], [1, 0, 0], [2, 0, 0]], "pinned": [0], "drag": [True, False, False]},
        "springs": {"pairs": [[0, 1], [1, 2]]},
    }
    scene = js.scene_from_dict(doc)
    obs = js.synthetic_observations(scene, {}, steps=200, save_every=20)
    report = js.identifiability(scene, obs, ["ks", "cd"], {"ks": 50.0, "cd": 0.1})
    assert any("cd is not identifiable" in w for w in report.warnings), report.warnings
    assert "the other standard errors hold cd fixed at 0.1: they leave out its uncertainty" in report.warnings
    assert not any(w.startswith("ks") for w in report.warnings)


def test_confounded_and_poorly_determined_parameters_are_reported():
    # 0.06 s of a falling chain with 1% noise: the springs barely stretch, ks and kd trade off
    experiment = js.load_experiment(ROOT / "fitting" / "chain.toml")
    obs = js.synthetic_observations(
        experiment.scene, experiment.true_values, steps=60, save_every=6, noise_relative=0.01
    )
    report = js.identifiability(experiment.scene, obs, ["ks", "kd", "cd"], experiment.true_values)
    assert report.names == ("cd", "kd", "ks")
    assert abs(report.correlation[1, 2]) > 0.95
    assert any(w.startswith("kd and ks are confounded") for w in report.warnings), report.warnings
    assert any(w.startswith("ks is poorly determined") for w in report.warnings), report.warnings
    # a longer window separates them again
    long = js.synthetic_observations(
        experiment.scene, experiment.true_values, steps=1000, save_every=10, noise_relative=0.01
    )
    report = js.identifiability(experiment.scene, long, ["ks", "kd", "cd"], experiment.true_values)
    assert not any("ks" in w for w in report.warnings), report.warnings


def test_rough_loss_is_flagged(experiments):
    """Contact makes the noisy jelly's loss rough: the report must say its standard errors are unreliable."""
    jelly = experiments["jelly"].replace(noise=0.01)
    report = js.identifiability(jelly.scene, jelly.observations(), jelly.params, jelly.true_values)
    assert any(w.startswith("kd: the loss is not smooth") for w in report.warnings), report.warnings
    chain = experiments["chain"].replace(noise=0.01)  # smooth: no such warning
    report = js.identifiability(chain.scene, chain.observations(), chain.params, chain.true_values)
    assert not any("not smooth" in w for w in report.warnings), report.warnings


@pytest.mark.slow
def test_multi_start_and_multi_target_batches():
    experiment = js.load_experiment(ROOT / "fitting" / "chain.toml")
    scene = experiment.scene
    short = experiment.replace(steps=300, save_every=10)
    obs = short.observations()
    inits = [{"ks": 400.0, "kd": 10.0}, {"ks": 3000.0, "kd": 2.0}]
    results = js.fit_batch(scene, [obs], ["ks", "kd"], inits, identify=False)
    assert len(results) == 2
    for r, init in zip(results, inits):
        assert float(r.initial["ks"]) == init["ks"]
        assert r.relative_errors()["ks"] < 1e-3 and r.relative_errors()["kd"] < 1e-3
    # two targets with different truths, fitted at once from one start each
    targets = [short.replace(true_values={**short.true_values, "ks": k}).observations() for k in (700.0, 1400.0)]
    results = js.fit_batch(scene, targets, ["ks", "kd"], [{"ks": 2000.0, "kd": 2.0}] * 2, identify=False)
    assert float(results[0].final["ks"]) == pytest.approx(700.0, rel=1e-3)
    assert float(results[1].final["ks"]) == pytest.approx(1400.0, rel=1e-3)


@pytest.mark.slow
def test_gauss_newton_polish_finishes_a_stopped_fit(experiments):
    experiment = experiments["chain"]
    obs = experiment.observations()
    rough = js.fit(experiment.scene, obs, experiment.params, experiment.init, iterations=4, identify=False)
    assert max(rough.relative_errors().values()) > 1e-3  # four L-BFGS iterations are not enough
    polished = js.fit(
        experiment.scene, obs, experiment.params, experiment.init, iterations=4, polish=True, identify=False
    )
    assert polished.stages[-1].kind == "gauss_newton"
    assert max(polished.relative_errors().values()) < 1e-6
    assert np.all(np.diff(polished.loss_history[polished.stage_of_iteration.size - 1 :]) <= 0)


@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["curriculum", "shooting"])
def test_long_horizon_strategies(strategy):
    experiment = js.load_experiment(ROOT / "fitting" / "chain.toml").replace(steps=3000, save_every=30)
    obs = experiment.observations()
    result = js.fit(experiment.scene, obs, ["ks", "kd"], {"ks": 2500.0, "kd": 2.0}, strategy=strategy, identify=False)
    assert len(result.stages) > 1 and result.stages[-1].frames == 100  # smooth: ends on the whole horizon
    assert max(result.relative_errors().values()) < 0.01


def test_auto_strategy_choice(scenes):
    chain, jelly = scenes["chain"], scenes["jelly"]
    settings = js.FitSettings()
    from jaxspring.fit.plan import plan_stages

    assert [s.kind for s in plan_stages(js.synthetic_observations(chain, {}, 500, 10), settings, chain)] == ["direct"]
    long = js.synthetic_observations(chain, {}, 3000, 30)
    assert [s.kind for s in plan_stages(long, settings, chain)] == ["shooting", "direct"]
    partial = js.synthetic_observations(chain, {}, 3000, 30, particles=[19])
    assert [s.kind for s in plan_stages(partial, settings, chain)] == ["direct"] * 4
    touching = js.synthetic_observations(jelly, {}, 700, 7)
    assert [s.kind for s in plan_stages(touching, settings, jelly, values=2)] == ["shooting", "ensemble"]
    many = plan_stages(touching, settings, jelly, values=9)  # too many values for a cloud: gradient stages only
    assert [s.kind for s in many] == ["shooting", "direct"]
    assert [s.kind for s in plan_stages(long, js.FitSettings(ensemble="ensemble"), chain)] == ["shooting", "ensemble"]
    positions = js.FitSettings(strategy="position_shooting")
    assert [(s.kind, s.frames) for s in plan_stages(long, positions, chain)] == [
        ("shooting", 10),
        ("position_shooting", 10),
    ]


CUSTOM = """
name = "tripod"
dt = 0.001
steps = 400
save_every = 10
[physics]
ks = [300.0, 300.0, 300.0, 150.0, 150.0, 150.0]
kd = 0.8
cd = 0.02
[particles]
x = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.0, 0.9], [0.5, -0.8, 0.3]]
v = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, -0.5]]
pinned = [0, 1, 2]
[springs]
pairs = [[0, 1], [1, 2], [2, 0], [0, 3], [1, 3], [2, 3]]
"""


@pytest.fixture(scope="module")
def custom_recording(tmp_path_factory):
    """Written once for the module's CLI tests, which only read it (or a copy)."""
    folder = tmp_path_factory.mktemp("tripod")
    scene_file = folder / "tripod.toml"
    scene_file.write_text(CUSTOM.replace("ks = [300.0, 300.0, 300.0, 150.0, 150.0, 150.0]", "ks = 150.0"))
    recording = folder / "tripod.h5"
    assert main(["run", str(scene_file), "--out", str(recording), "--quiet", "--dtype", "float64"]) == 0
    return recording


@pytest.mark.slow
def test_cli_fits_any_trajectory_file(tmp_path, custom_recording, capsys):
    out = tmp_path / "tripod.fit.h5"
    code = main(
        [
            "fit",
            "--target",
            str(custom_recording),
            "--params",
            "ks,kd,cd",
            "--init",
            "ks=400,kd=2,cd=0.06",
            "--out",
            str(out),
            "--quiet",
        ]
    )
    text = capsys.readouterr().out
    assert code == 0, text
    assert "file values" in text and "rel. diff." in text and "std. error" in text  # not "true": the file's own values
    with h5py.File(out) as f:
        assert f.attrs["format"] == "jaxspring.fit"
        final = dict(f["fit/final"].attrs)
        assert final["ks"] == pytest.approx(150.0, rel=1e-4)
        assert final["kd"] == pytest.approx(0.8, rel=1e-4)
        assert final["cd"] == pytest.approx(0.02, rel=1e-3)
        assert f["fit/history/loss"].shape[0] == f["fit/history/ks"].shape[0] > 3
        assert dict(f["fit/initial"].attrs)["ks"] == 400.0
    assert (tmp_path / "tripod.fit.png").stat().st_size > 1000


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--params", "ks,kg"], ["no parameter 'kg'"]),
        (["--params", "ks", "--init", "ks=-3"], ["init.ks", "> 0"]),
        (["--params", "ks", "--init", "ks=0"], ["init.ks", "> 0"]),
        (["--params", "gravity"], ["cannot be fitted"]),
    ],
)
def test_cli_fit_bad_input(tmp_path, custom_recording, capsys, extra, words):
    out = tmp_path / "bad.fit.h5"
    code = main(["fit", "--target", str(custom_recording), "--out", str(out), "--quiet"] + extra)
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    for word in words:
        assert word in err
    assert not out.exists()


def test_cli_fit_rejects_mismatched_and_nan_targets(tmp_path, custom_recording, capsys):
    # a chain experiment against a 4-particle recording
    code = main(
        [
            "fit",
            str(ROOT / "fitting" / "chain.toml"),
            "--target",
            str(custom_recording),
            "--out",
            str(tmp_path / "x.h5"),
            "--quiet",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "4 particles but the scene has 20" in err and len(err.strip().splitlines()) == 1
    nan_file = tmp_path / "nan.h5"
    nan_file.write_bytes(custom_recording.read_bytes())
    with h5py.File(nan_file, "r+") as f:
        x = f["trajectory/x"][()]
        x[3, 3, 1] = np.nan
        f["trajectory/x"][...] = x
    code = main(
        [
            "fit",
            "--target",
            str(nan_file),
            "--params",
            "ks",
            "--init",
            "ks=100",
            "--out",
            str(tmp_path / "y.h5"),
            "--quiet",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "NaN" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "y.h5").exists()


def _fit_args(experiment, out, *extra):
    return ["fit", str(experiment), "--out", str(out), "--quiet", "--checkpoint-every", "1", *extra]


def _fit_command(experiment, out, *extra):
    return [sys.executable, "-m", "jaxspring", *_fit_args(experiment, out, *extra)]


def _short_chain_experiment(folder):
    experiment = folder / "chain_short.toml"
    experiment.write_text(
        (ROOT / "fitting" / "chain.toml")
        .read_text()
        .replace('scene = "../scenes/chain.toml"', 'scene = "chain"')
        .replace("steps = 1000", "steps = 600")
        .replace("save_every = 10", "save_every = 6")
        .replace("noise = 0.0", "noise = 0.01")
    )
    return experiment


@pytest.fixture(scope="module")
def uninterrupted_fit(tmp_path_factory):
    """The short chain fit run through without a stop (in-process: the reference is not about
    the process), once for both signals."""
    folder = tmp_path_factory.mktemp("whole")
    whole = folder / "whole.fit.h5"
    assert main(_fit_args(_short_chain_experiment(folder), whole)) == 0
    return whole


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupted_fit_resumes_to_the_same_result(tmp_path, uninterrupted_fit, sig):
    experiment = _short_chain_experiment(tmp_path)
    whole = uninterrupted_fit

    parts = tmp_path / "parts.fit.h5"
    process = subprocess.Popen(
        _fit_command(experiment, parts), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    deadline = time.time() + 300
    iterations = 0
    while time.time() < deadline and process.poll() is None:
        if parts.exists():
            try:
                with h5py.File(parts, "r") as f:
                    iterations = f["fit/history/loss"].shape[0]
            except OSError:
                iterations = 0
            if iterations >= 4:
                break
        time.sleep(0.05)
    assert process.poll() is None, "the fit ended before it could be interrupted"
    process.send_signal(sig)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert "--resume" in err
    with h5py.File(parts, "r") as f:  # a valid checkpoint, not the finished fit
        assert not f.attrs["done"]
        stopped_at = f["fit/history/loss"].shape[0]
    assert stopped_at >= iterations
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary files left

    assert main(_fit_args(experiment, parts, "--resume")) == 0  # resumed in-process
    with h5py.File(whole, "r") as a, h5py.File(parts, "r") as b:
        assert b.attrs["done"]
        np.testing.assert_array_equal(a["fit/history/loss"][()], b["fit/history/loss"][()])
        for name in ("ks", "kd", "cd"):
            assert a["fit/final"].attrs[name] == b["fit/final"].attrs[name]
            np.testing.assert_array_equal(a[f"fit/history/{name}"][()], b[f"fit/history/{name}"][()])


@pytest.mark.slow  # on its own it runs the short chain fit it is refused against (the fixture)
def test_resume_refuses_a_different_fit(uninterrupted_fit, capsys):
    # the finished short chain fit, resumed with another iteration count: the refusal is about
    # the settings, before any fitting, and leaves the file as it was
    experiment = uninterrupted_fit.parent / "chain_short.toml"
    before = uninterrupted_fit.read_bytes()
    capsys.readouterr()
    assert main(_fit_args(experiment, uninterrupted_fit, "--iterations", "4", "--resume")) == 2
    err = capsys.readouterr().err
    assert "different fit" in err and "iterations" in err
    assert uninterrupted_fit.read_bytes() == before


def test_a_fit_never_returns_a_point_worse_than_one_it_passed():
    """Adam with a step far too large jumps around the answer: its last point is worse than
    points it saw. The stage ends on its best point, and the plan on the best of its stages on
    the final loss; two starts in one batch, each judged on its own."""
    experiment = js.load_experiment(ROOT / "fitting" / "chain.toml")
    obs = experiment.replace(steps=200, save_every=10).observations()
    inits = [{"ks": 400.0, "kd": 10.0}, {"ks": 3000.0, "kd": 2.0}]
    settings = js.FitSettings(optimizer="adam", learning_rate=1.5, clip=10.0, iterations=12, strategy="direct")
    results = js.fit_batch(experiment.scene, [obs], ["ks", "kd"], inits, settings, identify=False)
    went_back = 0
    for result in results:
        seen = result.loss_history[:-1]
        assert result.loss_history[-1] == pytest.approx(np.nanmin(seen), rel=1e-12)
        went_back += np.nanmin(seen) < seen[-1]  # its last point was not its best one
        i = int(np.nanargmin(seen))
        for n in ("ks", "kd"):  # the answer is the best point's values
            assert float(result.final[n]) == pytest.approx(float(result.value_history[n][i]), rel=1e-12)
    assert went_back  # for at least one start the last point was not the best


def test_the_best_stage_wins_on_the_final_loss():
    """Stages judged on the final objective by a loss written in the test: stage 1 walked away
    from where stage 0 left it (log ks 0.1 from the optimum at 0; stage 1 ended at 2.0)."""
    from jaxspring.fit.gradient import best_of_stages
    from jaxspring.fit.progress import FitProgress

    values = {
        "ks": [np.array([np.exp(3.0)]), np.array([np.exp(1.0)]), np.array([np.exp(0.1)]), np.array([np.exp(1.5)])]
    }
    progress = FitProgress(2, 0, {"ks": jnp.array([2.0])}, None, [np.ones(1)] * 4, values, [0, 0, 1, 1])
    theta, loss = best_of_stages(progress, ("ks",), lambda th, data: th["ks"] ** 2, None)
    np.testing.assert_allclose(theta["ks"], [0.1], rtol=1e-12)
    np.testing.assert_allclose(loss, [0.01], rtol=1e-12)


def test_identifiability_where_the_simulation_overflows_warns_instead_of_failing():
    """A fit can end where the time step only just simulates: the derivatives overflow. The report
    then has infinite standard errors and says why, rather than raising from the eigensolver."""
    scene = js.scene_from_dict(
        {
            "dt": 0.5,  # far past the stable step of ks = 1e6 on 1 kg: the rollout overflows
            "physics": {"ks": 1e6, "kd": 0.0, "gravity": [0.0, 0.0, 0.0]},
            "particles": {"x": [[0, 0, 0], [1.5, 0, 0]], "pinned": [0]},
            "springs": {"pairs": [[0, 1]], "rest_length": [1.0]},
        }
    )
    obs = js.synthetic_observations(scene.with_values({"ks": 1e-3}), {"ks": 1e-3}, steps=400, save_every=20)
    report = js.identifiability(scene, obs, ["ks"], {"ks": 1e6})
    assert np.isinf(float(report.standard_error["ks"]))
    assert any("not finite" in w for w in report.warnings), report.warnings
