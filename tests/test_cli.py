"""The command line: run, render, blow-up reports; the demo on a fresh process."""

import re
import subprocess
import sys

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.cli import main
from jaxspring.sim.stability import energy_threshold


def test_run_writes_file_and_summary(tmp_path, capsys):
    out = tmp_path / "chain.h5"
    code = main(
        ["run", "chain", "--steps", "400", "--save-every", "20", "--set", "ks=600", "--out", str(out), "--quiet"]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "400 steps" in text and "steps/s" in text and "energy" in text and str(out) in text
    scene, traj = js.load_trajectory(out)
    assert float(scene.params.ks) == 600.0
    assert traj.x.shape == (21, 20, 3)
    # the summary's end energy is the file's last frame's energy
    e_end = float(js.sim.energy(scene.model, scene.params, traj.frame(-1)))
    printed = float(re.search(r"-> (\S+) J", text).group(1))
    assert printed == pytest.approx(e_end, rel=1e-5)


@pytest.mark.slow
def test_run_float64_dtype(tmp_path):
    out = tmp_path / "pair.h5"
    assert main(["run", "mass_spring", "--steps", "100", "--dtype", "float64", "--out", str(out), "--quiet"]) == 0
    with h5py.File(out) as f:
        assert f.attrs["dtype"] == "float64" and f["trajectory/x"].dtype == np.float64


def test_blowup_reports_exact_step_and_stable_dt(tmp_path, capsys):
    out = tmp_path / "chain.h5"
    code = main(
        ["run", "chain", "--set", "ks=4e6", "--steps", "2000", "--save-every", "100", "--out", str(out), "--quiet"]
    )
    err = capsys.readouterr().err
    assert code == 2 and not out.exists()
    assert "warning" in err.splitlines()[0]  # the analyser warns before the run
    last = err.strip().splitlines()[-1]
    match = re.search(r"blew up at step (\d+).*reduce dt below (\S+) s", last)
    assert match, last
    step, bound = int(match.group(1)), float(match.group(2))
    assert 0.0002 < bound < 0.001  # 2/omega_max with omega_max ~ 2 sqrt(4 ks / m)
    # independently: step through and find the first state that is non-finite or over the energy limit
    scene = js.load_scene("chain").with_params(ks=4e6)
    traj = js.rollout(scene.model, scene.params, scene.state, steps=step, save_every=1)
    limit = energy_threshold(scene.model, scene.params, scene.state)
    e = np.asarray(js.sim.energy(scene.model, scene.params, traj))
    finite = np.isfinite(np.asarray(traj.x)).all(axis=(1, 2))
    bad = ~finite | ~np.isfinite(e) | (e > limit)
    assert bad[step] and not bad[:step].any()


def test_find_blowup_python_api(scenes):
    scene = scenes["chain"].with_params(ks=4e6)
    traj = js.rollout(scene.model, scene.params, scene.state, steps=1000, save_every=50)
    problem = js.sim.find_blowup(scene.model, scene.params, traj)
    assert problem is not None and 0 < problem.step <= 1000
    assert problem.stability.dt_bound < scene.model.dt
    healthy = scenes["chain"]
    ok = js.rollout(healthy.model, healthy.params, healthy.state, steps=1000, save_every=50)
    assert js.sim.find_blowup(healthy.model, healthy.params, ok) is None


def test_stable_dt_estimate_single_spring_hand_calculation():
    # one free particle of mass 2 on a spring ks = 50 to a pinned one: omega^2 = ks / m = 25
    model = js.sim.make_model(
        [[0, 1]], [1.0, 2.0], positions=[[0, 0, 0], [1, 0, 0]], pinned=[0], gravity=False, dt=0.01
    )
    params = js.Params(ks=50.0, kd=0.0)
    state = js.State(x=jnp.array([[0.0, 0, 0], [1.0, 0, 0]]), v=jnp.zeros((2, 3)))
    estimate = js.sim.estimate_stability(model, params, state)
    assert estimate.omega_max == pytest.approx(5.0, rel=1e-6)
    assert estimate.dt_bound == pytest.approx(0.4, rel=1e-6)
    # with damping kd = 4: c = kd / m = 2; (omega dt)^2 + 2 c dt = 4 -> dt = (-2 + sqrt(4 + 100)) / 25
    damped = js.sim.estimate_stability(model, params.replace(kd=4.0), state)
    assert damped.dt_bound == pytest.approx((-2 + np.sqrt(104)) / 25, rel=1e-6)


@pytest.mark.slow
def test_render_png_and_gif(tmp_path, capsys):
    h5 = tmp_path / "jelly.h5"
    assert main(["run", "jelly", "--steps", "200", "--save-every", "20", "--out", str(h5), "--quiet"]) == 0
    assert main(["render", str(h5), "--out", str(tmp_path / "frame.png"), "--quiet"]) == 0
    assert main(["render", str(h5), "--max-frames", "4", "--quiet"]) == 0
    from PIL import Image

    with Image.open(tmp_path / "frame.png") as png:
        assert png.size[0] > 200
        assert len(np.unique(np.asarray(png.convert("RGB")).reshape(-1, 3), axis=0)) > 20  # drawn
    with Image.open(tmp_path / "jelly.gif") as gif:
        assert gif.n_frames == 4
    assert main(["render", str(h5), "--out", str(tmp_path / "movie.mp4")]) == 2


@pytest.mark.slow
def test_demo_on_a_fresh_process(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "jaxspring", "demo", "--out-dir", str(tmp_path / "demo"), "--no-movies"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    for name in js.builtin_scenes():
        for suffix in (".h5", ".png"):  # movies: the render tests (half this test's time without them)
            assert (tmp_path / "demo" / f"{name}{suffix}").stat().st_size > 1000
        assert not (tmp_path / "demo" / f"{name}.gif").exists()
        scene, traj = js.load_trajectory(tmp_path / "demo" / f"{name}.h5")
        assert np.isfinite(np.asarray(traj.x)).all()
        assert name in result.stdout


@pytest.mark.slow
def test_commands_keep_their_compiled_programs_for_the_next_one(tmp_path):
    """Without a cache chosen by the user, a command writes JAX's compilation cache under
    $XDG_CACHE_HOME/jaxspring/jax and the next one reads it (no program is compiled twice);
    JAXSPRING_COMPILE_CACHE=0 writes none."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    run = [sys.executable, "-m", "jaxspring", "run", "mass_spring", "--steps", "20", "--out", "o.h5", "--quiet"]
    for setting, cache in (("0", tmp_path / "off"), ("1", tmp_path / "on")):
        env.update(XDG_CACHE_HOME=str(cache), JAXSPRING_COMPILE_CACHE=setting, JAX_LOG_COMPILES="1")
        first = subprocess.run(run, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert first.returncode == 0, first.stderr
        kept = sorted((cache / "jaxspring" / "jax").glob("*")) if cache.exists() else []
        if setting == "0":
            assert not kept
            continue
        assert kept  # the programs of the first run
        again = subprocess.run(run, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert again.returncode == 0, again.stderr

        def compiling(text):  # seconds in XLA compiles (a program loaded from the cache takes ~ms)
            return sum(float(s) for s in re.findall(r"Finished XLA compilation of .* in ([\d.e-]+) sec", text))

        assert compiling(again.stderr) < 0.2 * compiling(first.stderr), (
            compiling(first.stderr),
            compiling(again.stderr),
        )
