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
    keep_compiled_programs()
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


COMPILE_CACHE_SIZE = 2**30
"""Bytes the kept compiled programs may take; the least recently used go first."""


def keep_compiled_programs() -> None:
    """Keep what one command compiles for the next (JAX's persistent compilation cache, in
    $XDG_CACHE_HOME/jaxspring/jax or ~/.cache/jaxspring/jax): a fit resumed, run again or
    predicted from loads its programs instead of compiling them. Entries are keyed by the
    program, the JAX version and the machine, so a stale one is never used. A cache the user
    chose (JAX_COMPILATION_CACHE_DIR) is left as it is; JAXSPRING_COMPILE_CACHE=0 turns it off."""
    import os

    import jax

    if jax.config.jax_compilation_cache_dir or os.environ.get("JAXSPRING_COMPILE_CACHE", "1") == "0":
        return
    home = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    folder = os.path.join(home, "jaxspring", "jax")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:  # no writable cache folder: compile every time, as before
        return
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_compilation_cache_max_size", COMPILE_CACHE_SIZE)
