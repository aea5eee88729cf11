"""The run's command port: where every operator command is checked, queued and applied.

Whoever changes a running mission from outside its loop — the CLI, the operator console, a test,
a scripted :meth:`~btmission.runtime.runner.MissionRun.at` callback — goes through
:class:`CommandPort` (:mod:`btmission.runtime.commands` lists the commands):

1. :meth:`CommandPort.submit` (any thread) checks the command against the run as it stands — an
   unknown agent or task, a run that has ended — and raises
   :class:`~btmission.runtime.commands.CommandError` at once; a task to add, and a task's new
   priority, are checked by :attr:`CommandPort.tasks` (:mod:`btmission.runtime.taskcheck`: the
   one check of a task, whoever adds it, with the mission file's rules and messages), which
   reserves the task's id (:class:`~btmission.runtime.taskcheck.TaskError`);
2. the command waits in the run's :class:`~btmission.runtime.commands.CommandQueue` (an added
   task as checked: the coordinator puts it in the pool as it is);
3. between two steps the loop calls :meth:`CommandPort.apply_queued`: each command goes to its
   handler (one method per command type, :data:`CommandPort.handlers`), and is logged as a
   ``command`` event with its outcome, which the submitter's future then holds.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from btmission.allocation.tasks import TaskInfo
from btmission.runtime.commands import (
    AddTask,
    CancelTask,
    Command,
    CommandError,
    ExcludeAgent,
    IncludeAgent,
    KillAgent,
    Outcome,
    RecallAgent,
    Refused,
    SetAllocation,
    SetLink,
    SetPriority,
    Signal,
    Stop,
)
from btmission.runtime.eventkinds import (
    AgentLostEvent,
    CommandEvent,
    LinkEvent,
    SignalEvent,
)
from btmission.runtime.taskcheck import TaskCheck, TaskError

if TYPE_CHECKING:
    from btmission.runtime.runner import MissionRun


class CommandPort:
    """Checks, queues and applies a run's operator commands (module docstring)."""

    def __init__(self, run: MissionRun) -> None:
        self.run = run
        self.handlers: dict[type[Command], Callable[[Any, float], None]] = {
            Refused: self._refused,
            AddTask: self._add_task,
            Stop: self._stop,
            CancelTask: self._cancel_task,
            SetPriority: self._set_priority,
            RecallAgent: self._recall_agent,
            ExcludeAgent: self._exclude_agent,
            IncludeAgent: self._include_agent,
            SetAllocation: self._set_allocation,
            KillAgent: self._kill_agent,
            SetLink: self._set_link,
            Signal: self._signal,
        }
        """The handler of each command type, called with the command and the mission time."""
        self._schedule: list[tuple[float, int, Callable[[MissionRun], None]]] = []
        self._schedule_lock = threading.Lock()
        self.tasks = TaskCheck(
            run.mission,
            lambda: run.coordinator.state.pool,
            places=run.places,
            world=run.map,
        )
        """The one check of a task to add (and of a task's new priority), and the ids it
        reserved (:mod:`btmission.runtime.taskcheck`)."""

    # ---------------------------------------------------------------- submitting
    def submit(self, command: Command) -> Future[Outcome]:
        """Check ``command`` and queue it for the next step (thread-safe); the future of its
        outcome (module docstring)."""
        self.check(command)
        if isinstance(command, AddTask):
            return self._add(command)[1]
        if isinstance(command, SetPriority):
            command = replace(command, priority=self.tasks.priority(command.task, command.priority))
        return self.run.commands.put(command)

    def add_task(
        self, task: Mapping[str, Any] | TaskInfo, by: str
    ) -> tuple[TaskInfo, Future[Outcome]]:
        """Check a task (:class:`~btmission.runtime.taskcheck.TaskCheck`: its id, if it has
        none, is the next free one) and queue it, its id reserved; the task as the pool will
        have it, and the future of the command's outcome."""
        command = AddTask(task, by=by)
        self.check(command)
        return self._add(command)

    def _add(self, command: AddTask) -> tuple[TaskInfo, Future[Outcome]]:
        info = self.tasks.reserve(command.task, self.run.now())
        return info, self.run.commands.put(replace(command, task=info))

    def knows(self, task_id: str) -> bool:
        """Whether ``task_id`` is taken: in the pool or queued to enter it (any thread)."""
        return self.tasks.knows(task_id)

    def refuse_after_end(self, name: str) -> None:
        ended = self.run.ended
        if ended is not None:
            raise CommandError(f"{name}: the run has ended ({ended.reason})")

    def check(self, command: Command, *, tasks: bool = True) -> None:
        """Refuse a command naming an unknown agent (or, with ``tasks``, an unknown task), and
        any command once the run has ended."""
        run = self.run
        self.refuse_after_end(command.name)
        agent = getattr(command, "agent", None)
        if agent is not None and agent not in run.agents:
            raise CommandError(
                f"{command.name}: unknown agent '{agent}' (agents: {', '.join(run.agents)})"
            )
        if tasks and isinstance(command, (CancelTask, SetPriority)):
            if not self.tasks.knows(command.task):
                raise CommandError(f"{command.name}: unknown task '{command.task}'")

    # ---------------------------------------------------------------- scheduling
    def at(self, t: float, fn: Callable[[MissionRun], None] | Command) -> None:
        """At mission time ``t`` (before that step's auction round), call ``fn(run)`` — or
        submit the command ``fn``, checked now (its task may be added before then) and logged
        as refused if it no longer applies then (a task id taken meanwhile). Any thread."""
        call: Callable[[MissionRun], None]
        if isinstance(fn, Command):
            command = fn
            self.check(command, tasks=False)
            if isinstance(command, SetPriority):  # a bad value is refused now, not at t
                self.tasks.priority(command.task, command.priority)

            def call(run: MissionRun) -> None:
                try:
                    run.submit(command)
                except (CommandError, TaskError) as exc:
                    run.port.log(command, str(exc))

        else:
            call = fn
        with self._schedule_lock:
            self._schedule.append((t, len(self._schedule), call))
            self._schedule.sort(key=lambda x: (x[0], x[1]))

    def run_due(self, now: float) -> None:
        """Call what was scheduled for ``now`` or earlier, in time order (the loop's thread)."""
        while True:
            with self._schedule_lock:
                if not self._schedule or self._schedule[0][0] > now + 1e-9:
                    break
                _, _, fn = self._schedule.pop(0)
            fn(self.run)

    # ---------------------------------------------------------------- applying
    def apply_queued(self) -> None:
        """Apply every queued command, in order, each logged as a ``command`` event."""
        settled: list[tuple[Future[Outcome], Outcome]] = []
        for command, future in self.run.commands.take():
            error = ""
            try:
                self.apply(command)
            except (CommandError, TaskError) as exc:
                error = str(exc)
            settled.append((future, self.log(command, error)))
        if settled:  # whoever waits for an outcome then reads a snapshot that shows it
            self.run.publish()
            settle(settled)

    def settle_unapplied(self) -> list[tuple[Future[Outcome], Outcome]]:
        """The run has ended: every command still queued is logged as not applied (a stop as
        done); their outcomes, for :func:`settle` once the last snapshot is out."""
        left = self.run.commands.take()
        for command, _ in left:
            if isinstance(command, AddTask) and isinstance(command.task, TaskInfo):
                self.tasks.release(command.task.id)
        return [  # the run ended before their step came
            (future, self.log(
                command, "" if isinstance(command, Stop) else "not applied: the run had ended"
            ))
            for command, future in left
        ]  # fmt: skip

    def log(self, command: Command, error: str) -> Outcome:
        """The ``command`` event: who, what, its arguments, and whether it was refused; the
        command's outcome."""
        name = command.name
        if isinstance(command, Refused):  # refused before it reached the run: as it was asked
            name = command.command
            args = dict(command.args)
            error = command.error
        else:
            args = command.to_data()
        if isinstance(command, AddTask):
            args["task"] = command.task_id
        event = CommandEvent(
            command=name, by=command.by, ok=not error, error=error or None, extra=args
        )
        self.run.emit_event(event)
        return Outcome(self.run.last_t, not error, error, event.to_data())

    def apply(self, command: Command) -> None:
        """Apply one command now; raises :class:`CommandError` (or ``TaskError``) to refuse
        it."""
        for cls in type(command).__mro__:
            handler = self.handlers.get(cls)
            if handler is not None:
                handler(command, self.run.now())
                return
        raise CommandError(f"unknown command {command!r}")  # pragma: no cover - all have one

    # ---------------------------------------------------------------- one handler a command
    def _refused(self, command: Refused, now: float) -> None:
        raise CommandError(command.error)

    def _add_task(self, command: AddTask, now: float) -> None:
        # checked when submitted (submit): it enters the pool now (later commands may name it)
        info = command.task
        assert isinstance(info, TaskInfo), "an AddTask is queued as checked"
        try:
            self.run.coordinator.add_task(info, now, command.by)
        finally:
            self.tasks.release(info.id)

    def _stop(self, command: Stop, now: float) -> None:
        self.run.stop_asked = command.reason

    def _cancel_task(self, command: CancelTask, now: float) -> None:
        self.run.coordinator.cancel_task(command.task, now, command.reason)

    def _set_priority(self, command: SetPriority, now: float) -> None:
        self.run.coordinator.set_priority(command.task, float(command.priority), now)

    def _recall_agent(self, command: RecallAgent, now: float) -> None:
        a = self.run.agents[command.agent]
        if not a.alive:
            raise CommandError(f"recall_agent: agent {command.agent} is not running")
        self.run.coordinator.recall(command.agent, now)
        a.recall(now)

    def _exclude_agent(self, command: ExcludeAgent, now: float) -> None:
        self.run.coordinator.exclude(command.agent, True)

    def _include_agent(self, command: IncludeAgent, now: float) -> None:
        a = self.run.agents[command.agent]
        if not a.alive:
            raise CommandError(f"include_agent: agent {command.agent} is not running")
        self.run.coordinator.exclude(command.agent, False)
        a.include()

    def _set_allocation(self, command: SetAllocation, now: float) -> None:
        self.run.coordinator.pause(bool(command.paused))

    def _kill_agent(self, command: KillAgent, now: float) -> None:
        a = self.run.agents[command.agent]
        if a.alive:
            a.kill()
            self.run.emit_event(AgentLostEvent(agent=command.agent, reason=command.reason))

    def _set_link(self, command: SetLink, now: float) -> None:
        self.run.bus.set_link(command.agent, command.up)
        self.run.emit_event(LinkEvent(agent=command.agent, up=command.up))

    def _signal(self, command: Signal, now: float) -> None:
        self.run.agents[command.agent].ctx.state[command.signal] = command.value
        self.run.emit_event(
            SignalEvent(agent=command.agent, name=command.signal, value=command.value)
        )


def settle(outcomes: Iterable[tuple[Future[Outcome], Outcome]]) -> None:
    """Give each waiting submitter its command's outcome."""
    for future, outcome in outcomes:
        if not future.done():
            future.set_result(outcome)
