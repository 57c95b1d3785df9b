"""`jaxspring run`: simulate a scene and write its trajectory."""

from __future__ import annotations

from pathlib import Path

from ..steppers import BACKENDS
from .common import (
    BACKEND_HELP,
    INTEGRATOR_HELP,
    add_common,
    check_output,
    prepare_scene,
    simulate_and_save,
    summary,
)


def add_parser(sub):
    parser = sub.add_parser("run", help="simulate a scene and write its trajectory (HDF5)")
    parser.add_argument("scene", help="scene TOML file, or a built-in name (mass_spring, chain, jelly, cloth)")
    parser.add_argument("--steps", type=int, help="time steps (default: the scene's)")
    parser.add_argument("--save-every", type=int, help="keep one frame every K steps (default: the scene's)")
    parser.add_argument("--out", help="output file (default: SCENE_NAME.h5)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE", help="override a parameter, e.g. ks=600"
    )
    parser.add_argument("--integrator", metavar="NAME", help=INTEGRATOR_HELP)
    parser.add_argument("--dt", type=float, help="time step [s] (default: the scene's)")
    parser.add_argument("--backend", choices=BACKENDS, help=BACKEND_HELP)
    add_common(parser)


def command(args):
    from ..io.scene import resolve_scene_path
    from ..resources import check_trajectory, parse_size

    scene, steps, save_every = prepare_scene(args)
    out = Path(args.out or f"{scene.name}.h5")
    check_output(out, inputs=[resolve_scene_path(args.scene)])
    limit = parse_size(args.max_memory) if args.max_memory else None
    itemsize = 8 if args.dtype == "float64" else 4
    check_trajectory(steps // save_every, scene.model.particle_count, itemsize, out, limit)
    result = simulate_and_save(scene, steps, save_every, out, args.quiet)
    print(summary(scene, result, out))
