"""Errors a user can cause: one line naming the problem and the fix."""

from __future__ import annotations


class JaxspringError(ValueError):
    """Base class for user-caused errors; the CLI prints them as one line, exit code 2."""


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
