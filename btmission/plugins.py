"""Finding capability libraries and their implementations (DESIGN.md §4.1).

A library is found either

* by **name**, through the ``btmission.libraries`` entry-point group: the entry point's object is
  the library YAML (a path or ``importlib.resources`` traversable) or a callable returning one.
  The built-in libraries in ``library/`` are registered exactly this way in btmission's own
  ``pyproject.toml``; a third-party plugin does the same in its own; or
* by **path** to a YAML file.

Implementations live in the Python module named by the library's ``module:`` key, registered by
name on an :class:`Implementations` object called ``IMPLEMENTATIONS``::

    IMPLEMENTATIONS = Implementations("aerial")

    @IMPLEMENTATIONS.action("takeoff")
    class Takeoff(py_trees.behaviour.Behaviour): ...

    @IMPLEMENTATIONS.condition("is_flying")
    def is_flying(ctx, **args) -> bool: ...

The runtime binds leaves to these by name; synthesis and export never need them.

Checking is not running: inside :func:`implementation_imports` with ``"installed"`` (what
``library check``/``show``, ``synth`` and ``validate`` use), a library given by *path* is loaded
without importing its ``module:``, so checking a YAML file never executes code it names. An
installed library (entry point) is trusted: loading its entry point imports its package anyway.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import sys
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from types import MappingProxyType
from typing import Any, Literal, TypeVar

from btmission.diagnostics import Diagnostic, Location, Severity, SpecError
from btmission.settings import Setting, SettingValue, declared_settings, merge_declared
from btmission.spec.library import Library, load_library_source
from btmission.spec.source import parse_yaml, read_yaml

ENTRY_POINT_GROUP = "btmission.libraries"

T = TypeVar("T")

ImportPolicy = Literal["always", "installed", "never"]
"""When :func:`load_library` imports a library's implementation module (unless told explicitly):
``always``; ``installed`` libraries only (entry points: already trusted code), not libraries
given by path; ``never``."""
_IMPORT_POLICY: ContextVar[ImportPolicy] = ContextVar("btmission_import_policy", default="always")


@contextmanager
def implementation_imports(policy: ImportPolicy) -> Iterator[None]:
    """Within the block, :func:`load_library` (also through ``load_mission``) follows ``policy``
    whenever its ``import_module`` is not given."""
    token = _IMPORT_POLICY.set(policy)
    try:
        yield
    finally:
        _IMPORT_POLICY.reset(token)


class Implementations:
    """A registry of action and condition implementations of one library, keyed by name.

    ``vehicle`` is the kind of vehicle the library drives (``multirotor`` or ``ground``: the
    simulator builds that model for its agents); ``settings`` declares the tunables its
    implementations read (a mission sets them under ``runtime.settings``): a frozen dataclass
    whose typed fields have defaults and docs, which leaves read as one object
    (``ctx.settings_of(cls)``), or a plain mapping of names to defaults (the types are the
    defaults'): see :mod:`btmission.settings`. It may name a navigator setting too
    (``speed_m_s``): its default is then the library's for the runs that use it.
    Functions registered with :meth:`on_setup` run once per agent before its first tick (to put
    initial variables such as ``home`` on its blackboard). Factories registered with
    :meth:`service` build one object per *run*, shared by every agent of the library (a fleet
    dispatcher, a shared map database): see :meth:`service`.
    """

    def __init__(
        self,
        library: str,
        *,
        vehicle: str = "multirotor",
        settings: type | Mapping[str, SettingValue] | None = None,
    ) -> None:
        if vehicle not in ("multirotor", "ground"):
            raise ValueError(
                f"{library}: vehicle must be 'multirotor' or 'ground', got '{vehicle}'"
            )
        self.library = library
        self.vehicle = vehicle
        self.declared: dict[str, Setting] = declared_settings(settings, library)
        """Every setting the library declares (type, default, doc), by name."""
        self.actions: dict[str, Any] = {}
        self.conditions: dict[str, Any] = {}
        self.setup_hooks: list[Callable[[Any], None]] = []
        self.services: dict[str, Callable[[Any], Any]] = {}

    @property
    def settings(self) -> Mapping[str, SettingValue]:
        """The declared settings' defaults, by name (what a run starts from; read-only: the
        declaration is the place to change them)."""
        return MappingProxyType({name: s.default for name, s in self.declared.items()})

    def on_setup(self, fn: Callable[[Any], None]) -> Callable[[Any], None]:
        """Decorator: ``fn(ctx)`` runs once per agent before its first tick."""
        self.setup_hooks.append(fn)
        return fn

    def extend(
        self, library: str, *, settings: type | Mapping[str, SettingValue] | None = None
    ) -> Implementations:
        """A registry for a variant library ``library`` that starts with everything of this one
        — vehicle, settings (plus ``settings``: a name declared again takes the variant's
        default; with another type it is a TypeError), setup hooks, actions and conditions — and
        to which the variant adds its own (``aerial_mine`` = ``aerial`` + ``relocalize``);
        run-wide services are inherited too::

            IMPLEMENTATIONS = aerial.IMPLEMENTATIONS.extend("aerial_mine", settings=MineSettings)
        """
        out = Implementations(library, vehicle=self.vehicle)
        out.declared = merge_declared(self.declared, declared_settings(settings, library), library)
        out.actions.update(self.actions)
        out.conditions.update(self.conditions)
        out.setup_hooks.extend(self.setup_hooks)
        out.services.update(self.services)
        return out

    def _register(self, table: dict[str, Any], kind: str, name: str) -> Callable[[T], T]:
        def deco(obj: T) -> T:
            if name in table:
                raise ValueError(f"{self.library}: {kind} '{name}' is registered twice")
            table[name] = obj
            return obj

        return deco

    def action(self, name: str) -> Callable[[T], T]:
        """Decorator registering the implementation of action ``name``."""
        return self._register(self.actions, "action", name)

    def condition(self, name: str) -> Callable[[T], T]:
        """Decorator registering the implementation of condition ``name``."""
        return self._register(self.conditions, "condition", name)

    def service(self, name: str) -> Callable[[T], T]:
        """Decorator registering a run-wide service: ``factory(run) -> object``.

        The runtime calls each factory once per run, before any agent is set up, with a
        :class:`~btmission.runtime.leaves.RunContext` (the mission, its world, the clock,
        settings, seed, events). The object is shared by every agent (``ctx.services[name]``);
        if it has a ``step(now)`` method, the runtime calls it at the start of every step, before
        the auction and the ticks (a service does its periodic work there, in simulated time).
        """
        return self._register(self.services, "service", name)

    def check(self, library: Library) -> list[Diagnostic]:
        """Registered names the spec does not declare are errors; unimplemented ones are listed."""
        out: list[Diagnostic] = []
        where = Location(library.file)
        for kind, table, declared in (
            ("action", self.actions, library.actions),
            ("condition", self.conditions, library.conditions),
        ):
            for name in sorted(set(table) - set(declared)):
                out.append(
                    Diagnostic(
                        Severity.ERROR,
                        "unknown-implementation",
                        f"module {library.module} implements {kind} '{name}', which the library does not declare",
                        name,
                        where,
                    )
                )
        return out

    def missing(self, library: Library) -> list[str]:
        """Declared actions and conditions with no implementation (sorted)."""
        return sorted(
            [a for a in library.actions if a not in self.actions]
            + [c for c in library.conditions if c not in self.conditions]
        )


@dataclass
class LoadedLibrary:
    """A library with where it came from, its findings and (if importable) its implementations."""

    library: Library
    diagnostics: list[Diagnostic]
    origin: str
    implementations: Implementations | None = None
    import_error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    module_not_imported: bool = False
    """True when ``module:`` was deliberately not imported (checking, see
    :func:`implementation_imports`): nothing is known about its implementations."""

    @property
    def runnable(self) -> bool:
        impl = self.implementations
        return impl is not None and not impl.missing(self.library)


def installed_libraries() -> dict[str, metadata.EntryPoint]:
    """Every library registered in the ``btmission.libraries`` entry-point group, by name."""
    eps = metadata.entry_points(group=ENTRY_POINT_GROUP)
    return {ep.name: ep for ep in sorted(eps, key=lambda e: e.name)}


def looks_like_path(ref: str) -> bool:
    return ref.endswith((".yaml", ".yml")) or "/" in ref or "\\" in ref


def _spec_text(obj: Any, name: str) -> tuple[str, str]:
    """Text and display path of the YAML an entry point designates."""
    if callable(obj) and not hasattr(obj, "read_text"):
        obj = obj()
    if isinstance(obj, str):
        obj = Path(obj)
    if not hasattr(obj, "read_text"):
        raise TypeError(
            f"entry point '{name}' gives {type(obj).__name__}, expected a path to the YAML"
        )
    return obj.read_text(encoding="utf-8"), str(obj)


def load_library(
    ref: str,
    base_dir: Path | None = None,
    *,
    import_module: bool | None = None,
    where: Location = Location("<command line>"),
) -> LoadedLibrary:
    """Find a library by installed name or by path (relative to ``base_dir``) and load it.

    ``where`` is where ``ref`` was written, for the message when it cannot be found.
    ``import_module`` says whether to import the implementation module named by ``module:``;
    None (the default) follows :func:`implementation_imports` (outside it: import).

    Raises :class:`SpecError` when it cannot be found or its file is malformed; semantic findings
    (undefined references, …) are returned in ``diagnostics`` for the caller to judge.
    """
    installed = installed_libraries()
    if not looks_like_path(ref) and ref in installed:
        ep = installed[ref]
        try:
            text, shown = _spec_text(ep.load(), ref)
        except Exception as exc:  # a broken plugin must not crash the tool
            raise SpecError(
                [
                    Diagnostic(
                        Severity.ERROR,
                        "plugin-error",
                        f"library plugin '{ref}' ({ep.value}) could not be loaded: {exc}",
                        ref,
                        where,
                    )
                ]
            ) from None
        src = parse_yaml(text, shown)
        origin = f"entry point {ep.value}"
        installed_ep = True
    else:
        if not ref.strip():  # Path("") is the current directory
            known = ", ".join(installed) or "none"
            message = f"empty library reference: give an installed library ({known}) or a path"
            raise SpecError([Diagnostic(Severity.ERROR, "unknown-library", message, ref, where)])
        path = Path(ref)
        if base_dir is not None and not path.is_absolute():
            path = base_dir / path
        if not path.exists():
            known = ", ".join(installed) or "none"
            message = (
                f"library file '{path}' not found"
                if looks_like_path(ref)
                else f"unknown library '{ref}': no installed library of that name "
                f"(installed: {known}) and no such file"
            )
            raise SpecError([Diagnostic(Severity.ERROR, "unknown-library", message, ref, where)])
        src = read_yaml(path)
        origin = f"file {path}"
        installed_ep = False
    lib, diags = load_library_source(src)
    loaded = LoadedLibrary(lib, diags, origin)
    if import_module is None:
        policy = _IMPORT_POLICY.get()
        import_module = policy == "always" or (policy == "installed" and installed_ep)
    if lib.module:
        if import_module:
            bind_implementations(loaded)
        else:
            loaded.module_not_imported = True
    return loaded


def module_can_be_found(name: str) -> bool:
    """Whether ``import name`` would find a module, without executing any code (no parent
    package is imported: each level is looked up on the finders' paths)."""
    search: Any = None
    parts = name.split(".")
    for k in range(len(parts)):
        full = ".".join(parts[: k + 1])
        module = sys.modules.get(full)
        if module is not None:
            search = getattr(module, "__path__", None)
        else:
            try:
                spec = (
                    importlib.util.find_spec(full)
                    if k == 0
                    else importlib.machinery.PathFinder.find_spec(full, search)
                )
            except (ImportError, ValueError):
                return False
            if spec is None:
                return False
            search = spec.submodule_search_locations
        if search is None and k < len(parts) - 1:
            return False  # a plain module has no submodules
    return True


def _import_failed(loaded: LoadedLibrary, error: str) -> None:
    """Record that the library's module cannot be imported (it still synthesises and exports)."""
    loaded.import_error = error
    loaded.diagnostics.append(
        Diagnostic(
            Severity.WARNING,
            "module-import",
            f"cannot import implementation module '{loaded.library.module}' ({error}); "
            "the library synthesises and exports but cannot run",
            "module",
            Location(loaded.library.file),
        )
    )


def bind_implementations(loaded: LoadedLibrary) -> None:
    """Import the library's module and attach its ``IMPLEMENTATIONS`` registry (if any)."""
    lib = loaded.library
    assert lib.module
    try:
        mod = importlib.import_module(lib.module)
    except Exception as exc:  # report, don't crash: the library still synthesises
        _import_failed(loaded, f"{type(exc).__name__}: {exc}")
        return
    impl = getattr(mod, "IMPLEMENTATIONS", None)
    if isinstance(impl, Implementations):
        loaded.implementations = impl
        loaded.diagnostics.extend(impl.check(lib))


def library_catalog() -> Mapping[str, LoadedLibrary | SpecError]:
    """Every installed library loaded (or the error that stopped it), by name."""
    out: dict[str, LoadedLibrary | SpecError] = {}
    for name in installed_libraries():
        try:
            out[name] = load_library(name)
        except SpecError as exc:
            out[name] = exc
    return out
