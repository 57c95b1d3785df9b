"""`jaxspring cable`: a cable or harness scene and a ready experiment, from its recording files."""

from __future__ import annotations

import os
import re
from pathlib import Path

from .common import check_writable

MARK = "# written by jaxspring cable"
"""The first line of the files `cable` writes: the only existing files it replaces."""


def add_parser(sub):
    parser = sub.add_parser(
        "cable",
        help="write a cable or harness scene and an experiment that fits it, from marker recordings",
    )
    parser.add_argument("recordings", nargs="+", help="recording files (.h5 or .csv) of one object, to fit")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder for DIR/cable.toml and DIR/experiment.toml")
    parser.add_argument(
        "--edges",
        metavar="EDGES",
        help="neighbouring markers, e.g. 0-1,1-2,2-3,1-4 (a tree over every marker), or a file with one edge "
        "per line (default: the chain 0-1-...)",
    )
    parser.add_argument(
        "--driven", default="0,1,-2,-1", metavar="LIST", help="markers moved as recorded (default: 0,1,-2,-1)"
    )
    parser.add_argument(
        "--gravity", metavar="X,Y,Z", help="gravity in the recordings' axes [m/s^2] (default: read from the sag)"
    )
    parser.add_argument("--bending", action="store_true", help="bend with the bending term, not bend springs")
    parser.add_argument("--subdivide", type=int, default=1, metavar="K", help="particle intervals per marker interval")
    parser.add_argument(
        "--groups", default="1", metavar="G", help='segment groups along a chain, or "branch" (one per branch)'
    )
    parser.add_argument("--mass", type=float, default=1.0, help="the object's mass [kg] (default: 1)")
    parser.add_argument("--start", type=int, default=5, help="frame each simulation starts from (default: 5)")
    parser.add_argument("--smooth", type=int, default=5, help="smoothing half-window in frames (default: 5)")
    parser.add_argument("--evaluate", nargs="+", default=[], metavar="REC", help="held-out recordings to predict")


def command(args):
    from ..errors import InputError
    from ..io.cable import cable_scene
    from ..io.recording import load_recording
    from ..io.trajectory import atomic_path

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out", f"{str(out)!r} is a file", "give a folder")
    if not out.parent.is_dir():
        raise InputError("--out", f"folder {str(out.parent)!r} does not exist", "create it or choose another folder")
    targets = [out / "cable.toml", out / "experiment.toml"]
    for path in targets:
        if path.exists() and not _ours(path):
            raise InputError(
                "--out",
                f"{str(path)!r} exists and was not written by `jaxspring cable`",
                "move it away or choose another --out",
            )
    recordings = [load_recording(path) for path in args.recordings]
    for path in args.evaluate:
        load_recording(path)  # a held-out file that cannot be read is refused now, not after the fit
    groups = args.groups if args.groups == "branch" else _number("--groups", args.groups, int)
    cable = cable_scene(
        recordings,
        edges=_edges(args.edges),
        driven=[_number("--driven", item, int) for item in args.driven.split(",") if item.strip()],
        gravity=None
        if args.gravity is None
        else [_number("--gravity", item, float) for item in args.gravity.split(",")],
        bending=args.bending,
        subdivide=args.subdivide,
        groups=groups,
        mass=args.mass,
    )

    def relative(paths):
        return [Path(os.path.relpath(Path(p).resolve(), out.resolve())).as_posix() for p in paths]

    texts = [
        cable.toml(),
        cable.experiment(
            relative(args.recordings), start=args.start, smooth=args.smooth, evaluate=relative(args.evaluate)
        ),
    ]
    check_writable(out if out.is_dir() else out.parent, "--out")
    out.mkdir(exist_ok=True)  # every refusal came before: nothing is made or written for a bad input
    with atomic_path(targets[0]) as scene_tmp, atomic_path(targets[1]) as experiment_tmp:
        for tmp, text in zip((scene_tmp, experiment_tmp), texts, strict=True):  # both renamed, or neither
            Path(tmp).write_text(f"{MARK}\n{text}")
    print(
        f"wrote {targets[0]} ({len(cable.scene['particles']['mass'])} particles) and {targets[1]} "
        f"(fits {', '.join(cable.params)}); next: jaxspring fit {targets[1]}"
    )


def _ours(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8") as handle:
            return handle.readline().rstrip("\n") == MARK
    except (OSError, UnicodeDecodeError):
        return False


def _number(flag, text, kind):
    from ..errors import InputError

    try:
        return kind(text.strip())
    except ValueError:
        raise InputError(
            flag, f"{text.strip()!r} is not a number", f"see `jaxspring cable --help` for {flag}'s form"
        ) from None


def _edges(text):
    """Edges from `--edges`: "0-1,1-2" or a file with one edge per line ("0 1", "0-1" or "0,1"; # comments)."""
    from ..errors import InputError

    if text is None:
        return None
    if Path(text).is_file():
        try:
            items = [line.split("#")[0].strip() for line in Path(text).read_text().splitlines()]
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(
                "--edges", f"file {text!r} cannot be read ({exc})", "give a text file, one edge per line"
            ) from None
        source = f"file {text!r}"
    else:
        items = text.split(",")
        source = "--edges"
    edges = []
    for item in (i for i in items if i):
        match = re.fullmatch(r"\s*(-?\d+)\s*(?:-|,|\s)\s*(-?\d+)\s*", item)
        if match is None:
            raise InputError("--edges", f"{item!r} in {source} is not an edge", "write each edge as I-J, e.g. 0-1,1-2")
        edges.append((int(match[1]), int(match[2])))
    return edges
