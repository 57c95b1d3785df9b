"""`jaxspring fit`: fit parameters to a target."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from ..fit.settings import OPTIMIZERS
from ..steppers import BACKENDS
from .common import BACKEND_HELP, check_output, parse_sets

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
"""JAX's monitoring event for one XLA compile (its duration is summed into the fit's compile time)."""


def add_parser(sub):
    parser = sub.add_parser("fit", help="fit physical parameters to a recorded or synthetic trajectory")
    parser.add_argument("experiment", nargs="?", help="experiment TOML file (optional with --target)")
    parser.add_argument("--target", help="trajectory file to fit (default: the experiment's target)")
    parser.add_argument("--params", help="comma-separated parameters to fit, e.g. ks,kd,cd")
    parser.add_argument("--init", help="start values, e.g. ks=400,kd=2")
    parser.add_argument("--out", help="fit file (default: NAME.fit.h5); a loss/parameter plot goes beside it (.png)")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted fit from --out")
    parser.add_argument(
        "--optimizer",
        choices=list(OPTIMIZERS),
        help="optimizer (default: the experiment's, else auto: Levenberg-Marquardt on recordings, L-BFGS otherwise)",
    )
    parser.add_argument(
        "--strategy",
        choices=["auto", "direct", "curriculum", "shooting", "position_shooting", "free_shooting"],
        help="long-horizon strategy",
    )
    parser.add_argument(
        "--ensemble",
        choices=["auto", "gradient", "ensemble"],
        help="full-horizon stage: gradient optimiser or smoothed ensemble Gauss-Newton (auto: ensemble with contact)",
    )
    parser.add_argument("--iterations", type=int, help="most iterations per stage")
    parser.add_argument("--backend", choices=BACKENDS, help=BACKEND_HELP)
    parser.add_argument("--noise", type=float, help="relative observation noise of a synthetic target")
    parser.add_argument("--checkpoint-every", type=int, default=5, help="iterations between checkpoints (default 5)")
    parser.add_argument(
        "--dtype", choices=["float32", "float64"], default="float64", help="precision (default float64)"
    )
    parser.add_argument(
        "--max-memory",
        metavar="SIZE",
        help="refuse a fit whose iteration needs more memory, e.g. 4G (default: what is free)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _parse_values(text) -> dict:
    """ "ks=400,kd=2" -> {"ks": 400.0, "kd": 2.0}."""
    return parse_sets([item for item in (text or "").split(",") if item.strip()])


def _fit_problem(args):
    """(experiment, observations, names, init, settings, config) from the command line."""
    import dataclasses

    from ..errors import InputError
    from ..fit.settings import FitSettings
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
        if not (math.isfinite(args.noise) and args.noise >= 0):
            raise InputError(
                "--noise", f"must be finite and >= 0, got {args.noise}", "give a relative level such as 0.01"
            )
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
    if experiment.recordings:
        config.update(
            target=[str(p) for p in experiment.recordings],
            markers=None if experiment.markers is None else list(experiment.markers),
            driven=list(experiment.driven),
            start=experiment.start,
            smooth=experiment.smooth,
            fit_start=experiment.fit_start,
            fit_driven=experiment.fit_driven,
            loss=experiment.loss,
            huber_scale=experiment.huber_scale,
        )
    config["input_content"] = _input_digests(args, experiment)
    return experiment, observations, experiment.params, init, settings, config


def _input_digests(args, experiment) -> dict:
    """SHA-256 of the scene's text and of every file the fit reads its target from: a fit file
    remembers them, and `--resume` refuses inputs that changed since (by name, in its error)."""
    import hashlib

    digests = {"scene": hashlib.sha256(experiment.scene_text.encode("utf-8")).hexdigest()}
    files = [args.experiment, args.target, experiment.target_file, *experiment.recordings]
    for path in dict.fromkeys(str(p) for p in files if p is not None):
        if Path(path).is_file():
            digests[path] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return digests


def command(args):
    import copy
    import signal

    import jax
    from tqdm.auto import tqdm

    from ..errors import BlowUpError, InputError
    from ..fit.loop import fit_batch
    from ..io.fit_file import load_fit_progress, save_fit
    from ..render import plot_fit
    from ..resources import parse_size

    limit = parse_size(args.max_memory) if args.max_memory else None
    if args.checkpoint_every < 1:
        raise InputError("--checkpoint-every", "must be >= 1", "give a positive number of iterations")
    default = Path(args.experiment).stem if args.experiment else Path(args.target or "fit").stem
    out = Path(args.out or f"{default}.fit.h5")
    if out.suffix.lower() != ".h5":
        raise InputError(
            "--out", f"{str(out)!r} does not end in .h5", "name the fit file NAME.h5 (the plot goes beside it)"
        )
    plot = out.with_suffix(".png")
    experiment, observations, names, init, settings, config = _fit_problem(args)
    scene = experiment.scene
    inputs = [args.experiment, args.target, experiment.target_file, *experiment.recordings, *experiment.evaluate]
    prediction = None
    if experiment.recordings:
        prediction = {
            "scene_toml": experiment.scene_text,
            "markers": [int(m) for m in observations.markers],
            "driven": [int(d) for d in observations.driven],
            "start": observations.start,
            "smooth": experiment.smooth,
            "marker_names": list(observations.marker_names),
        }
    for path in (out, plot):
        check_output(path, inputs)
    fitted_markers = getattr(observations, "marker_names", None) or None  # recordings' names (None: a trajectory)
    held_out = _held_out(experiment, fitted_markers)  # checked before the fit, not after it
    progress = load_fit_progress(out, config, names) if args.resume else None
    existed = out.exists()
    present = scene.model.parameter_values(scene.params)
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
    compile_s = [0.0]  # XLA's compile time inside the fit, reported apart from the rest

    def compiled(event, duration, **_):
        if event == COMPILE_EVENT:
            compile_s[0] += duration

    jax.monitoring.register_event_duration_secs_listener(compiled)
    try:
        with bar:
            result = fit_batch(
                scene,
                [observations],
                names,
                [init],
                settings,
                progress=progress,
                on_iteration=on_iteration,
                max_memory=limit,
            )[0]
        finite = all(np.all(np.isfinite(np.asarray(v))) for v in result.final.values())
        if not finite or not np.all(np.isfinite(np.asarray(result.loss_history[-1:]))):
            if not existed:  # its checkpoints are of no use: nothing of this run is left
                out.unlink(missing_ok=True)
            raise BlowUpError(
                f"{experiment.name}: the fit blew up (its values or its misfit are not finite: every rollout from the start "
                "values went past the time step's stability limit); start from softer values (lower init), or "
                "give the scene a smaller dt"
            )
        final = latest[0] or progress
        save_fit(out, config, names, initial, final, result, prediction)
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
        jax.monitoring.unregister_event_duration_listener(compiled)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    plot_fit(result, plot)
    print(result.table())
    print(f"compiling: {compile_s[0]:.1f} s of the fit's {result.wall_s:.1f} s")
    if held_out:
        _evaluate(experiment, result, held_out, fitted_markers)
    print(f"wrote {out} and {plot}")


def _held_out(experiment, marker_names) -> list:
    """The experiment's `[evaluate]` recordings, read, their markers matched by name to the
    fitted ones, and checked against its markers, driven markers and start frame (each problem
    an InputError naming the file)."""
    from ..errors import InputError
    from ..fit.recordings import recording_target
    from ..io.recording import load_recording

    held_out = [load_recording(p) for p in experiment.evaluate]
    for path, recording in zip(experiment.evaluate, held_out):
        try:
            recording_target(
                experiment.scene,
                [recording],
                experiment.markers,
                experiment.driven,
                experiment.start,
                experiment.smooth,
                names=(Path(path).stem,),
                marker_names=marker_names,
            )
        except InputError as exc:
            raise exc.within(str(path), "evaluate") from None
    return held_out


def _evaluate(experiment, result, held_out, result_markers):
    """Print the fitted model's error on the experiment's held-out recordings; a prediction that
    blows up is reported as such (the fit itself is saved)."""
    from ..errors import BlowUpError
    from ..fit.predict import predict

    paths = experiment.evaluate
    try:
        predictions = predict(
            experiment.scene,
            result.final,
            held_out,
            experiment.markers,
            experiment.driven,
            experiment.start,
            experiment.smooth,
            names=tuple(Path(p).stem for p in paths),
            marker_names=result_markers,
        )
    except BlowUpError as exc:
        print(f"held-out: unstable, no error to report: {exc}")
        return
    print_errors("held-out", predictions)


def print_errors(title, predictions):
    """One line per prediction and one pooled over all (every seen marker coordinate after the
    start counts once): mean |error| per coordinate, mean and RMS distance, and the same for
    the frozen-at-start baseline; then the pooled mean |error| per marker."""
    from ..fit.predict import summarise

    print(
        f"{title:<24} {'mean |error| per coordinate [mm]':>33} {'mean distance [mm]':>19} {'RMS distance [mm]':>18}"
        f" {'frozen at start: per coordinate, distance [mm]':>47}"
    )
    rows = [(p.name, p) for p in predictions]
    summary = summarise(predictions)
    if len(predictions) > 1:
        rows.append((f"all {len(predictions)} (pooled)", summary))
    for name, p in rows:
        frozen = f"{1e3 * p.frozen_coordinate_error:.3f}, {1e3 * p.frozen_distance:.3f}"
        print(
            f"{name:<24} {1e3 * p.mean_coordinate_error:>33.3f} {1e3 * p.mean_distance:>19.3f}"
            f" {1e3 * p.rms_error:>18.3f} {frozen:>47}"
        )
    names = predictions[0].marker_names or tuple(str(k) for k in range(summary.marker_coordinate_error.size))
    cells = [f"{n} {1e3 * e:.2f}" for n, e in zip(names, summary.marker_coordinate_error)]
    print(f"per marker, mean |error| per coordinate [mm]: {', '.join(cells)}")
