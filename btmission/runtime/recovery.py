"""A restarted coordinator's state, rebuilt from the event log its predecessor wrote (issue #17).

The coordinator writes every change of its state to the append-only event log
(:mod:`btmission.runtime.events`): a task entering the pool (``task_added``), every entry of a
task's history (``task``), every round (``round``: its number, the assignments when they
changed, the agents it dropped), a holder withdrawn by a late report (``withdrawn``), every
attempt at a task that ended without success (``attempt``: a give-up, with the cool-down it
started, or a failure), an agent it took out of the auction for its give-ups
(``agent_excluded``) and every operator command it applied (``command`` with ``ok``: cancel,
priority, recall, exclude, include, allocation pause). :func:`recover` replays those events — no I/O: the caller reads the
log (``read_events(path).events``) — and returns a :class:`Recovered` that
:meth:`Coordinator.restore <btmission.runtime.coordinator.Coordinator.restore>` continues from.

The pool is rebuilt from the mission's tasks and the tasks operators added, through the pool's
own transitions (:class:`~btmission.allocation.tasks.TaskPool`: add, assign, commit, complete,
fail, take over, release, mark unreachable, cancel, reprioritise), so a replay the pool refuses
(a finished task changing again, a completion by an agent that does not hold the task) is
reported in :attr:`Recovered.problems` instead of being forced in. A round's ``task`` events are
written in pool order, not in the order they happened (a task won by an agent can come before
the completion that freed that agent), so "no agent holds two tasks" and "the holders are the
round's assignments" are checked when a round's ``round`` event is reached, not in between.

The log may be cut anywhere (the process died writing it): whatever it holds is taken, the
events of a round whose ``round`` event is missing included — the acknowledgements and the
assignment of that round were never sent (they go out after the ``round`` event), so the agents
resend its progress reports and the next round tells them who holds what.

What the log does not hold comes from the agents after the restart: their bids (the board the
auction works on; a holder keeps its task if it bids in the first round), statuses, and the
progress reports not acknowledged yet, which they resend.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from btmission.allocation.auction import AuctionState
from btmission.allocation.loop import Withdrawal
from btmission.allocation.tasks import PoolError, TaskInfo, TaskPool, TaskState
from btmission.links.bus import ProgressKey
from btmission.runtime.eventkinds import (
    AgentExcludedEvent,
    AttemptEvent,
    CommandEvent,
    RoundEvent,
    TaskAddedEvent,
    TaskStateEvent,
    WithdrawnEvent,
)
from btmission.runtime.events import (
    Event,
    EventError,
    TypedEvent,
)
from btmission.runtime.mission_auction import pool_from_mission
from btmission.spec.mission import Mission

LOG_DECIMALS = 4
"""Decimals of the times in a log (:meth:`Event.to_json` rounds them)."""

_PROGRESS_STATES = {TaskState.DONE: "done", TaskState.FAILED: "failed"}
_BID_COMMIT = "commit point (k_bt = 0)"
"""The reason of a commit point the auction read from a bid (not a progress report)."""


def logged_key(key: ProgressKey) -> ProgressKey:
    """A progress report's key with its time as a log holds it (rounded to
    :data:`LOG_DECIMALS`): what the coordinator remembers of the reports it took, so the ones a
    log shows are recognised when they are resent after a restart."""
    task, event, time_s = key
    return (task, event, round(time_s, LOG_DECIMALS))


@dataclass(frozen=True)
class Recovered:
    """What a new coordinator needs to continue from a log (:func:`recover`)."""

    pool: TaskPool
    """Every task of the mission and every task an operator added, with its state, agent,
    priority and history as the log shows them (a task's ``note`` is the reason of its last
    history entry: the rounds' note-only updates are not logged; the next round sets them)."""
    round: int = 0
    """The last round logged (0: none); the next round is ``round + 1``."""
    round_s: float | None = None
    """Mission time of that round."""
    assignments: Mapping[str, str] = field(default_factory=dict)
    """Agent → task after the last round that logged its assignments (they are logged when
    they change)."""
    dropped: Mapping[str, float] = field(default_factory=dict)
    """Agents the auction dropped (stopped bidding) → when, for those the log does not show
    holding or finishing a task since."""
    withdrawn: tuple[Withdrawal, ...] = ()
    """Holders that lost their task to another agent's late report, in log order."""
    recalled: frozenset[str] = frozenset()
    """Agents the operator recalled (and did not include again)."""
    excluded: frozenset[str] = frozenset()
    """Agents the operator took out of the auction."""
    paused: bool = False
    """Allocation paused by the operator."""
    seen: Mapping[str, frozenset[ProgressKey]] = field(default_factory=dict)
    """Per agent, the progress reports the log shows were taken, keyed as :func:`logged_key`
    (task, event, time rounded as in the log): every completion, failure and reported commit
    point. Reports that changed nothing (a commit point already read from a bid, a completion
    refused as late) leave no trace in the log; resent, they are refused again."""
    added: frozenset[str] = frozenset()
    """Tasks whose ``task_added`` event is in the log."""
    logged: Mapping[str, int] = field(default_factory=dict)
    """Task → how many entries of its history the log holds (the first, ``added``, is its
    ``task_added`` event); an operator's change not logged yet (a cancel or a recall applied
    just before the cut) is in the history but not counted, so the next round logs it."""
    streaks: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    """Agent → the different tasks it gave up since it last finished one or was taken out of
    the auction (:attr:`~btmission.allocation.auction.AuctionState.streaks`)."""
    attempts_logged: Mapping[str, int] = field(default_factory=dict)
    """Task → how many ``attempt`` events the log holds for it (an attempt applied just
    before the cut whose ``task`` event is missing is not logged again)."""
    time_s: float = 0.0
    """Mission time of the last event."""
    problems: tuple[str, ...] = ()
    """Events that could not be replayed (the pool refused them), and broken invariants."""

    def holders(self) -> dict[str, str]:
        """Agent → the task it holds (assigned or committed)."""
        return _holders(self.pool)


def recover(mission: Mission, events: Iterable[Event]) -> Recovered:
    """The coordinator's state after ``events`` (a log of a run of ``mission``, possibly cut
    anywhere; module docstring). Pure: no I/O, the events are not changed."""
    replay = _Replay(mission)
    for ev in events:
        replay.take(ev)
    return replay.result()


class _Replay:
    """The state being rebuilt, event by event."""

    def __init__(self, mission: Mission) -> None:
        self.mission = mission
        self.pool = pool_from_mission(mission)
        self.round = 0
        self.round_s: float | None = None
        self.assignments: dict[str, str] = {}
        self.dropped: dict[str, float] = {}
        self.withdrawn: list[Withdrawal] = []
        self.recalled: set[str] = set()
        self.excluded: set[str] = set()
        self.paused = False
        self.seen: dict[str, set[ProgressKey]] = {}
        self.added: set[str] = set()
        self.logged: dict[str, int] = {}
        self.streaks: dict[str, tuple[str, ...]] = {}
        self.attempts_logged: dict[str, int] = {}
        self.time_s = 0.0
        self.problems: list[str] = []

    def result(self) -> Recovered:
        return Recovered(
            pool=self.pool,
            round=self.round,
            round_s=self.round_s,
            assignments=dict(self.assignments),
            dropped=dict(self.dropped),
            withdrawn=tuple(self.withdrawn),
            recalled=frozenset(self.recalled),
            excluded=frozenset(self.excluded),
            paused=self.paused,
            seen={a: frozenset(keys) for a, keys in self.seen.items()},
            added=frozenset(self.added),
            logged=dict(self.logged),
            streaks=dict(self.streaks),
            attempts_logged=dict(self.attempts_logged),
            time_s=self.time_s,
            problems=tuple(self.problems),
        )

    def problem(self, ev: Event | TypedEvent, message: str) -> None:
        self.problems.append(f"t={ev.t:g}s {ev.kind}: {message}")

    # ---------------------------------------------------------------- events
    def take(self, event: Event) -> None:
        self.time_s = event.t
        try:
            match event.typed():
                case TaskAddedEvent() as ev:
                    self.task_added(ev)
                case TaskStateEvent() as ev:
                    self.task(ev)
                case RoundEvent() as ev:
                    self.round_(ev)
                case WithdrawnEvent() as ev:
                    self.withdrawn_(ev)
                case AttemptEvent() as ev:
                    self.attempt(ev)
                case AgentExcludedEvent() as ev:
                    self.excluded.add(ev.agent)
                    self.streaks.pop(ev.agent, None)
                case CommandEvent() as ev:
                    self.command(ev)
        except (PoolError, EventError, TypeError, ValueError) as exc:  # PoolError: the pool
            self.problem(event, str(exc))  # refused it; EventError: fields of the wrong types

    def task_added(self, ev: TaskAddedEvent) -> None:
        tid = str(ev.task)
        if tid not in self.pool:  # an operator's task (the mission's are in the pool already)
            self.pool = self.pool.add(self._info(tid, ev), ev.t)
        self.added.add(tid)
        self.logged[tid] = max(self.logged.get(tid, 0), 1)

    def _info(self, tid: str, ev: TaskAddedEvent) -> TaskInfo:
        ttype = str(ev.type)
        tt = self.mission.task_types.get(ttype)
        if tt is None:
            raise ValueError(f"task '{tid}' has type '{ttype}', which the mission does not have")
        # the log has no arrival time for an added task: it arrived when it entered the pool
        # (unless a later log says ``at``)
        return TaskInfo(
            tid,
            ttype,
            dict(ev.fields or {}),
            float(ev.priority) if ev.priority is not None else tt.priority,
            float(ev.at) if ev.at is not None else ev.t,
            tt.commit_after is not None,
            tt.max_attempts,
        )

    def task(self, ev: TaskStateEvent) -> None:
        tid = str(ev.task)
        state = TaskState(ev.state)
        agent = ev.agent
        reason = "" if ev.reason is None else str(ev.reason)
        t = self.pool[tid]
        n = self.logged.get(tid, 1)
        if n < len(t.history):  # an operator's change, applied when its command was logged
            entry = t.history[n]
            if (entry.state, entry.agent) != (state, agent):
                raise ValueError(
                    f"task '{tid}' is logged {state.value} ({agent or 'no agent'}), but the "
                    f"change it was given by a command is {entry}"
                )
        else:
            now = float(ev.reported_s) if ev.reported_s is not None else ev.t
            self.pool = _transition(self.pool, tid, state, agent, now, reason)
            self._seen(tid, state, agent, now, reason)
        self.logged[tid] = n + 1
        if agent is not None:
            self.dropped.pop(agent, None)
            if state is TaskState.DONE:  # a task done ends its agent's streak of give-ups
                self.streaks.pop(agent, None)

    def attempt(self, ev: AttemptEvent) -> None:
        """An attempt that ended without success, through the pool's transition (give up or
        fail): its history entry is made here, and the ``task`` event after it matched."""
        tid, agent, reason = str(ev.task), str(ev.agent), str(ev.reason)
        when = float(ev.reported_s) if ev.reported_s is not None else ev.t
        if ev.gave_up:
            self.pool = self.pool.give_up(tid, agent, when, reason)
            streak = self.streaks.get(agent, ())
            self.streaks[agent] = streak if tid in streak else (*streak, tid)
        else:
            self.pool = self.pool.fail(tid, agent, when, reason)
        got = self.pool[tid].state.value
        if got != ev.state:
            self.problem(ev, f"task '{tid}' is {got} after attempt {ev.attempt}, not {ev.state}")
        event = "gave_up" if ev.gave_up else "failed"
        self.seen.setdefault(agent, set()).add(logged_key((tid, event, when)))
        self.attempts_logged[tid] = self.attempts_logged.get(tid, 0) + 1

    def _seen(self, tid: str, state: TaskState, agent: str | None, now: float, reason: str) -> None:
        """Record the progress report a logged change came from (if it came from one)."""
        event = _PROGRESS_STATES.get(state)
        if state is TaskState.COMMITTED and reason != _BID_COMMIT:
            event = "committed"
        if event is not None and agent is not None:
            self.seen.setdefault(agent, set()).add(logged_key((tid, event, now)))

    def round_(self, ev: RoundEvent) -> None:
        self.round = int(ev.round)
        self.round_s = ev.t
        if ev.assignments is not None:
            self.assignments = {a: t for a, t in ev.assignments.items() if t is not None}
        for a in ev.dropped or ():
            self.dropped[a] = ev.t
        self._check_holders(ev)

    def _check_holders(self, ev: RoundEvent) -> None:
        """After a round: no agent holds two tasks, and the holders are the assignments."""
        held: dict[str, list[str]] = {}
        for t in self.pool:
            if t.agent is not None and t.state in (TaskState.ASSIGNED, TaskState.COMMITTED):
                held.setdefault(t.agent, []).append(t.id)
        for agent, tids in held.items():
            if len(tids) > 1:
                self.problem(ev, f"agent {agent} holds {', '.join(tids)}")
        holders = {a: tids[0] for a, tids in held.items()}
        if holders != self.assignments:
            self.problem(
                ev, f"the holders {holders} are not the round's assignments {self.assignments}"
            )

    def withdrawn_(self, ev: WithdrawnEvent) -> None:
        by = str(ev.by)
        done = (ev.reason or "").startswith(f"{by} completed")
        self.withdrawn.append(
            Withdrawal(str(ev.agent), str(ev.task), by, "done" if done else "committed")
        )

    def command(self, ev: CommandEvent) -> None:
        """An operator's command the run applied (``ok``): its effect on the coordinator."""
        if not ev.ok:
            return
        name = ev.command
        args = ev.args
        agent: Any = args.get("agent")
        if name == "cancel_task":
            self.pool = self.pool.cancel(str(args.get("task")), ev.t, str(args.get("reason", "")))
        elif name == "set_priority":
            priority: Any = args.get("priority")
            self.pool = self.pool.reprioritised(str(args.get("task")), float(priority))
        elif name == "recall_agent":  # as Coordinator.recall: its task back to the pool
            held = _holders(self.pool).get(agent)
            if held is not None:
                why = f"agent {agent} recalled by the operator"
                self.pool = self.pool.release(held, ev.t, why)
            self.recalled.add(agent)
        elif name == "exclude_agent":
            self.excluded.add(agent)
        elif name == "include_agent":
            self.excluded.discard(agent)
            self.recalled.discard(agent)
        elif name == "set_allocation":
            self.paused = bool(args.get("paused"))


def _holders(pool: TaskPool) -> dict[str, str]:
    """Agent → the task it holds (assigned or committed)."""
    return AuctionState(pool=pool).holders()


def _transition(
    pool: TaskPool, tid: str, state: TaskState, agent: str | None, now: float, reason: str
) -> TaskPool:
    """One logged history entry, through the pool transition that made it."""
    held = agent is not None and pool[tid].agent == agent
    if state is TaskState.ASSIGNED and agent is not None:
        return pool.assign(tid, agent, now, reason)
    if state is TaskState.DONE and agent is not None:
        if held:
            return pool.complete(tid, agent, now, reason)
        return pool.take_over(tid, agent, now, state, reason)  # a late report won
    if state is TaskState.COMMITTED and agent is not None:
        if held:
            return pool.commit(tid, agent, now, reason)
        return pool.take_over(tid, agent, now, state, reason)
    if state is TaskState.FAILED and agent is not None:
        return pool.fail(tid, agent, now, reason)
    if state is TaskState.OPEN:
        return pool.release(tid, now, reason)
    if state is TaskState.UNREACHABLE:
        return pool.unreachable(tid, now, reason)
    if state is TaskState.CANCELLED:
        return pool.cancel(tid, now, reason)
    raise PoolError(f"task '{tid}': {state.value} without an agent")
