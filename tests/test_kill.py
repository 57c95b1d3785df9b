"""SIGKILL during writes: `jaxspring run` and `jaxspring fit` killed at random moments leave
the destination absent, the old complete file or the new complete file, never a half file;
`fit --resume` after every kill ends with exactly the uninterrupted result."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

import jaxspring as js

KILLS = 4  # each kill is a process start-up: 4 of each (2 for predict), their moments stratified (`_moment`)
pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")


@pytest.fixture(autouse=True)
def own_compilation_cache(tmp_path_factory, monkeypatch):
    """The processes killed here get a compilation cache of their own: a kill may land while
    one writes an entry, which must not reach the other tests' processes."""
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path_factory.mktemp("compilation-cache")))


def _start(*args, cwd):
    return subprocess.Popen(
        [sys.executable, "-m", "jaxspring", *args], cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )


def _timed(*args, cwd) -> float:
    clock = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "jaxspring", *args], cwd=cwd, capture_output=True, timeout=600)
    assert done.returncode == 0, done.stderr.decode()[-2000:]
    return time.perf_counter() - clock


def _moment(rng, kill, kills, low, high) -> float:
    """The `kill`-th of `kills` kill moments, as a fraction of a run's duration: drawn uniformly
    in the kill-th of `kills` equal parts of [low, high], so that the kills together span the
    whole range (start-up, compiling, the work, the final write) however few they are."""
    width = (high - low) / kills
    return low + width * (kill + rng.uniform())


def _kill_after(process, seconds) -> tuple[bool, float]:
    """SIGKILL `process` after `seconds` unless it ended; whether it was killed, and when it
    ended [s] (a process that loads what an earlier one compiled ends sooner than timed)."""
    clock = time.perf_counter()
    try:
        process.wait(timeout=seconds)
        return False, time.perf_counter() - clock
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGKILL)
        process.wait()
        return True, time.perf_counter() - clock


@pytest.mark.slow
def test_run_killed_at_random_moments_leaves_an_old_or_new_complete_file(tmp_path, capsys):
    from jaxspring.cli import main

    rng = np.random.default_rng(3)
    run = ["run", "mass_spring", "--steps", "3000", "--save-every", "10", "--out", "out.h5", "--quiet"]
    # the old file, written in this process (a process start-up saved): any complete earlier output
    out = str(tmp_path / "out.h5")
    assert main(["run", "mass_spring", "--steps", "1000", "--save-every", "10", "--out", out, "--quiet"]) == 0
    old = (tmp_path / "out.h5").read_bytes()
    duration = _timed(*run, cwd=tmp_path)
    new = (tmp_path / "out.h5").read_bytes()
    (tmp_path / "out.h5").write_bytes(old)
    kills = outcomes = 0
    while kills < KILLS:
        killed, ended = _kill_after(_start(*run, cwd=tmp_path), _moment(rng, kills, KILLS, 0.5, 1.05) * duration)
        kills += killed
        duration = duration if killed else min(duration, ended)
        now = (tmp_path / "out.h5").read_bytes()
        assert now in (old, new) or _complete(tmp_path / "out.h5", 301)
        outcomes += now == new
        (tmp_path / "out.h5").write_bytes(old)
    assert main([*run[:-3], "--out", out, "--quiet"]) == 0  # a later write removes what killed writes left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.h5"]
    with capsys.disabled():  # the count shows in CI's log
        print(f"\nkill test, run: {kills} kills, {outcomes} ended with the new file")


def _complete(path: Path, frames: int) -> bool:
    _, trajectory = js.load_trajectory(path)
    return trajectory.x.shape[0] == frames


@pytest.mark.slow
def test_fit_killed_at_random_moments_resumes_to_the_uninterrupted_result(tmp_path, capsys):
    rng = np.random.default_rng(5)
    experiment = tmp_path / "exp.toml"
    experiment.write_text(
        'scene = "mass_spring"\n[target]\nsteps = 400\nsave_every = 10\nnoise = 0.01\n'
        '[fit]\nparams = ["ks", "kd"]\ninit = { ks = 25.0, kd = 0.02 }\niterations = 40\n'
    )  # kills land in start-up, compiling (or loading what the first run compiled), iterations and the final write
    fit = ["fit", "exp.toml", "--quiet", "--checkpoint-every", "1"]
    duration = _timed(*fit, "--out", "straight.h5", cwd=tmp_path)
    kills = 0
    while kills < KILLS:
        resume = ["--resume"] if (tmp_path / "killed.h5").exists() else []
        killed, ended = _kill_after(
            _start(*fit, "--out", "killed.h5", *resume, cwd=tmp_path), _moment(rng, kills, KILLS, 0.35, 0.9) * duration
        )
        kills += killed
        if (tmp_path / "killed.h5").exists():
            with h5py.File(tmp_path / "killed.h5") as f:  # every file on disk is complete and readable
                assert "fit" in f and "config" in f.attrs
            if not killed:  # finished before the kill: start over to place the next kill
                (tmp_path / "killed.h5").unlink()
                duration = min(duration, ended) if not resume else duration
    resume = ["--resume"] if (tmp_path / "killed.h5").exists() else []
    _timed(*fit, "--out", "killed.h5", *resume, cwd=tmp_path)
    assert _final(tmp_path / "killed.h5") == _final(tmp_path / "straight.h5")
    assert not [p.name for p in tmp_path.iterdir() if ".tmp" in p.name]  # killed writes' leftovers removed
    with capsys.disabled():
        print(f"\nkill test, fit: {kills} kills, resumed to the uninterrupted result")


def _final(path: Path) -> dict:
    with h5py.File(path) as f:
        assert bool(f.attrs["done"])
        return {k: json.dumps(np.asarray(v).tolist()) for k, v in f["fit/final"].attrs.items()}


@pytest.mark.slow
def test_predict_killed_at_random_moments_leaves_only_complete_predictions(tmp_path, capsys):
    """`predict` killed anywhere leaves each output absent or complete (never a half file, never
    a stray temporary one), and run again into the same folder it replaces only its own files."""
    from test_predict_promises import EXPERIMENT, SCENE_TOML, _recordings

    from jaxspring.cli import main

    rng = np.random.default_rng(11)
    takes = _recordings(3)
    for i, rec in enumerate(takes):
        js.save_recording(tmp_path / (f"held{i}.h5" if i else "take0.h5"), rec)
    (tmp_path / "rope.toml").write_text(SCENE_TOML)
    (tmp_path / "exp.toml").write_text(EXPERIMENT)
    assert main(["fit", str(tmp_path / "exp.toml"), "--out", str(tmp_path / "rope.fit.h5"), "--quiet"]) == 0
    inputs = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    predict = ["predict", "rope.fit.h5", "held1.h5", "held2.h5", "--out-dir", "pred", "--bands", "16", "--quiet"]
    duration = _timed(*predict, cwd=tmp_path)
    expected = {name: js.load_recording(tmp_path / "pred" / name).x for name in ("held1.h5", "held2.h5")}
    kills = 0
    while kills < KILLS // 2:
        killed, ended = _kill_after(
            _start(*predict, cwd=tmp_path), _moment(rng, kills, KILLS // 2, 0.3, 1.0) * duration
        )
        kills += killed
        duration = duration if killed else min(duration, ended)
        for path in (tmp_path / "pred").iterdir():  # every file there is complete (or a killed write's leftover)
            if path.suffix == ".h5" and ".tmp" not in path.name:
                np.testing.assert_array_equal(js.load_recording(path).x, expected[path.name])
    _timed(*predict, cwd=tmp_path)  # its own files it replaces, and killed writes' leftovers it removes
    assert not [p.name for p in (tmp_path / "pred").iterdir() if ".tmp" in p.name]
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == inputs
    with capsys.disabled():
        print(f"\nkill test, predict: {kills} kills, only complete predictions left")
