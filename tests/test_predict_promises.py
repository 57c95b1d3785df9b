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
        drive = js.Drive(particles=(0, N - 1), t=jnp.asarray(t), x=jnp.asarray(ends))
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
    glitch[12, 0] += 1e200  # a driven marker jumps by a distance no simulation survives
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
