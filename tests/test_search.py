"""The start search for recordings (`fit.search`): its Latin hypercube by hand, the window cut
against the full target's loss over the same frames, and fits from 10x off either way that
end within 3% of the truth on same-model recordings (1 mm noise)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.fit.recording_loss import loss_function, target_data
from jaxspring.fit.search import latin_starts, window
from jaxspring.fit.settings import Stage

N = 5
SCENE = {
    "name": "rope",
    "dt": 0.002,
    "physics": {"ks": {"stretch": 300.0, "bend": 2.0}, "kd": 0.5, "cd": 0.02},
    "particles": {"x": [[0.1 * i, 0.0, 0.0] for i in range(N)], "mass": 0.03, "drag": True},
    "springs": [
        {"name": "stretch", "pairs": [[i, i + 1] for i in range(N - 1)]},
        {"name": "bend", "pairs": [[i, i + 2] for i in range(N - 2)]},
    ],
}
TRUTH = {"ks.stretch": 400.0, "cd": 0.05}


@pytest.fixture(scope="module")
def rope():
    return js.scene_from_dict(SCENE)


@pytest.fixture(scope="module")
def recordings(rope):
    """Two takes of 80 frames at 100 Hz with TRUTH, the first end swung, 1 mm noise."""
    rng = np.random.default_rng(3)
    params = rope.model.params_with(rope.params, TRUTH)
    out = []
    for k in range(2):
        t = np.arange(80) * 0.01
        end = np.asarray(rope.state.x)[[0]] + 0.06 * np.sin(2 * np.pi * (1.0 + 0.3 * k) * t)[:, None, None] * [
            1,
            1,
            0.5,
        ]
        drive = js.sim.Drive(particles=(0,), t=jnp.asarray(t), x=jnp.asarray(end))
        traj = js.rollout(rope.model, params, rope.state, steps=79 * 5, save_every=5, drive=drive)
        out.append(js.Recording(t=t, x=np.asarray(traj.x) + rng.normal(0.0, 1e-3, (80, N, 3))))
    return out


def test_latin_starts_cover_every_stratum_once_within_the_spread():
    init = {"a": 2.0, "b": 0.1, "c": 50.0}
    starts = latin_starts(init, 9, 10.0, seed=1)
    assert starts[0] == init and len(starts) == 9
    logs = np.array([[math.log(s[n] / init[n]) for n in init] for s in starts[1:]])  # (8, 3)
    assert np.all(np.abs(logs) <= math.log(10.0))
    strata = np.floor((logs / math.log(10.0) + 1) / 2 * 8).astype(int)
    for column in strata.T:
        assert sorted(column) == list(range(8))  # one draw per eighth of the log range
    assert latin_starts(init, 9, 10.0, seed=1)[4] == starts[4]  # deterministic


@pytest.mark.slow
def test_a_window_is_the_full_targets_first_frames(rope, recordings):
    target = js.recording_target(rope, recordings, driven=[0], start=2, smooth=3)
    cut = window(target, 20)
    assert cut.frame_count == 21 and list(cut.lengths) == [21, 21]
    np.testing.assert_array_equal(cut.x, target.x[:, :21])
    theta = {"ks.stretch": jnp.log(350.0), "cd": jnp.log(0.03)}
    whole = loss_function(rope, target, list(theta), Stage("direct", 20))(theta, target_data(target))
    short = loss_function(rope, cut, list(theta), Stage("direct", 20))(theta, target_data(cut))
    np.testing.assert_allclose(float(short), float(whole), rtol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("factor", [0.1, 10.0, 100.0])
def test_fits_from_ten_times_off_end_at_the_truth(rope, recordings, factor):
    """From 10x off either way, and from 100x too stiff and draggy for the time step to simulate
    (omega_max dt = 4.6 > 2 at ks 40000: the search draws its starts again 10x lower)."""
    target = js.recording_target(rope, recordings, driven=[0], start=2, smooth=3)
    init = {n: factor * v for n, v in TRUTH.items()}
    # judged on its answer and its search alone: no identifiability report needed
    result = js.fit(rope, target, list(TRUTH), init=init, iterations=60, identify=False)
    search = result.search
    assert search is not None and len(search.starts) == 8 and search.window == 10 and search.lengthened == 20
    assert (search.lowered > 0) == (factor == 100.0)
    assert search.found_loss <= search.given_loss  # the search's point is kept only when better
    assert search.used_search
    # every fitted point is ranked on the whole horizon, and the lowest is the fit's start
    assert len(search.found) == 2 and search.found_loss == min(search.found_losses)
    lowest = search.found[int(np.argmin(search.found_losses))]
    assert all(np.allclose(search.chosen[n], lowest[n]) for n in TRUTH)
    if factor == 100.0:
        assert not math.isfinite(search.given_loss)
        assert all(s["ks.stretch"] <= 1000 * TRUTH["ks.stretch"] for s in search.starts)
    for n, v in TRUTH.items():
        assert abs(float(result.final[n]) / v - 1) < 0.03, (n, result.final)
    assert result.initial["ks.stretch"] == pytest.approx(init["ks.stretch"])  # reported from the given start
    assert "start search: 8 starts" in result.table() and "moved from the initial values" in result.table()
    skipped = js.fit(rope, target, list(TRUTH), init=init, iterations=1, starts=1, identify=False)
    assert skipped.search is None


def test_bad_search_settings_fail_in_one_line(rope, recordings):
    target = js.recording_target(rope, recordings, driven=[0], start=2)
    for kwargs, words in [({"starts": 0}, "starts"), ({"start_spread": 0.5}, "start_spread")]:
        with pytest.raises(js.InputError, match=words):
            js.fit(rope, target, ["cd"], **kwargs)
