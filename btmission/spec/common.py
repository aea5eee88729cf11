"""Helpers shared by the library and mission loaders: identifiers and pydantic → Diagnostic."""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated, Any, Literal, TypeVar

from pydantic import AllowInfNan, BaseModel, BeforeValidator, StringConstraints, ValidationError

from btmission.diagnostics import Diagnostic, Severity, SpecError
from btmission.spec.source import Source

Identifier = Annotated[str, StringConstraints(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")]
"""A name usable as a condition, action, parameter, agent or task id."""

DottedName = Annotated[
    str, StringConstraints(pattern=r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
]


def _not_bool(v: Any) -> Any:
    """``true``/``false`` are not numbers (pydantic would read them as 1 and 0), and NaN / ±inf
    are refused before any range check could report them less clearly."""
    if isinstance(v, bool) or (isinstance(v, float) and not math.isfinite(v)):
        raise ValueError(number_problem(v))
    return v


FiniteFloat = Annotated[float, BeforeValidator(_not_bool), AllowInfNan(False)]
"""A number that is finite (NaN, ±inf and out-of-range literals such as 1e400 are refused) and
not a boolean: use it for every float a user writes."""

Int = Annotated[int, BeforeValidator(_not_bool)]
"""An integer that is not a boolean."""


def _format_version(v: Any) -> Any:
    if isinstance(v, bool):  # true == 1 in Python: pydantic's literal check would take it
        raise ValueError(f"got {shown(v)}, expected 1")
    return v


FormatVersion = Annotated[Literal[1], BeforeValidator(_format_version)]
"""``version: 1`` of a library or mission file."""


def shown(v: Any) -> str:
    """A value as the user wrote it in YAML: ``true``, ``nan``, ``inf``, ``'text'``, ``1.5``."""
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return repr(v)


def number_problem(v: Any) -> str | None:
    """Why ``v`` is not a usable number (None when it is a finite int or float, not a bool)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return f"expected a number (got {shown(v)})"
    if not math.isfinite(v):
        return f"expected a finite number (got {shown(v)})"
    return None


def _explain(err: dict[str, Any]) -> str:
    kind = err.get("type", "")
    loc = err.get("loc", ())
    if kind == "extra_forbidden":
        if not loc:
            return "unknown key"
        key = str(loc[-1])
        if key.rstrip().endswith(")"):
            return (
                f"unknown key '{key}': a comma inside (...) in a YAML flow mapping {{...}} splits "
                'the value; quote it, e.g. goal: "delivered(pickup, dropoff)"'
            )
        return f"unknown key '{key}'"
    if (
        kind in ("missing", "too_short", "too_long") and loc and isinstance(loc[-1], int)
    ) or kind in ("too_short", "too_long", "tuple_type"):
        return f"expected {_expected_len(err)} (got {err.get('input')!r})"
    if kind == "missing":
        return f"missing required key '{loc[-1]}'" if loc else "missing required key"
    if kind == "finite_number":
        return f"expected a finite number (got {err.get('input')})"
    if kind == "string_pattern_mismatch":
        return f"'{err.get('input')}' is not a valid name (letters, digits and _; not starting with a digit)"
    if kind == "literal_error":
        expected = err.get("ctx", {}).get("expected", "")
        return f"got {err.get('input')!r}, expected {expected}"
    given = err.get("input")
    if kind in ("model_type", "dict_type", "model_attributes_type"):
        return f"expected a mapping of keys (got {given!r})"
    if kind == "list_type":
        return f"expected a list [...] (got {given!r})"
    msg = str(err.get("msg", "invalid value"))
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    if kind not in ("value_error", "assertion_error") and not isinstance(given, (dict, list)):
        msg += f" (got {given!r})"
    return msg


def _expected_len(err: dict[str, Any]) -> str:
    ctx = err.get("ctx", {})
    n = ctx.get("max_length") or ctx.get("min_length") or ctx.get("expected")
    return "3 values [x, y, z]" if n in (3, None) else f"{n} values"


def validate_model(model: type[BaseModel], src: Source, what: str) -> Any:
    """Validate ``src.data`` against ``model``; every schema problem becomes a located Diagnostic."""
    if not isinstance(src.data, dict):
        raise SpecError(
            [src.diag((), f"a {what} file must be a YAML mapping at the top level", "schema")]
        )
    try:
        return model.model_validate(src.data)
    except ValidationError as exc:
        diags: list[Diagnostic] = []
        for err in exc.errors():
            # pydantic appends union-member / tagged names to loc; keep only real path parts
            loc = tuple(
                p
                for p in err["loc"]
                if isinstance(p, int)
                or not str(p).startswith(("function-", "list[", "dict[", "tuple[", "union["))
            )
            loc = _strip_variant_tags(loc, src)
            if err.get("type") == "missing" and loc and isinstance(loc[-1], int):
                loc = loc[:-1]  # a short [x, y] tuple: point at the tuple, not the absent item
            diags.append(
                Diagnostic(
                    Severity.ERROR,
                    "schema",
                    _explain(dict(err)),
                    _format(loc),
                    src.locate(loc, key=err.get("type") in ("extra_forbidden", "missing")),
                )
            )
        raise SpecError(_dedupe(diags)) from None


def _strip_variant_tags(loc: tuple[Any, ...], src: Source) -> tuple[Any, ...]:
    """Drop pydantic's union-variant names (e.g. ``GenerateMap``) that are not keys in the data."""
    out: list[Any] = []
    node: Any = src.data
    for part in loc:
        if isinstance(node, dict) and part in node:
            out.append(part)
            node = node[part]
        elif isinstance(node, list) and isinstance(part, int) and 0 <= part < len(node):
            out.append(part)
            node = node[part]
        elif isinstance(node, (dict, list)):
            if isinstance(part, str) and part[:1].isupper():
                continue  # a model/variant name, not a key
            out.append(part)
            node = None
        else:
            continue
    return tuple(out)


def _format(loc: tuple[Any, ...]) -> str:
    from btmission.spec.source import format_path

    return format_path(loc)


def _dedupe(diags: list[Diagnostic]) -> list[Diagnostic]:
    seen: set[tuple[str, str, str]] = set()
    out = []
    for d in diags:
        key = (d.item, d.message, str(d.where))
        if key not in seen:
            seen.add(key)
            out.append(d)
    return out


_C = TypeVar("_C")


def config_from(cls: type[_C], section: BaseModel, **extra: Any) -> _C:
    """A subsystem's typed config (a dataclass) from its validated file section: every field of
    ``cls`` that the section has, by name, and ``extra`` (what the file does not hold, such as a
    signing key); the rest keep their defaults. One rule instead of a hand-copied field list:
    a field added to both is carried over, and ``tests/unit/spec/test_spec.py`` lists the section fields
    no config takes."""
    names = {f.name for f in dataclasses.fields(cls)} & set(type(section).model_fields)  # type: ignore[arg-type]
    return cls(**{name: getattr(section, name) for name in sorted(names)}, **extra)
