"""Frozen dataclasses built without their ``__init__``'s per-field ``object.__setattr__``
(:mod:`btmission.fastpaths`, item 5; re-exported by :mod:`btmission.types`).

A frozen dataclass's generated ``__init__`` stores each field with ``object.__setattr__`` — the
documented cost of ``frozen=True`` ("a tiny performance penalty"). The run builds some records by
the thousand per second (``Telemetry``: every vehicle, every step; ``Prediction``: every drone,
every control step; ``AgentState`` and ``Bid``: every agent, every auction round), so
:func:`recorder` gives such a class a builder that stores the fields straight into the new
instance's ``__dict__``, as the generated ``__init__`` would have, minus the per-field call.

Measured on a 12-field ``Telemetry`` (Python 3.11, this repository's machine, keywords written
at the call as the call sites do): the dataclass's ``__init__`` 1.54 µs; a generic builder
without generated code (``**fields``, a key check, ``__dict__.update``) 0.72 µs; the generated
keyword-only builder 0.38 µs. Hence the one piece of generated code, :func:`_keyword_builder`.
"""

from __future__ import annotations

import dataclasses
import inspect
import keyword
from collections.abc import Callable
from typing import Any, TypeVar, cast

__all__ = ["record", "recorder"]

_R = TypeVar("_R")

_RECORDERS: dict[type[Any], Callable[..., Any]] = {}

_NAMED = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)


def recorder(cls: type[_R]) -> Callable[..., _R]:
    """A builder of ``cls``, a frozen dataclass: ``recorder(cls)(**fields)`` is
    ``cls(**fields)`` minus the generated ``__init__``'s ``object.__setattr__`` per field (a
    12-field record: a quarter of the time, module docstring). Its arguments are keyword-only
    and named after the fields, so a missing or unknown field raises the ``TypeError`` the
    dataclass would. Made once per class (and kept); every field must be given, its default
    too. A class whose ``__init__`` does more than store its fields (:func:`_stored_fields`:
    a ``__post_init__``, an ``InitVar``, a field out of ``__init__``, ``slots``) gets ``cls``
    itself: the fallback, the dataclass's own construction."""
    built = _RECORDERS.get(cls)
    if built is None:
        names = _stored_fields(cls)
        built = cls if names is None else _keyword_builder(cls, names)
        _RECORDERS[cls] = built
    return built


def record(cls: type[_R], **fields: Any) -> _R:
    """``cls(**fields)`` through :func:`recorder` (hot paths keep ``recorder(cls)`` and call it
    directly: this adds a dictionary of the keywords)."""
    return recorder(cls)(**fields)


def _stored_fields(cls: type[Any]) -> tuple[str, ...] | None:
    """The names of ``cls``'s fields if its ``__init__`` only stores them, in order; else None.

    Through the public API only: ``dataclasses.fields`` (which leaves out ``InitVar`` and
    ``ClassVar`` pseudo-fields) must name exactly the parameters of ``inspect.signature(cls)``
    — an ``InitVar`` is a parameter that is no field, a ``field(init=False)`` a field that is
    no parameter — and there must be no ``__post_init__`` (a check or a derived field the
    builder would skip) and no ``__slots__`` (no instance ``__dict__``). The names must be
    plain identifiers, as the generated code spells them. (A dataclass that writes its own
    ``__init__`` with the fields' names as its parameters is not told apart: do not give
    :func:`recorder` one.)"""
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        return None
    if hasattr(cls, "__post_init__") or "__slots__" in cls.__dict__:
        return None
    names = tuple(f.name for f in dataclasses.fields(cast(Any, cls)))
    try:
        params = inspect.signature(cls).parameters
    except (TypeError, ValueError):
        return None
    if not names or tuple(params) != names or any(p.kind not in _NAMED for p in params.values()):
        return None
    if not all(_plain_name(n) for n in names):
        return None
    return names


def _plain_name(name: str) -> bool:
    return name.isidentifier() and not keyword.iskeyword(name) and not name.startswith("_")


def _keyword_builder(cls: type[_R], names: tuple[str, ...]) -> Callable[..., _R]:
    """The fast path, and the one piece of generated code in btmission: a function
    ``def Cls(*, a, b, ...)`` that makes a bare instance (``object.__new__``) and stores each
    argument in its ``__dict__`` under the field's name — what the dataclass's ``__init__``
    leaves there, without ``object.__setattr__`` per field.

    Why generated: named keyword-only parameters are what make it fast (no dictionary of the
    keywords, no key check) while keeping the dataclass's ``TypeError`` for a missing or unknown
    field, and Python only makes a function with named parameters from source — the way the
    dataclasses module makes ``__init__`` itself. What goes into the source is checked:
    ``names`` are plain identifiers (:func:`_stored_fields`), the class is passed in the
    namespace, never spelled. The result is an ordinary instance of ``cls``: equality, hash,
    ``repr``, ``replace``, pickling and the frozen ``__setattr__`` are the dataclass's own."""
    fn_name = cls.__name__ if _plain_name(cls.__name__) else "build"
    src = (
        f"def {fn_name}(*, {', '.join(names)}):\n"
        "    out = new(cls)\n"
        "    d = out.__dict__\n"
        + "".join(f"    d[{n!r}] = {n}\n" for n in names)
        + "    return out\n"
    )
    scope: dict[str, Any] = {"new": object.__new__, "cls": cls}
    exec(compile(src, f"<recorder({cls.__qualname__})>", "exec"), scope)
    built = cast(Callable[..., _R], scope[fn_name])
    built.__qualname__ = f"recorder({cls.__qualname__})"
    return built
