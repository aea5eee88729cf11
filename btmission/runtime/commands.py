"""Commands: the one way anything changes a running mission from outside its loop.

An operator (the CLI, a test, the web console of a later issue, a scripted
:meth:`~btmission.runtime.runner.MissionRun.at` callback) never reaches into the coordinator or
an agent while the loop runs. It *submits* a :class:`Command` to the run's
:class:`CommandQueue` — from any thread — and the loop applies every queued command between two
steps, in the order they were submitted. Each applied command is logged as a ``command`` event
(``by`` whom, ``command``, its arguments, ``ok`` and, if it was refused, ``error``) so the report
and the log show operator actions next to what they caused.

=====================  =====================================================================
:class:`AddTask`       a new task enters the pool (checked when submitted, as a task of the
                       mission file is: :mod:`btmission.runtime.taskcheck`)
:class:`CancelTask`    a task leaves the pool (state ``cancelled``); its agent stops it
:class:`SetPriority`   a task's priority changes (it is announced again)
:class:`RecallAgent`   an agent gives up its task, stops bidding and runs its default
                       behaviour now (e.g. return home and land)
:class:`ExcludeAgent`  an agent leaves the auction: it keeps the task it holds and wins
                       nothing else (``IncludeAgent`` brings it back, a recalled one too)
:class:`IncludeAgent`  an excluded or recalled agent takes part in the auction again
:class:`SetAllocation` allocation pauses (every holder keeps its task, nothing else is
                       assigned) or resumes
:class:`KillAgent`     an agent's computer stops: no ticks, bids or setpoints
:class:`SetLink`       an agent's link to the coordinator is cut or restored
:class:`Signal`        a supervisor signal its leaves read (``ctx.state[name]``)
:class:`Stop`          the run ends after the current step
=====================  =====================================================================

Commands are plain frozen dataclasses (the operator console's wire form is their
:meth:`Command.to_data`); what each one *does* lives with the run that applies it.
:meth:`MissionRun.submit <btmission.runtime.runner.MissionRun.submit>` returns a
:class:`~concurrent.futures.Future` of the command's :class:`Outcome`, set when its step
applied it (or refused it), so a console can answer with the result.
"""

from __future__ import annotations

import math
import queue
from collections.abc import Mapping
from concurrent.futures import Future
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar

from btmission.allocation.tasks import TaskInfo
from btmission.errors import BtmissionError


class CommandError(BtmissionError, ValueError):
    """A command that cannot be applied (the message says why)."""


@dataclass(frozen=True)
class Command:
    """Something an operator asks of a running mission (module docstring)."""

    name: ClassVar[str] = ""
    by: str = field(default="api", kw_only=True)
    """Who asked (``api``, ``mission``, ``console:<user>`` ...): logged with the command."""

    def to_data(self) -> dict[str, Any]:
        """The command's fields as plain data (for the ``command`` event)."""
        data = asdict(self)
        data.pop("by", None)
        return data


@dataclass(frozen=True)
class AddTask(Command):
    name: ClassVar[str] = "add_task"
    task: Mapping[str, Any] | TaskInfo
    """``{"id": "T8", "type": "inspect", "location": [x, y, z]}``, optionally ``priority``,
    ``at`` (without ``id``: the next free one). Once submitted, the queued command carries the
    task as checked (:mod:`btmission.runtime.taskcheck`): a TaskInfo."""

    @property
    def task_id(self) -> Any:
        """The task's id as given (None when the operator left it to the run)."""
        if isinstance(self.task, TaskInfo):
            return self.task.id
        return self.task.get("id") if isinstance(self.task, Mapping) else None


@dataclass(frozen=True)
class CancelTask(Command):
    name: ClassVar[str] = "cancel_task"
    task: str
    reason: str = "cancelled by the operator"


@dataclass(frozen=True)
class SetPriority(Command):
    name: ClassVar[str] = "set_priority"
    task: str
    priority: float


@dataclass(frozen=True)
class RecallAgent(Command):
    name: ClassVar[str] = "recall_agent"
    agent: str


@dataclass(frozen=True)
class ExcludeAgent(Command):
    name: ClassVar[str] = "exclude_agent"
    agent: str


@dataclass(frozen=True)
class IncludeAgent(Command):
    name: ClassVar[str] = "include_agent"
    agent: str


@dataclass(frozen=True)
class SetAllocation(Command):
    name: ClassVar[str] = "set_allocation"
    paused: bool


@dataclass(frozen=True)
class KillAgent(Command):
    name: ClassVar[str] = "kill_agent"
    agent: str
    reason: str = "killed"


@dataclass(frozen=True)
class SetLink(Command):
    name: ClassVar[str] = "set_link"
    agent: str
    up: bool


@dataclass(frozen=True)
class Signal(Command):
    name: ClassVar[str] = "signal"
    agent: str
    signal: str
    value: Any = True


@dataclass(frozen=True)
class Stop(Command):
    name: ClassVar[str] = "stop"
    reason: str = "interrupted"


@dataclass(frozen=True)
class Refused(Command):
    """A command refused before it reached the run (the operator console's checks: a task
    inside rock, an unknown agent...): the run only logs it, as a refused ``command`` event
    named ``command`` with ``args`` and ``error``, so the log shows who tried what. Not sent
    by name (not in :data:`COMMANDS`)."""

    name: ClassVar[str] = "refused"
    command: str
    args: Mapping[str, Any] = field(default_factory=dict)
    error: str = ""


COMMANDS: dict[str, type[Command]] = {
    c.name: c
    for c in (
        AddTask,
        CancelTask,
        SetPriority,
        RecallAgent,
        ExcludeAgent,
        IncludeAgent,
        SetAllocation,
        KillAgent,
        SetLink,
        Signal,
        Stop,
    )
}
"""Every command by name (what an operator console sends)."""


def command_from_data(name: str, data: Mapping[str, Any], by: str = "api") -> Command:
    """A command from its name and plain-data arguments; :class:`CommandError` if it is not one."""
    cls = COMMANDS.get(name)
    if cls is None:
        raise CommandError(f"unknown command '{name}' (commands: {', '.join(COMMANDS)})")
    try:
        return cls(**dict(data), by=by)
    except TypeError as exc:
        raise CommandError(f"command '{name}': {exc}") from None


PRIORITY_LEVELS: dict[str, float] = {"low": 0.5, "normal": 1.0, "high": 2.0, "urgent": 4.0}
"""Priority names an operator may use: multiples of the task type's own priority."""


def priority_value(value: Any, type_priority: float) -> float:
    """A priority given as a number (> 0, finite) or a name of :data:`PRIORITY_LEVELS` (a
    multiple of ``type_priority``). :class:`CommandError` says what was expected."""
    if isinstance(value, str):
        level = PRIORITY_LEVELS.get(value.strip().lower())
        if level is not None:
            return level * type_priority
        try:
            value = float(value)
        except ValueError:
            raise CommandError(
                f"priority '{value}' is not a number or one of {', '.join(PRIORITY_LEVELS)}"
            ) from None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CommandError(
            f"priority must be a number > 0 or one of {', '.join(PRIORITY_LEVELS)} (got {value!r})"
        )
    if not (math.isfinite(value) and value > 0):
        raise CommandError(f"priority must be a finite number > 0 (got {value!r})")
    return float(value)


@dataclass(frozen=True)
class Outcome:
    """What became of a submitted command: applied at mission time ``t`` (``ok``), or refused
    with ``error``; ``data`` is its ``command`` event's fields."""

    t: float
    ok: bool
    error: str = ""
    data: Mapping[str, Any] = field(default_factory=dict)


class CommandQueue:
    """Commands waiting for the next step (thread-safe; first in, first applied), each with
    the future of its :class:`Outcome`."""

    def __init__(self) -> None:
        self._q: queue.SimpleQueue[tuple[Command, Future[Outcome]]] = queue.SimpleQueue()

    def put(self, command: Command) -> Future[Outcome]:
        future: Future[Outcome] = Future()
        self._q.put((command, future))
        return future

    def take(self) -> list[tuple[Command, Future[Outcome]]]:
        """Everything queued so far, in order (empties the queue)."""
        out: list[tuple[Command, Future[Outcome]]] = []
        while True:
            try:
                out.append(self._q.get_nowait())
            except queue.Empty:
                return out

    def empty(self) -> bool:
        return self._q.empty()
