"""Behaviour-tree leaves bound to an agent: the blackboard, the context, and the leaf base classes.

Library implementations (``library/aerial.py`` and third-party plugins) register, on their
:class:`~btmission.plugins.Implementations` registry,

* **conditions** as functions ``fn(ctx, **args) -> bool`` — pure queries of the agent's state;
* **actions** as :class:`StatefulAction` subclasses with ``on_start`` / ``on_running`` /
  ``on_halted`` (STYLE.md item 5, BT.CPP's StatefulActionNode), mapped onto py_trees'
  ``initialise`` / ``update`` / ``terminate``. An action does no heavy work itself: it sends a
  request — to the backend, the path service, the navigator — through its :class:`AgentContext`
  and polls it on later ticks.

Arguments are bound by name from the abstract tree (:class:`~btmission.synthesis.tree.Arg`): a
literal stays as written; a symbol (``location``, ``home``) is read from the agent's
:class:`Blackboard` when the leaf is ticked — the runtime writes the current task's fields there,
and actions record variables such as ``home``.

The leaves of the mission tree itself (seed 000 Fig. 7) are built in: ``task_assigned(type)``,
``idle_timeout(seconds)`` and ``wait``.
"""

from __future__ import annotations

import functools
import traceback
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import py_trees
from py_trees.common import Status

from btmission.diagnostics import Diagnostic, Location, Severity, SpecError
from btmission.fastpaths.ticks import FAILURE as _FAILURE
from btmission.fastpaths.ticks import RUNNING as _RUNNING
from btmission.fastpaths.ticks import SUCCESS as _SUCCESS
from btmission.fastpaths.ticks import LeanTick
from btmission.runtime.eventkinds import (
    LeafErrorEvent,
    StageEvent,
)
from btmission.runtime.events import EmitEvent
from btmission.settings import settings_of
from btmission.synthesis.tree import Node

if TYPE_CHECKING:
    from btmission.allocation.tasks import TaskInfo
    from btmission.dispatch.topomap import TopoMap
    from btmission.runtime.agent import Agent
    from btmission.runtime.navigation import Navigator
    from btmission.runtime.paths import PathCosts
    from btmission.spec.mission import Mission
    from btmission.vehicles.base import Backend, Sensors, Telemetry
    from btmission.world.voxel import VoxelMap

UNSET = object()

S = TypeVar("S")


_ABSENT = object()


class Blackboard:
    """One agent's key-value store, under its own namespace (``/agents/<id>``).

    Deliberately not py_trees' ``Blackboard``, whose storage is class-level and so shared by
    every tree in the process (STYLE.md item 6): two agents — or two runs in one test session —
    must never see each other's keys. Every write is recorded with the time for observers.
    """

    def __init__(self, namespace: str) -> None:
        self.namespace = namespace
        self._data: dict[str, Any] = {}
        self.version = 0
        """Counts the writes (set, unset): an observer knows cheaply whether anything changed."""

    def get(self, key: str, default: Any = None) -> Any:
        return self._data.get(key, default)

    def __getitem__(self, key: str) -> Any:
        try:
            return self._data[key]
        except KeyError:
            raise KeyError(f"{self.namespace}: no key '{key}' on the blackboard") from None

    def __contains__(self, key: object) -> bool:
        return key in self._data

    def set(self, key: str, value: Any) -> None:
        self._data[key] = value
        self.version += 1

    def unset(self, key: str) -> None:
        if self._data.pop(key, _ABSENT) is not _ABSENT:
            self.version += 1

    def keys(self) -> Iterator[str]:
        return iter(self._data)

    def snapshot(self) -> dict[str, Any]:
        return dict(self._data)


@dataclass
class RunContext:
    """What a run-wide service factory gets (:meth:`~btmission.plugins.Implementations.service`):
    the whole run's shared facts, no agent in particular."""

    mission: Mission
    map: VoxelMap
    clock: Callable[[], float]
    settings: Mapping[str, Any]
    seed: int
    events: Callable[..., None] = field(default=lambda event, **fields: None)
    """``events(event)`` publishes a typed event (:mod:`btmission.runtime.events`: a
    :class:`~btmission.runtime.events.TypedEvent` of a built-in kind, or of one the library
    registered) for observers (log, report, viewer); ``events(kind, **fields)`` one of a kind of
    the library's own that has no class."""
    places: Mapping[str, tuple[float, float, float]] = field(default_factory=dict)
    """Named places (the nodes of the mission's topological map, on the ground)."""
    topomap: TopoMap | None = None
    """The mission's topological map (``world.topomap``), loaded once by the runner."""

    def now(self) -> float:
        return self.clock()

    def settings_of(self, cls: type[S]) -> S:
        """The run's instance of the settings dataclass ``cls`` (as in :class:`AgentContext`)."""
        return settings_of(self.settings, cls)

    def setting(self, name: str, default: Any) -> Any:
        """The untyped path (as in :class:`AgentContext`): prefer :meth:`settings_of`."""
        return self.settings.get(name, default)


class AgentView:
    """The narrow, read-mostly view of an agent that leaves and plugins get (``ctx.agent``).

    Leaves must not tick, kill or re-wire their agent: the runtime does that. They may read
    which task it executes and since when it is idle, and report why an action failed or which
    library variable nobody set. The agent itself stays private to the runtime, so its
    internals can change without breaking libraries."""

    __slots__ = ("_agent",)

    def __init__(self, agent: Agent) -> None:
        self._agent = agent

    @property
    def id(self) -> str:
        return self._agent.id

    @property
    def mission(self) -> Mission:
        return self._agent.mission

    @property
    def task(self) -> TaskInfo | None:
        """The task the agent executes now (None: no task; its default behaviour may run)."""
        return self._agent.task

    @property
    def committed(self) -> bool:
        """It has passed its task's commit point (k_bt = 0)."""
        return self._agent.committed

    @property
    def idle_since(self) -> float:
        """Mission time its last task ended (−inf once recalled: idle for ever)."""
        return self._agent.idle_since

    @property
    def errors(self) -> ErrorReporter:
        """Where the leaves' exceptions are reported (``leaf_error`` events)."""
        return self._agent.errors

    def note_failure(self, action: str, reason: str, *, refused: bool = False) -> None:
        """The reason reported if the task fails (a failing action calls it); ``refused``: the
        action failed because its vehicle refused (the agent hands the task back instead of
        failing it)."""
        self._agent.note_failure(action, reason, refused=refused)

    def unset_variables(self, leaf: str, names: list[str]) -> None:
        """Warn once that ``names`` are on nobody's blackboard (``warning`` events)."""
        self._agent.unset_variables(leaf, names)


@dataclass
class AgentContext:
    """Everything a leaf may use, passed explicitly at setup (no process-wide singletons)."""

    agent_id: str
    blackboard: Blackboard
    backend: Backend
    sensors: Sensors | None
    navigator: Navigator
    paths: PathCosts
    clock: Callable[[], float]
    settings: Mapping[str, Any]
    start: tuple[float, float, float]
    agent: AgentView | None = None
    """What a leaf may know of its agent (:class:`AgentView`), None outside a run."""
    events: Callable[..., None] = field(default=lambda event, **fields: None)
    """``events(event)`` publishes a typed event (:mod:`btmission.runtime.events`: a
    :class:`~btmission.runtime.events.TypedEvent` of a built-in kind, or of one the library
    registered, its ``agent`` this one) for observers (log, report, viewer);
    ``events(kind, **fields)`` one of a kind of the library's own that has no class (the agent
    adds its id)."""
    state: dict[str, Any] = field(default_factory=dict)
    """Per-agent scratch space for implementations (e.g. a localiser kept across actions)."""
    services: Mapping[str, Any] = field(default_factory=dict)
    """The run-wide services of the agent's library, by name (shared by all its agents)."""

    def now(self) -> float:
        return self.clock()

    def telemetry(self) -> Telemetry:
        return self.backend.telemetry()

    def settings_of(self, cls: type[S]) -> S:
        """The run's instance of the settings dataclass ``cls`` (a library's declaration,
        :mod:`btmission.settings`, or the navigator's :class:`NavConfig`): its fields from the
        mission's ``runtime.settings``, else the libraries' defaults, else the field defaults,
        of the declared types. Built once per run and shared by every agent."""
        return settings_of(self.settings, cls)

    def setting(self, name: str, default: Any) -> Any:
        """The value of setting ``name``, or ``default`` when the run has none: the untyped
        path, kept for code written before typed settings. Its ``default`` can disagree with
        the declared one and its value is not converted to the declared type; prefer
        :meth:`settings_of`."""
        return self.settings.get(name, default)


Condition = Callable[..., bool]
"""A condition implementation: ``fn(ctx, **args) -> bool``."""


def resolve(ctx: AgentContext, node: Node) -> dict[str, Any] | None:
    """The leaf's arguments, symbols read from the blackboard (None if one is not set yet)."""
    out: dict[str, Any] = {}
    for a in node.args:
        if a.literal:
            out[a.param] = a.value
            continue
        value = ctx.blackboard.get(a.value, UNSET)
        if value is UNSET:
            return None
        out[a.param] = value
    return out


def exception_event(exc: BaseException) -> dict[str, Any]:
    """The fields of a ``leaf_error`` event for ``exc``: its type, message, where it was raised
    (the innermost frame, ``file:line``) and the full traceback."""
    frames = traceback.extract_tb(exc.__traceback__)
    where = f"{frames[-1].filename}:{frames[-1].lineno}" if frames else ""
    return {
        "error": type(exc).__name__,
        "message": str(exc),
        "where": where,
        "traceback": "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)),
    }


def describe(exc: BaseException) -> str:
    """``Type: message (at file:line)`` — an exception of a library's code in one line."""
    where = exception_event(exc)["where"]
    return f"{type(exc).__name__}: {exc}" + (f" (at {where})" if where else "")


def setup_failed(code: str, message: str, item: str, file: str | None) -> SpecError:
    """A library's setup code (an ``on_setup`` hook, a service factory) raised before the run
    started: a clear error naming the mission, the item and the exception (exit status 2)."""
    return SpecError([Diagnostic(Severity.ERROR, code, message, item, Location(file))])


class ErrorReporter:
    """Turns exceptions raised by library code (leaves, services) into ``leaf_error`` events,
    each distinct error (leaf, phase, type, message) once, so a condition that raises on every
    tick does not flood the log. ``agent`` gives the agent whose leaves these are and its task
    now (None: a run's services, no agent)."""

    def __init__(
        self, emit: EmitEvent, agent: Callable[[], tuple[str, str | None]] | None = None
    ) -> None:
        self._emit = emit
        self._agent = agent
        self._seen: set[tuple[str, str, str, str]] = set()

    def report(self, leaf: str, phase: str, exc: BaseException) -> str:
        """Emit the event (first time) and return the short reason ``Type: message``."""
        reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        key = (leaf, phase, type(exc).__name__, str(exc))
        if key not in self._seen:
            self._seen.add(key)
            agent, task = self._agent() if self._agent is not None else (None, None)
            self._emit(
                LeafErrorEvent(
                    agent=agent, task=task, leaf=leaf, phase=phase, **exception_event(exc)
                )
            )
        return reason


def _guard_update(fn: Callable[..., Status]) -> Callable[..., Status]:
    @functools.wraps(fn)
    def update(self: GuardedLeaf) -> Status:
        if self._init_error:  # initialise() raised: this tick fails
            self._init_error = False
            return Status.FAILURE
        try:
            status = fn(self)
            if not isinstance(status, Status):
                raise TypeError(f"returned {status!r}, not a py_trees Status")
            return status
        except Exception as exc:  # a library's code must not end the run (docs/running.md)
            self._leaf_failed("update", exc)
            return Status.FAILURE

    update.__btmission_guarded__ = True  # type: ignore[attr-defined]
    return update


def _guard_initialise(fn: Callable[..., None]) -> Callable[..., None]:
    @functools.wraps(fn)
    def initialise(self: GuardedLeaf) -> None:
        self._init_error = False
        try:
            fn(self)
        except Exception as exc:
            self._leaf_failed("initialise", exc)
            self._init_error = True

    initialise.__btmission_guarded__ = True  # type: ignore[attr-defined]
    return initialise


def _guard_terminate(fn: Callable[..., None]) -> Callable[..., None]:
    @functools.wraps(fn)
    def terminate(self: GuardedLeaf, new_status: Status) -> None:
        try:
            fn(self, new_status)
        except Exception as exc:
            self._leaf_failed("terminate", exc)

    terminate.__btmission_guarded__ = True  # type: ignore[attr-defined]
    return terminate


_GUARDS: dict[str, Callable[[Any], Any]] = {
    "update": _guard_update,
    "initialise": _guard_initialise,
    "terminate": _guard_terminate,
}


class GuardedLeaf(LeanTick, py_trees.behaviour.Behaviour):
    """A leaf whose ``initialise`` / ``update`` / ``terminate`` — its own and any subclass's
    overrides — never raise: an exception becomes FAILURE for that tick and a ``leaf_error``
    event (type, message, traceback) through the agent's context, and the run goes on."""

    ctx: AgentContext
    _init_error = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        for name, guard in _GUARDS.items():
            fn = getattr(cls, name)  # through the MRO: a mixin's override is guarded too
            if not getattr(fn, "__btmission_guarded__", False):
                setattr(cls, name, guard(fn))
        if "tick" in cls.__dict__:  # its own tick() runs, not the lean one
            cls.tick_now = None  # type: ignore[assignment]

    def tick_now(self) -> None:
        """py_trees' ``Behaviour.tick`` — initialise unless RUNNING, update, stop unless
        RUNNING, take the new status — as a plain call (the quiet composites call it instead
        of running a generator: a fleet's leaves tick hundreds of thousands of times), and
        without formatting a debug message on every call (the guard on ``update`` already
        turns anything but a ``Status`` into FAILURE). A subclass that defines its own
        ``tick`` has no ``tick_now``, so its ``tick`` is what runs."""
        if self.status is not _RUNNING:
            self.initialise()
        new_status = self.update()
        if new_status is not _RUNNING:
            self.stop(new_status)
        self.status = new_status

    def stop(self, new_status: Status) -> None:
        """py_trees' ``Behaviour.stop`` (terminate, take the status) without its debug message;
        its fresh tick generator is made when ``iterator`` is read."""
        self.terminate(new_status)
        self.status = new_status

    def _leaf_failed(self, phase: str, exc: Exception) -> None:
        ctx = self.ctx
        agent = ctx.agent
        reporter = getattr(agent, "errors", None)
        if reporter is None:
            reporter = ctx.state.setdefault("_errors", ErrorReporter(ctx.events))
        reason = reporter.report(self.name, phase, exc)
        if isinstance(self, StatefulAction):
            self.reason = reason
        if agent is not None:
            agent.note_failure(self.name, reason)


class ConditionLeaf(GuardedLeaf):
    """A condition: SUCCESS iff its implementation says it holds (FAILURE if an argument is
    not on the blackboard yet)."""

    def __init__(self, node: Node, fn: Condition, ctx: AgentContext) -> None:
        super().__init__(name=node.label)
        self.node = node
        self.fn = fn
        self.ctx = ctx
        self._constant: dict[str, Any] | None = (
            {a.param: a.value for a in node.args} if all(a.literal for a in node.args) else None
        )
        """The arguments when all are literals (the node is frozen): no blackboard to read."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        hooks = ("initialise", "terminate", "stop")  # (resolved: a mixin's override counts)
        if cls.tick_now is not None and any(
            getattr(cls, h) is not getattr(ConditionLeaf, h) for h in hooks
        ):
            cls.tick_now = GuardedLeaf.tick_now  # type: ignore[method-assign]  # its hooks run
        elif cls.tick_now is ConditionLeaf.tick_now and cls.update is not ConditionLeaf.update:
            cls.tick_now = ConditionLeaf._tick_update  # type: ignore[method-assign]

    def tick_now(self) -> None:
        """:meth:`GuardedLeaf.tick_now` for a condition, whose ``initialise`` and ``terminate``
        are py_trees' no-ops (guarded): the initialise guard's reset, the update (its guard
        inlined: an exception is this tick's FAILURE and a ``leaf_error``), the new status —
        the same, without the calls (a fleet ticks thousands of conditions a second). A
        subclass that overrides a hook ticks through :meth:`GuardedLeaf.tick_now`; one that
        overrides ``update`` through :meth:`_tick_update`."""
        self._init_error = False  # (the initialise guard's reset: this status is never RUNNING)
        try:
            args = self._constant
            if args is None:
                args = resolve(self.ctx, self.node)
            status = _FAILURE if args is None or not self.fn(self.ctx, **args) else _SUCCESS
        except Exception as exc:  # (as the update guard: a library's code must not end the run)
            self._leaf_failed("update", exc)
            status = _FAILURE
        self.status = status

    def _tick_update(self) -> None:
        """:meth:`tick_now` through ``self.update()`` (a subclass's own, guarded)."""
        if self.status is not _RUNNING:
            self._init_error = False
        self.status = self.update()

    def update(self) -> Status:
        args = resolve(self.ctx, self.node)
        if args is None:
            return Status.FAILURE
        return Status.SUCCESS if self.fn(self.ctx, **args) else Status.FAILURE


class StatefulAction(GuardedLeaf):
    """Base class of action implementations (STYLE.md item 5).

    Override :meth:`on_start` (first tick: send the request; return RUNNING, or SUCCESS/FAILURE
    at once), :meth:`on_running` (later ticks: poll) and :meth:`on_halted` (a higher-priority
    branch took over: cancel). ``self.args`` are the bound arguments, ``self.ctx`` the agent's
    :class:`AgentContext`. Set ``self.reason`` when returning FAILURE: it is reported with the
    task. Set ``self.refused`` too when the failure is the vehicle's refusal (a command it
    would not take, :class:`~btmission.runtime.actions.Command`), not the task's: the agent
    then gives the task back to the pool for another agent instead of failing it. An exception
    raised by any of them fails the action (its reason is the exception's type and message)
    and is logged as a ``leaf_error`` event: the run goes on.
    """

    def __init__(self, node: Node, ctx: AgentContext) -> None:
        super().__init__(name=node.label)
        self.node = node
        self.ctx = ctx
        self.args: dict[str, Any] = {}
        self.reason = ""
        self.refused = False
        self._started = False

    # py_trees plumbing ------------------------------------------------------------------
    def initialise(self) -> None:
        self._started = False
        self.reason = ""
        self.refused = False

    def update(self) -> Status:
        if not self._started:
            args = resolve(self.ctx, self.node)
            if args is None:
                missing = [
                    a.value
                    for a in self.node.args
                    if not a.literal and a.value not in self.ctx.blackboard
                ]
                self.reason = f"{self.name}: {', '.join(missing)} not on the blackboard"
                if self.ctx.agent is not None:
                    self.ctx.agent.unset_variables(self.name, missing)
                return Status.FAILURE
            self.args = args
            self._started = True
            agent = self.ctx.agent
            task = agent.task if agent is not None else None
            self.ctx.events(
                StageEvent(
                    agent=self.ctx.agent_id,
                    task=task.id if task is not None else None,
                    action=self.name,
                )
            )
            status = self.on_start()
        else:
            status = self.on_running()
        if status is Status.FAILURE and self.ctx.agent is not None:
            self.ctx.agent.note_failure(self.name, self.reason, refused=self.refused)
        return status

    def terminate(self, new_status: Status) -> None:
        if new_status is Status.INVALID and self._started:
            self.on_halted()
        self._started = False

    # to override ------------------------------------------------------------------------
    def on_start(self) -> Status:
        return self.on_running()

    def on_running(self) -> Status:
        return Status.SUCCESS

    def on_halted(self) -> None:
        pass


# ------------------------------------------------------------------ built-in leaves (Fig. 7)
def task_assigned(ctx: AgentContext, type: str) -> bool:
    """The agent's current task (from the auction) is of this type."""
    agent = ctx.agent
    return agent is not None and agent.task is not None and agent.task.type == type


def idle_timeout(ctx: AgentContext, seconds: str) -> bool:
    """No task has been assigned for ``seconds``."""
    agent = ctx.agent
    if agent is None or agent.task is not None:
        return False
    return ctx.now() - agent.idle_since >= float(seconds)


class Wait(StatefulAction):
    """Hold position (keep streaming setpoints) until something changes: always RUNNING."""

    def on_start(self) -> Status:
        if self.ctx.navigator.status.command != "hold":
            self.ctx.navigator.hold()
        return Status.RUNNING

    def on_running(self) -> Status:
        return Status.RUNNING


BUILTIN_CONDITIONS: dict[str, Condition] = {
    "task_assigned": task_assigned,
    "idle_timeout": idle_timeout,
}
BUILTIN_ACTIONS: dict[str, type[StatefulAction]] = {"wait": Wait}
