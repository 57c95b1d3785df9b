"""Recordings of real motion: marker positions over time (HDF5 or CSV, docs/file-formats.md)."""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from pathlib import Path

import h5py
import numpy as np

from ..errors import FileFormatError, InputError
from ..resources import check_hdf5_read
from .trajectory import atomic_path, open_hdf5

RECORDING_FORMAT = "jaxspring.recording"
FORMAT_VERSION = 1
HDF5_SUFFIXES = (".h5", ".hdf5", ".hdf")
CSV_AXES = ("x", "y", "z")
MAX_POSITION = 1e12
"""Largest marker coordinate a recording may hold [m]: beyond it, no simulation of it is finite."""


@dataclasses.dataclass(frozen=True, eq=False)
class Recording:
    """Marker positions seen at frame times; NaN where a marker was not seen.

    Arrays are stored as read-only float64 NumPy arrays. Construction checks them:
    t finite and strictly increasing with at least 2 frames, x of shape (F, M, 3) with
    no infinite value nor one beyond 1e12 m, a marker lost in all three coordinates or none, every marker seen
    in at least one frame, and M distinct non-empty names.

    Attributes:
        t: frame times [s], shape (F,), strictly increasing.
        x: marker positions [m], shape (F, M, 3); NaN where a marker was not seen.
        markers: M marker names (default "m0", "m1", ...).

    Example:
        >>> rec = Recording(t=[0.0, 0.01, 0.02], x=np.zeros((3, 2, 3)), markers=("left", "right"))
        >>> rec.frame_count, rec.marker_count
        (3, 2)
    """

    t: np.ndarray
    x: np.ndarray
    markers: tuple[str, ...] | None = None

    def __post_init__(self):
        t = _as_float_array("t", self.t)
        x = _as_float_array("x", self.x)
        _check_times(t)
        _check_shape(x, t.shape[0])
        markers = _check_markers(self.markers, x.shape[1])
        _check_positions(x, markers)
        t.setflags(write=False)
        x.setflags(write=False)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "markers", markers)

    @property
    def frame_count(self) -> int:
        """Number of frames F."""
        return int(self.t.shape[0])

    @property
    def marker_count(self) -> int:
        """Number of markers M."""
        return int(self.x.shape[1])

    @property
    def seen(self) -> np.ndarray:
        """Whether each marker was seen at each frame, bool shape (F, M).

        Example:
            >>> rec.seen.sum(axis=0)   # frames in which each marker was seen
        """
        return np.isfinite(self.x).all(axis=-1)


def save_recording(path, recording: Recording, bands=None, writer: str | None = None) -> None:
    """Write a recording to an HDF5 file (docs/file-formats.md), atomically.

    The file holds /t float64 (F,), /x float64 (F, M, 3) with NaN where a marker was
    not seen, and /markers (M,) names; root attributes format="jaxspring.recording",
    format_version=1. `bands` (low, high), each (F, M, 3), adds a prediction's 95% band
    as /band_low and /band_high (readers of recordings ignore them); `writer` names the
    program that wrote it (root attribute `writer`; `jaxspring predict` replaces only its own files).

    Example:
        >>> js.save_recording("take1.h5", js.Recording(t=t, x=x))
    """
    if not isinstance(recording, Recording):
        raise TypeError(f"save_recording expects a js.Recording, got {type(recording).__name__}")
    path = Path(path)
    if path.suffix.lower() == ".csv":
        raise InputError(
            "out", f"{str(path)!r}: recordings are written as HDF5", "choose a name ending in .h5 (CSV is read only)"
        )
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs.update(format=RECORDING_FORMAT, format_version=FORMAT_VERSION)
        if writer is not None:
            f.attrs["writer"] = writer
        f.create_dataset("t", data=recording.t)
        f.create_dataset("x", data=recording.x)
        f.create_dataset("markers", data=list(recording.markers), dtype=h5py.string_dtype("utf-8"))
        if bands is not None:
            f.create_dataset("band_low", data=np.asarray(bands[0], dtype=float))
            f.create_dataset("band_high", data=np.asarray(bands[1], dtype=float))


def load_recording(path) -> Recording:
    """Read a recording from an HDF5 recording file or a CSV; values are cast to float64.

    A name ending in .csv is read as CSV (header `t,<name>_x,<name>_y,<name>_z,...`, one
    row per frame, empty cells where a marker was not seen); .h5, .hdf5 or .hdf as HDF5;
    any other name by its content. Everything is checked (see `Recording`); a problem is
    one `InputError` or `FileFormatError` naming the file, the problem and the fix.

    Example:
        >>> rec = js.load_recording("take1.csv")
        >>> rec.x.shape   # (frames, markers, 3)
    """
    path = Path(path)
    if not path.exists():
        raise FileFormatError(f"{path}: file not found; check the path")
    if not path.is_file():
        raise FileFormatError(f"{path}: not a file; give a recording file (.h5 or .csv)")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return _load_csv(path)
    if suffix in HDF5_SUFFIXES or h5py.is_hdf5(path):
        return _load_hdf5(path)
    with open(path, "rb") as handle:
        start = handle.read(2)
    if start in (b"t,", b"t\r", b"t\n") or start.startswith(b"\xef\xbb"):
        return _load_csv(path)
    raise FileFormatError(
        f"{path}: not a recording (neither HDF5 nor a CSV whose header starts with 't,'); "
        "give a file written by js.save_recording or a CSV as in docs/file-formats.md"
    )


def _load_hdf5(path: Path) -> Recording:
    with open_hdf5(path, "give a recording written by js.save_recording") as f:
        kind = f.attrs.get("format")
        if isinstance(kind, bytes):
            kind = kind.decode("utf-8", "replace")
        elif kind is not None and not isinstance(kind, str):
            kind = str(kind)
        if kind != RECORDING_FORMAT:
            what = "has no format attribute" if kind is None else f"has format={kind!r}"
            raise FileFormatError(
                f"{path}: not a jaxspring recording (the file {what}, expected {RECORDING_FORMAT!r}); "
                "give a file written by js.save_recording or a CSV"
            )
        raw_version = f.attrs.get("format_version")
        try:
            version = int(raw_version)
        except (TypeError, ValueError):
            version = None
        if version != FORMAT_VERSION:
            shown = "missing" if raw_version is None else str(raw_version)
            raise FileFormatError(
                f"{path}: recording format_version {shown} is not supported; "
                f"this jaxspring reads version {FORMAT_VERSION}"
            )
        check_hdf5_read(f, path)  # a small file can hold a dataset far too large to read
        arrays = {}
        for name in ("t", "x"):
            if not isinstance(f.get(name), h5py.Dataset):
                raise FileFormatError(f"{path}: dataset /{name} is missing; a recording holds /t and /x")
            try:
                arrays[name] = f[name][()]
            except (OSError, TypeError, ValueError) as exc:
                raise FileFormatError(f"{path}: dataset /{name} cannot be read ({exc}); re-create the file") from None
        markers = None
        if "markers" in f:
            if not isinstance(f["markers"], h5py.Dataset):
                raise FileFormatError(f"{path}: /markers is not a dataset; store the names as (M,) strings")
            markers = _decode_names(path, f["markers"][()])
    try:
        return Recording(t=arrays["t"], x=arrays["x"], markers=markers)
    except InputError as exc:
        raise exc.within(str(path)) from None


def _decode_names(path: Path, raw) -> tuple:
    names = np.asarray(raw)
    if names.ndim != 1:
        raise FileFormatError(f"{path}: /markers has shape {names.shape}; store the names as (M,) strings")
    decoded = []
    for name in names.tolist():
        if isinstance(name, bytes):
            try:
                name = name.decode("utf-8")
            except UnicodeDecodeError:
                raise FileFormatError(f"{path}: /markers holds a name that is not UTF-8; store UTF-8 strings") from None
        decoded.append(name)
    return tuple(decoded)


def _load_csv(path: Path) -> Recording:
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FileFormatError(
            f"{path}: not UTF-8 text (invalid byte at offset {exc.start}); give a CSV saved as UTF-8 or an HDF5 recording"
        ) from None
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        rows = [(reader.line_num, row) for row in reader]
    except csv.Error as exc:
        raise FileFormatError(f"{path}: not a readable CSV ({exc}); give a plain comma-separated file") from None
    rows = [(line, row) for line, row in rows if row and any(cell.strip() for cell in row)]
    if not rows:
        raise FileFormatError(f"{path}: the CSV is empty; give a header 't,<name>_x,<name>_y,<name>_z,...' and rows")
    header_line, header = rows[0]
    markers = _csv_markers(path, [cell.strip() for cell in header])
    width = len(header)
    t = np.empty(len(rows) - 1)
    x = np.empty((len(rows) - 1, len(markers) * 3))
    for frame, (line, row) in enumerate(rows[1:]):
        if len(row) != width:
            raise FileFormatError(
                f"{path}: line {line} has {len(row)} cells, the header has {width}; "
                "give one cell per column (empty where a marker was not seen)"
            )
        t[frame] = _csv_number(path, line, header[0], row[0], empty_ok=False)
        for column in range(1, width):
            x[frame, column - 1] = _csv_number(path, line, header[column].strip(), row[column], empty_ok=True)
    try:
        return Recording(t=t, x=x.reshape(len(t), len(markers), 3), markers=markers)
    except InputError as exc:
        raise exc.within(str(path)) from None


def _csv_markers(path: Path, header: list[str]) -> tuple[str, ...]:
    expected = "give a header 't,<name>_x,<name>_y,<name>_z,...'"
    if header[0] != "t":
        raise FileFormatError(f"{path}: the CSV header's first column is {header[0]!r}, not 't'; {expected}")
    columns = header[1:]
    if not columns or len(columns) % 3:
        raise FileFormatError(
            f"{path}: the CSV header has {len(columns)} marker columns, not a positive multiple of 3; {expected}"
        )
    markers = []
    for first in range(0, len(columns), 3):
        triple = columns[first : first + 3]
        name = triple[0][:-2] if triple[0].endswith("_x") else None
        if not name or triple != [f"{name}_{axis}" for axis in CSV_AXES]:
            raise FileFormatError(
                f"{path}: CSV columns {first + 2}-{first + 4} are {','.join(triple)}, not one marker's "
                f"<name>_x,<name>_y,<name>_z; {expected}"
            )
        markers.append(name)
    return tuple(markers)


def _csv_number(path: Path, line: int, column: str, cell: str, empty_ok: bool) -> float:
    cell = cell.strip()
    if not cell:
        if empty_ok:
            return math.nan
        raise FileFormatError(f"{path}: line {line}: the frame time is empty; give a time [s] on every row")
    try:
        return float(cell)
    except ValueError:
        raise FileFormatError(
            f"{path}: line {line}, column {column}: {cell[:40]!r} is not a number; "
            "give a number, or leave the cell empty where a marker was not seen"
        ) from None


def _as_float_array(field: str, value) -> np.ndarray:
    array = np.asarray(value)
    if array.dtype.kind not in "fiu":
        raise InputError(field, f"holds {array.dtype.name} values, not numbers", "store numbers (floats or integers)")
    return np.array(array, dtype=np.float64, copy=True)


def _check_times(t: np.ndarray) -> None:
    if t.ndim != 1:
        raise InputError("t", f"has shape {t.shape}, not (frames,)", "give one time [s] per frame")
    if t.shape[0] < 2:
        raise InputError("t", f"has {t.shape[0]} frame(s), fewer than 2", "give a recording of at least 2 frames")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise InputError(
            "t", f"frame {bad[0]} has a non-finite time {float(t[bad[0]])}", "give a finite time [s] per frame"
        )
    step = np.flatnonzero(np.diff(t) <= 0)
    if step.size:
        k = int(step[0]) + 1
        raise InputError(
            "t",
            f"not strictly increasing at frame {k} (t[{k}] = {float(t[k])!r} <= t[{k - 1}] = {float(t[k - 1])!r})",
            "give frames in time order with distinct times",
        )


def _check_shape(x: np.ndarray, frame_count: int) -> None:
    if x.ndim != 3 or x.shape[2] != 3 or x.shape[0] != frame_count or x.shape[1] < 1:
        raise InputError(
            "x",
            f"has shape {x.shape}, expected ({frame_count}, markers, 3) for {frame_count} frames",
            "give positions [m] of shape (frames, markers, 3) with at least one marker",
        )


def _check_positions(x: np.ndarray, markers: tuple[str, ...]) -> None:
    frame, marker = np.nonzero(np.isinf(x).any(axis=-1))
    if frame.size:
        raise InputError(
            "x",
            f"frame {frame[0]}, marker {markers[marker[0]]!r} (index {marker[0]}) has an infinite position",
            "give finite positions, or NaN where a marker was not seen",
        )
    with np.errstate(invalid="ignore"):
        far = np.abs(x) > MAX_POSITION
    frame, marker = np.nonzero(far.any(axis=-1))
    if frame.size:
        raise InputError(
            "x",
            f"frame {frame[0]}, marker {markers[marker[0]]!r} (index {marker[0]}) is more than {MAX_POSITION:.0e} m "
            "from the origin",
            "give positions in metres (NaN where a marker was not seen); remove tracking glitches",
        )
    lost = np.isnan(x)
    frame, marker = np.nonzero(lost.any(axis=-1) & ~lost.all(axis=-1))
    if frame.size:
        raise InputError(
            "x",
            f"frame {frame[0]}, marker {markers[marker[0]]!r} (index {marker[0]}) is NaN in some coordinates but not all",
            "mark a marker that was not seen with NaN (or empty cells) in all three coordinates",
        )
    never = np.flatnonzero(lost.all(axis=-1).all(axis=0))
    if never.size:
        k = int(never[0])
        raise InputError(
            "x",
            f"marker {markers[k]!r} (index {k}) is not seen in any frame",
            "remove that marker or check its tracking",
        )


def _check_markers(markers, marker_count: int) -> tuple[str, ...]:
    if markers is None:
        return tuple(f"m{k}" for k in range(marker_count))
    if isinstance(markers, str):
        raise InputError("markers", "is one string, not a list of names", f"give {marker_count} names")
    markers = tuple(markers)
    if len(markers) != marker_count:
        raise InputError(
            "markers", f"has {len(markers)} names for {marker_count} markers in x", "give one name per marker"
        )
    for name in markers:
        if not isinstance(name, str) or not name:
            raise InputError("markers", f"name {name!r} is not a non-empty string", "give each marker a name")
    duplicate = next((name for k, name in enumerate(markers) if name in markers[:k]), None)
    if duplicate is not None:
        raise InputError("markers", f"name {duplicate!r} is used twice", "give each marker its own name")
    return markers


def _unnamed(markers) -> bool:
    """Whether `markers` are the default names a recording gets without any (m0, m1, ...)."""
    return tuple(markers) == tuple(f"m{k}" for k in range(len(markers)))


def matched_by_name(recordings, names, order=None) -> list:
    """`recordings` with their marker columns in the order of the names `order` (default: the
    first recording's names): a recording with the same names in another order is reordered;
    one with other names is refused, unless either side has only the default names (m0, m1,
    ... in order: no names at all), which are matched by column."""
    order = tuple(recordings[0].markers if order is None else order)
    out = []
    for name, rec in zip(names, recordings):
        if tuple(rec.markers) == order:
            out.append(rec)
        elif len(rec.markers) == len(order) and set(rec.markers) == set(order):
            columns = [rec.markers.index(m) for m in order]
            out.append(type(rec)(t=rec.t, x=np.asarray(rec.x)[:, columns], markers=order))
        elif len(rec.markers) == len(order) and (_unnamed(rec.markers) or _unnamed(order)):
            out.append(type(rec)(t=rec.t, x=rec.x, markers=order))
        else:
            raise InputError(
                "recordings",
                f"{name} names its markers {', '.join(rec.markers)}; expected {', '.join(order)}",
                "give recordings of one marker set (matched by name)",
            )
    return out
