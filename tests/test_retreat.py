"""A stage that stops early goes on from softer values where they are lower (`fit.retreat`):
the choice per member against a quadratic by hand, and through `js.fit` on a mass-spring chain
made to stop after two iterations."""

import importlib
import math

import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.fit.gradient import RETREAT_FACTORS, RETREAT_GAIN, retreat
from jaxspring.fit.progress import FitProgress
from jaxspring.io.fit_file import load_fit_progress, save_fit

stages = importlib.import_module("jaxspring.fit.stages")


def test_retreat_picks_the_lowest_softer_point_per_member():
    """loss = sum over ks, kd of (log value - log target)^2 + gravity's: each member's target
    sits at its own factor of the current values; "gravity" and the fitted start are kept."""
    current = {"ks": 100.0, "kd": 2.0}
    # member 0: truth 0.9x (-> 0.9); 1: at the truth (stays); 2: 0.95x (0.97 is nearer in log than 0.9);
    # 3: 0.999x, below RETREAT_GAIN's reach (0.97 is further than the point itself)
    factors = np.array([0.9, 1.0, 0.95, 0.999])
    targets = {n: np.log(v * factors) for n, v in current.items()}
    theta = {
        "ks": jnp.full(4, math.log(current["ks"])),
        "kd": jnp.full(4, math.log(current["kd"])),
        "gravity": jnp.full(4, 0.3),
        "start": jnp.zeros((4, 2, 6)),
    }

    def value(th, _):
        return sum((th[n] - targets[n]) ** 2 for n in ("ks", "kd")) + (th["gravity"] - 0.3) ** 2

    progress = FitProgress(0, 0, dict(theta), None, [], {}, [])
    moved = retreat(progress, ["ks", "kd", "gravity"], value, None)
    np.testing.assert_array_equal(moved, [True, False, True, False])
    expected = np.array([0.9, 1.0, 0.97, 1.0])
    for n, v in current.items():
        np.testing.assert_allclose(np.exp(np.asarray(progress.theta[n])), v * expected, rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(progress.theta["gravity"]), 0.3)
    np.testing.assert_array_equal(np.asarray(progress.theta["start"]), 0.0)
    # the gain rule by hand: member 2 at 0.97 loses 2 (log(0.97/0.95))^2 from 2 (log(1/0.95))^2
    before, after = 2 * math.log(1 / 0.95) ** 2, 2 * math.log(0.97 / 0.95) ** 2
    assert after <= (1 - RETREAT_GAIN) * before
    assert RETREAT_FACTORS[0] == 0.97


def test_retreat_leaves_a_stage_without_stiffness_alone():
    progress = FitProgress(0, 0, {"gravity": jnp.zeros(2)}, None, [], {}, [])
    moved = retreat(progress, ["gravity"], lambda th, _: (th["gravity"] - 1.0) ** 2, None)
    assert not moved.any()


@pytest.fixture(scope="module")
def chain_target():
    scene = js.scene_from_dict(
        {
            "name": "chain",
            "dt": 0.002,
            "physics": {"ks": 200.0, "kd": 0.2},
            "particles": {"x": [[0.0, -0.1 * i, 0.0] for i in range(4)], "mass": 0.05, "pinned": [0]},
            "springs": [{"pairs": [[i, i + 1] for i in range(3)]}],
        }
    )
    return scene, js.synthetic_observations(scene, {"ks": 200.0, "kd": 0.2}, 150, 10)


# A step tolerance no step can beat stops the stage after two iterations from 1.6x the truth.
# Both tests below judge this one fit (the second as the uninterrupted reference): run once.
STOPPING = dict(strategy="direct", step_tolerance=1e9, iterations=12, polish=False, identify=False)
START = {"ks": 320.0, "kd": 0.32}


@pytest.fixture(scope="module")
def retreating_fit(chain_target):
    """The fit with retreats, and the ks it stood at after each iteration."""
    scene, target = chain_target
    stops = []
    result = js.fit_batch(
        scene,
        [target],
        ["ks", "kd"],
        [START],
        on_iteration=lambda p, _: stops.append(np.exp(float(p.theta["ks"][0]))),
        **STOPPING,
    )[0]
    return result, stops


def test_fit_goes_on_from_softer_values_after_an_early_stop(chain_target, retreating_fit, monkeypatch):
    """A step tolerance no step can beat stops the stage after two iterations from 1.6x the
    truth; the retreat restarts it from exactly 0.97x or 0.9x the point it stopped at, and
    the fit ends lower than the same fit without retreats."""
    scene, target = chain_target
    result, stops = retreating_fit
    assert result.retreats, result.table()
    assert "went on from softer values" in result.table()
    for i in result.retreats:
        ratio = result.value_history["ks"][i] / stops[i - 1]
        assert min(abs(ratio - f) for f in RETREAT_FACTORS) < 1e-9, ratio
    monkeypatch.setattr(stages, "RETREATS", 0)
    plain = js.fit(scene, target, ["ks", "kd"], init=START, **STOPPING)
    assert not plain.retreats and plain.iterations == 2
    assert result.final_loss < plain.final_loss


def test_a_fit_resumed_after_a_retreat_goes_on_as_an_uninterrupted_one(chain_target, retreating_fit, tmp_path):
    """Interrupted two iterations after its retreat, saved to a fit file and resumed from it, the fit
    repeats the uninterrupted one's iterations and retreats exactly (the stage's retreats
    are counted from the file, not started again)."""
    scene, target = chain_target
    args = (scene, [target], ["ks", "kd"], [START])
    options = STOPPING
    whole = retreating_fit[0]  # the same fit, run through without a stop
    assert whole.retreats

    class Stop(Exception):
        pass

    def interrupt(progress, stages):
        if progress.retreats and len(progress.loss) == progress.retreats[0][0] + 2:
            save_fit(tmp_path / "f.fit.h5", {"a": 1}, ["ks", "kd"], args[3][0], progress)
            raise Stop

    with pytest.raises(Stop):
        js.fit_batch(*args, on_iteration=interrupt, **options)
    progress = load_fit_progress(tmp_path / "f.fit.h5", {"a": 1}, ["ks", "kd"])
    assert [i for i, _ in progress.retreats] == [whole.retreats[0]]
    resumed = js.fit_batch(*args, progress=progress, **options)[0]
    assert resumed.retreats == whole.retreats
    np.testing.assert_allclose(resumed.loss_history, whole.loss_history, rtol=1e-12)
