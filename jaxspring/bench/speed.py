"""Speed: forward steps/s, gradient cost, compile time, memory and batch throughput,
against peers measured in the same run (see `_peers`).

Every time is the median of `repeats` runs of an already compiled function. Memory is
XLA's own accounting of the compiled program (arguments + outputs + temporaries), the
peak the program needs; the process's peak RSS is reported once at the end.
"""

from __future__ import annotations

import dataclasses
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..io.scene import load_scene, scene_from_dict
from ..io.trajectory import write_rows_csv
from ..render import pyplot, save_figure
from ..sim.rollout import simulate
from ..sim.scene import Scene
from . import peers as _peers

# cloth sizes of the scaling study: the seed cloth's material, spacing and dt
CLOTH_SIZES = ((31, 41), (100, 100), (310, 410))
BATCH = 64


def cloth_of_size(shape) -> Scene:
    """The seed cloth's physics on a lattice of `shape`, pinned at the two corners of one edge."""
    nx, nz = shape
    return scene_from_dict(
        {
            "name": f"cloth_{nx}x{nz}",
            "dt": 0.002,
            "physics": {"ks": 5000.0, "kd": 0.5, "cd": 0.0025, "gravity": [0.0, -9.81, 0.0]},
            "lattice": {
                "shape": [nx, nz],
                "axes": ["x", "z"],
                "spacing": 1.0,
                "springs": ["structural", "shear"],
                "pinned": [[0, 0], [nx - 1, 0]],
                "mass": 1.0,
                "drag": True,
            },
        }
    )


@dataclasses.dataclass
class SpeedRow:
    workload: str
    implementation: str
    particles: int
    springs: int
    steps_per_second: float
    ns_per_spring_step: float
    stepper: str = ""  # which stepper ran (jaxspring rows)
    gradient_ratio: float = float("nan")  # value_and_grad time / forward time, same horizon
    gradient_mode: str = ""
    compile_forward_s: float = float("nan")
    compile_gradient_s: float = float("nan")
    memory_forward_mib: float = float("nan")
    memory_gradient_mib: float = float("nan")
    batch_ratio: float = float("nan")  # rollout-steps/s of a batch of 64 over a single rollout
    max_difference: float = float("nan")  # peer's final positions against jaxspring's [m]


def _median_time(fn, repeats):
    return _alternating_medians([fn], repeats)[0]


def _alternating_medians(fns, repeats):
    """Median wall time of each of fns, run in turn `repeats` times: a ratio of two is
    then measured over the same stretch of a shared, drifting machine."""
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, kept in zip(fns, times):
            start = time.perf_counter()
            fn()
            kept.append(time.perf_counter() - start)
    return [float(np.median(kept)) for kept in times]


def _memory_mib(compiled) -> float:
    m = compiled.memory_analysis()
    return (m.temp_size_in_bytes + m.argument_size_in_bytes + m.output_size_in_bytes) / 2**20


def _steps_for(springs: int) -> int:
    """Enough steps that a jaxspring run takes a good fraction of a second."""
    return int(max(200, min(20_000, 2e8 / max(springs, 1) / 10)) // 100 * 100)


def measure_jaxspring(scene: Scene, steps: int, repeats: int, gradient_steps: int, batch: bool) -> SpeedRow:
    """jaxspring itself: "jaxspring" as a loaded scene runs by default (backend "auto"),
    "jaxspring_jax" on the pure-JAX backend (the reference path, and the one GPUs run)."""
    m, p, s = scene.model, scene.params, scene.state
    start = time.perf_counter()
    forward = simulate.lower(m, p, s, 1, steps).compile()
    compile_forward = time.perf_counter() - start
    jax.block_until_ready(forward(m, p, s))
    wall = _median_time(lambda: jax.block_until_ready(forward(m, p, s)), repeats)
    label = "jaxspring_jax" if m.backend == "jax" else "jaxspring"
    row = SpeedRow(
        scene.name, label, m.particle_count, m.spring_count, steps / wall, wall / steps / m.spring_count * 1e9
    )
    row.stepper = m.stepper.name
    row.compile_forward_s, row.memory_forward_mib = compile_forward, _memory_mib(forward)

    names = [n for n in ("ks", "kd", "cd") if getattr(p, n) is not None]

    def make_loss(checkpoint):
        def loss(values):
            params = p.replace(**values)
            from ..sim.rollout import rollout

            x = rollout(m, params, s, gradient_steps, gradient_steps, checkpoint=checkpoint).x
            return jnp.mean(x[-1] ** 2)

        return loss

    values = {n: getattr(p, n) for n in names}
    mode = None
    for checkpoint in (None, "sqrt"):
        start = time.perf_counter()
        compiled = jax.jit(jax.value_and_grad(make_loss(checkpoint))).lower(values).compile()
        if _memory_mib(compiled) < 2048 or checkpoint == "sqrt":
            mode = checkpoint
            row.compile_gradient_s = time.perf_counter() - start
            break
    row.gradient_mode = "plain" if mode is None else "checkpoint sqrt"
    row.memory_gradient_mib = _memory_mib(compiled)
    jax.block_until_ready(compiled(values))
    fwd = simulate.lower(m, p, s, 1, gradient_steps).compile()
    jax.block_until_ready(fwd(m, p, s))
    grad_wall, fwd_wall = _alternating_medians(
        [lambda: jax.block_until_ready(compiled(values)), lambda: jax.block_until_ready(fwd(m, p, s))], repeats
    )
    row.gradient_ratio = grad_wall / fwd_wall

    if batch:
        ks = p.ks * jnp.linspace(0.8, 1.2, BATCH, dtype=s.x.dtype)
        batched = jax.jit(jax.vmap(lambda k: simulate(m, p.replace(ks=k), s, 1, steps)[0].x)).lower(ks).compile()
        jax.block_until_ready(batched(ks))
        batch_wall, single_wall = _alternating_medians(
            [lambda: jax.block_until_ready(batched(ks)), lambda: jax.block_until_ready(forward(m, p, s))], repeats
        )
        row.batch_ratio = BATCH * single_wall / batch_wall  # rollout-steps/s, batch over single
    return row


CHECK_STEPS = 200  # peers are checked against jaxspring over this many steps (float32 round-off grows later)


def measure_peer(scene: Scene, name: str, steps: int, repeats: int) -> SpeedRow:
    make = {"jax_segment_sum": _peers.jax_segment_sum, "numpy": _peers.numpy_step, "warp": _peers.warp_step}[name]
    run = make(scene)
    check = min(steps, CHECK_STEPS)
    reference = np.asarray(jax.block_until_ready(simulate(scene.model, scene.params, scene.state, 1, check)[0].x))
    difference = float(np.max(np.abs(run(check) - reference)))
    run(steps)  # compile / warm up
    wall = _median_time(lambda: run(steps), repeats)
    m = scene.model
    row = SpeedRow(
        scene.name, name, m.particle_count, m.spring_count, steps / wall, wall / steps / m.spring_count * 1e9
    )
    row.max_difference = difference
    return row


def workloads(quick: bool = False):
    if quick:
        return [load_scene("chain"), cloth_of_size((31, 41))]
    return [load_scene(n) for n in ("mass_spring", "chain", "jelly", "cloth")] + [
        cloth_of_size(s) for s in CLOTH_SIZES[1:]
    ]


def sweep(quick: bool = False, repeats: int = 5, peers=("jax_segment_sum", "numpy", "warp"), progress=None):
    """Measure jaxspring and the peers on every workload (float32)."""
    rows = []
    for scene in workloads(quick):
        springs = scene.model.spring_count
        steps = 200 if quick else _steps_for(springs)
        big = scene.model.particle_count > 20_000
        gradient_steps = 200 if (quick or big) else 2000
        variants = [scene]  # the default path: what `load_scene` + `rollout` run
        if scene.model.stepper.name != scene.with_backend("jax").model.stepper.name:
            variants.append(scene.with_backend("jax"))
        for variant in variants:
            row = measure_jaxspring(variant, steps, repeats, gradient_steps, batch=not big)
            rows.append(row)
            if progress:
                progress(row)
        has_ground = scene.model.has("ground")
        for peer in peers:
            if has_ground or (peer == "warp" and not _peers.warp_available()):
                continue
            peer_steps = steps
            if peer == "numpy":  # slow: a fixed time budget
                peer_steps = max(10, int(min(steps, 2e6 / max(springs, 1))))
            rows.append(measure_peer(scene, peer, peer_steps, max(3, repeats // 2) if peer == "numpy" else repeats))
            if progress:
                progress(rows[-1])
    return rows


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def write_csv(rows, path):
    write_rows_csv(rows, path)


def markdown(rows) -> str:
    by = {(r.workload, r.implementation): r for r in rows}
    peers = [p for p in ("jax_segment_sum", "numpy", "warp") if any(r.implementation == p for r in rows)]
    header = "| workload | jaxspring (stepper) | particles | springs | steps/s | " + " | ".join(f"x {p}" for p in peers)
    header += " | grad / fwd | compile fwd / grad [s] | memory fwd / grad [MiB] | batch 64 / single |"
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        if not r.implementation.startswith("jaxspring"):
            continue
        ratios = []
        for p in peers:
            peer = by.get((r.workload, p))
            ratios.append(f"{r.steps_per_second / peer.steps_per_second:.1f}" if peer else "—")
        batch = "—" if np.isnan(r.batch_ratio) else f"{r.batch_ratio:.2f}"
        grad = f"{r.gradient_ratio:.2f}" + (" (ckpt)" if r.gradient_mode != "plain" else "")
        lines.append(
            f"| {r.workload} | {r.implementation} ({r.stepper}) | {r.particles} | "
            f"{r.springs} | {r.steps_per_second:,.0f} | {' | '.join(ratios)} | "
            f"{grad} | {r.compile_forward_s:.2f} / {r.compile_gradient_s:.2f} | "
            f"{r.memory_forward_mib:.1f} / {r.memory_gradient_mib:.1f} | {batch} |"
        )
    lines += ["", "Peers (steps/s):", ""]
    lines += [
        "| workload | implementation | steps/s | ns per spring-step | max diff vs jaxspring after 200 steps [m] |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        if not r.implementation.startswith("jaxspring"):
            lines.append(
                f"| {r.workload} | {r.implementation} | {r.steps_per_second:,.1f} | {r.ns_per_spring_step:.2f} | "
                f"{r.max_difference:.1e} |"
            )
    return "\n".join(lines) + "\n"


def plot(rows, path):
    """Cost per spring-step against size for the cloth lattices, per implementation."""
    plt = pyplot()
    cloths = [r for r in rows if r.workload.startswith("cloth")]
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, marker in zip(("jaxspring", "jaxspring_jax", "jax_segment_sum", "numpy", "warp"), "ovsD^"):
        mine = sorted((r for r in cloths if r.implementation == name), key=lambda r: r.springs)
        if mine:
            ax.loglog([r.springs for r in mine], [r.ns_per_spring_step for r in mine], marker=marker, label=name)
    ax.set_xlabel("springs")
    ax.set_ylabel("ns per spring-step (lower is better)")
    ax.set_title("cloth, float32, single rollout, this machine")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.set_dpi(110)
    save_figure(fig, path)
