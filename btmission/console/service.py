"""The operator console's logic, without HTTP: a running mission's commands and status.

:class:`Console` sits between a request (from the viewer page, ``btmission task ...`` or a
script) and the run. Each method checks what it is given, submits one
:class:`~btmission.runtime.commands.Command` to the run (thread-safe) and waits, a bounded time,
for the step that applies it, so the answer carries the result: ``T8 added at 116.1 s``, or why
it was refused. A refusal is a :class:`ConsoleError` with the HTTP status it maps to and, for a
bad field, the field's name.

A task added here is checked by the run, as a task added by any other way is
(:mod:`btmission.runtime.taskcheck`): as a task of the mission file, with the same model and
messages, and its positions against the map as ``btmission validate`` checks them (outside the
map, inside rock); the console only maps a refusal to its HTTP status. A task no agent can reach
is left ``unreachable`` by the auction, with the reason, as any task is.

A flood of requests cannot stall the run: at most :data:`MAX_PENDING` commands wait for their
step at once, and a token bucket (:class:`RateLimit`) admits :data:`COMMAND_RATE_HZ` commands a
second on average; beyond either the request is refused with 429.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator, Mapping
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from typing import Any

from btmission.errors import BtmissionError
from btmission.runtime.commands import (
    PRIORITY_LEVELS,
    CancelTask,
    Command,
    CommandError,
    ExcludeAgent,
    IncludeAgent,
    Outcome,
    RecallAgent,
    Refused,
    SetAllocation,
    SetLink,
    SetPriority,
    Stop,
)
from btmission.runtime.taskcheck import TOO_MANY, TaskError

WAIT_S = 5.0
"""How long (wall time) a request waits for the step that applies its command; past it the
answer is 202 (queued: the result will be in the log and on the page)."""
MAX_PENDING = 32
"""Commands waiting for their step at once; more is 429."""
COMMAND_RATE_HZ = 20.0
"""Commands admitted per second on average ..."""
COMMAND_BURST = 40
"""... and at most this many in a burst."""
HISTORY = 20
"""A task's latest changes in a status answer (what a client polling it may have missed)."""
LINK_DRILL_SCHEMES = ("sim", "fake")
"""Vehicle providers whose agents' links may be cut for drills (in the simulator only)."""


class ConsoleError(BtmissionError):
    """A request the console refuses: ``status`` (HTTP), ``message`` (one sentence naming the
    field), ``field`` (the body's field at fault, if one is)."""

    def __init__(
        self, status: int, message: str, field: str | None = None, *, logged: bool = False
    ) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.field = field
        self.logged = logged
        """The run logged it already (it refused the command when it applied it)."""


class RateLimit:
    """A token bucket: ``rate`` admissions a second on average, ``burst`` at once
    (thread-safe). :meth:`take` returns 0 when admitted, else the seconds to wait."""

    def __init__(self, rate: float, burst: int, clock: Any = time.monotonic) -> None:
        self.rate = rate
        self.burst = float(burst)
        self.clock = clock
        self._tokens = float(burst)
        self._t = clock()
        self._lock = threading.Lock()

    def take(self) -> float:
        with self._lock:
            now = self.clock()
            self._tokens = min(self.burst, self._tokens + (now - self._t) * self.rate)
            self._t = now
            if self._tokens >= 1.0:
                self._tokens -= 1.0
                return 0.0
            return (1.0 - self._tokens) / self.rate


@dataclass(frozen=True)
class Result:
    """A command's answer: ``ok`` (applied at mission time ``t``) and a sentence; ``status``
    202 when its step had not come within :data:`WAIT_S`."""

    command: str
    ok: bool
    t: float
    message: str
    status: int = 200
    task: str | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "ok": self.ok,
            "command": self.command,
            "t": round(self.t, 3),
            "message": self.message,
        }
        if self.task is not None:
            out["task"] = self.task
        return out


class Console:
    """A running mission's operator console (module docstring). ``session`` is the
    :class:`~btmission.runtime.session.RunSession` (its mission), ``run`` its
    :class:`~btmission.runtime.runner.MissionRun`."""

    def __init__(
        self,
        session: Any,
        run: Any,
        *,
        wait_s: float = WAIT_S,
        max_pending: int = MAX_PENDING,
        rate: RateLimit | None = None,
        read_only: str | None = None,
    ) -> None:
        self.read_only = read_only
        """Why commands are refused (a run started with --view); None: they are taken."""
        self.mission = session.mission
        self.run = run
        self.wait_s = wait_s
        self.max_pending = max_pending
        self.rate = rate if rate is not None else RateLimit(COMMAND_RATE_HZ, COMMAND_BURST)
        self._pending = 0
        self._status_cache: tuple[Any, bytes] | None = None
        self._lock = threading.Lock()
        self.drill_agents = frozenset(
            a.id for a in self.mission.agents if a.vehicle.scheme in LINK_DRILL_SCHEMES
        )

    # ------------------------------------------------------------------ what the page needs
    def info(self) -> dict[str, Any]:
        """The task types (their fields, which are positions, their priority), the places,
        the priority names and the next free task id: what the page's form is built from."""
        types = {}
        for name, tt in self.mission.task_types.items():
            fields = _field_order(tt)
            positions = [f for f in fields if f in tt.cost.symbols or f in _goal_args(tt)]
            types[name] = {
                "fields": fields,
                "positions": positions,
                "priority": tt.priority,
                "multi_stage": tt.commit_after is not None,
            }
        return {
            "enabled": self.read_only is None,
            "reason": self.read_only,
            "task_types": types,
            "places": sorted(self.run.port.tasks.places),
            "priorities": dict(PRIORITY_LEVELS),
            "next_task_id": self.next_task_id(),
            "next_task_ids": {name: self.next_task_id(name) for name in types},
            "pick_offset_m": 0.0 if self._ground_fleet() else 1.0,
            "link_drills": bool(self.drill_agents),
            "drill_agents": sorted(self.drill_agents),
        }

    def _ground_fleet(self) -> bool:
        """Whether every agent drives (a task picked on a floor then stays on it)."""
        return {a.vehicle for a in self.run.snapshot.agents} == {"ground"}

    def next_task_id(self, task_type: str | None = None) -> str:
        """The next free id in the mission's own pattern (T1..T7 → T8), that of the tasks of
        ``task_type`` if it has some (P1 → P2 beside I1, I2), else ``T<n>``: the id the run
        gives a task added without one (:meth:`~btmission.runtime.taskcheck.TaskCheck.next_id`)."""
        return str(self.run.port.tasks.next_id(task_type))

    def status_json(self) -> bytes:
        """:meth:`status` as JSON, encoded once per snapshot however many read it (a flood of
        status reads costs the run one encoding a step, not one a request)."""
        snap = self.run.snapshot
        cached = self._status_cache
        if cached is not None and cached[0] is snap:
            return cached[1]
        data = json.dumps(self.status(snap), separators=(",", ":")).encode()
        self._status_cache = (snap, data)
        return data

    def status(self, snap: Any = None) -> dict[str, Any]:
        """Agents and tasks as the run's last step left them (its immutable snapshot)."""
        snap = snap if snap is not None else self.run.snapshot
        if snap is None:
            raise ConsoleError(409, "the run is not built yet")
        tasks = [_task_row(t, snap.time_s) for t in snap.pool]
        return {
            "t": round(snap.time_s, 3),
            "steps": snap.steps,
            "running": snap.ended is None,
            "ended": snap.ended,
            "allocation": {"paused": snap.paused},
            "agents": [
                {
                    "id": a.id,
                    "alive": a.alive,
                    "link_up": a.link_up,
                    "recalled": a.recalled,
                    "excluded": a.id in snap.excluded,
                    "task": a.task,
                    "action": a.action,
                    "mode": a.mode,
                    "armed": a.armed,
                    "p": [round(v, 2) for v in a.position],
                    "yaw": round(a.yaw, 3),
                }
                for a in snap.agents
            ],
            # the arrived ones in the pool's order, then those still to arrive
            "tasks": sorted(tasks, key=lambda row: row["state"] == "scheduled"),
        }

    # ------------------------------------------------------------------ commands
    def add_task(self, body: Any, by: str) -> Result:
        """Add the task ``body`` (``{id?, type, priority?, at?, <fields>}``; the id defaults to
        the next free one of its type, the priority may be a name of PRIORITY_LEVELS)."""
        args = {"task": body.get("id"), "type": body.get("type")} if isinstance(body, dict) else {}
        with self._audit("add_task", by, args):
            return self._add_task(body, by)

    def _add_task(self, body: Any, by: str) -> Result:
        with self._slot():
            try:  # the run's one check of a task (module docstring); its id reserved
                info, future = self.run.port.add_task(body, by)
            except TaskError as exc:
                raise _task_refused(exc) from None
            except CommandError as exc:  # the run has ended
                raise ConsoleError(409, _plain_error(str(exc), "add_task")) from None
            later = ""
            if info.arrival_s > self.run.now() + 1e-9:
                later = f", announced from {info.arrival_s:g} s"
            return self._wait(future, "add_task", f"{info.id} added", later, info.id)

    def cancel_task(self, task: str, by: str, reason: str = "") -> Result:
        with self._audit("cancel_task", by, {"task": task}):
            cmd = CancelTask(task, reason or f"by the operator ({by})", by=by)
            return self._submit(cmd, f"{task} cancelled", task=task)

    def set_priority(self, task: str, value: Any, by: str) -> Result:
        with self._audit("set_priority", by, {"task": task, "priority": value}):
            try:  # the bounds of a task's priority, wherever it is given (module docstring)
                prio = self.run.port.tasks.priority(task, value)
            except TaskError as exc:
                raise _task_refused(exc) from None
            cmd = SetPriority(task, prio, by=by)
            return self._submit(cmd, f"{task} priority {prio:g}", task=task)

    def recall(self, agent: str, by: str) -> Result:
        with self._audit("recall_agent", by, {"agent": agent}):
            was = self._agent(agent)
            already = " (it was already)" if was is not None and was.recalled else ""
            return self._submit(RecallAgent(agent, by=by), f"{agent} recalled home", already)

    def exclude(self, agent: str, out: bool, by: str) -> Result:
        name = "exclude_agent" if out else "include_agent"
        with self._audit(name, by, {"agent": agent}):
            snap, was = self.run.snapshot, self._agent(agent)
            inside = was is not None and snap is not None and agent not in snap.excluded
            inside = inside and was is not None and not was.recalled
            if out:
                note = "" if inside or was is None else " (it was already)"
                return self._submit(ExcludeAgent(agent, by=by), f"{agent} out of the auction", note)
            note = " (it was already)" if inside else ""
            return self._submit(IncludeAgent(agent, by=by), f"{agent} back in the auction", note)

    def set_link(self, agent: str, up: bool, by: str) -> Result:
        with self._audit("set_link", by, {"agent": agent, "up": up}):
            if self._agent(agent) is not None and agent not in self.drill_agents:
                raise ConsoleError(
                    409,
                    f"{agent} flies a real vehicle: link drills are for the simulator only "
                    f"(backend: {LINK_DRILL_SCHEMES[0]})",
                )
            was = self._agent(agent)
            note = " (it was already)" if was is not None and was.link_up == up else ""
            what = f"{agent}'s link restored" if up else f"{agent}'s link cut"
            return self._submit(SetLink(agent, up, by=by), what, note)

    def set_allocation(self, paused: bool, by: str) -> Result:
        with self._audit("set_allocation", by, {"paused": paused}):
            snap = self.run.snapshot
            note = " (it was already)" if snap is not None and snap.paused == paused else ""
            what = "allocation paused" if paused else "allocation resumed"
            return self._submit(SetAllocation(paused, by=by), what, note)

    def stop(self, by: str, reason: str = "") -> Result:
        with self._audit("stop", by, {"reason": reason}):
            why = f"{reason} ({by})" if reason else f"stopped by the operator ({by})"
            return self._submit(Stop(why, by=by), "run stopping")

    # ------------------------------------------------------------------ helpers
    @contextmanager
    def _audit(self, name: str, by: str, args: Mapping[str, Any]) -> Iterator[None]:
        """Admit the request (the command rate: 429 beyond it, before any work), and log a
        refusal that never reached the run (a bad task, an unknown agent...) as a refused
        ``command`` event, so the log shows who tried what."""
        if self.read_only is not None:
            raise ConsoleError(403, self.read_only)
        wait = self.rate.take()
        if wait > 0:
            raise ConsoleError(
                429, f"too many commands: at most {COMMAND_RATE_HZ:g} a second; retry in "
                f"{wait:.2f} s"
            )  # fmt: skip
        try:
            yield
        except ConsoleError as exc:
            if not exc.logged and exc.status != 429:
                with suppress(CommandError):  # the run has ended: nothing to log it in
                    self.run.submit(Refused(name, dict(args), exc.message, by=by))
            raise

    def _agent(self, agent: str) -> Any:
        snap = self.run.snapshot
        if snap is None:
            return None
        return next((a for a in snap.agents if a.id == agent), None)

    @contextmanager
    def _slot(self) -> Iterator[None]:
        """A place among the :data:`MAX_PENDING` commands waiting for their step (429 when
        there is none), held until the answer."""
        with self._lock:
            if self._pending >= self.max_pending:
                raise ConsoleError(
                    429, f"{self._pending} commands are waiting for the run already; retry shortly"
                )
            self._pending += 1
        try:
            yield
        finally:
            with self._lock:
                self._pending -= 1

    def _submit(
        self, command: Command, done: str, note: str = "", task: str | None = None
    ) -> Result:
        """Submit ``command`` (at most :data:`MAX_PENDING` wait at once) and wait for the step
        that applies it; ``done`` says what happened, ``note`` is added after its time."""
        with self._slot():
            try:
                future = self.run.submit(command)
            except TaskError as exc:
                raise _task_refused(exc) from None
            except CommandError as exc:
                text = _plain_error(str(exc), command.name)
                raise ConsoleError(404 if text.startswith("unknown") else 409, text) from None
            return self._wait(future, command.name, done, note, task)

    def _wait(
        self, future: Future[Outcome], name: str, done: str, note: str, task: str | None
    ) -> Result:
        """Wait, at most :attr:`wait_s`, for the step that applies the command ``name``: its
        answer (202 when it did not come)."""
        try:
            outcome = future.result(timeout=self.wait_s)
        except FutureTimeout:
            now = self.run.now()
            return Result(name, True, now, f"{done}: queued for the next step", 202, task)
        if not outcome.ok:
            raise ConsoleError(409, _plain_error(outcome.error, name), logged=True)
        text = f"{done} at {outcome.t:.1f} s{note}"
        return Result(name, True, outcome.t, text, 200, task)


def _task_row(t: Any, now: float) -> dict[str, Any]:
    """One task of the status: a pool task as it stands at ``now`` (``scheduled`` while its
    arrival time is still to come), with its latest changes."""
    scheduled = t.info.arrival_s > now + 1e-9
    return {
        "id": t.id,
        "type": t.info.type,
        "state": "scheduled" if scheduled else t.state.value,
        "agent": None if scheduled else t.agent,
        "priority": t.info.priority,
        "added_s": round(t.info.arrival_s, 3),
        "note": f"announced from {t.info.arrival_s:g} s" if scheduled else t.note,
        "since_s": round(t.history[-1].time_s, 3),
        "history": []
        if scheduled
        else [  # its latest changes: [t, state, agent, reason]
            [round(h.time_s, 3), h.state.value, h.agent, h.reason] for h in t.history[-HISTORY:]
        ],
        "fields": _plain(t.info.fields),
    }


def _task_refused(exc: TaskError) -> ConsoleError:
    """The answer to a task (or a priority) the run's check refused: 422 naming the field; 409
    when the pool is full (the run's state, not the task, is at fault)."""
    return ConsoleError(409 if exc.code == TOO_MANY else 422, exc.message, exc.field)


def _plain_error(text: str, name: str) -> str:
    """The run's message without its command's name (``recall_agent: unknown agent 'R9'`` →
    ``unknown agent 'R9'``): a person asked to recall, not to ``recall_agent``."""
    prefix = f"{name}: "
    return text[len(prefix) :] if text.startswith(prefix) else text


def _field_order(tt: Any) -> list[str]:
    """A task type's fields in the order a person fills them: as its goal names them
    (``delivered(pickup, dropoff)``), then its commit condition, then its cost, then the rest."""
    order: list[str] = []
    atoms = [*getattr(tt, "goals", ()), *([tt.commit_after] if tt.commit_after else [])]
    for name in [a for atom in atoms for a in atom.args] + list(tt.cost.symbols):
        if name in tt.fields and name not in order:
            order.append(name)
    return order + [f for f in tt.fields if f not in order]


def _goal_args(tt: Any) -> set[str]:
    """Field names a task type's goal conditions take (``at_goal(location)`` → location)."""
    out: set[str] = set()
    for g in getattr(tt, "goals", ()):
        for arg in getattr(g, "args", ()):
            out.add(str(arg))
    return out


def _plain(fields: Mapping[str, Any]) -> dict[str, Any]:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in fields.items()}
