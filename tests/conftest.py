"""Shared fixtures. Correctness tests run in float64 (tests that need float32 cast explicitly)."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import shutil  # noqa: E402
from pathlib import Path  # noqa: E402

import h5py  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hostile import _jaxspring  # noqa: E402

import jaxspring as js  # noqa: E402


@pytest.fixture(scope="session")
def scenes():
    """The four seed scenes, loaded once (float64)."""
    return {name: js.load_scene(name) for name in js.builtin_scenes()}


@pytest.fixture(scope="module")
def float32_recording(tmp_path_factory):
    """A chain recording written by `jaxspring run` with its default settings (float32)."""
    folder = tmp_path_factory.mktemp("float32")
    result = _jaxspring(
        "run", "chain", "--steps", "400", "--save-every", "20", "--out", "rec.h5", "--quiet", cwd=folder
    )
    assert result.returncode == 0, result.stderr
    with h5py.File(folder / "rec.h5") as f:
        assert f["trajectory/x"].dtype == np.float32  # the case under test
    return folder


@pytest.fixture(scope="module")
def inputs(float32_recording, tmp_path_factory):
    """A folder with a scene (c.toml), a recording (R.h5) and a small synthetic experiment (exp.toml)."""
    folder = tmp_path_factory.mktemp("inputs")
    (folder / "c.toml").write_bytes((Path(js.__file__).parents[1] / "scenes" / "chain.toml").read_bytes())
    shutil.copy(float32_recording / "rec.h5", folder / "R.h5")
    (folder / "exp.toml").write_text(
        'scene = "c.toml"\n[target]\nsteps = 20\nsave_every = 10\n[fit]\nparams = ["ks"]\niterations = 2\n'
    )
    return folder
