"""Diagnostics: one problem found in a user's file, with where it is and what was expected.

Every loader and checker reports through :class:`Diagnostic` so the CLI prints them the same way::

    missions/x.yaml:12:5: agents[1].library: unknown library 'aerail' (expected one of: aerial, ground)

Checkers collect *all* problems they find and raise :class:`SpecError` once at the end.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import Enum

from btmission.errors import BtmissionError


class Severity(str, Enum):
    """How bad a finding is. ``--strict`` turns warnings into errors."""

    ERROR = "error"
    WARNING = "warning"
    INFO = "info"


@dataclass(frozen=True)
class Location:
    """A place in a source file (1-based line and column)."""

    file: str | None = None
    line: int | None = None
    col: int | None = None

    def __str__(self) -> str:
        parts = [self.file or "<input>"]
        if self.line is not None:
            parts.append(str(self.line))
            if self.col is not None:
                parts.append(str(self.col))
        return ":".join(parts)


@dataclass(frozen=True)
class Diagnostic:
    """One finding: severity, a stable code, the item (dotted path) and a human message."""

    severity: Severity
    code: str
    message: str
    item: str = ""
    where: Location = Location()

    def format(self) -> str:
        """``file:line:col: item: message`` (warnings and infos are tagged)."""
        tag = "" if self.severity is Severity.ERROR else f"{self.severity.value}: "
        item = f"{self.item}: " if self.item else ""
        return f"{self.where}: {tag}{item}{self.message}"

    def as_error(self) -> Diagnostic:
        """The same finding promoted to an error (used by strict mode)."""
        return Diagnostic(Severity.ERROR, self.code, self.message, self.item, self.where)

    def to_dict(self) -> dict[str, object]:
        """Plain-data form for JSON output."""
        return {
            "severity": self.severity.value,
            "code": self.code,
            "message": self.message,
            "item": self.item,
            "file": self.where.file,
            "line": self.where.line,
            "col": self.where.col,
        }


def errors(diags: Iterable[Diagnostic]) -> list[Diagnostic]:
    """Only the errors among ``diags``."""
    return [d for d in diags if d.severity is Severity.ERROR]


def promote(diags: Iterable[Diagnostic], strict: bool) -> list[Diagnostic]:
    """In strict mode every warning becomes an error; infos stay infos."""
    out = list(diags)
    if not strict:
        return out
    return [d.as_error() if d.severity is Severity.WARNING else d for d in out]


class SpecError(BtmissionError):
    """Bad input: the file cannot be used. Carries every problem found (never just the first)."""

    def __init__(self, diagnostics: Sequence[Diagnostic]):
        self.diagnostics = list(diagnostics)
        super().__init__("\n".join(d.format() for d in self.diagnostics))
