"""Speed against error: every integrator on every scene over a sweep of time steps.

For each scene a float64 reference is computed with RK4 at a small step and shown to
be converged (halving its step changes it by `reference_change`, which must be below
every error reported). Each (integrator, dt) run is timed (median of `repeats`
compiled runs) and compared with the reference at common frames: the error is the
largest over frames of the RMS position error over particles. The energy error is
the largest |E(t) - E_ref(t)| over frames divided by the largest |E_ref|: in damped
scenes energy is lost physically, so it is measured against the reference's energy.
A run is stable when it stays finite and below the blow-up detector's energy limit.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import time

import jax
import numpy as np

from ..io.scene import load_scene
from ..io.trajectory import write_rows_csv
from ..render import pyplot, save_figure
from ..sim.integrators import INTEGRATORS
from ..sim.rollout import energy
from ..sim.rollout import simulate as simulate_frames
from ..sim.scene import Scene
from ..sim.stability import energy_threshold
from ..sim.state import Trajectory

# scene -> (horizon [s], frame interval [s], dt values as divisors of the frame interval)
SWEEPS = {
    "mass_spring": (5.0, 0.1, (1, 2, 5, 10, 20, 50, 100)),
    "chain": (2.0, 0.02, (1, 2, 4, 5, 10, 20, 40)),
    "cloth": (1.0, 0.02, (2, 4, 5, 10, 20, 40)),
    "jelly": (1.0, 0.02, (4, 5, 10, 20, 40, 80)),
}
QUICK_SWEEPS = {"mass_spring": (1.0, 0.1, (2, 5, 10, 20)), "chain": (0.2, 0.02, (2, 5, 10, 20))}
REFERENCE_DIVISOR = {"mass_spring": 1000, "chain": 200, "cloth": 200, "jelly": 800}
QUICK_REFERENCE_DIVISOR = {"mass_spring": 400, "chain": 100}


@dataclasses.dataclass(frozen=True)
class AccuracyRow:
    scene: str
    integrator: str
    dt: float
    seconds_per_simulated_second: float
    error: float
    energy_error: float
    stable: bool
    reference_change: float


def _frames(scene: Scene, integrator: str, dt: float, horizon: float, interval: float):
    model = scene.model.replace(integrator=integrator, dt=dt)
    every = int(round(interval / dt))
    frames = int(round(horizon / interval))
    return model, every, frames


def simulate(scene: Scene, integrator: str, dt: float, horizon: float, interval: float, repeats: int = 1):
    """(trajectory, median wall seconds of a compiled run) of one configuration."""
    model, every, frames = _frames(scene, integrator, dt, horizon, interval)
    compiled = simulate_frames.lower(model, scene.params, scene.state, frames, every).compile()
    times = []
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        _, x, v = jax.block_until_ready(compiled(model, scene.params, scene.state))
        times.append(time.perf_counter() - start)
    x = np.concatenate([np.asarray(scene.state.x)[None], np.asarray(x)])
    v = np.concatenate([np.asarray(scene.state.v)[None], np.asarray(v)])
    return model, Trajectory(x=x, v=v, t=np.arange(frames + 1) * interval), float(np.median(times))


def rms_error(x, reference) -> float:
    """Largest over frames of the RMS (over particles) position error [m]."""
    per_frame = np.sqrt(np.mean(np.sum((np.asarray(x) - np.asarray(reference)) ** 2, axis=-1), axis=-1))
    return float(np.max(per_frame)) if np.all(np.isfinite(per_frame)) else math.inf


def reference(scene: Scene, horizon: float, interval: float, divisor: int):
    """RK4 at dt = interval / divisor and at half that; returns (trajectory, change on halving)."""
    _, coarse, _ = simulate(scene, "rk4", interval / divisor, horizon, interval)
    _, fine, _ = simulate(scene, "rk4", interval / (2 * divisor), horizon, interval)
    return fine, rms_error(coarse.x, fine.x)


def sweep(names=None, quick: bool = False, repeats: int = 3, progress=None) -> list[AccuracyRow]:
    """Run the sweep (float64) for `names` (default: the four seed scenes)."""
    if not jax.config.jax_enable_x64:
        raise RuntimeError("the accuracy sweep needs float64: jax.config.update('jax_enable_x64', True)")
    table = QUICK_SWEEPS if quick else SWEEPS
    divisors = QUICK_REFERENCE_DIVISOR if quick else REFERENCE_DIVISOR
    names = list(names or table)
    rows = []
    for name in names:
        scene = load_scene(name)
        horizon, interval, steps = table[name]
        ref, change = reference(scene, horizon, interval, divisors[name])
        ref_energy = np.asarray(energy(scene.model, scene.params, ref))
        limit = energy_threshold(scene.model, scene.params, scene.state)
        for integrator in INTEGRATORS:
            for divisor in steps:
                dt = interval / divisor
                model, traj, wall = simulate(scene, integrator, dt, horizon, interval, repeats)
                e = np.asarray(energy(model, scene.params, traj))
                finite = bool(np.all(np.isfinite(e)) and np.all(np.isfinite(traj.x)))
                scale = max(float(np.max(np.abs(ref_energy))), 1e-300)
                energy_error = float(np.max(np.abs(e - ref_energy))) / scale if finite else math.inf
                error = rms_error(traj.x, ref.x) if finite else math.inf
                stable = finite and float(np.max(e)) <= limit
                rows.append(AccuracyRow(name, integrator, dt, wall / horizon, error, energy_error, stable, change))
                if progress:
                    progress(rows[-1])
    return rows


def write_csv(rows, path):
    write_rows_csv(rows, path)


def read_csv(path) -> list[AccuracyRow]:
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        return [
            AccuracyRow(
                r["scene"],
                r["integrator"],
                float(r["dt"]),
                float(r["seconds_per_simulated_second"]),
                float(r["error"]),
                float(r["energy_error"]),
                r["stable"] == "True",
                float(r["reference_change"]),
            )
            for r in reader
        ]


def recommend(rows, tolerance: float = 1e-3):
    """Per scene: the cheapest stable (integrator, dt) whose error [m] is below `tolerance`.

    A scene that no setting brings below `tolerance` gets the cheapest one below 10x,
    then 100x it (the jelly after its impact). Returns scene -> (row, tolerance used).
    """
    best = {}
    for scene in dict.fromkeys(r.scene for r in rows):
        for limit in (tolerance, 10 * tolerance, 100 * tolerance):
            fits = [r for r in rows if r.scene == scene and r.stable and r.error <= limit]
            if fits:
                best[scene] = (min(fits, key=lambda r: r.seconds_per_simulated_second), limit)
                break
    return best


def markdown(rows, tolerance: float = 1e-3) -> str:
    lines = [
        "| scene | integrator | dt [s] | wall s / simulated s | max RMS error [m] | energy error | stable |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.scene} | {r.integrator} | {r.dt:.3g} | {r.seconds_per_simulated_second:.3g} | "
            f"{r.error:.2e} | {r.energy_error:.2e} | {'yes' if r.stable else 'no'} |"
        )
    lines += [
        "",
        f"Recommended: the cheapest stable setting with error below {tolerance:g} m (or the tolerance shown):",
        "",
    ]
    lines += [
        "| scene | integrator | dt [s] | wall s / simulated s | error [m] | tolerance [m] | reference change on halving [m] |"
    ]
    lines += ["|---|---|---|---|---|---|---|"]
    refs = {r.scene: r.reference_change for r in rows}
    for scene, (r, limit) in recommend(rows, tolerance).items():
        lines.append(
            f"| {scene} | {r.integrator} | {r.dt:.3g} | {r.seconds_per_simulated_second:.3g} | {r.error:.2e} | "
            f"{limit:g} | {refs[scene]:.1e} |"
        )
    return "\n".join(lines) + "\n"


def plot(rows, path):
    """Log-log error against wall time per simulated second, one panel per scene (the Pareto fronts)."""
    plt = pyplot()
    scenes = list(dict.fromkeys(r.scene for r in rows))
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.8), squeeze=False)
    markers = dict(zip(INTEGRATORS, "osD^"))
    for ax, scene in zip(axes[0], scenes):
        for integrator in INTEGRATORS:
            mine = [r for r in rows if r.scene == scene and r.integrator == integrator and r.stable and r.error > 0]
            if mine:
                ax.loglog(
                    [r.seconds_per_simulated_second for r in mine],
                    [r.error for r in mine],
                    marker=markers[integrator],
                    label=integrator,
                )
        change = next(r.reference_change for r in rows if r.scene == scene)
        if change > 0:
            ax.axhline(change, color="grey", lw=0.8, ls=":", label="reference change on halving")
        ax.set_title(scene)
        ax.set_xlabel("wall time per simulated second [s]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("max RMS position error [m]")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.set_dpi(110)
    save_figure(fig, path)
