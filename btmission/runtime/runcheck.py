"""What ``btmission run`` needs of a loaded mission beyond its schema, checked in one place.

``btmission validate`` and :class:`~btmission.runtime.runner.MissionRun` both call
:func:`run_problems`, so that a mission ``validate`` accepts is one ``run`` can start: every
agent's ``backend:`` names an installed vehicle provider, the same for the whole fleet
(:func:`backend_problems`), every library has its implementations, and every
``runtime.settings`` entry is a setting someone declares, of its declared type, in its range;
and what each library's own ``check_mission`` finds (:func:`library_problems`). Problems are located (file:line:col) and unknown setting names
get a did-you-mean.

Settings are declared (:mod:`btmission.settings`: a name, a type, a default, a doc) in two
places: the run's own (the navigator's :class:`~btmission.runtime.navconfig.NavConfig`, the
tree events' :class:`~btmission.runtime.treestatus.TreeEventSettings` and the refused commands'
:class:`~btmission.runtime.actions.CommandRetrySettings`: every run has them) and
each library's implementations (``Implementations(settings=...)``: a frozen dataclass, or a
mapping whose defaults give the types). A value must be of the declared type
(:meth:`~btmission.settings.Setting.problem`); the ranges are in :data:`SETTING_RANGES`, and a
setting not listed there whose name ends in a unit (``_s``, ``_m``, ``_m_s``, ``_hz``, ``_px``)
must be ≥ 0.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from btmission.diagnostics import Diagnostic, Location, Severity
from btmission.settings import Setting, declared_settings
from btmission.spec.common import shown
from btmission.spec.source import format_path

if TYPE_CHECKING:
    from btmission.missions import LoadedMission

SETTING_RANGES: dict[str, tuple[float, bool]] = {
    # setting: (lower bound, bound excluded)
    "speed_m_s": (0.0, True),
    "lookahead_m": (0.0, True),
    "tolerance_m": (0.0, True),
    "altitude_m": (0.0, False),
    "stuck_s": (0.0, True),
    "replans": (0.0, False),
    "refusal_retries": (0.0, False),
    "apf_gain": (0.0, False),
    "clearance_m": (0.0, False),
    "dispatch_budget_s": (0.0, True),
    "dispatch_generations": (1.0, False),
    "reloc_spacing_m": (0.0, True),
    "explore_time_s": (0.0, True),
}
"""Lower bounds of the settings the built-in libraries and the navigator read."""

UNIT_SUFFIXES = ("_s", "_m", "_m_s", "_hz", "_px")
"""A setting named with one of these is a physical quantity: it must be ≥ 0 unless listed above."""


def declared_run_settings(mission: LoadedMission) -> dict[str, Setting]:
    """Every setting a run of ``mission`` reads, as declared (type, default, doc): the
    navigator's and the runtime's (every run has them), then each library's
    (``Implementations(settings=...)``). A name declared by both keeps the first declaration's
    type: a library may give a navigator setting its own default (``ground``: ``speed_m_s`` 0.4),
    not another type."""
    from btmission.runtime.actions import CommandRetrySettings
    from btmission.runtime.navconfig import NavConfig
    from btmission.runtime.treestatus import TreeEventSettings

    declared: dict[str, Setting] = {}
    for cls in (NavConfig, TreeEventSettings, CommandRetrySettings):
        declared.update(declared_settings(cls))
    for loaded in mission.libraries.values():
        impl = loaded.implementations
        if impl is None:
            continue
        for name, setting in impl.declared.items():
            declared.setdefault(name, setting)
    return declared


def setting_problem(name: str, value: Any, declared: Setting | Any) -> str | None:
    """Why ``value`` cannot be used for the setting ``name``: not of its declared type (a
    :class:`~btmission.settings.Setting`; a bare default stands for a setting of its type), or
    out of its range (:data:`SETTING_RANGES`, the unit suffixes)."""
    if not isinstance(declared, Setting):
        declared = declared_settings({name: declared})[name]
    setting: Setting = declared
    problem = setting.problem(value)
    if problem or setting.kind not in (int, float):
        return problem
    low, excluded = SETTING_RANGES.get(name, (0.0, False) if name.endswith(UNIT_SUFFIXES) else
                                       (-math.inf, False))  # fmt: skip
    if value < low or (excluded and value == low):
        bound = f"{'>' if excluded else '≥'} {low:g}"
        return f"expected {setting.expected} {bound} (got {shown(value)})"
    return None


def settings_problems(
    settings: Mapping[str, Any],
    defaults: Mapping[str, Setting | Any],
    locate: Any,
    complete: bool = True,
) -> list[Diagnostic]:
    """Unknown names (with a did-you-mean), wrong types and values out of range in ``settings``.

    ``defaults``: the known settings, as declared (:func:`declared_run_settings`) or by their
    defaults. ``locate(path, key=...)`` gives the location of ``("runtime", "settings", name)``;
    ``complete`` False means some library's settings are not known (its module was not
    imported), so unknown names are not judged."""
    out: list[Diagnostic] = []
    for name, value in settings.items():
        path: Sequence[str | int] = ("runtime", "settings", name)
        if name not in defaults:
            if not complete:
                continue
            close = difflib.get_close_matches(name, list(defaults), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            known = ", ".join(sorted(defaults))
            message = f"unknown setting '{name}'{hint}; known: {known}"
            out.append(Diagnostic(Severity.ERROR, "unknown-setting", message,
                                  format_path(path), locate(path, key=True)))  # fmt: skip
            continue
        problem = setting_problem(name, value, defaults[name])
        if problem:
            out.append(Diagnostic(Severity.ERROR, "bad-setting", problem,
                                  format_path(path), locate(path)))  # fmt: skip
    return out


def implementation_problems(
    mission: LoadedMission, *, abstract_ok: bool = False
) -> list[Diagnostic]:
    """Libraries that cannot run: no implementation module, missing or unusable leaves.

    ``abstract_ok``: a library without ``module:`` (abstract: it synthesises and exports, by
    design) is not a problem; ``validate`` accepts it, ``run`` refuses it. A library whose module
    was not imported (checking without importing) is only looked up: it must exist."""
    import sys

    from btmission.plugins import module_can_be_found
    from btmission.runtime.leaves import StatefulAction

    out: list[Diagnostic] = []

    def refuse(i: int, message: str) -> None:
        path = ("agents", i, "library")
        out.append(Diagnostic(Severity.ERROR, "not-runnable", message, format_path(path),
                              mission.locate(path)))  # fmt: skip

    first = {a.library: i for i, a in reversed(list(enumerate(mission.agents)))}
    for ref, loaded in mission.libraries.items():
        impl, lib, i = loaded.implementations, loaded.library, first.get(ref, 0)
        if impl is None:
            if not lib.module and abstract_ok:
                continue
            why = loaded.import_error
            if lib.module and why is None and lib.module not in sys.modules:
                if module_can_be_found(lib.module):  # looked up without running any of it
                    continue  # not imported: its registry cannot be judged
                why = f"ModuleNotFoundError: No module named '{lib.module}'"
            why = why or (
                f"module '{lib.module}' has no IMPLEMENTATIONS registry"
                if lib.module
                else f"library '{lib.name}' has no implementation module (it is abstract: "
                "synth, export and `mission tree` work without one)"
            )
            refuse(i, f"library '{ref}' cannot run: {why}")
            continue
        missing = impl.missing(lib)
        if missing:
            refuse(i, f"library '{ref}' cannot run: no implementation of {', '.join(missing)}")
        wrong = sorted(
            name
            for name, cls in impl.actions.items()
            if not (isinstance(cls, type) and issubclass(cls, StatefulAction))
        )
        if wrong:
            refuse(i, f"library '{ref}' cannot run: the implementations of {', '.join(wrong)} "
                   "are not StatefulAction subclasses (btmission.runtime.leaves.StatefulAction: "
                   "constructed as cls(node, ctx), see docs/plugins.md)")  # fmt: skip
    return out


def library_problems(mission: LoadedMission) -> list[Diagnostic]:
    """What the libraries' own checks find: an implementation module may define
    ``check_mission(mission) -> list[Diagnostic]`` for what its run-wide services or setup hooks
    would refuse (the haulage fleet's topological map and truck starts, a place database that
    is not a file), so that ``validate`` finds it before ``run`` builds anything."""
    import sys

    out: list[Diagnostic] = []
    seen: set[str] = set()
    for loaded in mission.libraries.values():
        module = loaded.library.module
        if loaded.implementations is None or not module or module in seen:
            continue
        seen.add(module)
        check = getattr(sys.modules.get(module), "check_mission", None)
        if not callable(check):
            continue
        try:
            out.extend(check(mission))
        except Exception as exc:  # a plugin's check must not crash validate
            out.append(Diagnostic(Severity.ERROR, "plugin-error",
                                  f"{module}.check_mission failed: {type(exc).__name__}: {exc}",
                                  "agents", Location(mission.file)))  # fmt: skip
    return out


def backend_problems(
    mission: LoadedMission, agents: Collection[str] | None = None
) -> list[Diagnostic]:
    """Agents whose ``backend:`` no installed vehicle provider serves (its URL scheme is not in
    the ``btmission.providers`` entry-point group), and fleets that mix providers: a run has one
    clock, and simulated time cannot be mixed with the wall clock; and references whose address
    their provider refuses (its plugin's ``check_address``: the only reader of an address).
    ``agents``: those one process of a distributed run flies (the others' vehicles are another
    process's). An entry point is loaded only for a reference with an address
    (:mod:`btmission.vehicles.provider`)."""
    from btmission.spec.vehicleref import EXPECTED, VehicleRef
    from btmission.vehicles.provider import (
        installed_providers,
        load_provider,
        unknown_scheme_message,
    )

    installed = installed_providers()
    checks: dict[str, Callable[[VehicleRef], str | None] | Exception | None] = {}
    """Each scheme's address check, its plugin loaded once (or why it could not be)."""
    out: list[Diagnostic] = []

    def refuse(i: int, code: str, message: str) -> None:
        path = ("agents", i, "backend")
        out.append(Diagnostic(Severity.ERROR, code, message, format_path(path),
                              mission.locate(path)))  # fmt: skip

    for i, agent in enumerate(mission.agents):
        ref = agent.vehicle
        if ref.scheme not in installed:
            refuse(i, "unknown-backend",
                   f"backend '{ref}': {unknown_scheme_message(ref.scheme, list(installed))}")  # fmt: skip
            continue
        if not ref.address and ref.well_formed:
            continue  # a scheme alone (sim): nothing for its provider to read
        if ref.scheme not in checks:
            try:
                checks[ref.scheme] = load_provider(ref.scheme, installed).check_address
            except Exception as exc:  # a plugin's module: say which, never a traceback
                checks[ref.scheme] = exc
        check = checks[ref.scheme]
        if isinstance(check, Exception):
            refuse(i, "provider-failed", f"backend '{ref}': the '{ref.scheme}' provider could "
                   f"not be loaded: {type(check).__name__}: {check}")  # fmt: skip
            continue
        problem = check(ref) if check is not None else None if ref.well_formed else EXPECTED
        if problem is not None:
            refuse(i, "bad-backend", problem)
    here = [(i, a) for i, a in enumerate(mission.agents) if agents is None or a.id in agents]
    if out or not here:
        return out
    first = here[0][1]
    for i, agent in here:
        if agent.vehicle.scheme != first.vehicle.scheme:
            refuse(i, "mixed-backends",
                   f"backend '{agent.backend}': agent '{first.id}' uses '{first.backend}'; "
                   "every agent of a mission must use the same vehicle provider (a run steps one "
                   "provider, on one clock: simulated time, or the wall clock for real vehicles)")  # fmt: skip
            break
    return out


def run_problems(
    mission: LoadedMission, *, abstract_ok: bool = False, agents: Collection[str] | None = None
) -> list[Diagnostic]:
    """Everything that stops a loaded mission from running (module docstring); ``abstract_ok``
    as in :func:`implementation_problems` (``validate`` passes True); ``agents`` as in
    :func:`backend_problems`."""
    out = backend_problems(mission, agents) + implementation_problems(
        mission, abstract_ok=abstract_ok
    )
    if not out:
        out.extend(library_problems(mission))
    settings = mission.spec.runtime.settings
    if settings:
        declared = declared_run_settings(mission)
        complete = all(
            lb.implementations is not None or not lb.library.module
            for lb in mission.libraries.values()
        )
        out.extend(settings_problems(settings, declared, mission.locate, complete))
    return out
