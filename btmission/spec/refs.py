"""Parsing of condition references such as ``has_path(goal)`` or ``delivered(pickup, dropoff=d)``.

A reference names a condition and binds its parameters to symbols, positionally or by keyword.
Symbols are identifiers: an enclosing action's parameter, a library variable, or (in a goal) a
task field / blackboard key.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from btmission.errors import BtmissionError

IDENT = r"[A-Za-z_][A-Za-z0-9_]*"
_IDENT_RE = re.compile(rf"^{IDENT}$")
_REF_RE = re.compile(rf"^\s*(?P<name>{IDENT})\s*(?:\((?P<args>[^()]*)\))?\s*$")


class RefSyntaxError(BtmissionError, ValueError):
    """The text is not ``name`` or ``name(arg, ...)``."""


@dataclass(frozen=True, slots=True)
class Ref:
    """A parsed reference: ``name``, positional ``args`` and keyword ``kwargs`` (param, symbol)."""

    name: str
    args: tuple[str, ...] = ()
    kwargs: tuple[tuple[str, str], ...] = ()

    def __str__(self) -> str:
        parts = list(self.args) + [f"{k}={v}" for k, v in self.kwargs]
        return f"{self.name}({', '.join(parts)})" if parts else self.name


def is_identifier(text: str) -> bool:
    return bool(_IDENT_RE.match(text))


def parse_ref(text: str) -> Ref:
    """Parse ``name``, ``name()`` or ``name(a, b=c)``.

    >>> parse_ref("has_path(goal)")
    Ref(name='has_path', args=('goal',), kwargs=())
    >>> str(parse_ref("delivered(pickup, dropoff=place)"))
    'delivered(pickup, dropoff=place)'
    """
    if not isinstance(text, str):
        raise RefSyntaxError(f"expected a condition reference like 'name(arg)', got {text!r}")
    m = _REF_RE.match(text)
    if not m and text.count("(") != text.count(")"):
        raise RefSyntaxError(
            f"'{text}' has unbalanced parentheses: inside a YAML flow list or mapping ([...] or "
            "{...}) a comma splits the text, so quote references with several arguments, e.g. "
            '"delivered(pickup, dropoff)"'
        )
    if not m:
        raise RefSyntaxError(
            f"'{text}' is not a condition reference (expected name or name(arg, ...))"
        )
    args: list[str] = []
    kwargs: list[tuple[str, str]] = []
    raw = m.group("args")
    if raw is not None and raw.strip():
        for part in raw.split(","):
            part = part.strip()
            if "=" in part:
                k, _, v = part.partition("=")
                k, v = k.strip(), v.strip()
                if not (is_identifier(k) and is_identifier(v)):
                    raise RefSyntaxError(f"bad keyword argument '{part}' in '{text}'")
                if any(k == kk for kk, _ in kwargs):
                    raise RefSyntaxError(f"parameter '{k}' given twice in '{text}'")
                kwargs.append((k, v))
            else:
                if kwargs:
                    raise RefSyntaxError(f"positional argument after keyword argument in '{text}'")
                if not is_identifier(part):
                    raise RefSyntaxError(f"bad argument '{part}' in '{text}' (expected a name)")
                args.append(part)
    return Ref(m.group("name"), tuple(args), tuple(kwargs))
