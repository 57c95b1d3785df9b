"""Pieces every subcommand shares: the parser class, scene preparation, output checks."""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
from pathlib import Path

from ..sim.integrators import INTEGRATORS

EXIT_USER_ERROR = 2
INTEGRATOR_HELP = f"time integrator: {', '.join(INTEGRATORS)} (default: the scene's)"


class Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit code 2
        self.exit(EXIT_USER_ERROR, f"{self.prog}: error: {message}; see `{self.prog} --help`\n")


BACKEND_HELP = (
    "auto (default): the native C++ lattice kernel where it is built and runs the scene, else pure JAX; "
    "jax: pure JAX (forward mode); native: the C++ kernels"
)


def add_common(sub):
    sub.add_argument("--dtype", choices=["float32", "float64"], default="float32", help="floating-point precision")
    sub.add_argument(
        "--max-memory",
        metavar="SIZE",
        help="refuse work estimated to need more memory, e.g. 4G (default: what is free)",
    )
    sub.add_argument("--quiet", action="store_true", help="no progress bar")


def parse_sets(items) -> dict:
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


def prepare_scene(args):
    from ..io.scene import load_scene
    from ..sim.rollout import frame_count, step_count

    scene = load_scene(args.scene)
    if args.integrator:
        scene = scene.with_integrator(args.integrator)
    if getattr(args, "dt", None) is not None:
        scene = scene.with_dt(args.dt)
    if getattr(args, "backend", None):
        scene = scene.with_backend(args.backend)
    overrides = parse_sets(args.set)
    if overrides:
        scene = scene.with_params(**overrides)
    if args.command == "check":
        return scene, None, None
    steps = scene.steps if args.steps is None else args.steps
    save_every = scene.save_every if args.save_every is None else args.save_every
    fields = (
        "--steps" if args.steps is not None else f"{scene.name}: steps",
        "--save-every" if args.save_every is not None else f"{scene.name}: save_every",
    )
    steps = step_count(steps, fields[0], minimum=1)
    frame_count(steps, save_every, fields=fields)
    return scene, steps, save_every


def check_output(out: Path, inputs=(), flag="--out"):
    """Refuse, before any work, an output that is a folder, lies in a missing or unwritable
    folder, or is one of the command's `inputs` (paths; None is skipped)."""
    from ..errors import InputError

    if out.is_dir():
        raise InputError(flag, f"{str(out)!r} is a folder", "give a file name")
    folder = out.parent
    if not folder.is_dir():
        raise InputError(flag, f"folder {str(folder)!r} does not exist", "create it or choose another path")
    check_writable(folder, flag)
    for source in inputs:
        if source is not None and same_file(out, Path(source)):
            raise InputError(flag, f"{str(out)!r} is also an input of this command", "give the output another name")


def check_writable(folder: Path, flag: str):
    """Refuse a folder this process cannot create a file in (tried, not guessed from permissions)."""
    from ..errors import InputError

    try:
        with tempfile.NamedTemporaryFile(prefix=".jaxspring-check.", dir=folder):
            pass
    except OSError as exc:
        raise InputError(
            flag, f"cannot write in folder {str(folder)!r} ({exc.strerror})", "choose another folder"
        ) from None


def same_file(a: Path, b: Path) -> bool:
    """Whether two paths name one file: equal once resolved, or the same existing file (a hard link)."""
    if a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def simulate_and_save(scene, steps, save_every, out: Path, quiet: bool):
    from ..errors import BlowUpError
    from ..io.trajectory import save_trajectory
    from ..sim.run import run_scene
    from ..sim.stability import estimate_stability

    stability = estimate_stability(scene.model, scene.params, scene.state)
    refuse_overflowing(scene, stability)
    if stability.margin < 1:
        print(f"jaxspring: warning: {instability_advice(scene, stability)}", file=sys.stderr, flush=True)
    result = run_scene(scene, steps, save_every, show_progress=not quiet, stability=stability)
    if result.blowup is not None:
        raise BlowUpError(f"{scene.name}: {result.blowup.describe()}; no file was written")
    save_trajectory(out, scene, result.trajectory)
    return result


def refuse_overflowing(scene, stability) -> None:
    """A one-line error for a scene whose stability estimate is not a finite number: its
    stiffness, damping or masses are beyond what any time step can run."""
    from ..errors import InputError

    numbers = (stability.omega_max, stability.damping_max)  # the margin is infinite for backward Euler
    if not all(math.isfinite(n) for n in numbers) or stability.omega_max * scene.model.dt > 1e150:
        raise InputError(
            "scene",
            f"its stability estimate overflows (omega_max {stability.omega_max:.3g} rad/s, "
            f"damping rate {stability.damping_max:.3g} 1/s): no time step can run it",
            "give physical stiffness, damping and masses",
        )


TRIAL_STEPS = 10
"""`check` runs this many steps as `run` would: a scene whose energy overflows or whose
estimate misjudges it (stiffness near the largest float) blows up there."""


def instability_advice(scene, stability) -> str:
    stable = [n for n, b in stability.bounds.items() if b >= scene.model.dt]
    return (
        f"{scene.name}: dt {scene.model.dt:g} s exceeds {stability.integrator}'s stable-dt estimate "
        f"{stability.dt_bound:.3g} s; expect a blow-up (stable at this dt: {', '.join(stable)})"
    )


def summary(scene, result, out) -> str:
    return (
        f"{scene.name}: {result.steps} steps of {scene.model.dt:g} s in {result.wall_s:.3f} s "
        f"({result.steps_per_second:,.0f} steps/s; compile {result.compile_s:.2f} s); "
        f"energy {result.energy_start:.6g} J -> {result.energy_end:.6g} J; wrote {out}"
    )


def render_with_progress(scene, trajectory, out, frame, max_frames, quiet, label, max_memory=None):
    from tqdm.auto import tqdm

    from ..render import render

    with tqdm(
        total=0, desc=label, unit="frame", file=sys.stderr, disable=quiet or not sys.stderr.isatty(), leave=False
    ) as bar:

        def progress(done, total):
            bar.total = total
            bar.n = done + 1
            bar.refresh()

        render(scene, trajectory, out, frame=frame, max_frames=max_frames, progress=progress, max_memory=max_memory)
