"""`predict`, bands, `[evaluate]` and `--resume` keep their promises on hostile input: no file
replaced that predict did not write, a blow-up is an error or a reported instability (never
frames "not seen"), bands from the stable draws only, a resumed fit refuses changed inputs, and
every refusal comes before any file or folder is made."""

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.cli import main
from jaxspring.io.recording import matched_by_name

N = 4
ROPE = {
    "name": "rope",
    "dt": 0.002,
    "physics": {"ks": {"stretch": 300.0}, "kd": {"stretch": 0.5}, "cd": 0.02},
    "particles": {"x": [[0.1 * i, 0.0, 0.0] for i in range(N)], "mass": 0.03, "drag": True},
    "springs": [{"name": "stretch", "pairs": [[i, i + 1] for i in range(N - 1)]}],
}
SCENE_TOML = (
    'name = "rope"\ndt = 0.002\n[physics]\nks = { stretch = 300.0 }\nkd = { stretch = 0.5 }\ncd = 0.02\n'
    f"[particles]\nx = {ROPE['particles']['x']}\nmass = 0.03\ndrag = true\n"
    f'[[springs]]\nname = "stretch"\npairs = {ROPE["springs"][0]["pairs"]}\n'
)
FRAMES = 30


def _recordings(count, seed=0):
    """Takes of the rope with both ends swung (100 Hz, 0.5 mm noise)."""
    scene = js.scene_from_dict(ROPE)
    params = scene.model.params_with(scene.params, {"ks.stretch": 400.0})
    rng = np.random.default_rng(seed)
    rest = np.asarray(scene.state.x)[[0, N - 1]]
    t = np.arange(FRAMES) * 0.01
    out = []
    for _ in range(count):
        ends = rest + rng.uniform(0.02, 0.05, (2, 3)) * np.sin(2 * np.pi * t[:, None, None])
        drive = js.sim.Drive(particles=(0, N - 1), t=jnp.asarray(t), x=jnp.asarray(ends))
        traj = js.rollout(scene.model, params, scene.state, steps=(FRAMES - 1) * 5, save_every=5, drive=drive)
        out.append(js.Recording(t=t, x=np.asarray(traj.x) + rng.normal(0.0, 5e-4, (FRAMES, N, 3))))
    return out


EXPERIMENT = """scene = "rope.toml"
[target]
recordings = ["take*.h5"]
driven = [0, 3]
start = 1
[fit]
params = ["ks.stretch"]
init = { "ks.stretch" = 300.0 }
strategy = "direct"
iterations = 4
"""


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A folder with two training takes, a held-out take, the experiment and its finished fit."""
    folder = tmp_path_factory.mktemp("predict")
    for i, rec in enumerate(_recordings(3)):
        js.save_recording(folder / ("held.h5" if i == 2 else f"take{i}.h5"), rec)
    (folder / "rope.toml").write_text(SCENE_TOML)
    (folder / "exp.toml").write_text(EXPERIMENT)
    assert main(["fit", str(folder / "exp.toml"), "--out", str(folder / "rope.fit.h5"), "--quiet"]) == 0
    return folder


def _snapshot(folder):
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _refused(argv, capsys, words):
    assert main(argv) == 2
    error = capsys.readouterr().err.strip()
    assert words in error and "\n" not in error, error
    return error


@pytest.mark.slow
def test_predict_never_replaces_a_file_it_did_not_write(fitted, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "held.h5").write_bytes((fitted / "take0.h5").read_bytes())  # a training take of the same name
    before = _snapshot(tmp_path)
    fit = str(fitted / "rope.fit.h5")
    _refused(["predict", fit, str(fitted / "held.h5"), "--out-dir", str(out)], capsys, "was not written by")
    assert _snapshot(tmp_path) == before
    # its own earlier output it replaces (predicting twice into one folder works)
    fresh = tmp_path / "fresh"
    for _ in range(2):
        assert main(["predict", fit, str(fitted / "held.h5"), "--out-dir", str(fresh), "--quiet"]) == 0
    capsys.readouterr()
    with h5py.File(fresh / "held.h5") as f:
        assert f.attrs["writer"] == "jaxspring predict"
    # a picture that is not its own is not replaced either
    (fresh / "errors.png").write_bytes(b"\x89PNG not ours")
    before = _snapshot(tmp_path)
    _refused(["predict", fit, str(fitted / "held.h5"), "--out-dir", str(fresh)], capsys, "errors.png")
    assert _snapshot(tmp_path) == before


def test_a_prediction_that_blows_up_is_an_error_not_frames_unseen(fitted, tmp_path, capsys):
    held = js.load_recording(fitted / "held.h5")
    glitch = np.array(held.x)
    glitch[12, 0] += 1e9  # a driven marker jumps by a distance no simulation survives (drag blows up)
    js.save_recording(tmp_path / "glitch.h5", js.Recording(t=held.t, x=glitch))
    out = tmp_path / "out"
    _refused(
        ["predict", str(fitted / "rope.fit.h5"), str(tmp_path / "glitch.h5"), "--out-dir", str(out)],
        capsys,
        "glitch: the prediction blew up at frame",
    )
    assert not out.exists()  # and no empty folder left behind
    scene = js.scene_from_dict(ROPE)
    with pytest.raises(js.BlowUpError, match="blew up at frame"):  # past the stability limit, in Python
        js.predict(scene, {"ks.stretch": 1.2e4}, [held], driven=[0, 3])
    fine = js.predict(scene, {"ks.stretch": 400.0}, [held], driven=[0, 3])[0]
    assert np.isfinite(fine.x).all() and fine.mean_distance < 0.5 * fine.frozen_distance


def test_bands_come_from_the_stable_draws_and_need_sixteen(fitted, capsys):
    scene = js.scene_from_dict(ROPE)
    held = js.load_recording(fitted / "held.h5")
    # this rope at dt 2 ms blows up between ks.stretch 1.0e4 and 1.2e4 N/m (tried): a log spread
    # of 1 around 1e4 puts about half the draws past it
    covariance = {"names": ["ks.stretch"], "matrix": np.array([[1.0]])}
    (p,) = js.predict(scene, {"ks.stretch": 1.0e4}, [held], driven=[0, 3], covariance=covariance, samples=64)
    assert 0 < p.band_unstable < 64 and p.band_draws == 64
    assert np.isfinite(p.low).all() and np.isfinite(p.high).all()
    assert np.all(p.low <= p.high) and 0.0 <= p.coverage <= 1.0
    with pytest.raises(js.InputError, match="cannot make a 95% band"):
        js.predict(scene, {"ks.stretch": 400.0}, [held], driven=[0, 3], covariance=covariance, samples=4)
    with pytest.warns(UserWarning, match="rests on"):  # too few stable draws: said, not hidden
        js.predict(scene, {"ks.stretch": 1.0e4}, [held], driven=[0, 3], covariance=covariance, samples=16)
    fit = str(fitted / "rope.fit.h5")
    for bands in ("1", "15"):
        _refused(["predict", fit, str(fitted / "held.h5"), "--out-dir", "never", "--bands", bands], capsys, "16")


def test_resume_refuses_changed_recordings_naming_the_file(fitted, capsys):
    argv = ["fit", str(fitted / "exp.toml"), "--out", str(fitted / "rope.fit.h5"), "--quiet", "--resume"]
    assert main(argv) == 0  # unchanged inputs: the finished fit is read back
    capsys.readouterr()
    take, scene = (fitted / "take1.h5").read_bytes(), (fitted / "rope.toml").read_text()
    try:
        js.save_recording(fitted / "take1.h5", _recordings(1, seed=7)[0])
        before = _snapshot(fitted)
        _refused(argv, capsys, "take1.h5")
        assert _snapshot(fitted) == before
        (fitted / "take1.h5").write_bytes(take)
        (fitted / "rope.toml").write_text(scene.replace("mass = 0.03", "mass = 0.04"))
        _refused(argv, capsys, "scene")
    finally:
        (fitted / "take1.h5").write_bytes(take)
        (fitted / "rope.toml").write_text(scene)


def test_evaluate_recordings_are_checked_before_the_fit(fitted, tmp_path, capsys):
    short = js.Recording(t=np.arange(FRAMES) * 0.01, x=np.zeros((FRAMES, N - 1, 3)))  # a marker short
    js.save_recording(fitted / "wrong.h5", short)
    experiment = fitted / "eval.toml"
    experiment.write_text(EXPERIMENT + '[evaluate]\nrecordings = ["wrong.h5"]\n')
    out = tmp_path / "never.fit.h5"
    error = _refused(["fit", str(experiment), "--out", str(out), "--quiet"], capsys, "wrong.h5")
    assert "evaluate" in error
    assert not out.exists() and not out.with_suffix(".png").exists()


@pytest.mark.parametrize(
    "change, words",
    [
        ({"smooth": 20}, "window of 41 frames is longer than take0 (30 frames)"),
        ({"smooth": -1}, "smooth: must be >= 0"),
        ({"smooth": 2.5}, "whole number"),
        ({"start": 1.5}, "whole number"),
        ({"driven": [0, 3, 3]}, "names particle 3 twice"),
        ({"driven": [0, 1, 2, 3], "fit_start": True}, "no start state is left to fit"),
        ({"driven": [0, 1, 2, 3], "fit_driven": True}, "fit_driven"),
    ],
)
def test_settings_that_cannot_mean_anything_are_refused(change, words):
    scene = js.scene_from_dict(ROPE)
    recordings = _recordings(2)
    settings = {"driven": [0, 3], "start": 1, "smooth": 0, **change}
    with pytest.raises(js.InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
        js.recording_target(scene, recordings, names=("take0", "take1"), **settings)


def test_times_in_nanoseconds_are_refused_in_one_line(tmp_path, capsys):
    scene = js.scene_from_dict(ROPE)
    rec = _recordings(1)[0]
    nanoseconds = js.Recording(t=1.7e18 + rec.t * 1e9, x=rec.x)
    with pytest.raises(js.InputError, match="give frame times in seconds"):
        js.recording_target(scene, [nanoseconds], driven=[0, 3])
    js.save_recording(tmp_path / "take0.h5", nanoseconds)
    (tmp_path / "rope.toml").write_text(SCENE_TOML)
    (tmp_path / "exp.toml").write_text(EXPERIMENT)
    _refused(["fit", str(tmp_path / "exp.toml"), "--out", str(tmp_path / "x.fit.h5")], capsys, "take0 spans")
    assert not (tmp_path / "x.fit.h5").exists()


def test_markers_are_matched_by_name_not_by_column():
    """The same takes with their marker columns shuffled give the same target and prediction."""
    scene = js.scene_from_dict(ROPE)
    names = ("left", "a", "b", "right")
    named = [js.Recording(t=r.t, x=r.x, markers=names) for r in _recordings(2)]
    order = [2, 3, 0, 1]
    shuffled = [js.Recording(t=r.t, x=r.x[:, order], markers=tuple(names[k] for k in order)) for r in named]
    plain = js.recording_target(scene, named, driven=[0, 3])
    mixed = js.recording_target(scene, [named[0], shuffled[1]], driven=[0, 3])
    np.testing.assert_array_equal(mixed.x, plain.x)
    assert mixed.marker_names == names
    first = js.predict(scene, {"ks.stretch": 400.0}, [named[1]], driven=[0, 3], marker_names=names)[0]
    again = js.predict(scene, {"ks.stretch": 400.0}, [shuffled[1]], driven=[0, 3], marker_names=names)[0]
    np.testing.assert_array_equal(again.x, first.x)
    assert again.marker_names == names
    other = js.Recording(t=named[1].t, x=named[1].x, markers=("left", "a", "c", "right"))
    with pytest.raises(js.InputError, match="names its markers left, a, c, right; expected left, a, b, right"):
        js.recording_target(scene, [named[0], other], driven=[0, 3])


@pytest.mark.parametrize(
    "change, words",
    [
        ({"driven": (0, 4)}, "marker 4 is outside -4..3"),
        ({"driven": (0, 1.5)}, "whole number"),
        ({"driven": (0, 3, -1)}, "names marker 3 twice"),
        ({"driven": (True, 3)}, "whole number"),
        ({"subdivide": 2.5}, "whole number"),
        ({"reference": (5, 0)}, "recording 5 is outside 0..1"),
        ({"reference": (0, 99)}, "frame 99 is outside 0..29"),
        ({"reference": (0, -1)}, "frame -1 is outside"),
        ({"reference": 3}, "give (recording, frame)"),
    ],
)
def test_cable_scene_checks_every_index_up_front(change, words):
    recordings = _recordings(2)
    with pytest.raises(js.InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
        js.cable_scene(recordings, **{"driven": (0, 3), **change})


def test_cable_scene_refuses_coincident_markers_and_quotes_any_name():
    recordings = _recordings(2)
    stuck = [js.Recording(t=r.t, x=np.concatenate([r.x[:, :2], r.x[:, 1:]], axis=1)) for r in recordings]
    with pytest.raises(js.InputError, match="markers 1 and 2 are at one place"):
        js.cable_scene(stuck, driven=(0, -1))
    name = 'two\nlines "quoted" \\ and a tab\t'
    cable = js.cable_scene(recordings, driven=(0, -1), name=name)
    text = cable.toml()
    scene = js.scene_from_dict(__import__("tomllib").loads(text))
    assert scene.name == name
    np.testing.assert_allclose(np.asarray(scene.state.x), np.asarray(cable.scene["particles"]["x"]), rtol=1e-15)


def test_marker_names_decide_the_columns_even_when_they_look_like_defaults():
    rec = _recordings(1)[0]
    swapped = js.Recording(t=rec.t, x=rec.x[:, [1, 0, 2, 3]], markers=("m1", "m0", "m2", "m3"))
    (back,) = matched_by_name([swapped], ("s",), ("m0", "m1", "m2", "m3"))
    np.testing.assert_array_equal(back.x, rec.x)
    named = js.Recording(t=rec.t, x=rec.x, markers=("a", "b", "c", "d"))
    (same,) = matched_by_name([named], ("n",), ("m0", "m1", "m2", "m3"))  # unnamed fit: by column
    np.testing.assert_array_equal(same.x, rec.x)


def test_a_band_spreads_a_value_the_data_do_not_determine_as_far_as_the_cap():
    scene = js.scene_from_dict(ROPE)
    held = _recordings(3)[2]
    bands = {}
    for label, variance in [("inf", np.inf), ("nan", np.nan), ("capped", 1e6)]:
        covariance = {"names": ["ks.stretch"], "matrix": np.array([[variance]])}
        (p,) = js.predict(scene, {"ks.stretch": 300.0}, [held], driven=[0, 3], covariance=covariance, samples=16)
        bands[label] = p.high - p.low
    assert np.max(bands["capped"]) > 1e-3  # a log spread of 1 moves the markers
    np.testing.assert_array_equal(bands["inf"], bands["capped"])
    np.testing.assert_array_equal(bands["nan"], bands["capped"])


def test_a_fit_that_blows_up_is_an_error_and_leaves_no_file(fitted, tmp_path, capsys):
    experiment = fitted / "unstable.toml"
    experiment.write_text(EXPERIMENT.replace('"ks.stretch" = 300.0', '"ks.stretch" = 1e7'))
    out = tmp_path / "unstable.fit.h5"
    _refused(["fit", str(experiment), "--out", str(out), "--quiet"], capsys, "the fit blew up")
    assert not out.exists() and not out.with_suffix(".png").exists()


def test_damaged_fit_files_and_dangling_links_are_one_line(fitted, tmp_path, capsys):
    held = str(fitted / "held.h5")
    for damage in ("no fit group", "prediction not JSON", "value missing", "negative value"):
        broken = tmp_path / f"{damage.replace(' ', '_')}.fit.h5"
        broken.write_bytes((fitted / "rope.fit.h5").read_bytes())
        with h5py.File(broken, "r+") as f:
            if damage == "no fit group":
                del f["fit"]
            elif damage == "prediction not JSON":
                f.attrs["prediction"] = "{not json"
            elif damage == "value missing":
                del f["fit/final"].attrs["ks.stretch"]
            else:
                f["fit/final"].attrs["ks.stretch"] = -5.0
        _refused(["predict", str(broken), held, "--out-dir", str(tmp_path / "out")], capsys, str(broken))
    link = tmp_path / "dangling"
    link.symlink_to(tmp_path / "nowhere" / "x")
    _refused(["predict", str(fitted / "rope.fit.h5"), held, "--out-dir", str(link)], capsys, "link to nothing")
    assert not (tmp_path / "out").exists() and not (tmp_path / "nowhere").exists()


def test_recordings_too_large_or_too_far_are_refused_before_reading(tmp_path):
    bomb = tmp_path / "bomb.h5"
    with h5py.File(bomb, "w") as f:  # a small file holding a dataset of terabytes
        f.attrs.update(format="jaxspring.recording", format_version=1)
        f.create_dataset("t", shape=(10**6,), dtype=float, chunks=(1000,))
        f.create_dataset("x", shape=(10**6, 10**5, 3), dtype=float, chunks=(1, 10, 3))
    assert bomb.stat().st_size < 10**6
    with pytest.raises(js.InputError, match="of memory"):
        js.load_recording(bomb)
    x = np.zeros((3, 2, 3))
    x[1, 1, 0] = 1e300
    with pytest.raises(js.InputError, match="frame 1, marker 'm1'.*more than 1e\\+12 m"):
        js.Recording(t=[0.0, 0.01, 0.02], x=x)


def test_one_file_named_twice_is_fitted_once(tmp_path):
    from jaxspring.io.experiment import recording_paths

    for name in ("take0.h5", "take1.h5"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "link.h5").symlink_to(tmp_path / "take0.h5")
    found = recording_paths(["take*.h5", str(tmp_path / "take0.h5"), "link.h5"], tmp_path, "target.recordings")
    assert [p.rsplit("/", 1)[-1] for p in found] == ["take0.h5", "take1.h5"]


def test_a_cable_through_markers_in_a_line_spaced_one_to_two_is_finite():
    t = np.arange(5) * 0.01
    for x in ([[0, 0, 0], [1, 0, 0], [3, 0, 0]], [[0, 0, 0], [1, 0, 0], [3, 0, 0], [4, 0, 0]]):
        marks = np.array(x, float)
        cable = js.cable_scene(
            [js.Recording(t=t, x=np.repeat(marks[None], 5, 0))], driven=(0, -1), subdivide=3, gravity=(0, -9.81, 0)
        )
        positions = np.array(cable.scene["particles"]["x"])
        assert np.isfinite(positions).all()
        np.testing.assert_allclose(positions[cable.markers], marks, atol=1e-12)  # through every marker


def test_a_band_too_large_for_memory_and_a_marker_count_mismatch_are_one_line(fitted, tmp_path, capsys):
    out = tmp_path / "out"
    _refused(
        [
            "predict",
            str(fitted / "rope.fit.h5"),
            str(fitted / "held.h5"),
            "--out-dir",
            str(out),
            "--bands",
            "10" + "0" * 12,
        ],
        capsys,
        "of memory",
    )
    assert not out.exists()
    rec = _recordings(1)[0]
    js.save_recording(tmp_path / "three.h5", js.Recording(t=rec.t, x=rec.x[:, :3]))
    _refused(
        ["predict", str(fitted / "rope.fit.h5"), str(tmp_path / "three.h5"), "--out-dir", str(out)], capsys, "three"
    )
    scene = js.scene_from_dict(ROPE)
    with pytest.raises(js.InputError, match="short has 3 markers but long has 4"):
        js.recording_target(scene, [rec, js.Recording(t=rec.t, x=rec.x[:, :3])], names=("long", "short"), driven=[0])
