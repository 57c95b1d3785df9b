"""Cables: fit recordings of a model jaxspring does not contain, predict held-out ones.

The recordings come from benchmarks/cable_recordings.py (a discrete elastic rod with twist,
natural curvature, non-uniform mass and anisotropic drag, clamped with orientation by two
grippers; 12 markers at 100 Hz, 1 mm noise, drop-outs). Every variant below is fitted to the
training recordings with `js.fit` (default settings) and predicts the held-out ones from their
start frame with the grippers' markers driven as recorded. The floor is the baseline "free
markers frozen at the start frame". Each variant runs in its own process, so its wall time and
peak memory (max RSS) are its own.

    python benchmarks/cables.py [--data DIR] [--train 8 --held-out 14 --frames 500] [--variants a,b]
    python benchmarks/cables.py --starts 0.1,1,10      # the start sweep around the best values

The start sweep (with --starts) first runs a dense search: the training misfit at `--dense` points
of a Latin hypercube between the table's fitted values / 10 and x 10, then a fit from each of the
two lowest; the fit of lowest held-out error among them and the table's is "the best".
Then every start value of the best point times each factor is a start of a default fit, which
passes when its held-out error is within 5% of the best.

Writes benchmarks/results/cables_<train>x<frames>.md (and, with --starts, the sweep's tables).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).parent
VARIANTS = {  # name: (description, cable_scene keyword arguments)
    "rope": ("rope, a particle per marker, straight at rest", dict(subdivide=1, rest="straight")),
    "rope_rest": ("rope, a particle per marker, rest shape from data", dict(subdivide=1, rest="data")),
    "cable2": ("cable, 2 particles per marker interval, straight at rest", dict(subdivide=2, rest="straight")),
    "cable2_rest": ("cable, 2 per interval, rest shape from data", dict(subdivide=2, rest="data")),
    "rope_bending": (
        "rope, a particle per marker, straight at rest, bending term",
        dict(subdivide=1, rest="straight", bending=True),
    ),
    "rope_bending_rest": (
        "rope, a particle per marker, rest shape from data, bending term",
        dict(subdivide=1, rest="data", bending=True),
    ),
    "cable2_bending": (
        "cable, 2 per interval, straight, bending term, dt 0.5 ms",
        dict(subdivide=2, rest="straight", bending=True, dt=5e-4),
    ),
    "cable3_groups": (
        "cable, 3 per interval, straight, 3 segment groups",
        dict(subdivide=3, rest="straight", groups=3),
    ),
}
START, SMOOTH, MASS, DRIVEN = 5, 5, 0.2, (0, 1, -2, -1)


def load(folder: Path, part: str, frames: int, count: int | None = None):
    import jaxspring as js

    out = []
    for path in sorted((folder / part).glob("*.h5"))[:count]:
        r = js.load_recording(path)
        out.append(js.Recording(t=r.t[:frames], x=r.x[:frames], markers=r.markers))
    return out


def _setup(folder: Path, name: str, frames: int, train: int, held_out: int):
    """The variant's scene, training target, fitted names, scene values, held-out takes and predict options."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxspring as js

    train, held = load(folder, "train", frames, train), load(folder, "held_out", frames, held_out)
    cable = js.cable_scene(train, driven=DRIVEN, mass=MASS, reference=(0, START), **VARIANTS[name][1])
    scene = js.scene_from_dict(cable.scene)
    target = js.recording_target(scene, train, markers=cable.markers, driven=cable.driven, start=START, smooth=SMOOTH)
    physics = cable.scene["physics"]
    scalars = [k for k in ("cd", "kb", "kbd") if k in physics]
    params = [f"ks.{g}" for g in physics["ks"]] + [f"kd.{g}" for g in physics["kd"]] + scalars
    values = {f"{k}.{g}": v for k in ("ks", "kd") for g, v in physics[k].items()}
    values |= {k: physics[k] for k in scalars}
    options = dict(markers=cable.markers, driven=cable.driven, start=START, smooth=SMOOTH)
    return scene, target, params, values, held, options


def run_variant(
    folder: Path,
    name: str,
    frames: int,
    factor: float,
    train: int,
    held_out: int,
    center: dict | None = None,
    iterations: int | None = None,
    search_starts: int | None = None,
) -> dict:
    """Fit one variant (in this process) from `factor` x `center` (default: the scene's values) and
    predict the held-out recordings; the numbers as a dict. `iterations`, `search_starts`: the
    fit's most iterations per stage and its start search's starts (default: js.fit's)."""
    import jaxspring as js

    scene, target, params, values, held, options = _setup(folder, name, frames, train, held_out)
    init = {n: factor * float((center or values)[n]) for n in params}
    budget = {k: v for k, v in dict(iterations=iterations, starts=search_starts).items() if v is not None}
    clock = time.perf_counter()
    result = js.fit(scene, target, params, init=init, **budget)
    fit_s = time.perf_counter() - clock
    fitted = js.fitting.summarise(js.predict(scene, result.final, held, **options))
    started = js.fitting.summarise(js.predict(scene, init, held, **options))
    return dict(
        name=name,
        particles=int(scene.state.x.shape[0]),
        params=len(params),
        factor=factor,
        fit_s=fit_s,
        iterations=int(result.iterations),
        train_loss=float(result.loss_history[-1]),
        coordinate=fitted.mean_coordinate_error,
        distance=fitted.mean_distance,
        frozen_coordinate=fitted.frozen_coordinate_error,
        frozen_distance=fitted.frozen_distance,
        start_coordinate=started.mean_coordinate_error,
        moved={n: float(result.final[n]) / init[n] for n in params},
        final={n: float(result.final[n]) for n in params},
        peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    )


def run_dense(
    folder: Path, name: str, frames: int, train: int, held_out: int, center: dict, count: int, fits: int = 2
) -> dict:
    """The dense search (module docstring): the training misfit at `count` points around `center`,
    then a fit (no start search) from each of the `fits` lowest, predicting the held-out takes."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxspring as js
    from jaxspring.fit.recording_loss import loss_function, target_data
    from jaxspring.fit.search import latin_starts
    from jaxspring.fit.settings import Stage

    scene, target, params, _, held, options = _setup(folder, name, frames, train, held_out)
    clock = time.perf_counter()
    points = latin_starts({n: float(center[n]) for n in params}, count + 1, 10.0, seed=1)[1:]
    misfit = jax.jit(jax.vmap(loss_function(scene, target, params, Stage("direct", target.frame_count - 1)), (0, None)))
    data, chunk, losses = target_data(target), 16, []
    for i in range(0, count, chunk):
        logs = {n: jnp.log(jnp.asarray([p[n] for p in points[i : i + chunk]])) for n in params}
        losses += [float(v) if math.isfinite(float(v)) else math.inf for v in misfit(logs, data)]
    scan_s = time.perf_counter() - clock
    fitted = []
    for i in np.argsort(losses)[:fits]:
        clock = time.perf_counter()
        r = js.fit(scene, target, params, init=points[i], starts=1)
        final = {n: float(r.final[n]) for n in params}
        error = js.fitting.summarise(js.predict(scene, final, held, **options)).mean_coordinate_error
        fitted.append(
            dict(
                start=points[i],
                start_loss=losses[i],
                final=final,
                coordinate=float(error),
                train_loss=float(r.loss_history[-1]),
                fit_s=time.perf_counter() - clock,
            )
        )
    return dict(
        name=name,
        count=count,
        simulated=int(np.isfinite(losses).sum()),
        scan_s=scan_s,
        points=fitted,
        peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    )


def child(
    folder: Path,
    name: str,
    frames: int,
    factor: float,
    train: int,
    held_out: int,
    center=None,
    dense: int = 0,
    iterations: int | None = None,
    search_starts: int | None = None,
) -> dict:
    """`run_variant` (or with `dense`, `run_dense`) in a fresh process (its own wall time and peak memory)."""
    argv = [sys.executable, __file__, "--data", str(folder), "--frames", str(frames), "--child", name]
    argv += ["--train", str(train), "--held-out", str(held_out)]
    argv += ["--factor", repr(factor), "--dense", str(dense)]
    if iterations is not None:
        argv += ["--iterations", str(iterations)]
    if search_starts is not None:
        argv += ["--search-starts", str(search_starts)]
    if center is not None:
        argv += ["--center", json.dumps(center)]
    done = subprocess.run(argv, capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    if done.returncode:
        raise SystemExit(f"variant {name} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def table(rows: list[dict], title: str) -> list[str]:
    lines = [
        title,
        "",
        "| variant | particles | fitted values | fit [s] | peak memory [MB] | training misfit [mm^2] "
        "| held-out mean abs. error per coordinate [mm] | mean distance [mm] | at the start values [mm] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {VARIANTS[r['name']][0]} | {r['particles']} | {r['params']} | {r['fit_s']:.0f} | {r['peak_mb']:.0f} "
            f"| {1e6 * r['train_loss']:.1f} | {1e3 * r['coordinate']:.2f} | {1e3 * r['distance']:.2f} "
            f"| {1e3 * r['start_coordinate']:.2f} |"
        )
    r = rows[0]
    lines.append(
        f"| floor: free markers frozen at the start frame | | | | | | {1e3 * r['frozen_coordinate']:.2f} "
        f"| {1e3 * r['frozen_distance']:.2f} | |"
    )
    return lines


def start_sweep(folder: Path, args, rows: list[dict]) -> list[str]:
    """The dense search around the table's fit of the sweep's variant, then a default fit from every
    factor on the best point found (module docstring); the two tables' lines."""
    reference = min(rows, key=lambda r: r["coordinate"])
    if args.sweep_variant:
        reference = next(r for r in rows if r["name"] == args.sweep_variant)
    name, where = reference["name"], (folder, reference["name"], args.frames)
    dense = child(*where, 1.0, args.train, args.held_out, center=reference["final"], dense=args.dense)
    print(json.dumps(dense), flush=True)
    candidates = [dict(final=reference["final"], coordinate=reference["coordinate"], start="the table's fit")]
    candidates += [dict(p, start="a dense-search fit") for p in dense["points"]]
    best = min(candidates, key=lambda p: p["coordinate"])
    sweep = []
    for f in args.starts.split(","):
        sweep.append(child(*where, float(f), args.train, args.held_out, center=best["final"]))
        print(json.dumps(sweep[-1]), flush=True)
    top = best["coordinate"]
    lines = [
        "",
        f"Dense search around the table's fit of {VARIANTS[name][0]}: the training misfit at {dense['count']} points "
        f"of a Latin hypercube between its values / 10 and x 10 ({dense['simulated']} simulate; "
        f"{dense['scan_s']:.0f} s), then a default fit without start search from each of the "
        f"{len(dense['points'])} lowest: "
        + "; ".join(
            f"{1e6 * p['start_loss']:.1f} -> {1e6 * p['train_loss']:.1f} mm^2, held out {1e3 * p['coordinate']:.2f} mm "
            f"({p['fit_s']:.0f} s)"
            for p in dense["points"]
        )
        + f". The best point ({best['start']}): {1e3 * top:.2f} mm, "
        + ", ".join(f"{n} {v:.4g}" for n, v in best["final"].items())
        + ".",
        "",
        "Start sweep: every value of the best point times a factor, a default fit (js.fit) from there.",
        "",
        "| start factor | fit [s] | iterations | training misfit [mm^2] | held-out mean abs. error per coordinate [mm] "
        "| within 5% of the best | largest move (fitted / start) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in sweep:
        move = max(r["moved"].values(), key=lambda m: abs(math.log(m)))
        lines.append(
            f"| {r['factor']:g} | {r['fit_s']:.0f} | {r['iterations']} | {1e6 * r['train_loss']:.1f} "
            f"| {1e3 * r['coordinate']:.2f} | {'yes' if r['coordinate'] <= 1.05 * top else 'no'} | {move:.3g} |"
        )
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", help="folder of cable_recordings.py output (default: made in a temporary folder)")
    parser.add_argument("--train", type=int, default=8)
    parser.add_argument("--held-out", type=int, default=14)
    parser.add_argument("--frames", type=int, default=500)
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    parser.add_argument("--starts", help="start sweep: factors on every start value (e.g. 0.1,1,10), best variant")
    parser.add_argument("--sweep-variant", help="the start sweep's variant (default: the best of the table)")
    parser.add_argument("--out", help="results file (default benchmarks/results/cables_<train>x<frames>.md)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--dense", type=int, default=256, help="points of the start sweep's dense search")
    parser.add_argument(
        "--iterations", type=int, help="most iterations per stage of the table's fits (default: js.fit's; for tests)"
    )
    parser.add_argument(
        "--search-starts", type=int, help="start search starts of the table's fits (default: js.fit's; 1: no search)"
    )
    parser.add_argument("--factor", type=float, default=1.0, help=argparse.SUPPRESS)
    parser.add_argument("--center", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        center = json.loads(args.center) if args.center else None
        where = (Path(args.data), args.child, args.frames)
        if center is not None and args.dense:
            print(json.dumps(run_dense(*where, args.train, args.held_out, center, args.dense)))
        else:
            budget = (args.iterations, args.search_starts)
            print(json.dumps(run_variant(*where, args.factor, args.train, args.held_out, center, *budget)))
        return
    folder = Path(args.data) if args.data else Path(tempfile.mkdtemp(prefix="jaxspring-cables-"))
    if not (folder / "truth.json").exists():
        sys.path.insert(0, str(HERE))
        import cable_recordings

        cable_recordings.make_cable_recordings(folder, train=args.train, held_out=args.held_out, frames=args.frames)
    names = args.variants.split(",")
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variant {unknown[0]!r}: give some of {', '.join(VARIANTS)}")
    title = (
        f"# Cables: fit {args.train} x {args.frames} frames, predict {args.held_out} held out "
        f"(benchmarks/cables.py, {os.cpu_count()} cores)"
    )
    rows = []
    for name in names:
        budget = dict(iterations=args.iterations, search_starts=args.search_starts)
        rows.append(child(folder, name, args.frames, 1.0, args.train, args.held_out, **budget))
        print(json.dumps(rows[-1]), flush=True)
    lines = table(rows, title)
    if args.starts:
        lines += start_sweep(folder, args, rows)
    out = Path(args.out) if args.out else HERE / "results" / f"cables_{args.train}x{args.frames}.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
