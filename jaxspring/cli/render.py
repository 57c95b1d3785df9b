"""`jaxspring render`: pictures and movies of a trajectory file."""

from __future__ import annotations

from pathlib import Path

from .common import check_output, render_with_progress


def add_parser(sub):
    parser = sub.add_parser("render", help="draw a trajectory file to a PNG frame or a GIF movie")
    parser.add_argument("file", help="trajectory file written by `jaxspring run`")
    parser.add_argument("--out", help="output .png or .gif (default: FILE with .gif)")
    parser.add_argument("--frame", type=int, default=-1, help="frame a PNG shows (default: last)")
    parser.add_argument("--max-frames", type=int, default=60, help="frames in a GIF (default: 60)")
    parser.add_argument(
        "--max-memory",
        metavar="SIZE",
        help="refuse a file or movie that needs more memory, e.g. 4G (default: what is free)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def command(args):
    from ..errors import InputError
    from ..io.trajectory import load_trajectory
    from ..resources import parse_size

    limit = parse_size(args.max_memory) if args.max_memory else None
    if args.max_frames < 1:
        raise InputError("--max-frames", f"must be >= 1, got {args.max_frames}", "give a positive frame count")
    out = Path(args.out) if args.out else Path(args.file).with_suffix(".gif")
    check_output(out, inputs=[args.file])
    scene, trajectory = load_trajectory(args.file, max_memory=limit)
    render_with_progress(
        scene, trajectory, out, args.frame, args.max_frames, args.quiet, f"render {out.name}", max_memory=limit
    )
    print(f"wrote {out}")
