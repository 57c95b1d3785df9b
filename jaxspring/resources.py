"""What this machine can hold: up-front memory and disk checks with one-line errors.

A run keeps its frames in memory and writes them to disk; a scene's arrays grow with its
particle count; a file is read whole; a fit's iteration needs what XLA plans for it; a
movie keeps its pictures until it is written. Each is estimated before that work starts
and refused, with the numbers, when it exceeds the memory available (or a `--max-memory`
limit) or the disk free.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from .errors import InputError

BYTES_PER_PARTICLE = 2048
"""A generous bound on a scene's memory per particle: positions, velocities, masses, flags,
up to 13 springs with their rest lengths and parameters, and the rollout's working arrays."""

UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def available_memory() -> int:
    """Bytes of memory available to a new allocation (MemAvailable; total memory elsewhere)."""
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 2**63


def parse_size(text: str, field: str = "--max-memory") -> int:
    """ "512M", "4G", "1.5T" or a number of bytes -> bytes.

    Example:
        >>> parse_size("4G")
        4294967296
    """
    value = str(text).strip().upper().removesuffix("B").removesuffix("I")
    unit = value[-1:] if value[-1:] in UNITS and value[-1:] else ""
    try:
        number = float(value[: len(value) - len(unit)])
    except ValueError:
        number = -1.0
    if not number > 0 or number == float("inf"):
        raise InputError(field, f"{text!r} is not a size", "write e.g. 512M or 4G")
    return int(number * UNITS[unit])


def human(size: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if size < 1024 or unit == "TiB":
            return f"{size:.3g} {unit}"
        size /= 1024
    return f"{size:.3g} TiB"


def check_memory(need: int, what: str, field: str, fix: str, limit: int | None = None) -> None:
    """Refuse `need` bytes for `what` beyond `limit` (default: the memory available)."""
    have = available_memory() if limit is None else limit
    if need > have:
        source = "--max-memory" if limit is not None else "this machine has available"
        raise InputError(field, f"{what} needs ~{human(need)} of memory but {source} {human(have)}", fix)


def compiled_memory(compiled) -> int | None:
    """Bytes XLA plans for one call of a compiled function (arguments, outputs and scratch),
    or None where the backend does not say."""
    try:
        stats = compiled.memory_analysis()
        return int(
            stats.temp_size_in_bytes
            + stats.argument_size_in_bytes
            + stats.output_size_in_bytes
            - stats.alias_size_in_bytes
        )
    except Exception:  # noqa: BLE001 - an estimate is optional; some backends have none
        return None


def check_compiled(function, args, what: str, field: str, fix: str, limit: int | None = None):
    """Compile `function` (a `jax.jit`) for `args`, refuse it when XLA's own memory plan exceeds
    the memory available (or `limit`), and return the compiled function."""
    compiled = function.lower(*args).compile()
    need = compiled_memory(compiled)
    if need is not None:
        check_memory(need, what, field, fix, limit)
    return compiled


def check_hdf5_read(f, path, limit: int | None = None) -> None:
    """Refuse reading an open HDF5 file whose datasets together exceed the memory available."""
    sizes = []
    f.visititems(lambda _, item: sizes.append(item.size * item.dtype.itemsize) if hasattr(item, "dtype") else None)
    check_memory(sum(sizes), f"reading {path}", "file", "give a smaller file or free memory", limit)


def check_disk(need: int, out: Path, what: str, field: str, fix: str) -> None:
    """Refuse writing `need` bytes to `out` when its folder's disk has less free."""
    folder = out.parent if str(out.parent) else Path(".")
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if need > free:
        raise InputError(field, f"{what} needs ~{human(need)} of disk but {folder} has {human(free)} free", fix)


GIF_BYTES_PER_PIXEL = 8
"""A movie's frames are kept as RGBA pictures, and quantised copies of them, until written."""


def check_movie(frames: int, width: int, height: int, limit: int | None = None) -> None:
    """Refuse a GIF of `frames` pictures of width x height pixels that cannot be held in memory."""
    need = frames * width * height * GIF_BYTES_PER_PIXEL
    what = f"a movie of {frames:,} frames of {width}x{height} pixels"
    check_memory(need, what, "--max-frames", "draw fewer frames (a smaller --max-frames)", limit)


def check_particles(count: int, field: str = "lattice.shape") -> None:
    """Refuse a scene of `count` particles that cannot fit in memory."""
    check_memory(count * BYTES_PER_PARTICLE, f"a scene of {count:,} particles", field, "use a smaller lattice")


def check_trajectory(frames: int, particles: int, itemsize: int, out: Path | None, limit: int | None = None) -> None:
    """A run saving `frames` frames of `particles` particles: memory (x and v kept until written) and disk."""
    need = (frames + 1) * particles * 3 * 2 * itemsize
    what = f"a trajectory of {frames + 1:,} frames x {particles:,} particles"
    fix = "save fewer frames (a larger --save-every, or fewer --steps)"
    check_memory(need + particles * BYTES_PER_PARTICLE, what, "--steps", fix, limit)
    if out is not None:
        check_disk(need, out, what, "--steps", fix)
