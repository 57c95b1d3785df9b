"""Faults and resources: `check` never says ok about a scene that blows up, the blow-up step
is exact, work beyond memory or disk is refused up front (run, fit, render), temporary files
of killed writes are removed and the folder is synced, and NumPy never lengthens an error.
Each test is a reproducer of a measured failure; refusals follow the contract of
tests/test_hostile_input.py (exit 2, one line, nothing written)."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hostile import _jaxspring, _refused

from jaxspring.cli import main
from jaxspring.io.scene import resolve_scene_path


def test_check_never_says_ok_about_a_scene_that_blows_up(capsys, tmp_path):
    """Huge stiffness or damping: the estimate stays finite and says the scene would blow up
    (exit 1); masses so small that the estimate overflows are refused (exit 2)."""
    for value in ("ks=1e300", "kd=1e300", "ks=1e200"):
        assert main(["check", "chain", "--set", value]) == 1, value
        captured = capsys.readouterr()
        assert "ok:" not in captured.out and "expect a blow-up" in captured.err, captured
    scene = tmp_path / "light.toml"
    text = resolve_scene_path("chain").read_text()
    scene.write_text(text.replace("mass = 1.0", "mass = 1e-320"))
    _refused(capsys, tmp_path, "check", scene, naming=("overflows",))
    # measured: `run` printed a warning "(stable at this dt: )" and an error "omega_max nan"
    _refused(capsys, tmp_path, "run", scene, "--steps", "20", "--save-every", "10", "--out", tmp_path / "q.h5")


@pytest.mark.slow
@pytest.mark.parametrize(
    "scene, change",
    [
        ("heavy", ()),
        ("chain", ("--set", "ks=1e308")),
        ("chain", ("--set", "kd=1e308")),
        ("chain", ("--set", "cd=1e308")),
        ("cloth", ("--set", "ks=1e308")),
    ],
)
def test_check_runs_a_trial_before_it_says_ok(capsys, tmp_path, scene, change):
    """Measured: "ok (margin 3.17e+155x)" for masses of 1e308 (energies overflow) and "omega_max 0
    ... ok" for stiffness near the largest float, while `run` blew up at step 1 or 2. The linear
    estimate cannot see these; `check` now runs 10 steps as `run` does before it says ok."""
    if scene == "heavy":
        scene = tmp_path / "heavy.toml"
        scene.write_text(resolve_scene_path("chain").read_text().replace("mass = 1.0", "mass = 1e308"))
    _refused(capsys, tmp_path, "check", scene, *change, naming=("blew up at step", "a trial run of 10 steps"))
    capsys.readouterr()
    assert main(["check", "chain"]) == 0 and "ok:" in capsys.readouterr().out


def test_stale_temporary_files_of_killed_writes_are_removed(tmp_path):
    from jaxspring.io.trajectory import atomic_path

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".out.h5.{dead.pid}.x1.tmp.h5"
    live = tmp_path / f".out.h5.{os.getpid()}.x2.tmp.h5"  # a write in progress
    other = tmp_path / f".other.h5.{dead.pid}.x3.tmp.h5"
    for path in (stale, live, other):
        path.write_bytes(b"partial")
    with atomic_path(tmp_path / "out.h5") as tmp:
        Path(tmp).write_bytes(b"done")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, other.name, "out.h5"])
    assert (tmp_path / "out.h5").read_bytes() == b"done"


def test_work_beyond_memory_or_disk_is_refused_up_front(capsys, tmp_path):
    huge = tmp_path / "huge.toml"
    huge.write_text('name = "huge"\ndt = 0.001\n[physics]\nks = 1.0\nkd = 0.0\n[lattice]\nshape = [30000, 30000]\n')
    _refused(capsys, tmp_path, "run", huge, "--out", tmp_path / "h.h5", naming=("lattice.shape", "900,000,000"))
    _refused(
        capsys,
        tmp_path,
        "run",
        "cloth",
        "--steps",
        "100000000",
        "--save-every",
        "1",
        "--out",
        tmp_path / "c.h5",
        naming=("--steps", "TiB", "--save-every"),
    )
    _refused(
        capsys,
        tmp_path,
        "run",
        "cloth",
        "--steps",
        "1000",
        "--save-every",
        "1",
        "--max-memory",
        "10M",
        "--out",
        tmp_path / "c.h5",
        naming=("--max-memory 10 MiB",),
    )
    _refused(
        capsys, tmp_path, "run", "chain", "--max-memory", "lots", "--out", tmp_path / "c.h5", naming=("--max-memory",)
    )


@pytest.mark.slow
def test_fits_and_renders_beyond_memory_are_refused_up_front(inputs, capsys, tmp_path, monkeypatch):
    """Fit: XLA's own memory plan of an iteration; render: the file's arrays, then the movie's
    pictures (measured ~4.9 bytes a pixel of peak memory; 8 assumed)."""
    from jaxspring import resources

    folder = tmp_path / "work"
    shutil.copytree(inputs, folder)
    line = _refused(
        capsys,
        folder,
        "fit",
        folder / "exp.toml",
        "--out",
        folder / "f.h5",
        "--max-memory",
        "10K",
        "--quiet",
        naming=("fit: an iteration of the direct stage", "--max-memory 10 KiB"),
    )
    assert "KiB of memory" in line or "MiB of memory" in line
    _refused(
        capsys, folder, "render", folder / "R.h5", "--out", folder / "r.gif", "--max-memory", "1K", naming=("reading",)
    )
    # 21 frames of 540x450 pixels at 8 bytes: 40.8 MB
    line = _refused(
        capsys,
        folder,
        "render",
        folder / "R.h5",
        "--out",
        folder / "r.gif",
        "--max-memory",
        "30M",
        naming=("--max-frames", "21 frames of 540x450"),
    )
    assert "~38.9 MiB" in line
    monkeypatch.setattr(resources, "available_memory", lambda: 2**20)
    _refused(capsys, folder, "render", folder / "R.h5", "--out", folder / "r.gif", naming=("this machine has",))


def test_scene_files_that_are_not_regular_or_too_large_or_too_deep(capsys, tmp_path, monkeypatch):
    from jaxspring.io import schema

    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    _refused(capsys, tmp_path, "run", fifo, "--out", tmp_path / "o.h5", naming=("not a regular file",))
    if Path("/dev/zero").exists():
        _refused(capsys, tmp_path, "run", "/dev/zero", "--out", tmp_path / "o.h5", naming=("not a regular file",))
    deep = tmp_path / "deep.toml"
    deep.write_text('name = "x"\ndt = 0.1\na = ' + "[" * 1000 + "]" * 1000 + "\n")
    _refused(capsys, tmp_path, "run", deep, "--out", tmp_path / "o.h5", naming=("too deeply",))
    monkeypatch.setattr(schema, "MAX_TOML_BYTES", 100)
    large = tmp_path / "large.toml"
    large.write_text("# " + "x" * 200 + "\n")
    _refused(capsys, tmp_path, "run", large, "--out", tmp_path / "o.h5", naming=("more than the 100",))


@pytest.mark.slow
def test_the_blowup_step_does_not_depend_on_save_every(capsys, tmp_path):
    scene = tmp_path / "jelly.toml"
    scene.write_text(resolve_scene_path("jelly").read_text().replace("dt = 0.001", "dt = 0.01"))
    lines = set()
    for stride in ("1", "20", "40"):
        out = tmp_path / f"j{stride}.h5"
        assert main(["run", str(scene), "--steps", "400", "--save-every", stride, "--out", str(out), "--quiet"]) == 2
        lines.add(capsys.readouterr().err.strip().splitlines()[-1])
        assert not out.exists()
    assert len(lines) == 1 and "blew up at step" in lines.pop()


def test_tiny_masses_are_warned_about_by_check(capsys, tmp_path):
    scene = tmp_path / "light.toml"
    scene.write_text(resolve_scene_path("chain").read_text().replace("mass = 1.0", "mass = 1e-300"))
    assert main(["check", str(scene)]) == 1
    assert "expect a blow-up" in capsys.readouterr().err


@pytest.mark.slow
def test_numpy_warnings_never_lengthen_the_error_line(tmp_path):
    """In a fresh process (pytest would catch warnings in-process): a scene whose estimate
    overflows, where NumPy warns, still ends in exactly one line."""
    scene = tmp_path / "light.toml"
    scene.write_text(resolve_scene_path("chain").read_text().replace("mass = 1.0", "mass = 1e-320"))
    for command in (["check", str(scene)], ["run", str(scene), "--out", str(tmp_path / "q.h5"), "--quiet"]):
        result = _jaxspring(*command, cwd=tmp_path)
        assert result.returncode == 2, result.stderr
        assert result.stderr.count("\n") == 1 and result.stderr.startswith("jaxspring: error: "), result.stderr
    before = np.geterr()  # in-process, the command leaves NumPy's settings as it found them
    assert main(["check", str(scene)]) == 2
    assert np.geterr() == before


def test_the_folder_is_synced_after_the_rename(tmp_path, monkeypatch):
    from jaxspring.io import trajectory

    events = []
    monkeypatch.setattr(trajectory.os, "replace", lambda a, b: (events.append("rename"), os.rename(a, b)))
    real = trajectory._fsync_folder
    monkeypatch.setattr(
        trajectory, "_fsync_folder", lambda folder: (events.append(("sync", Path(folder))), real(folder))
    )
    with trajectory.atomic_path(tmp_path / "out.h5") as tmp:
        Path(tmp).write_bytes(b"x")
    assert events == ["rename", ("sync", tmp_path)]
    assert (tmp_path / "out.h5").read_bytes() == b"x"
