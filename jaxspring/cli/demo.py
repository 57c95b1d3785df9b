"""`jaxspring demo`: the four seed scenes, end to end."""

from __future__ import annotations

import time
from pathlib import Path

from .common import add_common, check_writable, render_with_progress, simulate_and_save, summary


def add_parser(sub):
    parser = sub.add_parser("demo", help="run the four seed scenes; write trajectories, pictures and movies")
    parser.add_argument("--out-dir", default="demo_output", help="folder to write into (default: demo_output)")
    parser.add_argument("--no-movies", action="store_true", help="skip the GIFs (faster)")
    add_common(parser)


def command(args):
    from ..errors import InputError
    from ..io.scene import builtin_scenes, load_scene

    folder = Path(args.out_dir)
    if folder.exists() and not folder.is_dir():
        raise InputError("--out-dir", f"{str(folder)!r} is a file", "give a folder name")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(
            "--out-dir", f"cannot create {str(folder)!r} ({exc.strerror})", "choose another place"
        ) from None
    check_writable(folder, "--out-dir")
    start = time.perf_counter()
    rows = []
    for name in builtin_scenes():
        scene = load_scene(name)
        out = folder / f"{name}.h5"
        result = simulate_and_save(scene, scene.steps, scene.save_every, out, args.quiet)
        print(summary(scene, result, out), flush=True)
        traj = result.trajectory
        render_with_progress(scene, traj, folder / f"{name}.png", -1, 60, args.quiet, f"{name}.png")
        if not args.no_movies:
            render_with_progress(scene, traj, folder / f"{name}.gif", -1, 60, args.quiet, f"{name}.gif")
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
