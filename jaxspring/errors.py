"""Errors a user can cause: one line naming the problem and the fix."""

from __future__ import annotations


class JaxspringError(ValueError):
    """Base class for user-caused errors; the CLI prints them as one line, exit code 2.

    The message is one line by construction: line breaks and runs of spaces in whatever it
    quotes (an array read from a file, a parser's message) become single spaces, and a quoted
    value too long to read is cut.
    """

    def __init__(self, *args):
        if len(args) == 1 and isinstance(args[0], str):
            args = (one_line(args[0]),)
        super().__init__(*args)


def one_line(text: str, limit: int = 1000) -> str:
    """`text` with all whitespace runs as single spaces, cut to `limit` characters."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


class InputError(JaxspringError):
    """Invalid input: names the field, the problem and the fix.

    Example:
        >>> raise InputError("physics.ks", "must be >= 0, got -5", "set a non-negative ks")
    """

    def __init__(self, field: str, problem: str, fix: str, source: str | None = None):
        self.field, self.problem, self.fix, self.source = field, problem, fix, source
        super().__init__(self._text())

    def _text(self) -> str:
        where = f"{self.source}: " if self.source else ""
        return f"{where}{self.field}: {self.problem}; {self.fix}"

    def within(self, source: str, prefix: str = "") -> InputError:
        """The same error, attributed to a file and a field prefix (e.g. a TOML table)."""
        field = f"{prefix}.{self.field}" if prefix and not self.field.startswith(prefix) else self.field
        return InputError(field, self.problem, self.fix, source=self.source or source)


class FileFormatError(JaxspringError):
    """A file that is missing, truncated or not of the expected format."""


class BlowUpError(JaxspringError):
    """A rollout went non-finite or its energy exploded."""
