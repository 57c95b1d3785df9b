"""Branched cables: fit recordings of a wire harness from a model jaxspring does not contain, and
predict held-out takes.

The recordings come from benchmarks/harness_recordings.py (a volumetric rod: a parent cable with
two thinner branches joined rigidly, natural curvature, swung by two grippers at the parent's
ends, or at one end and the middle; 18 markers at 100 Hz, 1 mm noise, drop-outs). Every variant
is a `js.cable_scene` over the recordings' marker tree (`truth.json`'s edges and driven markers,
gravity inferred from the sag, or given for a grasp that shows none), fitted with `js.fit`
(default settings: start search, Levenberg-Marquardt) to the training takes, and predicting the
held-out ones from their start frame with the grippers' markers driven as recorded: the
pipeline of `jaxspring cable` -> `fit` -> `predict`. The floor is "free markers frozen at the
start frame". Each variant runs in its own process (its own wall time and peak memory).

    python benchmarks/harness.py [--data DIR] [--grasp ends|middle] [--train 8 --held-out 14 --frames 500]
                                 [--variants a,b] [--iterations N --search-starts N]

Writes benchmarks/results/harness_<grasp>_<train>x<frames>.md.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
from cables import load  # noqa: E402  (the same recordings reader as the chain cable benchmark)

VARIANTS = {  # name: (description, cable_scene keyword arguments)
    "tree": ("a particle per marker, bending term (junctions too), dt 1 ms", dict(subdivide=1, bending=True)),
    "tree_dt": (
        "a particle per marker, bending term, dt 0.25 ms",
        dict(subdivide=1, bending=True, dt=2.5e-4),
    ),
    "tree_branch_groups": (
        "a particle per marker, bending term, a stretch group per branch, dt 0.25 ms",
        dict(subdivide=1, bending=True, groups="branch", dt=2.5e-4),
    ),
    "tree2": ("2 particles per marker interval, bending term, dt 0.25 ms", dict(subdivide=2, bending=True, dt=2.5e-4)),
    "tree_springs": ("a particle per marker, bend springs (no bending term), dt 0.25 ms", dict(subdivide=1, dt=2.5e-4)),
}
START, SMOOTH, MASS = 5, 5, 0.25


def run_variant(folder: Path, name: str, frames: int, train: int, held_out: int, iterations=None, starts=None) -> dict:
    """Fit one variant in this process and predict the held-out recordings; the numbers as a dict."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxspring as js

    truth = json.loads((folder / "truth.json").read_text())
    train_recs, held = load(folder, "train", frames, train), load(folder, "held_out", frames, held_out)
    shape = dict(edges=truth["edges"], driven=truth["driven"], mass=MASS, reference=(0, START), **VARIANTS[name][1])
    with contextlib.redirect_stdout(io.StringIO()) as said:
        try:
            cable = js.cable_scene(train_recs, **shape)
        except js.InputError as exc:  # a single grasp shows no sag: the user gives gravity
            if "held at one place only" not in str(exc):
                raise
            cable = js.cable_scene(train_recs, gravity=truth["gravity"], **shape)
    scene = js.scene_from_dict(cable.scene)
    options = dict(markers=cable.markers, driven=cable.driven, start=START, smooth=SMOOTH)
    target = js.recording_target(scene, train_recs, **options)
    budget = {k: v for k, v in dict(iterations=iterations, starts=starts).items() if v is not None}
    clock = time.perf_counter()
    result = js.fit(scene, target, cable.params, **budget)
    fit_s = time.perf_counter() - clock
    try:
        predictions, blew_up = js.predict(scene, result.final, held, **options), 0
    except js.BlowUpError:  # counted in the table, not hidden: the fit ended past the stability limit
        predictions, blew_up = [], 0
        for take in held:
            try:
                predictions += js.predict(scene, result.final, [take], **options)
            except js.BlowUpError:
                blew_up += 1
    fitted = js.fitting.summarise(predictions) if predictions else None
    nan = float("nan")
    return dict(
        name=name,
        particles=int(scene.state.x.shape[0]),
        params=len(cable.params),
        fit_s=fit_s,
        iterations=int(result.iterations),
        train_loss=float(result.loss_history[-1]),
        coordinate=fitted.mean_coordinate_error if fitted else nan,
        distance=fitted.mean_distance if fitted else nan,
        frozen_coordinate=fitted.frozen_coordinate_error if fitted else nan,
        frozen_distance=fitted.frozen_distance if fitted else nan,
        blew_up=blew_up,
        final={n: float(result.final[n]) for n in cable.params},
        gravity=said.getvalue().strip() or cable.gravity_note,
        peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    )


def child(folder: Path, name: str, args) -> dict:
    argv = [sys.executable, __file__, "--data", str(folder), "--frames", str(args.frames), "--child", name]
    argv += ["--train", str(args.train), "--held-out", str(args.held_out)]
    for flag, value in (("--iterations", args.iterations), ("--search-starts", args.search_starts)):
        if value is not None:
            argv += [flag, str(value)]
    done = subprocess.run(argv, capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    if done.returncode:
        raise SystemExit(f"variant {name} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def table(rows: list[dict], title: str) -> list[str]:
    lines = [
        title,
        "",
        "| variant | particles | fitted values | fit [s] | iterations | peak memory [MB] | training misfit [mm^2] "
        "| held-out mean abs. error per coordinate [mm] | mean distance [mm] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {VARIANTS[r['name']][0]} | {r['particles']} | {r['params']} | {r['fit_s']:.0f} | {r['iterations']} "
            f"| {r['peak_mb']:.0f} | {1e6 * r['train_loss']:.1f} | {1e3 * r['coordinate']:.2f}"
            + (f" ({r['blew_up']} of the takes blew up: left out)" if r["blew_up"] else "")
            + " "
            f"| {1e3 * r['distance']:.2f} |"
        )
    r = next((r for r in rows if r["frozen_coordinate"] == r["frozen_coordinate"]), rows[0])
    lines.append(
        f"| floor: free markers frozen at the start frame | | | | | | | {1e3 * r['frozen_coordinate']:.2f} "
        f"| {1e3 * r['frozen_distance']:.2f} |"
    )
    lines += ["", f"Gravity: {r['gravity']}", ""]
    lines += ["Fitted values:", ""] + [
        f"- {r['name']}: " + ", ".join(f"{n} {v:.4g}" for n, v in r["final"].items()) for r in rows
    ]
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", help="folder of harness_recordings.py output (default: made in a temporary folder)")
    parser.add_argument("--grasp", choices=["ends", "middle"], default="ends", help="grippers (when data is made)")
    parser.add_argument("--train", type=int, default=8)
    parser.add_argument("--held-out", type=int, default=14)
    parser.add_argument("--frames", type=int, default=500)
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    parser.add_argument("--iterations", type=int, help="most iterations per stage (default: js.fit's; for tests)")
    parser.add_argument("--search-starts", type=int, help="start search starts (default: js.fit's; 1: no search)")
    parser.add_argument("--dt", type=float, default=5e-5, help="the generator's time step, when data is made")
    parser.add_argument("--out", help="results file (default benchmarks/results/harness_<grasp>_<train>x<frames>.md)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        budget = (args.iterations, args.search_starts)
        print(json.dumps(run_variant(Path(args.data), args.child, args.frames, args.train, args.held_out, *budget)))
        return
    names = args.variants.split(",")
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variant {unknown[0]!r}: give some of {', '.join(VARIANTS)}")
    folder = Path(args.data) if args.data else Path(tempfile.mkdtemp(prefix="jaxspring-harness-"))
    if not (folder / "truth.json").exists():
        import harness_recordings

        harness_recordings.make_harness_recordings(
            folder, train=args.train, held_out=args.held_out, frames=args.frames, grasp=args.grasp, dt=args.dt
        )
    grasp = json.loads((folder / "truth.json").read_text())["grasp"]
    title = (
        f"# Branched cables ({grasp} held): fit {args.train} x {args.frames} frames, predict {args.held_out} held out "
        f"(benchmarks/harness.py, {os.cpu_count()} cores)"
    )
    rows = []
    for name in names:
        rows.append(child(folder, name, args))
        print(json.dumps(rows[-1]), flush=True)
    lines = table(rows, title)
    out = Path(args.out or HERE / "results" / f"harness_{grasp}_{args.train}x{args.frames}.md")
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
