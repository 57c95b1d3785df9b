"""Shared by the hostile-input and fault tests: the CLI in a fresh process, or in-process with
the refusal contract checked (exit 2, one line, nothing written). Their input files are the
fixtures `float32_recording` and `inputs` in conftest.py."""

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from jaxspring.cli import main


def _jaxspring(*args, cwd):
    return subprocess.run(
        [sys.executable, "-m", "jaxspring", *args], capture_output=True, text=True, cwd=cwd, timeout=600
    )


def _fitted_loss_fell(path):
    with h5py.File(path) as f:
        loss = np.asarray(f["fit/history/loss"])
    assert np.isfinite(loss).all() and loss[-1] < 1e-2 * loss[0], loss


UNWRITABLE = Path("/sys")  # no process may create a file here, root included
needs_unwritable = pytest.mark.skipif(not UNWRITABLE.is_dir(), reason="needs Linux /sys")


def _snapshot(folder):
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir()) if path.is_file()}


def _refused(capsys, folder, *argv, naming=()):
    """Run the CLI in-process; assert exit 2, one line on stderr naming `naming`, and `folder` unchanged."""
    before = _snapshot(folder)
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxspring: error: "), err
    for word in naming:
        assert word in lines[0], lines[0]
    assert _snapshot(folder) == before  # nothing written, no input touched
    return lines[0]
