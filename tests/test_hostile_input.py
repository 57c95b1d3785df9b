"""Inputs a user did not make with the same settings: every documented workflow must accept them.

Each test is a reproducer of a measured failure; what it asserts is checked independently
(the file's own dtype, a rollout of the cast state, the fit's loss history).
"""

import subprocess
import sys

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js


def _jaxspring(*args, cwd):
    return subprocess.run(
        [sys.executable, "-m", "jaxspring", *args], capture_output=True, text=True, cwd=cwd, timeout=600
    )


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


def _fitted_loss_fell(path):
    with h5py.File(path) as f:
        loss = np.asarray(f["fit/history/loss"])
    assert np.isfinite(loss).all() and loss[-1] < 1e-2 * loss[0], loss


def test_fit_target_reads_a_float32_file_from_run(float32_recording):
    """The README's workflow: `run` (float32 by default), then `fit --target` (float64)."""
    result = _jaxspring(
        "fit", "--target", "rec.h5", "--params", "ks,kd", "--init", "ks=400,kd=2",
        "--iterations", "8", "--out", "cli.fit.h5", "--quiet", cwd=float32_recording,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    _fitted_loss_fell(float32_recording / "cli.fit.h5")


def test_experiment_target_file_reads_a_float32_file(float32_recording):
    (float32_recording / "exp.toml").write_text(
        'scene = "chain"\n[target]\nfile = "rec.h5"\n[fit]\nparams = ["ks"]\ninit = { ks = 400.0 }\niterations = 8\n'
    )
    result = _jaxspring("fit", "exp.toml", "--out", "exp.fit.h5", "--quiet", cwd=float32_recording)
    assert result.returncode == 0, result.stderr
    _fitted_loss_fell(float32_recording / "exp.fit.h5")


def test_observations_take_the_fits_precision(float32_recording):
    scene, trajectory = js.load_trajectory(float32_recording / "rec.h5")
    obs = js.observations_from_trajectory(scene, trajectory, scene.save_every)
    assert obs.x.dtype == np.float64 and obs.initial_state.x.dtype == jnp.float64
    assert obs.states.x.dtype == jnp.float64 and obs.states.v.dtype == jnp.float64
    np.testing.assert_array_equal(obs.x, np.asarray(trajectory.x, np.float64)[:, obs.particles])


def test_rollout_promotes_a_float32_state_on_a_float64_model(scenes):
    scene = scenes["chain"]
    low = js.State(x=scene.state.x.astype(jnp.float32) + 0.1, v=scene.state.v.astype(jnp.float32))
    cast = js.State(x=low.x.astype(jnp.float64), v=low.v.astype(jnp.float64))
    got = js.rollout(scene.model, scene.params, low, steps=50, save_every=10)
    want = js.rollout(scene.model, scene.params, cast, steps=50, save_every=10)
    assert got.x.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(got.x), np.asarray(want.x))
    end = js.final_state(scene.model, scene.params, low, steps=50)
    np.testing.assert_array_equal(np.asarray(end.x), np.asarray(want.x[-1]))
