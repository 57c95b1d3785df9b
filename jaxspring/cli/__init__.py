"""The `jaxspring` command line (docs/cli.md): one module per subcommand.

Every error a user can cause ends in one line naming the problem and the fix,
exit code 2, no traceback, and no output file left half-written.
"""

from __future__ import annotations

import sys

from . import bench, cable, check, demo, fit, predict, render, run
from .common import EXIT_USER_ERROR, Parser

COMMANDS = {
    "run": run,
    "check": check,
    "bench": bench,
    "render": render,
    "fit": fit,
    "predict": predict,
    "cable": cable,
    "demo": demo,
}


def build_parser() -> Parser:
    """The argument parser of every subcommand.

    Example:
        >>> build_parser().parse_args(["run", "chain", "--steps", "100"]).steps
        100
    """
    parser = Parser(prog="jaxspring", description="Differentiable mass-spring simulation in JAX.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for module in COMMANDS.values():
        module.add_parser(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the `jaxspring` console script; returns the exit code."""
    args = build_parser().parse_args(argv)
    import warnings

    import numpy as np

    from ..errors import JaxspringError

    # numerical trouble is reported by the commands in one line; NumPy's own warnings would
    # turn that line into several (silenced only while the command runs)
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            if getattr(args, "dtype", "float32") == "float64" or (args.command == "bench" and args.kind == "accuracy"):
                import jax

                jax.config.update("jax_enable_x64", True)
            return COMMANDS[args.command].command(args) or 0
    except JaxspringError as exc:
        print(f"jaxspring: error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("jaxspring: interrupted; no output file was written", file=sys.stderr)
        return 130
