"""Scene files: the seed scenes' structure, and every invalid input as a one-line error with exit code 2."""

import os
import subprocess
import sys

import numpy as np
import pytest

import jaxspring as js
from jaxspring.cli import main

GOOD = """
name = "tiny"
dt = 0.001
steps = 20
save_every = 10

[physics]
ks = 100.0
kd = 1.0

[particles]
x = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]
mass = 1.0
pinned = [0]

[springs]
pairs = [[0, 1], [1, 2]]
"""

# (what is wrong, text replaced, replacement, words the one-line message must contain)
INVALID = [
    ("unknown key", "steps = 20", "steps = 20\nstepz = 3", ["stepz", "unknown key"]),
    ("missing field", "dt = 0.001\n", "", ["dt", "missing"]),
    ("zero mass", "mass = 1.0", "mass = 0.0", ["particles.mass", "> 0"]),
    ("negative mass", "mass = 1.0", "mass = [1.0, -2.0, 1.0]", ["particles.mass", "> 0"]),
    ("dt zero", "dt = 0.001", "dt = 0.0", ["dt", "> 0"]),
    ("dt negative", "dt = 0.001", "dt = -0.001", ["dt", "> 0"]),
    ("negative stiffness", "ks = 100.0", "ks = -100.0", ["physics.ks", ">= 0"]),
    ("spring index out of range", "[1, 2]]", "[1, 3]]", ["springs", "out of range"]),
    ("duplicate spring", "[1, 2]]", "[1, 2], [1, 0]]", ["springs", "duplicate"]),
    ("NaN", "kd = 1.0", "kd = nan", ["physics.kd", "NaN"]),
    ("NaN position", "[2.0, 0.0, 0.0]]", "[2.0, nan, 0.0]]", ["particles.x", "NaN"]),
    ("bad TOML", "[physics]", "[physics", ["not valid TOML"]),
    ("neither lattice nor particles", "[particles]", "[particlez]", ["particlez", "unknown"]),
]


def test_seed_scene_structure(scenes):
    cloth, jelly, chain, pair = scenes["cloth"], scenes["jelly"], scenes["chain"], scenes["mass_spring"]
    # cloth 31 x 41: structural 30*41 + 31*40, shear 2*30*40
    assert cloth.model.particle_count == 31 * 41
    assert cloth.model.spring_count == 30 * 41 + 31 * 40 + 2 * 30 * 40 == 4870
    assert int(np.sum(np.asarray(cloth.model.pinned))) == 2
    assert cloth.faces.shape == (2 * 30 * 40, 3)
    # jelly 7 x 6 x 5: axis, face diagonals, body diagonals, skip-one (bend) springs
    structural = 6 * 6 * 5 + 7 * 5 * 5 + 7 * 6 * 4
    shear = 2 * (6 * 5 * 5 + 6 * 6 * 4 + 7 * 5 * 4)
    diagonal = 4 * 6 * 5 * 4
    bend = 5 * 6 * 5 + 7 * 4 * 5 + 7 * 6 * 3
    assert jelly.model.spring_count == structural + shear + diagonal + bend
    assert jelly.faces.shape == (2 * 2 * (6 * 5 + 6 * 4 + 5 * 4), 3)
    # all rest lengths are the initial distances: 1, sqrt 2, sqrt 3 or 2
    assert set(np.round(np.asarray(jelly.model.rest_length) ** 2, 9)) == {1.0, 2.0, 3.0, 4.0}
    assert chain.model.particle_count == 20 and chain.model.spring_count == 19
    assert np.allclose(np.asarray(chain.state.x)[:, 1], 0.0)  # horizontal
    assert pair.model.terms == ("springs", "gravity")
    assert float(pair.params.ks) == 2.0 and float(pair.params.kd) == 0.1 and pair.model.dt == 0.001
    assert float(cloth.params.cd) == 0.0025 and cloth.model.dt == 0.002
    assert float(jelly.params.kg) == 1e5 and float(jelly.params.kgd) == 0.4
    # the jelly spins about its centre of mass: zero net momentum, non-zero angular momentum
    x, v = np.asarray(jelly.state.x), np.asarray(jelly.state.v)
    assert np.allclose(v.sum(axis=0), 0.0, atol=1e-9)
    assert np.linalg.norm(np.cross(x - x.mean(axis=0), v).sum(axis=0)) > 1.0


@pytest.mark.parametrize("case, old, new, words", INVALID, ids=[c[0] for c in INVALID])
def test_invalid_scene_is_one_line_exit_2_no_file(tmp_path, capsys, case, old, new, words):
    assert old in GOOD
    scene_file = tmp_path / "tiny.toml"
    scene_file.write_text(GOOD.replace(old, new, 1))
    out = tmp_path / "out.h5"
    code = main(["run", str(scene_file), "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    assert code == 2
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert "Traceback" not in captured.err
    assert str(scene_file) in lines[0]
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert sorted(os.listdir(tmp_path)) == ["tiny.toml"]


def test_the_good_scene_runs(tmp_path, capsys):
    scene_file = tmp_path / "tiny.toml"
    scene_file.write_text(GOOD)
    out = tmp_path / "out.h5"
    assert main(["run", str(scene_file), "--out", str(out), "--quiet"]) == 0
    assert out.exists()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["run", "no_such_scene.toml"], ["not found"]),
        (["run", "chain", "--set", "ks=-5"], ["ks", ">= 0"]),
        (["run", "chain", "--set", "kg=5"], ["kg", "no ground"]),
        (["run", "chain", "--set", "nonsense=5"], ["nonsense", "not a parameter"]),
        (["run", "chain", "--steps", "15", "--save-every", "10"], ["multiple"]),
        (["run", "chain", "--integrator", "magic"], ["unknown integrator"]),
        (["run", "chain", "--out", "missing_folder/x.h5"], ["does not exist"]),
        (["run", "chain", "--steps", "ten"], ["invalid int"]),
    ],
)
def test_bad_command_line_is_one_line_exit_2(tmp_path, capsys, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    try:
        code = main(argv + ["--quiet"])
    except SystemExit as exc:  # argparse's own errors
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    for word in words:
        assert word in err
    assert os.listdir(tmp_path) == []


def test_error_through_the_console_script_has_no_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(GOOD.replace("ks = 100.0", "ks = -1.0"))
    result = subprocess.run(
        [sys.executable, "-m", "jaxspring", "run", str(bad), "--out", str(tmp_path / "o.h5")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert "physics.ks" in result.stderr
    assert not (tmp_path / "o.h5").exists()


def test_python_api_raises_input_error(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(GOOD.replace("dt = 0.001", "dt = -1.0"))
    with pytest.raises(js.InputError, match="dt"):
        js.load_scene(bad)
