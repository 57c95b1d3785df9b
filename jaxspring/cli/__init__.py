"""The `jaxspring` command line (DESIGN.md section 5).

Every error a user can cause ends in one line naming the problem and the fix,
exit code 2, no traceback, and no output file left half-written.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from ..sim.integrators import INTEGRATORS
from ..steppers import BACKENDS

EXIT_USER_ERROR = 2
INTEGRATOR_HELP = f"time integrator: {', '.join(INTEGRATORS)} (default: the scene's)"


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit code 2
        self.exit(EXIT_USER_ERROR, f"{self.prog}: error: {message}; see `{self.prog} --help`\n")


BACKEND_HELP = (
    "auto (default): the native C++ lattice kernel where it is built and runs the scene, else pure JAX; "
    "jax: pure JAX (forward mode); native: the C++ kernels"
)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="jaxspring", description="Differentiable mass-spring simulation in JAX.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    run = sub.add_parser("run", help="simulate a scene and write its trajectory (HDF5)")
    run.add_argument("scene", help="scene TOML file, or a built-in name (mass_spring, chain, jelly, cloth)")
    run.add_argument("--steps", type=int, help="time steps (default: the scene's)")
    run.add_argument("--save-every", type=int, help="keep one frame every K steps (default: the scene's)")
    run.add_argument("--out", help="output file (default: SCENE_NAME.h5)")
    run.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE", help="override a parameter, e.g. ks=600"
    )
    run.add_argument("--integrator", metavar="NAME", help=INTEGRATOR_HELP)
    run.add_argument("--dt", type=float, help="time step [s] (default: the scene's)")
    run.add_argument("--backend", choices=BACKENDS, help=BACKEND_HELP)
    _add_common(run)

    check = sub.add_parser(
        "check", help="estimate omega_max and every integrator's stable dt; exit 1 if the scene's would blow up"
    )
    check.add_argument("scene", help="scene TOML file, or a built-in name")
    check.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="override a parameter")
    check.add_argument("--integrator", metavar="NAME", help=INTEGRATOR_HELP)
    check.add_argument("--dt", type=float, help="time step [s] (default: the scene's)")
    check.add_argument("--dtype", choices=["float32", "float64"], default="float64", help="precision (default float64)")

    bench = sub.add_parser("bench", help="benchmarks: speed against peers; speed against error of every integrator")
    bench.add_argument(
        "kind",
        choices=["speed", "accuracy"],
        help="speed: steps/s, gradient cost, compile time, memory, batches, against peers (float32); "
        "accuracy: dt sweep against float64 references",
    )
    bench.add_argument("--scenes", help="accuracy: comma-separated scenes (default: the four seed scenes)")
    bench.add_argument("--peers", default="jax_segment_sum,numpy,warp", help="speed: peers to measure")
    bench.add_argument("--quick", action="store_true", help="small workloads and short horizons (a smoke run)")
    bench.add_argument("--repeats", type=int, default=3, help="timed runs per configuration; the median counts")
    bench.add_argument("--out-dir", default="bench_results", help="folder for the CSV, table and plot")
    bench.add_argument("--quiet", action="store_true", help="no progress lines")

    render = sub.add_parser("render", help="draw a trajectory file to a PNG frame or a GIF movie")
    render.add_argument("file", help="trajectory file written by `jaxspring run`")
    render.add_argument("--out", help="output .png or .gif (default: FILE with .gif)")
    render.add_argument("--frame", type=int, default=-1, help="frame a PNG shows (default: last)")
    render.add_argument("--max-frames", type=int, default=60, help="frames in a GIF (default: 60)")
    render.add_argument("--quiet", action="store_true", help="no progress bar")

    fit = sub.add_parser("fit", help="fit physical parameters to a recorded or synthetic trajectory")
    fit.add_argument("experiment", nargs="?", help="experiment TOML file (optional with --target)")
    fit.add_argument("--target", help="trajectory file to fit (default: the experiment's target)")
    fit.add_argument("--params", help="comma-separated parameters to fit, e.g. ks,kd,cd")
    fit.add_argument("--init", help="start values, e.g. ks=400,kd=2")
    fit.add_argument("--out", help="fit file (default: NAME.fit.h5); a loss/parameter plot goes beside it (.png)")
    fit.add_argument("--resume", action="store_true", help="continue an interrupted fit from --out")
    fit.add_argument("--optimizer", choices=["lbfgs", "adam"], help="optimizer (default: the experiment's, else lbfgs)")
    fit.add_argument("--strategy", choices=["auto", "direct", "curriculum", "shooting"], help="long-horizon strategy")
    fit.add_argument(
        "--ensemble",
        choices=["auto", "gradient", "ensemble"],
        help="full-horizon stage: gradient optimiser or smoothed ensemble Gauss-Newton (auto: ensemble with contact)",
    )
    fit.add_argument("--iterations", type=int, help="most iterations per stage")
    fit.add_argument("--backend", choices=BACKENDS, help=BACKEND_HELP)
    fit.add_argument("--noise", type=float, help="relative observation noise of a synthetic target")
    fit.add_argument("--checkpoint-every", type=int, default=5, help="iterations between checkpoints (default 5)")
    fit.add_argument("--dtype", choices=["float32", "float64"], default="float64", help="precision (default float64)")
    fit.add_argument("--quiet", action="store_true", help="no progress bar")

    demo = sub.add_parser("demo", help="run the four seed scenes; write trajectories, pictures and movies")
    demo.add_argument("--out-dir", default="demo_output", help="folder to write into (default: demo_output)")
    demo.add_argument("--no-movies", action="store_true", help="skip the GIFs (faster)")
    _add_common(demo)
    return parser


def _add_common(sub):
    sub.add_argument("--dtype", choices=["float32", "float64"], default="float32", help="floating-point precision")
    sub.add_argument("--quiet", action="store_true", help="no progress bar")


def main(argv=None) -> int:
    """Entry point of the `jaxspring` console script; returns the exit code."""
    args = build_parser().parse_args(argv)
    from ..errors import JaxspringError

    try:
        if getattr(args, "dtype", "float32") == "float64" or (args.command == "bench" and args.kind == "accuracy"):
            import jax

            jax.config.update("jax_enable_x64", True)
        handler = {
            "run": _cmd_run,
            "check": _cmd_check,
            "bench": _cmd_bench,
            "render": _cmd_render,
            "demo": _cmd_demo,
            "fit": _cmd_fit,
        }[args.command]
        return handler(args) or 0
    except JaxspringError as exc:
        print(f"jaxspring: error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("jaxspring: interrupted; no output file was written", file=sys.stderr)
        return 130


def _parse_sets(items) -> dict:
    from ..errors import InputError

    values = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise InputError("--set", f"{item!r} is not NAME=VALUE", "write e.g. --set ks=600")
        try:
            value = float(text)
        except ValueError:
            raise InputError(f"--set {name}", f"{text!r} is not a number", f"write e.g. --set {name}=600") from None
        if not math.isfinite(value):
            raise InputError(f"--set {name}", "must be finite", "give a finite number")
        values[name.strip()] = value
    return values


def _prepare_scene(args):
    from ..errors import InputError
    from ..io.scene import load_scene

    scene = load_scene(args.scene)
    if args.integrator:
        scene = scene.with_integrator(args.integrator)
    if getattr(args, "dt", None) is not None:
        scene = scene.with_dt(args.dt)
    if getattr(args, "backend", None):
        scene = scene.with_backend(args.backend)
    overrides = _parse_sets(args.set)
    if overrides:
        scene = scene.with_params(**overrides)
    if args.command == "check":
        return scene, None, None
    steps = scene.steps if args.steps is None else args.steps
    save_every = scene.save_every if args.save_every is None else args.save_every
    if save_every < 1:
        raise InputError("--save-every", f"must be >= 1, got {save_every}", "give a positive stride")
    if steps < 1:
        raise InputError("--steps", f"must be >= 1, got {steps}", "give a positive number of steps")
    if steps % save_every:
        raise InputError("--steps", f"{steps} is not a multiple of --save-every {save_every}", "make it one")
    return scene, steps, save_every


def _check_out_folder(path: Path):
    from ..errors import InputError

    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InputError("--out", f"folder {str(folder)!r} does not exist", "create it or choose another path")


def _simulate_and_save(scene, steps, save_every, out: Path, quiet: bool):
    from ..errors import BlowUpError
    from ..io.trajectory import save_trajectory
    from ..sim.run import run_scene
    from ..sim.stability import estimate_stability

    stability = estimate_stability(scene.model, scene.params, scene.state)
    if stability.margin < 1:
        print(f"jaxspring: warning: {_instability_advice(scene, stability)}", file=sys.stderr, flush=True)
    result = run_scene(scene, steps, save_every, show_progress=not quiet, stability=stability)
    if result.blowup is not None:
        raise BlowUpError(f"{scene.name}: {result.blowup.describe()}; no file was written")
    save_trajectory(out, scene, result.trajectory)
    return result


def _instability_advice(scene, stability) -> str:
    stable = [n for n, b in stability.bounds.items() if b >= scene.model.dt]
    return (
        f"{scene.name}: dt {scene.model.dt:g} s exceeds {stability.integrator}'s stable-dt estimate "
        f"{stability.dt_bound:.3g} s; expect a blow-up (stable at this dt: {', '.join(stable)})"
    )


def _cmd_check(args):
    from ..sim.stability import estimate_stability

    scene, _, _ = _prepare_scene(args)
    stability = estimate_stability(scene.model, scene.params, scene.state)
    m = scene.model
    print(
        f"{scene.name}: {m.particle_count} particles, {m.spring_count} springs, terms {', '.join(m.terms)}; "
        f"dt {m.dt:g} s, integrator {m.integrator}"
    )
    print(
        f"linearised at the initial state{' with every particle in ground contact' if m.has('ground') else ''}: "
        f"omega_max {stability.omega_max:.4g} rad/s, damping rate {stability.damping_max:.4g} 1/s"
    )
    print(stability.table())
    if stability.margin < 1:
        print(f"jaxspring: warning: {_instability_advice(scene, stability)}", file=sys.stderr)
        return 1
    print(f"ok: {m.integrator} at dt {m.dt:g} s is within its stable dt (margin {stability.margin:.3g}x)")
    return 0


def _cmd_bench(args):
    if args.kind == "speed":
        return _bench_speed(args)
    return _bench_accuracy(args)


def _bench_folder(args) -> Path:
    from ..errors import InputError

    if args.repeats < 1:
        raise InputError("--repeats", f"must be >= 1, got {args.repeats}", "time at least one run")
    out = Path(args.out_dir)
    if not out.is_dir():
        if out.exists() or not out.parent.is_dir():
            raise InputError("--out-dir", f"cannot create folder {str(out)!r}", "choose a folder")
        out.mkdir()
    return out


def _bench_speed(args):
    import jax

    from ..bench import peers as _peers
    from ..bench import speed as _speed
    from ..errors import InputError

    peers = [p.strip() for p in args.peers.split(",") if p.strip()]
    for peer in peers:
        if peer not in ("jax_segment_sum", "numpy", "warp"):
            raise InputError("--peers", f"unknown peer {peer!r}", "use some of jax_segment_sum, numpy, warp")
    if "warp" in peers and not _peers.warp_available():
        print("jaxspring: notice: warp-lang is not installed; skipping the Warp peer", file=sys.stderr)
    out = _bench_folder(args)

    def progress(row):
        if not args.quiet:
            extra = f"  grad/fwd {row.gradient_ratio:.2f}" if row.implementation.startswith("jaxspring") else ""
            print(
                f"{row.workload:14s} {row.implementation:16s} {row.steps_per_second:12,.1f} steps/s"
                f"  {row.ns_per_spring_step:8.2f} ns/spring-step{extra}",
                file=sys.stderr,
                flush=True,
            )

    x64 = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", False)  # speed is measured in float32
    try:
        rows = _speed.sweep(quick=args.quick, repeats=args.repeats, peers=peers, progress=progress)
    finally:
        jax.config.update("jax_enable_x64", x64)
    _speed.write_csv(rows, out / "speed.csv")
    table = _speed.markdown(rows) + f"\nPeak process memory: {_speed.peak_rss_mib():.0f} MiB.\n"
    (out / "speed.md").write_text(table)
    _speed.plot(rows, out / "speed.png")
    print(table)
    print(f"wrote {out / 'speed.csv'}, {out / 'speed.md'}, {out / 'speed.png'}")


def _bench_accuracy(args):
    from ..bench import accuracy as _accuracy
    from ..errors import InputError

    table = _accuracy.QUICK_SWEEPS if args.quick else _accuracy.SWEEPS
    names = [n.strip() for n in args.scenes.split(",")] if args.scenes else list(table)
    for name in names:
        if name not in table:
            raise InputError("--scenes", f"no accuracy sweep for {name!r}", f"use some of {', '.join(table)}")
    out = _bench_folder(args)

    def progress(row):
        if not args.quiet:
            print(
                f"{row.scene:12s} {row.integrator:20s} dt {row.dt:9.3g}  {row.seconds_per_simulated_second:9.3g} s/s"
                f"  error {row.error:9.2e}  energy error {row.energy_error:9.2e}  {'stable' if row.stable else 'UNSTABLE'}",
                file=sys.stderr,
                flush=True,
            )

    rows = _accuracy.sweep(names, quick=args.quick, repeats=args.repeats, progress=progress)
    _accuracy.write_csv(rows, out / "accuracy.csv")
    (out / "accuracy.md").write_text(_accuracy.markdown(rows))
    _accuracy.plot(rows, out / "accuracy.png")
    print(_accuracy.markdown(rows))
    print(f"wrote {out / 'accuracy.csv'}, {out / 'accuracy.md'}, {out / 'accuracy.png'}")


def _summary(scene, result, out) -> str:
    return (
        f"{scene.name}: {result.steps} steps of {scene.model.dt:g} s in {result.wall_s:.3f} s "
        f"({result.steps_per_second:,.0f} steps/s; compile {result.compile_s:.2f} s); "
        f"energy {result.energy_start:.6g} J -> {result.energy_end:.6g} J; wrote {out}"
    )


def _cmd_run(args):
    scene, steps, save_every = _prepare_scene(args)
    out = Path(args.out or f"{scene.name}.h5")
    _check_out_folder(out)
    result = _simulate_and_save(scene, steps, save_every, out, args.quiet)
    print(_summary(scene, result, out))


def _render_with_progress(scene, trajectory, out, frame, max_frames, quiet, label):
    from tqdm.auto import tqdm

    from ..render import render

    with tqdm(
        total=0, desc=label, unit="frame", file=sys.stderr, disable=quiet or not sys.stderr.isatty(), leave=False
    ) as bar:

        def progress(done, total):
            bar.total = total
            bar.n = done + 1
            bar.refresh()

        render(scene, trajectory, out, frame=frame, max_frames=max_frames, progress=progress)


def _cmd_render(args):
    from ..io.trajectory import load_trajectory

    scene, trajectory = load_trajectory(args.file)
    out = Path(args.out) if args.out else Path(args.file).with_suffix(".gif")
    _check_out_folder(out)
    _render_with_progress(scene, trajectory, out, args.frame, args.max_frames, args.quiet, f"render {out.name}")
    print(f"wrote {out}")


def _parse_values(text) -> dict:
    """ "ks=400,kd=2" -> {"ks": 400.0, "kd": 2.0}."""
    return _parse_sets([item for item in (text or "").split(",") if item.strip()])


def _fit_problem(args):
    """(experiment, observations, names, init, settings, config) from the command line."""
    import dataclasses

    from ..errors import InputError
    from ..fit.core import FitSettings
    from ..io.experiment import Experiment, load_experiment, observations_from_file
    from ..io.trajectory import load_trajectory

    if args.experiment:
        experiment = load_experiment(args.experiment)
    elif args.target:
        recorded, _ = load_trajectory(args.target)
        experiment = Experiment(name=Path(args.target).stem, scene=recorded, params=(), init={}, settings=FitSettings())
    else:
        raise InputError("fit", "nothing to fit", "give an EXPERIMENT.toml or --target FILE.h5")
    if args.backend:
        experiment = experiment.replace(scene=experiment.scene.with_backend(args.backend))
    if args.params:
        experiment = experiment.replace(params=tuple(p.strip() for p in args.params.split(",") if p.strip()))
    if not experiment.params:
        raise InputError("--params", "no parameters named", "give e.g. --params ks,kd,cd")
    init = {k: v for k, v in experiment.init.items() if k in experiment.params}  # --params may narrow the fit
    init.update(_parse_values(args.init))
    changes = {
        k: getattr(args, k) for k in ("optimizer", "strategy", "ensemble", "iterations") if getattr(args, k) is not None
    }
    settings = dataclasses.replace(experiment.settings, **changes).validate()
    if args.noise is not None:
        if args.noise < 0:
            raise InputError("--noise", "must be >= 0", "give a relative noise level such as 0.01")
        experiment = experiment.replace(noise=args.noise)
    if args.target:
        observations = observations_from_file(experiment.scene, args.target)
    else:
        observations = experiment.observations()
    config = {
        "experiment": str(args.experiment) if args.experiment else None,
        "target": str(args.target or experiment.target_file or "synthetic"),
        "params": list(experiment.params),
        "init": {k: np.asarray(v).tolist() for k, v in sorted(init.items())},
        **{f"settings.{k}": v for k, v in dataclasses.asdict(settings).items()},
        "noise": experiment.noise,
        "steps": experiment.steps,
        "save_every": experiment.save_every,
        "seed": experiment.seed,
        "dtype": args.dtype,
        "backend": experiment.scene.model.backend,
    }
    return experiment, observations, experiment.params, init, settings, config


def _cmd_fit(args):
    import copy
    import signal

    from tqdm.auto import tqdm

    from ..errors import InputError
    from ..fit.core import fit_batch
    from ..io.fit_file import load_fit_progress, save_fit
    from ..render import plot_fit

    if args.checkpoint_every < 1:
        raise InputError("--checkpoint-every", "must be >= 1", "give a positive number of iterations")
    experiment, observations, names, init, settings, config = _fit_problem(args)
    scene = experiment.scene
    default = Path(args.experiment).stem if args.experiment else Path(args.target).stem
    out = Path(args.out or f"{default}.fit.h5")
    _check_out_folder(out)
    progress = load_fit_progress(out, config, names) if args.resume else None
    present = scene.params.to_dict()
    initial = {n: np.asarray(init.get(n, present[n]), dtype=float) for n in names if n in present}
    latest = [None]
    bar = tqdm(
        total=settings.iterations,
        desc=f"fit {experiment.name}",
        unit="it",
        file=sys.stderr,
        disable=args.quiet or not sys.stderr.isatty(),
        leave=False,
    )

    # SIGINT/SIGTERM stop the fit at the next iteration (a flag, so no library code in
    # between can swallow the interrupt); a second signal stops it at once.
    interrupted = []

    def on_iteration(current, stages):
        snapshot = copy.copy(current)
        snapshot.loss, snapshot.stage_of_iteration = list(current.loss), list(current.stage_of_iteration)
        snapshot.values = {n: list(v) for n, v in current.values.items()}
        latest[0] = snapshot
        if interrupted:  # saved (with this iteration) by the handler below
            raise KeyboardInterrupt
        if current.loss:
            values = " ".join(f"{n}={float(np.mean(np.exp(np.asarray(current.theta[n])))):.5g}" for n in names)
            bar.set_description(f"fit {experiment.name} stage {min(current.stage, len(stages) - 1) + 1}/{len(stages)}")
            bar.set_postfix_str(f"loss={float(np.asarray(current.loss[-1])[0]):.3e} {values}", refresh=False)
            bar.n = current.iteration
            bar.refresh()
        if current.done or current.iteration == 0 or len(current.loss) % args.checkpoint_every == 0:
            save_fit(out, config, names, initial, snapshot)

    def terminate(signum, frame):
        if interrupted:
            raise KeyboardInterrupt
        interrupted.append(signum)

    previous = {sig: signal.signal(sig, terminate) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with bar:
            result = fit_batch(
                scene, [observations], names, [init], settings, progress=progress, on_iteration=on_iteration
            )[0]
        final = latest[0] or progress
        save_fit(out, config, names, initial, final, result)
    except KeyboardInterrupt:
        if latest[0] is not None:
            save_fit(out, config, names, initial, latest[0])
            done = len(latest[0].loss)
            print(
                f"jaxspring: interrupted after {done} iterations; saved to {out}; continue with --resume",
                file=sys.stderr,
            )
        return 130
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    plot = plot_fit(result, out.with_suffix(".png"))
    print(result.table())
    print(f"wrote {out} and {plot}")


def _cmd_demo(args):
    from ..io.scene import builtin_scenes, load_scene

    folder = Path(args.out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    rows = []
    for name in builtin_scenes():
        scene = load_scene(name)
        out = folder / f"{name}.h5"
        result = _simulate_and_save(scene, scene.steps, scene.save_every, out, args.quiet)
        print(_summary(scene, result, out), flush=True)
        traj = result.trajectory
        _render_with_progress(scene, traj, folder / f"{name}.png", -1, 60, args.quiet, f"{name}.png")
        if not args.no_movies:
            _render_with_progress(scene, traj, folder / f"{name}.gif", -1, 60, args.quiet, f"{name}.gif")
        rows.append((name, scene.model.particle_count, scene.model.spring_count, result))
    print()
    print(
        f"{'scene':<12}{'particles':>10}{'springs':>9}{'steps':>8}{'steps/s':>12}{'E start [J]':>14}{'E end [J]':>14}"
    )
    for name, n, s, r in rows:
        print(
            f"{name:<12}{n:>10}{s:>9}{r.steps:>8}{r.steps_per_second:>12,.0f}{r.energy_start:>14.6g}{r.energy_end:>14.6g}"
        )
    print(
        f"\nwrote trajectories (.h5), last frames (.png){'' if args.no_movies else ' and movies (.gif)'} "
        f"to {folder}/ in {time.perf_counter() - start:.1f} s"
    )


if __name__ == "__main__":
    sys.exit(main())
