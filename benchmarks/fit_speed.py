"""Fit speed: what one evaluation of a cable fit's misfit costs, and what a whole fit costs.

The cable of benchmarks/cables.py ("rope_bending": 12 particles, 11 springs, 10 bending triples,
the ends clamped by driven markers) fitted to recordings of an independent elastic rod
(benchmarks/cable_recordings.py, 500 frames at 100 Hz, dt 1 ms: 4,950 steps a take).

Part 1, in this process: the whole-horizon misfit of `--takes` takes (default 8), median of
`--repeats` calls after a first one that compiles (reported apart):
  * value and gradient on the default path (the scene as loaded: the native spring and bending
    kernels where built, reverse mode), and on the pure-JAX path;
  * the forward misfit alone on both paths;
  * the Jacobian of the residuals with respect to the 5 log values (jacfwd, pure JAX): what one
    Levenberg-Marquardt iteration takes besides a forward evaluation or two.
Part 2, each fit in its own process (so its wall time and peak memory are its own): `js.fit` with
default settings (the start search included) and with optimizer "lm" (the default on
recordings) and "lbfgs", for each count in `--fits` (default 8), with the held-out error of
14 takes.

    python benchmarks/fit_speed.py [--data DIR] [--takes 8] [--fits 8:auto+lbfgs,56:auto] [--optimizers auto,lbfgs]

DIR holds `python benchmarks/cable_recordings.py --out DIR --train 56` output (made in a
temporary folder when not given). Writes benchmarks/results/fit_speed.md.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).parent
VARIANT = "rope_bending"


def _median_time(call, repeats: int) -> float:
    import jax
    import numpy as np

    times = []
    for _ in range(repeats):
        clock = time.perf_counter()
        jax.block_until_ready(call())
        times.append(time.perf_counter() - clock)
    return float(np.median(times))


def evaluation_costs(folder: Path, takes: int, repeats: int) -> dict:
    """Part 1 (module docstring): seconds per call, and the first call's (compile included)."""
    import jax
    import jax.numpy as jnp
    from cables import _setup

    from jaxspring.fit.objective import loss_function, stage_residual_function, target_data
    from jaxspring.fit.settings import Stage

    scene, target, params, values, _, _ = _setup(folder, VARIANT, 500, takes, 1)
    stage = Stage("direct", target.frame_count - 1)
    data = target_data(target)
    theta = {n: jnp.log(jnp.asarray(float(values[n]))) for n in params}
    out = {"takes": takes, "steps": int(round((target.times[0, -1] - target.times[0, 1]) / scene.model.dt))}
    out["stepper"] = scene.model.stepper.name
    jax_scene = scene.with_backend("jax")
    programs = {
        "value and gradient, default path": jax.jit(jax.value_and_grad(loss_function(scene, target, params, stage))),
        "value and gradient, pure JAX": jax.jit(jax.value_and_grad(loss_function(jax_scene, target, params, stage))),
        "misfit alone, default path": jax.jit(loss_function(scene, target, params, stage)),
        "misfit alone, pure JAX": jax.jit(loss_function(jax_scene, target, params, stage)),
        "Jacobian of the residuals (jacfwd, 5 columns)": jax.jit(
            jax.jacfwd(stage_residual_function(scene, target, params, stage))
        ),
    }
    rows = []
    for name, program in programs.items():
        clock = time.perf_counter()
        jax.block_until_ready(program(theta, data))
        first = time.perf_counter() - clock
        rows.append(dict(name=name, first_s=first, median_s=_median_time(lambda p=program: p(theta, data), repeats)))
    out["rows"] = rows
    return out


def run_fit(folder: Path, takes: int, optimizer: str) -> dict:
    """Part 2: one default fit (start search included) in this process, and its held-out error."""
    from cables import _setup

    import jaxspring as js

    scene, target, params, values, held, options = _setup(folder, VARIANT, 500, takes, 14)
    init = {n: float(values[n]) for n in params}
    clock = time.perf_counter()
    result = js.fit(scene, target, params, init=init, optimizer=optimizer)
    wall = time.perf_counter() - clock
    summary = js.fitting.summarise(js.predict(scene, result.final, held, **options))
    report = result.identifiability
    return dict(
        takes=takes,
        optimizer=optimizer,
        wall_s=wall,
        search_s=result.search.wall_s if result.search else 0.0,
        iterations=int(result.iterations),
        loss=float(result.loss_history[-1]),
        held_out_mm=summary.mean_coordinate_error * 1e3,
        final={n: float(result.final[n]) for n in params},
        se={n: float(report.standard_error[n]) for n in params} if report else {},
        peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    )


def _child(args) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    kind, folder = args.child, Path(args.data)
    if kind == "costs":
        print(json.dumps(evaluation_costs(folder, args.takes, args.repeats)))
    else:
        takes, optimizer = kind.split(":")
        print(json.dumps(run_fit(folder, int(takes), optimizer)))


def _in_child(args, kind: str) -> dict:
    command = [sys.executable, __file__, "--child", kind, "--data", str(args.data), "--takes", str(args.takes)]
    command += ["--repeats", str(args.repeats)]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{kind} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _table(costs: dict, fits: list[dict], command: str) -> str:
    lines = [
        f"# Fit speed: the cable misfit and whole fits (benchmarks/fit_speed.py, 2 cores, {time.strftime('%Y-%m-%d')})",
        "",
        f"Cable `{VARIANT}` of benchmarks/cables.py (12 particles, 11 springs, 10 bending triples; default stepper "
        f"`{costs['stepper']}`), {costs['takes']} takes x 500 frames ({costs['steps']} steps of 1 ms a take), float64.",
        "",
        "| one evaluation of the whole-horizon misfit | first call, compile included [s] | median [s] |",
        "|---|---|---|",
    ]
    lines += [f"| {r['name']} | {r['first_s']:.2f} | {r['median_s']:.3f} |" for r in costs["rows"]]
    lines += [
        "",
        "| takes | optimizer | fit wall [s] | of it the start search [s] | iterations | training misfit [mm^2] "
        "| held-out mean abs. error per coordinate [mm] | peak memory [MB] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for f in fits:
        lines.append(
            f"| {f['takes']} | {f['optimizer']} | {f['wall_s']:.0f} | {f['search_s']:.0f} | {f['iterations']} "
            f"| {f['loss'] * 1e6:.2f} | {f['held_out_mm']:.2f} | {f['peak_mb']:.0f} |"
        )
    lines += ["", "Fitted values (± standard error):", ""]
    for f in fits:
        values = ", ".join(f"{n} {v:.4g} ± {f['se'].get(n, float('nan')):.2g}" for n, v in f["final"].items())
        lines.append(f"- {f['takes']} takes, {f['optimizer']}: {values}")
    lines += ["", f"Measured with `{command}`, alone on the machine."]
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", help="cable_recordings.py output with >= max(--fits) training takes")
    parser.add_argument("--takes", type=int, default=8, help="takes in part 1 (default 8)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--fits", default="8", help="take counts of part 2, each with its own optimizers if given: 8:auto+lbfgs,56:auto"
    )
    parser.add_argument("--optimizers", default="auto,lbfgs", help="optimizers of part 2 (default auto,lbfgs)")
    parser.add_argument("--out", default=str(HERE / "results" / "fit_speed.md"))
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        _child(args)
        return
    plan = []  # (takes, optimizers)
    for item in args.fits.split(","):
        count, _, chosen = item.partition(":")
        plan.append((int(count), (chosen.replace("+", ",") or args.optimizers).split(",")))
    counts = [count for count, _ in plan]
    with tempfile.TemporaryDirectory() as scratch:
        if args.data is None:
            args.data = Path(scratch) / "cables"
            train = str(max(counts + [args.takes]))
            subprocess.run(
                [sys.executable, str(HERE / "cable_recordings.py"), "--out", str(args.data), "--train", train],
                check=True,
                capture_output=True,
            )
        costs = _in_child(args, "costs")
        for r in costs["rows"]:
            print(f"{r['name']}: first {r['first_s']:.2f} s, median {r['median_s']:.3f} s", flush=True)
        fits = []
        for count, optimizers in plan:
            for optimizer in optimizers:
                fits.append(_in_child(args, f"{count}:{optimizer}"))
                f = fits[-1]
                print(
                    f"{count} takes, {optimizer}: {f['wall_s']:.0f} s, held out {f['held_out_mm']:.2f} mm", flush=True
                )
    command = "python benchmarks/fit_speed.py " + " ".join(a for a in (argv or sys.argv[1:]))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_suffix(".md.partial")
    partial.write_text(_table(costs, fits, command.strip()))
    partial.replace(out)  # whole or not at all
    print(f"wrote {out}")


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    main()
