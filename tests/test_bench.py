"""`jaxspring check` and `jaxspring bench accuracy|speed`: outputs and their numbers.

Besides the benchmarks' own consistency, their numbers are checked against independent
ones computed here: an accuracy error recomputed from a loop-based reference and a
converged SciPy solution, peers' and jaxspring's positions against a NumPy step loop
written in this file, sizes counted by hand, and speeds against wall times measured here.
"""

import csv
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy_reference import reference_for_scene
from scipy.integrate import solve_ivp

import jaxspring as js
from jaxspring.bench import peers, speed
from jaxspring.cli import main


def test_check_prints_every_integrators_bound(capsys):
    assert main(["check", "chain"]) == 0
    out = capsys.readouterr().out
    for name in ("semi_implicit_euler", "verlet", "rk4", "backward_euler"):
        assert name in out
    assert "omega_max 63.0" in out  # 2 sqrt(ks / m) for the chain's alternating mode: 2 sqrt(1000) = 63.2
    assert main(["check", "chain", "--dt", "0.05"]) == 1  # beyond 0.027 s
    assert "expect a blow-up" in capsys.readouterr().err
    assert main(["check", "chain", "--dt", "-1"]) == 2
    assert "dt" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_accuracy_quick(tmp_path, capsys):
    out = tmp_path / "bench"
    assert (
        main(["bench", "accuracy", "--quick", "--scenes", "mass_spring", "--repeats", "1", "--out-dir", str(out)]) == 0
    )
    with open(out / "accuracy.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4 * 4  # integrators x dt values
    assert (out / "accuracy.png").stat().st_size > 10_000 and "Recommended" in (out / "accuracy.md").read_text()
    error = {(r["integrator"], float(r["dt"])): float(r["error"]) for r in rows}
    change = float(rows[0]["reference_change"])
    assert change < 1e-3 * min(error.values())  # the reference is converged far below every reported error
    for dt in (0.05, 0.02, 0.01, 0.005):
        assert error[("rk4", dt)] < error[("verlet", dt)] < error[("semi_implicit_euler", dt)]
    # halving dt halves the first-order error and quarters the second-order one
    assert np.isclose(error[("semi_implicit_euler", 0.01)] / error[("semi_implicit_euler", 0.005)], 2, rtol=0.1)
    assert np.isclose(error[("verlet", 0.01)] / error[("verlet", 0.005)], 4, rtol=0.1)
    # the semi-implicit Euler errors recomputed independently: the loop-based reference
    # stepper against a converged SciPy solution of the same ODE, over the quick sweep's
    # horizon (1 s, frames every 0.1 s), error = largest over frames of the RMS over particles
    exact = _mass_spring_solution(np.linspace(0.0, 1.0, 11))
    scene = js.load_scene("mass_spring")
    for dt in (0.05, 0.02, 0.01, 0.005):
        every = round(0.1 / dt)
        x, _ = reference_for_scene(scene.with_dt(dt), 10 * every, every)
        mine = float(np.max(np.sqrt(np.mean(np.sum((x - exact) ** 2, axis=-1), axis=-1))))
        assert np.isclose(error[("semi_implicit_euler", dt)], mine, rtol=1e-6), (dt, mine)
    assert main(["bench", "accuracy", "--scenes", "nope"]) == 2


def _mass_spring_solution(times):
    """Positions (frames, 2, 3) of the mass_spring scene from SciPy's DOP853 at tight
    tolerances: the free particle under gravity and a damped spring to the pinned one."""
    scene = js.load_scene("mass_spring")
    m = scene.model
    pin, mass, rest = np.asarray(scene.state.x[0]), float(m.mass[1]), float(m.rest_length[0])
    ks, kd, gravity = float(scene.params.ks), float(scene.params.kd), np.asarray(scene.params.gravity)

    def rate(_, y):
        x, v = y[:3], y[3:]
        d = x - pin
        length = math.sqrt(d @ d)
        u = d / length
        force = -(ks * (length - rest) + kd * (v @ u)) * u + mass * gravity
        return np.concatenate([v, force / mass])

    y0 = np.concatenate([np.asarray(scene.state.x[1]), np.asarray(scene.state.v[1])])
    solution = solve_ivp(rate, (times[0], times[-1]), y0, method="DOP853", t_eval=times, rtol=1e-12, atol=1e-12)
    assert solution.success
    return np.stack([np.broadcast_to(pin, (len(times), 3)), solution.y[:3].T], axis=1)


def _numpy_positions(scene, steps):
    """Final positions after `steps` semi-implicit Euler steps, float64, written from the
    formulas (springs: Hooke + damping of the closing speed; gravity; quadratic drag on
    the drag-flagged particles; pinned particles held at rest)."""
    m, p = scene.model, scene.params
    a, b = np.asarray(m.springs).T
    rest, mass = np.asarray(m.rest_length, float)[:, None], np.asarray(m.mass, float)[:, None]
    pinned, drag = np.asarray(m.pinned)[:, None], np.asarray(m.drag)[:, None]
    ks, kd, cd, dt = float(p.ks), float(p.kd), float(p.cd), float(m.dt)
    gravity = np.asarray(p.gravity, float)
    x, v = np.array(scene.state.x, float), np.array(scene.state.v, float)
    for _ in range(steps):
        d = x[b] - x[a]
        length = np.linalg.norm(d, axis=1, keepdims=True)
        u = d / length
        tension = ks * (length - rest) + kd * np.sum((v[b] - v[a]) * u, axis=1, keepdims=True)
        force = mass * gravity - cd * drag * np.linalg.norm(v, axis=1, keepdims=True) * v
        np.add.at(force, a, tension * u)
        np.add.at(force, b, -tension * u)
        v = np.where(pinned, 0.0, v + dt * force / mass)
        x = x + dt * v
    return x


@pytest.mark.slow
def test_bench_speed_quick(tmp_path, capsys):
    out = tmp_path / "speed"
    args = ["bench", "speed", "--quick", "--peers", "jax_segment_sum,numpy", "--repeats", "1", "--out-dir", str(out)]
    start = time.perf_counter()
    assert main(args) == 0
    wall = time.perf_counter() - start
    with open(out / "speed.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert {r["implementation"] for r in rows} >= {"jaxspring", "jax_segment_sum", "numpy"}
    assert {r["workload"] for r in rows} == {"chain", "cloth_31x41"}
    for r in rows:
        assert float(r["steps_per_second"]) > 0
        if not r["implementation"].startswith("jaxspring"):  # every peer computes the same motion
            assert float(r["max_difference"]) < 1e-3
        else:
            assert float(r["gradient_ratio"]) > 1 and float(r["memory_gradient_mib"]) > 0
    assert (out / "speed.png").stat().st_size > 10_000
    assert "x jax_segment_sum" in (out / "speed.md").read_text()
    assert main(["bench", "speed", "--peers", "cuda"]) == 2
    assert jax.config.jax_enable_x64  # the float32 benchmark restored the suite's float64

    by = {(r["workload"], r["implementation"]): r for r in rows}
    # sizes counted by hand: a 20-particle chain; a 31 x 41 cloth with structural
    # (30 * 41 + 31 * 40) and shear (2 * 30 * 40) springs
    for r in rows:
        expected = (20, 19) if r["workload"] == "chain" else (31 * 41, 30 * 41 + 31 * 40 + 2 * 30 * 40)
        assert (int(r["particles"]), int(r["springs"])) == expected
        rate = float(r["steps_per_second"])
        assert np.isclose(float(r["ns_per_spring_step"]), 1e9 / rate / expected[1], rtol=1e-6)
        assert 200 / rate < wall  # one timed run of the quick sweep's 200 steps fits in the command's wall time

    # the motion that was timed, against the NumPy loop above (float64): the peers as
    # timed (float32), jaxspring in float64 and float32, and the reported differences
    # (peer against jaxspring in float32) within the sum of the two measured errors
    for scene in speed.workloads(quick=True):
        want = _numpy_positions(scene, 200)
        scale = np.max(np.abs(want - np.asarray(scene.state.x)))
        assert scale > 0.1  # the workload moved
        x64 = js.sim.final_state(scene.model, scene.params, scene.state, steps=200).x
        assert np.max(np.abs(np.asarray(x64) - want)) < 1e-9 * np.max(np.abs(want))
        to32 = lambda tree: jax.tree_util.tree_map(  # noqa: E731
            lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree
        )
        x32 = np.asarray(js.sim.final_state(to32(scene.model), to32(scene.params), to32(scene.state), steps=200).x)
        error32 = float(np.max(np.abs(x32 - want)))
        assert error32 < 1e-4
        for name, make in (("jax_segment_sum", peers.jax_segment_sum), ("numpy", peers.numpy_step)):
            peer_error = float(np.max(np.abs(make(scene)(200) - want)))
            assert peer_error < 1e-4, (scene.name, name, peer_error)
            assert float(by[(scene.name, name)]["max_difference"]) <= peer_error + error32 + 1e-7

    # the NumPy peer's reported rate against one measured here (same 200 steps of the chain)
    run = peers.numpy_step(speed.workloads(quick=True)[0])
    run(200)
    times = []
    for _ in range(3):
        start = time.perf_counter()
        run(200)
        times.append(time.perf_counter() - start)
    measured = 200 / float(np.median(times))
    assert 0.1 < float(by[("chain", "numpy")]["steps_per_second"]) / measured < 10
