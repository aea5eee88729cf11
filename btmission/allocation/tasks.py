"""Tasks and the task pool the auctioneer works on (seed 003 §II, seed 000 §IV-B).

A task is what the operator or the mission file asks for: a type (``inspect``,
``pick_and_deliver``…), the fields its type's goal and cost read (``location``, ``pickup``…), a
priority and the time it arrives. Single-stage tasks (seed 000's inspections) have no commit
point; multi-stage tasks (seed 003's pick-and-deliver) declare ``commit_after``, the condition
after which the agent may no longer be re-routed (k_bt = 0, eq. 8-10).

Each task in the pool has a state, and every change of state or agent is appended to its
history::

    open ──► assigned ──► committed ──► done
     ▲  ▲       │            │
     │  └───────┘ outbid     └──► failed     (reported by the agent)
     │  agent lost / stopped reporting / gave up (attempt n of max_attempts)
     └── unreachable (no agent can reach it; announced again every round)

    any state but done and failed ──► cancelled   (by the operator)

An agent that **gives up** a task (its vehicle kept refusing a command: arming, OFFBOARD)
hands it back: the task is open again, and the give-up is an :class:`Attempt` (who, when,
why) recorded on that history entry. The attempt that reaches the type's ``max_attempts``
fails the task for good, with every attempt's reason. A **failure** the agent reports (the
task itself cannot be done: its goal unreachable, a leaf's failure that is no refusal) fails it
at once, as its last attempt.

The pool is immutable: every operation returns a new :class:`TaskPool` (sharing the unchanged
tasks), so the auctioneer's step function stays pure and any earlier state can be kept for
replay or inspection.
"""

from __future__ import annotations

import enum
import math
from bisect import bisect_right
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from btmission.errors import BtmissionError


class TaskState(str, enum.Enum):
    """Where a task stands (see the module docstring for the transitions)."""

    OPEN = "open"
    ASSIGNED = "assigned"
    COMMITTED = "committed"
    DONE = "done"
    FAILED = "failed"
    UNREACHABLE = "unreachable"
    CANCELLED = "cancelled"

    @property
    def terminal(self) -> bool:
        return self in (TaskState.DONE, TaskState.FAILED, TaskState.CANCELLED)

    @property
    def announced(self) -> bool:
        """Whether an arrived task in this state is announced to the agents."""
        return not self.terminal


_ANNOUNCED = frozenset(s for s in TaskState if s.announced)
"""The states in which an arrived task is announced (:attr:`TaskState.announced`)."""

HELD = frozenset((TaskState.ASSIGNED, TaskState.COMMITTED))
"""The states in which a task's agent holds it."""


@dataclass(frozen=True)
class TaskInfo:
    """What is announced about a task: enough for any agent to compute its bid."""

    id: str
    type: str
    fields: Mapping[str, Any]
    priority: float = 1.0
    arrival_s: float = 0.0
    multi_stage: bool = False
    """True when the type declares a commit point (``commit_after``)."""
    max_attempts: int = 3
    """Agents' attempts (give-ups) after which the task fails for good (its type's
    ``max_attempts``)."""

    def __post_init__(self) -> None:
        if not self.id:
            raise ValueError("a task needs an id")
        if not self.max_attempts >= 1:
            raise ValueError(f"task '{self.id}': max_attempts must be ≥ 1, got {self.max_attempts}")
        if not (self.priority > 0 and math.isfinite(self.priority)):
            raise ValueError(f"task '{self.id}': priority must be > 0, got {self.priority}")
        if not (self.arrival_s >= 0 and math.isfinite(self.arrival_s)):
            raise ValueError(f"task '{self.id}': arrival time must be ≥ 0, got {self.arrival_s}")


@dataclass(frozen=True)
class Attempt:
    """An agent's attempt at a task that ended without success: it gave the task up (its
    vehicle kept refusing), or reported it failed."""

    agent: str
    time_s: float
    """When the agent reported it."""
    reason: str
    """The agent's reason."""
    gave_up: bool = True
    """True: handed back (the task may go to another agent); False: a failure (final)."""


@dataclass(frozen=True)
class TaskEvent:
    """One entry of a task's history."""

    time_s: float
    state: TaskState
    agent: str | None = None
    reason: str = ""
    attempt: Attempt | None = None
    """The attempt this change ended (a give-up or a failure), if it ended one."""

    def __str__(self) -> str:
        who = f" {self.agent}" if self.agent else ""
        why = f" ({self.reason})" if self.reason else ""
        return f"t={self.time_s:.2f}s {self.state.value}{who}{why}"


@dataclass(frozen=True)
class PoolTask:
    """A task in the pool: its announcement data, state, agent, current note and history."""

    info: TaskInfo
    state: TaskState = TaskState.OPEN
    agent: str | None = None
    """The agent holding it (assigned or committed), else None."""
    note: str = ""
    """Why it is in its state now, e.g. why an open task has no agent."""
    history: tuple[TaskEvent, ...] = ()

    @property
    def id(self) -> str:
        return self.info.id

    def arrived(self, now: float) -> bool:
        return self.info.arrival_s <= now

    @property
    def attempts(self) -> tuple[Attempt, ...]:
        """The attempts that ended without success, oldest first (from the history)."""
        return tuple(e.attempt for e in self.history if e.attempt is not None)

    def moved(
        self,
        now: float,
        state: TaskState,
        agent: str | None = None,
        reason: str = "",
        attempt: Attempt | None = None,
    ) -> PoolTask:
        """The task in a new state/agent, with the change appended to its history."""
        return replace(
            self,
            state=state,
            agent=agent,
            note=reason,
            history=(*self.history, TaskEvent(now, state, agent, reason, attempt)),
        )


class PoolError(BtmissionError, ValueError):
    """An operation the pool cannot do (unknown task, wrong agent, task already finished…)."""


@dataclass(frozen=True)
class TaskPool:
    """Immutable collection of tasks keyed by id, in the order they were added."""

    tasks: Mapping[str, PoolTask] = field(default_factory=dict)

    # -- queries ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.tasks)

    def __iter__(self) -> Iterator[PoolTask]:
        return iter(self.tasks.values())

    def __contains__(self, task_id: object) -> bool:
        return task_id in self.tasks

    def __getitem__(self, task_id: str) -> PoolTask:
        try:
            return self.tasks[task_id]
        except KeyError:
            raise PoolError(f"unknown task '{task_id}'") from None

    def get(self, task_id: str) -> PoolTask | None:
        return self.tasks.get(task_id)

    def _order(self) -> tuple[str, ...]:
        """Every task's key by (arrival, id): computed once per pool, and handed on by
        :meth:`with_tasks` (which changes no task's arrival or id, so not the order)."""
        order = self.__dict__.get("_sorted")
        if order is None:
            ranked = sorted(self.tasks.items(), key=lambda kv: (kv[1].info.arrival_s, kv[1].id))
            order = tuple(k for k, _ in ranked)
            object.__setattr__(self, "_sorted", order)
        return order  # type: ignore[no-any-return]

    def announced(self, now: float) -> list[PoolTask]:
        """Tasks to announce at ``now``: arrived and not finished, by (arrival, id)."""
        tasks = self.tasks
        live = []
        for k in self._order():
            t = tasks[k]
            if t.state in _ANNOUNCED and t.info.arrival_s <= now:  # t.arrived(now)
                live.append(t)
        return live

    def announced_infos(self, now: float) -> tuple[TaskInfo, ...]:
        """The infos of :meth:`announced` at ``now``, as one tuple kept with the pool and handed
        on by :meth:`with_tasks` while no task changes whether it is announced or its info: the
        auctioneer asks every round, and most rounds change only notes and agents, so the
        announcement's tasks stay the same tuple (:func:`~btmission.allocation.auction.announce`
        then compares one object, not every task)."""
        arrivals = self.__dict__.get("_arrivals")
        if arrivals is None:
            tasks = self.tasks
            arrivals = [tasks[k].info.arrival_s for k in self._order()]
            object.__setattr__(self, "_arrivals", arrivals)
        # the arrived tasks are a prefix of the (arrival, id) order (a NaN time: none arrived)
        n = bisect_right(arrivals, now) if now == now else 0
        live = self.__dict__.get("_infos_at")
        if live is None:
            live = {}
            object.__setattr__(self, "_infos_at", live)
        infos: tuple[TaskInfo, ...] | None = live.get(n)
        if infos is None:
            tasks = self.tasks
            infos = live[n] = tuple(
                t.info for k in self._order()[:n] if (t := tasks[k]).state in _ANNOUNCED
            )
        return infos

    def holders(self) -> dict[str, str]:
        """Agent → the task it holds (assigned or committed), in pool order (an agent named by
        two tasks: the later one). Kept with the pool (a copy is returned) and handed on by
        :meth:`with_tasks` while no task changes agent or whether it is held."""
        held = self.__dict__.get("_holders")
        if held is None:
            held = {
                t.agent: t.id
                for t in self.tasks.values()
                if t.agent is not None and t.state in HELD
            }
            object.__setattr__(self, "_holders", held)
        return dict(held)

    def held_by(self, agent: str) -> PoolTask | None:
        """The task ``agent`` holds (assigned or committed), if any."""
        for t in self.tasks.values():
            if t.agent == agent and t.state in HELD:
                return t
        return None

    def in_state(self, *states: TaskState) -> list[PoolTask]:
        return [t for t in self.tasks.values() if t.state in states]

    def next_arrival(self, now: float) -> float | None:
        """The earliest arrival time after ``now`` (for a loop that wants to wake up then)."""
        later = [t.info.arrival_s for t in self.tasks.values() if t.info.arrival_s > now]
        return min(later) if later else None

    # -- changes (each returns a new pool) --------------------------------------------------
    def add(self, info: TaskInfo, now: float | None = None) -> TaskPool:
        """Add a task (open from its arrival time). Ids are unique."""
        if info.id in self.tasks:
            raise PoolError(f"duplicate task id '{info.id}'")
        t = info.arrival_s if now is None else max(now, info.arrival_s)
        task = PoolTask(info, note="added", history=(TaskEvent(t, TaskState.OPEN, None, "added"),))
        return TaskPool({**self.tasks, info.id: task})

    def add_all(self, infos: Iterable[TaskInfo]) -> TaskPool:
        pool = self
        for info in infos:
            pool = pool.add(info)
        return pool

    def with_tasks(self, changed: Mapping[str, PoolTask]) -> TaskPool:
        """The pool with ``changed`` tasks replaced (they must already be in it). What the pool
        keeps about itself is handed on where the changes cannot alter it: the (arrival, id)
        order, the announced infos (:meth:`announced_infos`) and the holders
        (:meth:`holders`)."""
        if not changed:
            return self
        tasks = self.tasks
        pool = TaskPool({**tasks, **changed})
        kept = self.__dict__
        same_live = same_held = True
        for k, t in changed.items():
            old = tasks.get(k)
            if old is None or t.id != old.id or t.info.arrival_s != old.info.arrival_s:
                return pool  # (a task's place in the order may differ: nothing is handed on)
            if t.info is not old.info or (t.state in _ANNOUNCED) != (old.state in _ANNOUNCED):
                same_live = False
            if t.agent != old.agent or (t.state in HELD) != (old.state in HELD):
                same_held = False
        for name, same in (
            ("_sorted", True),
            ("_arrivals", True),
            ("_infos_at", same_live),
            ("_holders", same_held),
        ):
            if same and name in kept:
                object.__setattr__(pool, name, kept[name])
        return pool

    def commit(
        self, task_id: str, agent: str, now: float, reason: str = "commit point"
    ) -> TaskPool:
        """The agent reports passing the task's commit point (k_bt = 0 from now on)."""
        t = self._held(task_id, agent, "commit to")
        if t.state is TaskState.COMMITTED:
            return self
        if not t.info.multi_stage:
            raise PoolError(f"task '{task_id}' has no commit point (its type has no commit_after)")
        return self.with_tasks({task_id: t.moved(now, TaskState.COMMITTED, agent, reason)})

    def complete(self, task_id: str, agent: str, now: float, reason: str = "completed") -> TaskPool:
        """The agent reports the task done."""
        t = self._held(task_id, agent, "complete")
        return self.with_tasks({task_id: t.moved(now, TaskState.DONE, agent, reason)})

    def fail(self, task_id: str, agent: str, now: float, reason: str = "") -> TaskPool:
        """The agent reports the task failed (it is not retried): its last attempt."""
        t = self._held(task_id, agent, "fail")
        why = reason or "reported failed"
        attempt = Attempt(agent, now, why, gave_up=False)
        return self.with_tasks({task_id: t.moved(now, TaskState.FAILED, agent, why, attempt)})

    def give_up(self, task_id: str, agent: str, now: float, reason: str = "") -> TaskPool:
        """The agent hands the task back (its vehicle kept refusing): one more attempt; the
        task is open again, or failed for good with every attempt's reason once it has had
        its ``max_attempts``."""
        t = self._held(task_id, agent, "give up")
        attempt = Attempt(agent, now, reason or "gave up")
        tried = (*t.attempts, attempt)
        n, most = len(tried), t.info.max_attempts
        if n >= most:
            why = f"failed after {n} attempt(s): " + "; ".join(
                f"{a.agent}: {a.reason}" for a in tried
            )
            moved = t.moved(now, TaskState.FAILED, agent, why, attempt)
        else:
            why = f"{agent} gave up (attempt {n} of {most}): {attempt.reason}"
            moved = t.moved(now, TaskState.OPEN, None, why, attempt)
        return self.with_tasks({task_id: moved})

    def take_over(
        self, task_id: str, agent: str, now: float, state: TaskState, reason: str
    ) -> TaskPool:
        """``agent`` reports a task it no longer holds (it lost it while its link was down) as
        ``state`` (done or committed): the task is its, whoever held it (the caller withdraws
        the other holder)."""
        t = self[task_id]
        if t.state.terminal:
            raise PoolError(f"task '{task_id}' is already {t.state.value}")
        return self.with_tasks({task_id: t.moved(now, state, agent, reason)})

    def assign(self, task_id: str, agent: str, now: float, reason: str) -> TaskPool:
        """``agent`` won the task (an auction round's result, e.g. replayed from a log)."""
        t = self._live(task_id, "assign")
        return self.with_tasks({task_id: t.moved(now, TaskState.ASSIGNED, agent, reason)})

    def unreachable(self, task_id: str, now: float, reason: str) -> TaskPool:
        """No agent can reach the task (it stays announced, without an agent)."""
        t = self._live(task_id, "mark unreachable")
        return self.with_tasks({task_id: t.moved(now, TaskState.UNREACHABLE, None, reason)})

    def release(self, task_id: str, now: float, reason: str) -> TaskPool:
        """Back to the pool (open, no agent), e.g. when its agent was lost."""
        t = self[task_id]
        if t.state.terminal:
            raise PoolError(f"task '{task_id}' is already {t.state.value}")
        return self.with_tasks({task_id: t.moved(now, TaskState.OPEN, None, reason)})

    def cancel(self, task_id: str, now: float, reason: str) -> TaskPool:
        """The operator takes the task out (state ``cancelled``; its agent is unassigned at
        the next round)."""
        t = self[task_id]
        if t.state.terminal:
            raise PoolError(f"cannot cancel task '{task_id}': it is already {t.state.value}")
        return self.with_tasks({task_id: t.moved(now, TaskState.CANCELLED, None, reason)})

    def reprioritised(self, task_id: str, priority: float) -> TaskPool:
        """The task with a new priority (announced again with it); same state, agent and
        history (the run logs the change as a ``command`` event)."""
        t = self[task_id]
        if t.state.terminal:
            raise PoolError(
                f"cannot change the priority of task '{task_id}': it is already {t.state.value}"
            )
        info = replace(t.info, priority=priority)  # TaskInfo checks it (> 0, finite)
        return self.with_tasks({task_id: replace(t, info=info)})

    def _live(self, task_id: str, verb: str) -> PoolTask:
        """The task, if it is not finished (done, failed or cancelled)."""
        t = self[task_id]
        if t.state.terminal:
            raise PoolError(f"cannot {verb} task '{task_id}': it is already {t.state.value}")
        return t

    def _held(self, task_id: str, agent: str, verb: str) -> PoolTask:
        t = self._live(task_id, verb)
        if t.agent != agent:
            holder = f"held by {t.agent}" if t.agent else "not assigned"
            raise PoolError(f"agent '{agent}' cannot {verb} task '{task_id}': it is {holder}")
        return t
