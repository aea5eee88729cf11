"""Typed settings: what a library (or the navigator) declares it reads, checked and built once.

A mission tunes a run with ``runtime.settings`` (``{speed_m_s: 1.5, dispatch_generations: 50}``):
one flat namespace shared by the navigator, the runtime and every library of the mission. Whoever
reads settings *declares* them, with a type, a default and a doc, as a frozen dataclass::

    @dataclass(frozen=True)
    class HaulageSettings:
        dispatch_generations: int = 200
        \"\"\"GA generations per optimisation (runs are reproducible).\"\"\"

    IMPLEMENTATIONS = Implementations("haulage", settings=HaulageSettings)

and reads them as one typed object (``ctx.settings_of(HaulageSettings).dispatch_generations``),
never by name with a default of its own at the call site: the default is declared once, so it
cannot disagree with the one the checks and the docs show. A plain mapping of names to defaults
(``settings={"scan_time_s": 3.0}``, what libraries written before this module give) still
declares settings, their types taken from the defaults.

Why one vocabulary: ``btmission validate`` checks each ``runtime.settings`` value against the
declared type (:meth:`Setting.problem`: an ``int`` setting takes whole numbers, a ``float`` one
any finite number, a ``bool`` one only true/false, a ``str`` one only text), so a run never meets a
value its reader cannot use; the run merges the values once (:class:`RunSettings`: each
library's defaults, then the mission's) and builds each dataclass from them once
(:func:`settings_from`), converting as declared (``speed_m_s: 2`` → ``2.0``).

A field's doc (:attr:`Setting.doc`, what ``btmission library show`` prints) is its
``field(metadata={"doc": ...})`` when given, else the string literal under it (the attribute
docstring, read from the class's source), else empty.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import itertools
import math
import sys
import textwrap
import typing
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

from btmission.errors import BtmissionError
from btmission.spec.common import shown

SettingValue = bool | int | float | str
"""A setting's value: what ``runtime.settings`` holds (YAML scalars)."""

S = TypeVar("S")

TYPE_NAMES: dict[type, str] = {
    bool: "true or false",
    int: "an integer",
    float: "a number",
    str: "a string",
}
"""The types a setting may have, as a message names what it expects."""


@dataclass(frozen=True)
class Setting:
    """One declared setting: its name, type (bool, int, float or str), default and doc."""

    name: str
    kind: type
    """``bool``, ``int``, ``float`` or ``str``."""
    default: SettingValue
    owner: type | None = field(default=None, compare=False, repr=False)
    """The dataclass declaring it (None: a mapping did), where :attr:`doc` is read from."""

    @property
    def doc(self) -> str:
        """What the setting does: the field's ``metadata["doc"]``, else its attribute
        docstring, else empty. Read when asked (parsing the class's source takes ~15 ms: a run
        needs the types, not the docs)."""
        if self.owner is None:
            return ""
        declared = self.owner.__dataclass_fields__[self.name]  # type: ignore[attr-defined]
        return str(declared.metadata.get("doc", attribute_docs(self.owner).get(self.name, "")))

    @property
    def expected(self) -> str:
        """What a value must be, in words (``an integer``)."""
        return TYPE_NAMES[self.kind]

    def problem(self, value: Any) -> str | None:
        """Why ``value`` is not of this setting's type (None when it is): a bool is no number,
        an integer setting takes integral numbers (``3.0``), a number setting takes integers."""
        if self.kind is bool or self.kind is str:
            ok = isinstance(value, self.kind)
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            ok = False
        elif isinstance(value, int):
            ok = self.kind is int or abs(value) <= sys.float_info.max  # (a float holds it)
        else:
            ok = math.isfinite(value) and (self.kind is float or value.is_integer())
        return None if ok else f"expected {self.expected} (got {shown(value)})"

    def convert(self, value: Any) -> SettingValue:
        """``value`` as this setting's type (``2`` → ``2.0`` for a number, ``200.0`` → ``200``
        for an integer); :class:`SettingError` when it is not of that type."""
        problem = self.problem(value)
        if problem is not None:
            raise SettingError(f"setting '{self.name}': {problem}", self, value)
        return self.kind(value)  # type: ignore[no-any-return]


class SettingError(BtmissionError, ValueError):
    """A setting's value is not of its declared type (``validate`` and ``run`` refuse such a
    mission first: this is met by a context made by hand, or two declarations at odds)."""

    def __init__(self, message: str, setting: Setting | None = None, value: Any = None) -> None:
        super().__init__(message)
        self.setting = setting
        """The setting (None when only the message is known)."""
        self.value = value
        """The value it was given."""


def _declaration_error(owner: str, message: str) -> TypeError:
    return TypeError(f"{owner}: {message}")


def _of_value(name: str, value: Any, owner: str) -> Setting:
    """A setting declared by its default alone (a plain mapping): the default's type."""
    for kind in (bool, int, float, str):  # bool first: True is an int too
        if isinstance(value, kind):
            return Setting(name, kind, value)
    raise _declaration_error(
        owner,
        f"setting '{name}': default {value!r} is a {type(value).__name__}; a setting is a bool, "
        "an int, a float or a str",
    )


@functools.cache
def attribute_docs(cls: type) -> Mapping[str, str]:
    """The string literal under each annotated attribute of ``cls`` and its bases (the
    attribute docstrings Sphinx shows), read from their source; empty where there is none (a
    class made at run time)."""
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is object:
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for stmt, after in itertools.pairwise(body):
            if (
                isinstance(stmt, ast.AnnAssign)
                and isinstance(stmt.target, ast.Name)
                and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)
            ):
                out[stmt.target.id] = inspect.cleandoc(after.value.value)
    return out


@functools.cache
def _of_dataclass(cls: type) -> Mapping[str, Setting]:
    owner = cls.__qualname__
    params = getattr(cls, "__dataclass_params__", None)
    if params is None or not params.frozen:
        raise _declaration_error(
            owner,
            "settings are declared as a frozen dataclass (@dataclass(frozen=True)): one instance "
            "is shared by every agent of a run",
        )
    try:
        hints = typing.get_type_hints(cls)
    except Exception as exc:  # an annotation naming what the module does not define
        raise _declaration_error(owner, f"cannot read the settings' types: {exc}") from None
    out: dict[str, Setting] = {}
    for f in dataclasses.fields(cls):
        kind = hints.get(f.name)
        if kind not in TYPE_NAMES:
            raise _declaration_error(
                owner,
                f"setting '{f.name}' is a {kind}; a setting is a bool, an int, a float or a str",
            )
        if f.default is dataclasses.MISSING:
            raise _declaration_error(owner, f"setting '{f.name}' has no default")
        setting = Setting(f.name, kind, f.default, cls)  # type: ignore[arg-type]
        problem = setting.problem(f.default)
        if problem is not None:
            raise _declaration_error(owner, f"setting '{f.name}': default {problem}")
        out[f.name] = setting
    return out


def declared_settings(
    settings: type | Mapping[str, SettingValue] | None, owner: str = "settings"
) -> dict[str, Setting]:
    """The settings a frozen dataclass (its fields: type, default, doc) or a mapping (names →
    defaults, types from the defaults) declares, by name; TypeError naming ``owner`` (or the
    class) for a declaration that is not one: a field with no default, a type other than bool,
    int, float or str, a default not of its type."""
    if settings is None:
        return {}
    if isinstance(settings, type):
        return dict(_of_dataclass(settings))
    if not isinstance(settings, Mapping):
        raise _declaration_error(
            owner,
            f"settings must be a frozen dataclass or a mapping, not {type(settings).__name__}",
        )
    return {name: _of_value(name, value, owner) for name, value in settings.items()}


def merge_declared(
    base: Mapping[str, Setting], more: Mapping[str, Setting], owner: str
) -> dict[str, Setting]:
    """``base`` with ``more`` over it (a variant's own default wins); TypeError when one name
    is declared with two types (no value could satisfy both readers)."""
    out = dict(base)
    for name, setting in more.items():
        before = out.get(name)
        if before is not None and before.kind is not setting.kind:
            raise _declaration_error(
                owner,
                f"setting '{name}' is declared {setting.kind.__name__} here and "
                f"{before.kind.__name__} before",
            )
        out[name] = setting
    return out


def settings_from(cls: type[S], values: Mapping[str, Any]) -> S:
    """The settings dataclass ``cls`` from a run's values: each field from the value of its
    name, converted to its declared type (:meth:`Setting.convert`), or its default."""
    declared = _of_dataclass(typing.cast(type, cls))  # (a class is hashable: mypy misses it)
    return cls(**{name: s.convert(values[name]) for name, s in declared.items() if name in values})


class RunSettings(Mapping[str, Any]):
    """The settings of one run: the merged values (each library's defaults, then the mission's
    ``runtime.settings``), read by name through the mapping (the untyped path,
    ``ctx.setting(name, default)``), and each settings dataclass built from them once
    (:meth:`of`), shared by every agent and service of the run."""

    def __init__(self, values: Mapping[str, Any]) -> None:
        self._values = dict(values)
        self._built: dict[type, Any] = {}

    def __getitem__(self, name: str) -> Any:
        return self._values[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        return f"RunSettings({self._values!r})"

    def of(self, cls: type[S]) -> S:
        """The instance of ``cls`` for this run (built on first use)."""
        built = self._built.get(cls)
        if built is None:
            built = self._built[cls] = settings_from(cls, self._values)
        return built  # type: ignore[no-any-return]


def settings_of(settings: Mapping[str, Any], cls: type[S]) -> S:
    """``cls`` from ``settings``: once per run for a :class:`RunSettings`, built each call from
    any other mapping (a context made by hand, in a test)."""
    if isinstance(settings, RunSettings):
        return settings.of(cls)
    return settings_from(cls, settings)
