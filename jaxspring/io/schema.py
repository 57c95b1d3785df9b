"""The schema checker shared by scene and experiment files: every value checked, every unknown key reported.

`Table(data, path)` wraps one TOML table; `take(key, check)` reads a key through a
check function (below) that turns the value into what the loader needs or raises
`Bad` with what was expected; `finish()` reports keys nobody took.
"""

from __future__ import annotations

import math
import stat
import tomllib
from pathlib import Path
from typing import Any

from ..errors import InputError

MAX_TOML_BYTES = 64 * 2**20
"""The largest scene or experiment file read (64 MiB: ~1 million particles written out)."""


def read_toml(path: Path, what: str) -> dict:
    """The parsed contents of a TOML file; unreadable bytes, bad UTF-8 or bad syntax raise one `InputError`.

    `what` names the file's kind in the message ("scene", "experiment").

    Example:
        >>> document = read_toml(Path("scenes/chain.toml"), "scene")
    """
    try:
        info = path.stat()
        if not stat.S_ISREG(info.st_mode):  # a device or a FIFO would be read forever
            raise InputError(what, "is not a regular file", f"give a regular {what} TOML file", source=str(path))
        if info.st_size > MAX_TOML_BYTES:
            raise InputError(
                what,
                f"is {info.st_size:,} bytes, more than the {MAX_TOML_BYTES:,} a {what} file may have",
                "keep large arrays out of TOML (a lattice, or a trajectory file)",
                source=str(path),
            )
        with open(path, "rb") as handle:
            data = handle.read(MAX_TOML_BYTES + 1)
    except OSError as exc:
        raise InputError(what, f"cannot read ({exc.strerror})", "check the path", source=str(path)) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        problem = f"byte 0x{data[exc.start]:02x} on line {line} is not UTF-8"
        raise InputError("toml", problem, "save the file as UTF-8 text", source=str(path)) from None
    if _nesting(text) > MAX_TOML_NESTING:  # not left to the interpreter's recursion limit
        raise InputError("toml", "nests arrays or tables too deeply", "flatten the file", source=str(path))
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError("toml", f"not valid TOML ({exc})", "fix the syntax", source=str(path)) from None
    except RecursionError:
        raise InputError("toml", "nests arrays or tables too deeply", "flatten the file", source=str(path)) from None


class Table:
    def __init__(self, data: Any, path: str):
        if not isinstance(data, dict):
            raise InputError(path or "scene", "must be a table", f"write it as [{path}]")
        self.data, self.path, self.seen = data, path, set()

    def _field(self, key):
        return f"{self.path}.{key}" if self.path else key

    def take(self, key, check, required=False, default=None):
        self.seen.add(key)
        if key not in self.data:
            if required:
                raise InputError(self._field(key), "missing", f"add {key} = ...")
            return default
        try:
            return check(self.data[key])
        except Bad as bad:
            got = repr(self.data[key])
            got = got if len(got) <= 60 else got[:57] + "..."
            raise InputError(self._field(key), f"{bad.problem}, got {got}", bad.fix) from None

    def tables(self, key) -> list[Table]:
        """An array of tables, [[key]] (one [key] table counts as one); [] when absent."""
        self.seen.add(key)
        value = self.data.get(key)
        if value is None:
            return []
        items = value if isinstance(value, list) else [value]
        return [
            Table(item, f"{self._field(key)}[{i}]" if isinstance(value, list) else self._field(key))
            for i, item in enumerate(items)
        ]

    def table(self, key, required=False):
        self.seen.add(key)
        if key not in self.data:
            if required:
                raise InputError(self._field(key), "missing table", f"add a [{self._field(key)}] table")
            return None
        return Table(self.data[key], self._field(key))

    def finish(self):
        unknown = sorted(set(self.data) - self.seen)
        if unknown:
            known = ", ".join(sorted(self.seen))
            raise InputError(self._field(unknown[0]), "unknown key", f"remove it or use one of: {known}")


class Bad(Exception):
    def __init__(self, problem, fix):
        self.problem, self.fix = problem, fix


def string(value):
    if not isinstance(value, str):
        raise Bad("must be a string", 'quote it: "..."')
    return value


def boolean(value):
    if not isinstance(value, bool):
        raise Bad("must be true or false", "write true or false")
    return value


def flags(value):
    if isinstance(value, bool):
        return value
    if isinstance(value, list) and all(isinstance(v, bool) for v in value):
        return value
    raise Bad("must be true/false or a list of them", "write true, false or [true, false, ...]")


def number(value):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Bad("must be a number", "write a number")
    if not math.isfinite(value):
        raise Bad("must be finite (no NaN or inf)", "write a finite number")
    return float(value)


def positive(value):
    value = number(value)
    if value <= 0:
        raise Bad("must be > 0", "give a positive number")
    return value


def count(value):
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise Bad("must be a non-negative integer", "write a whole number")
    return value


def values(value, check):
    if isinstance(value, list):
        if not value:
            raise Bad("must not be empty", "give a number or a non-empty list")
        return [check(v) for v in value]
    return check(value)


def non_negative_values(value):
    def check(v):
        v = number(v)
        if v < 0:
            raise Bad("must be >= 0", "give a non-negative value")
        return v

    return values(value, check)


def grouped_non_negative_values(value):
    """Non-negative values, or a table of them by spring group: { stretch = 1000.0, bend = 10.0 }."""
    if isinstance(value, dict):
        if not value:
            raise Bad("must not be an empty table", "give a value per group, e.g. { stretch = 1000.0 }")
        return {str(group): non_negative_values(v) for group, v in value.items()}
    return non_negative_values(value)


def positive_values(value):
    return values(value, positive)


def vector3(value):
    if not isinstance(value, list) or len(value) != 3:
        raise Bad("must be a list of 3 numbers", "write [x, y, z]")
    return tuple(number(v) for v in value)


def vectors(value):
    if not isinstance(value, list) or not value:
        raise Bad("must be a non-empty list of [x, y, z]", "write [[x, y, z], ...]")
    return [vector3(v) for v in value]


def index(value):
    if isinstance(value, bool) or not isinstance(value, int):
        raise Bad("must hold integer indices", "write whole numbers")
    if not -(2**63) <= value < 2**63:
        raise Bad(f"index {value} is beyond any particle count", "give indices of the scene's particles")
    return value


def index_list(value):
    if not isinstance(value, list):
        raise Bad("must be a list of particle indices", "write [i, j, ...]")
    return [index(v) for v in value]


def index_lists(value):
    if not isinstance(value, list):
        raise Bad("must be a list of lattice indices", "write [[i, j], ...]")
    return [index_list(v) for v in value]


def tuples(value, size, what):
    if not isinstance(value, list) or any(not isinstance(v, list) or len(v) != size for v in value):
        raise Bad(f"must be a list of {what}", f"write [[{', '.join('abc'[:size])}], ...]")
    return [[index(i) for i in v] for v in value]


def index_pairs(value):
    return tuples(value, 2, "index pairs")


def index_triples(value):
    return tuples(value, 3, "index triples")


def shape(value):
    if not isinstance(value, list) or not 1 <= len(value) <= 3:
        raise Bad("must be a list of 1 to 3 counts", "write e.g. [31, 41]")
    for v in value:
        if isinstance(v, int) and not isinstance(v, bool) and v >= 2**63:
            raise Bad(f"count {v} is beyond any lattice", "write e.g. [31, 41]")
    counts = [index(v) for v in value]
    if any(c < 1 for c in counts):
        raise Bad("counts must be >= 1", "give positive counts")
    return tuple(counts)


def string_list(value):
    if not isinstance(value, list):
        raise Bad("must be a list of strings", 'write ["a", "b"]')
    return [string(v) for v in value]


MAX_TOML_NESTING = 100
"""Deepest nesting of arrays and inline tables a scene or experiment file may have."""


def _nesting(text: str) -> int:
    """The deepest nesting of `[` and `{` in TOML `text`, outside strings and comments."""
    depth = deepest = 0
    quote, escaped, comment = None, False, False
    for ch in text:
        if comment:
            comment = ch != "\n"
        elif quote:
            if escaped:
                escaped = False
            elif ch == "\\" and quote == '"':
                escaped = True
            elif ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            comment = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest
