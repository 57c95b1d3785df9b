"""Shared fixtures. Correctness tests run in float64 (tests that need float32 cast explicitly)."""

import os
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")
# One compilation cache for the test runs: both test workers, and the CLI processes and
# notebook kernels the tests start, load what another compiled instead of compiling it
# again (a `jaxspring fit` process: 15 s -> 8 s). Entries are keyed by the compiled program,
# so a stale one is never used; a size limit turns on JAX's file lock, so no process reads
# an entry another is still writing. It is kept between runs (`rm -rf .pytest_cache/jax`
# empties it; `pytest --cache-clear` does not); CI starts from a clean clone, without one.
# Processes the tests kill get a cache of their own (tests/test_kill.py).
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.1")
os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(4 * 2**30))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import shutil  # noqa: E402

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


# The heaviest test files first: two workers each take a file at a time (`--dist loadfile`),
# so a heavy file started last would run alone at the end. Measured per-file worker time
# on 2 cores, heaviest first; files not listed follow in their usual order.
HEAVY_FIRST = [
    "test_fitting.py",
    "test_native.py",
    "test_recordings_fit.py",
    "test_noisy_recorded_states.py",
    "test_integrators.py",
    "test_hard_cases.py",
    "test_free_shooting.py",
    "test_cable.py",
    "test_cable_tree.py",
    "test_kill.py",
    "test_horizon.py",
    "test_notebooks.py",
    "test_fast_paths.py",
    "test_search.py",
    "test_distributed.py",
]


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(HEAVY_FIRST)))  # stable: order within a file kept
