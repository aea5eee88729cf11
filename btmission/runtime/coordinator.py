"""The coordinator: the auction loop of a running mission, and the operator's way in.

It wraps :class:`~btmission.allocation.loop.AuctionLoop` (the pure round function
:func:`~btmission.allocation.auction.auction_round` at ``coordination.auction_rate_hz``) around
the message bus: each round it announces the open tasks to the agents, collects their bids and
progress reports, allocates, and sends everyone their assignment (seed 000 §IV-B, seed 003 §IV).
Around that it

* adds the mission's tasks at their ``at:`` time (the pool holds them from the start; they are
  announced from their arrival), and tasks added while the mission runs (:meth:`Coordinator.
  add_task`, called by the run's command port with a task it checked,
  :mod:`btmission.runtime.taskcheck`);
* drops agents that stop bidding for ``coordination.agent_timeout_s`` from the auction and
  returns their task to the pool when their lease ends, ``coordination.lease_s`` after their last
  bid (the auction's stale-bid rule: a bid is also the agent's heartbeat and renews its lease);
* leaves tasks no agent can reach open (state ``unreachable``) with the reason, and says at once
  when an added task's location is outside the map or inside rock;
* publishes every change of a task's state as an event (``task``), every round (``round``) and
  every arrival (``task_added``);
* collects bids for ``coordination.bid_window_s`` after each announcement (0: in the same step,
  which the in-process bus gives); bids for an older announcement, or arriving when no round is
  collecting, are ignored and counted in the ``round`` event (``stale_bids``, ``late_bids``);
* takes an agent's give-up (its vehicle kept refusing: progress ``gave_up``) as one attempt at
  the task: the task goes back to the pool (an ``attempt`` event, then the ``task`` event) and
  the agent takes no part in its allocation for ``coordination.cooldown_s``; the task fails for
  good at its type's ``max_attempts`` with every attempt's reason. An agent that gives up
  ``coordination.exclude_after`` different tasks in a row is taken out of the auction, as the
  operator's exclude does (``agent_excluded``; the operator's include brings it back);
* acknowledges every progress report (:class:`~btmission.links.bus.ProgressAck`) and ignores
  copies of one it has seen, so an agent can resend until acknowledged. A completion (or commit
  point) reported late by an agent that lost the task while its link was down wins if it is the
  first: the task is credited to that agent, and the agent that held it meanwhile is withdrawn
  in the same round (``withdrawn`` event; its assignment no longer names the task).

Each coordinator has an *epoch*, chosen at random when it is created (:func:`new_epoch`): its
announcements and assignments carry it, with serials and rounds counted from the start. An
agent follows only an assignment newer than the last it followed (a later round of the same
epoch, or another epoch: a restarted coordinator), so one delivered late changes nothing.
"""

from __future__ import annotations

import math
import secrets
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import replace

from btmission.allocation.auction import Announcement, AuctionConfig, AuctionState
from btmission.allocation.loop import AuctionLoop, Inbox, Progress, RoundResult
from btmission.allocation.tasks import PoolError, PoolTask, TaskEvent, TaskInfo, TaskState
from btmission.links.bus import (
    AgentStatus,
    Assignment,
    CoordinatorInbox,
    CoordinatorLink,
    ProgressAck,
    ProgressKey,
    progress_key,
)
from btmission.runtime.eventkinds import (
    AgentExcludedEvent,
    AttemptEvent,
    RoundEvent,
    TaskAddedEvent,
    TaskStateEvent,
    WarningEvent,
    WithdrawnEvent,
)
from btmission.runtime.events import EmitEvent
from btmission.runtime.mission_auction import pool_from_mission
from btmission.runtime.recovery import Recovered, logged_key
from btmission.runtime.taskcheck import TaskError
from btmission.spec.mission import Mission


def new_epoch() -> int:
    """A random coordinator epoch, 1 … 2**53 - 1 (exact as a JSON number in any language;
    0 means "unknown")."""
    return secrets.randbelow(2**53 - 1) + 1


class _Now:
    """The auction loop's clock from a ``now()`` function (the runner steps time itself)."""

    def __init__(self, now: Callable[[], float]) -> None:
        self.now = now

    def sleep_until(self, t: float) -> None:  # pragma: no cover - never called: rounds are stepped
        pass


class Coordinator:
    """Runs the auction during a mission (module docstring); call :meth:`step` every step."""

    def __init__(
        self,
        mission: Mission,
        link: CoordinatorLink,
        clock: Callable[[], float],
        emit: EmitEvent,
        *,
        check_location: Callable[[tuple[float, float, float]], str | None] | None = None,
        places: Mapping[str, tuple[float, float, float]] | None = None,
        epoch: int | None = None,
    ) -> None:
        self.mission = mission
        self.epoch = new_epoch() if epoch is None else epoch
        """This coordinator's incarnation (module docstring)."""
        self.link = link
        self._clock = clock
        self.bid_window_s = float(getattr(mission.spec.coordination, "bid_window_s", 0.0))
        self._open: tuple[int, float, CoordinatorInbox] | None = None
        """The round collecting bids: (serial, closes at, what arrived so far)."""
        self._seen: dict[str, set[ProgressKey]] = {}
        """Progress reports taken, per agent, keyed with their time as the log has it
        (:func:`~btmission.runtime.recovery.logged_key`): copies of them are ignored."""
        self._acks: dict[str, list[ProgressKey]] = {}
        self._emit = emit
        self._check = check_location
        self._places = dict(places or {})
        cfg = AuctionConfig.from_spec(mission.spec.coordination)
        state = AuctionState(
            cfg, pool_from_mission(mission), announcement=Announcement(epoch=self.epoch)
        )
        self.loop = AuctionLoop(state, _Now(clock), self._collect, self._publish)
        self.period_s = self.loop.period_s
        self.next_round = 0.0
        self._added: set[str] = set()
        self._history_len: dict[str, int] = {}
        self._attempts_len: dict[str, int] = {}
        """Task → how many of its attempts have their ``attempt`` event logged."""
        self.statuses: dict[str, AgentStatus] = {}
        self.rounds: list[float] = []
        """Wall time (s) of each round (announce, bids, allocation, publication)."""
        self.bid_times: list[float] = []
        """Wall time (s) of each round's bidding stage (every agent's bid, in this process)."""
        self.round_cpu: list[float] = []
        """CPU time (s) this thread spent on each round run in one step (no bid window):
        unlike :attr:`rounds`, it does not grow when other processes share the CPU."""
        self.last: RoundResult | None = None
        self._last_assignments: dict[str, str] = {}
        self.recalled: set[str] = set()
        """Agents the operator recalled: their bids are no longer taken."""
        self.expect: Callable[[], Iterable[str]] | None = None
        """The agents whose bids a round's bid window waits for (None: it waits its whole
        length): over a network, those the link can reach."""

    # ---------------------------------------------------------------- operator API
    @property
    def state(self) -> AuctionState:
        return self.loop.state

    def add_task(self, info: TaskInfo, now: float, by: str = "api") -> None:
        """A task enters the pool now (a ``task_added`` event); it is announced from the next
        round at or after its arrival. The loop's thread, applying an
        :class:`~btmission.runtime.commands.AddTask`: the run's
        :class:`~btmission.runtime.taskcheck.TaskCheck` checked the task and reserved its id
        when it was submitted, so the pool takes it as it is."""
        if info.id in self.state.pool:  # (a caller that went around the run's check)
            raise TaskError(f"id: duplicate task id '{info.id}'", "id", "duplicate-id")
        self.loop.state = self.state.add_task(info, now)
        self._emit_added(info, now, by)

    def cancel_task(self, task_id: str, now: float, reason: str) -> None:
        """Take a task out of the pool (state ``cancelled``); its agent is told at the next
        round. Raises :class:`TaskError` if it is unknown or already over."""
        try:
            self.loop.state = replace(self.state, pool=self.state.pool.cancel(task_id, now, reason))
        except (KeyError, PoolError) as exc:
            raise TaskError(str(exc).strip("'\"")) from None

    def set_priority(self, task_id: str, priority: float, now: float) -> None:
        """Change a task's priority (announced again from the next round)."""
        try:
            pool = self.state.pool.reprioritised(task_id, priority)
        except (KeyError, PoolError, ValueError) as exc:
            raise TaskError(str(exc).strip("'\"")) from None
        self.loop.state = replace(self.state, pool=pool)

    def recall(self, agent: str, now: float) -> None:
        """The operator recalled ``agent``: it leaves the auction (its last bid is dropped, so
        it wins nothing more) and the task it holds goes back to the pool."""
        state = self.state
        held = state.holders().get(agent)
        pool = state.pool
        if held is not None:
            pool = pool.release(held, now, f"agent {agent} recalled by the operator")
        board = {a: b for a, b in state.board.items() if a != agent}
        self.recalled.add(agent)
        self.loop.state = replace(state, pool=pool, board=board)

    def exclude(self, agent: str, out: bool) -> None:
        """The operator takes ``agent`` out of the auction (``out``: it keeps the task it holds
        and wins nothing else) or brings it back (a recalled agent too)."""
        state = self.state
        excluded = state.excluded | {agent} if out else state.excluded - {agent}
        if not out:
            self.recalled.discard(agent)
        self.loop.state = replace(state, excluded=frozenset(excluded))

    def pause(self, paused: bool) -> None:
        """Pause allocation (every holder keeps its task, nothing else is assigned; the rounds
        go on, so bids keep the agents alive) or resume it."""
        self.loop.state = replace(self.state, paused=paused)

    @property
    def paused(self) -> bool:
        return self.state.paused

    def restore(self, recovered: Recovered) -> None:
        """Continue from a predecessor's log (:func:`~btmission.runtime.recovery.recover`):
        its pool, round count (the next round is numbered after the last), assignments, the
        operator's recalls, exclusions and pause, and the progress reports it took (resent
        copies are ignored). Each holder keeps its task until its lease ends, ``lease_s``
        after the last round logged, unless it bids again before. Nothing the log has is logged again; what it lacks (bids,
        statuses, unacknowledged progress) comes from the agents. Call it on a coordinator that
        has not stepped yet."""
        if self.state.round or self._added or self._open is not None:
            raise RuntimeError("restore() needs a coordinator that has not run a round yet")
        self.loop.state = replace(
            self.state,
            pool=recovered.pool,
            round=recovered.round,
            # announcements after the restart (this coordinator's epoch) are numbered after
            # any the predecessor made (at most one per round)
            announcement=Announcement(serial=recovered.round, epoch=self.epoch),
            paused=recovered.paused,
            excluded=recovered.excluded,
        )
        cool = self.state.config.cooldown_s
        cooldown: dict[tuple[str, str], float] = {}
        for t in recovered.pool:  # an agent that gave a task up is still cooling down for it
            if t.state is TaskState.OPEN and cool > 0:
                for a in t.attempts:
                    if a.gave_up:
                        cooldown[(a.agent, t.id)] = a.time_s + cool  # (the latest)
        # every holder keeps its task for its lease, counted from the last round logged: an
        # agent cut off from the old coordinator as well is not stripped of it at once
        since = recovered.round_s if recovered.round_s is not None else 0.0
        silent = dict.fromkeys(recovered.pool.holders(), since)
        self.loop.state = replace(
            self.state, cooldown=cooldown, streaks=dict(recovered.streaks), silent=silent
        )
        self.recalled = set(recovered.recalled)
        self._added = set(recovered.added)
        self._history_len = dict(recovered.logged)
        self._attempts_len = dict(recovered.attempts_logged)
        self._last_assignments = dict(recovered.assignments)
        self._seen = {agent: set(keys) for agent, keys in recovered.seen.items()}

    # ---------------------------------------------------------------- stepping
    def step(self, now: float) -> RoundResult | None:
        """Report arrivals, and run a round if one is due."""
        pool = self.state.pool
        if len(self._added) < len(pool):  # some task has not arrived yet
            for t in pool:
                if t.id not in self._added and t.info.arrival_s <= now:
                    self._emit_added(t.info, t.info.arrival_s, "mission")
        if self._open is not None:  # a round is collecting bids (bid window)
            serial, closes, inbox = self._open
            self._take(self.link.drain(), inbox)
            if now + 1e-9 < closes and not self._all_bid(serial, inbox):
                return None
            self._open = None
            return self.loop.close_round(inbox, now, serial)
        if now + 1e-9 < self.next_round:
            return None
        self.next_round = self.next_round + self.period_s
        if self.next_round <= now:  # a long step: skip to the next slot
            self.next_round = (math.floor(now / self.period_s) + 1) * self.period_s
        if self.bid_window_s <= 0:
            c0 = time.thread_time()
            result = self.loop.step()  # announce, collect (_collect) and allocate now
            self.round_cpu.append(time.thread_time() - c0)
            return result
        early = self._collect_early()
        ann = self.loop.open_round(now)
        self._announce(ann)
        self._open = (ann.serial, now + self.bid_window_s, early)
        return None

    def _all_bid(self, serial: int, inbox: CoordinatorInbox) -> bool:
        """Every agent :attr:`expect` names (and the auction takes bids from) has answered
        announcement ``serial``: the bid window can close early."""
        if self.expect is None:
            return False
        want = set(self.expect()) - self.recalled
        if not want:
            return False
        return want <= {b.agent for b in inbox.bids if b.serial == serial}

    def _emit_added(self, info: TaskInfo, t: float, by: str) -> None:
        self._added.add(info.id)
        problems = []
        if self._check is not None:
            for name, value in info.fields.items():
                if isinstance(value, str) and value in self._places:
                    value = self._places[value]
                if isinstance(value, (list, tuple)) and len(value) == 3:
                    why = self._check((float(value[0]), float(value[1]), float(value[2])))
                    if why:
                        problems.append(f"{name}: {why}")
        self._emit(
            TaskAddedEvent(
                t=t,
                task=info.id,
                type=info.type,
                fields=dict(info.fields),
                priority=info.priority,
                by=by,
                problems=problems,
                at=info.arrival_s if info.arrival_s > t + 1e-9 else None,
            )
        )

    def _collect(self, ann: Announcement, now: float) -> Inbox:
        """A round without a bid window: announce, and take what is back at once."""
        inbox = self._collect_early()
        self._announce(ann)  # in one process, every agent computes its bid right here
        self._take(self.link.drain(), inbox)
        return inbox

    def _announce(self, ann: Announcement) -> None:
        t0 = time.perf_counter()
        self.link.announce(ann)
        self.bid_times.append(time.perf_counter() - t0)

    def _collect_early(self) -> CoordinatorInbox:
        """What arrived between rounds: progress and statuses are kept; bids are late (the
        round they answered has closed)."""
        inbox = CoordinatorInbox()
        got = self.link.drain()
        inbox.late_bids += len(got.bids)
        got.bids = []
        self._take(got, inbox)
        return inbox

    def _take(self, got: CoordinatorInbox, into: CoordinatorInbox) -> None:
        """Add what arrived to the round's inbox: progress reports not seen before (every one
        is acknowledged after the round), bids, statuses."""
        if self.recalled:  # the operator recalled them: out of the auction
            into.bids.extend(b for b in got.bids if b.agent not in self.recalled)
        else:
            into.bids.extend(got.bids)
        into.late_bids += got.late_bids
        for p in got.progress:
            if self._first(p):
                into.progress.append(p)
        for s in got.statuses:
            self.statuses[s.agent] = s
        into.statuses.extend(got.statuses)

    def _first(self, p: Progress) -> bool:
        """Whether ``p`` is new (not a resent copy); it will be acknowledged either way."""
        key = progress_key(p)
        self._acks.setdefault(p.agent, []).append(key)
        seen = self._seen.setdefault(p.agent, set())
        taken = logged_key(key)  # its time as the log has it: what a restart can rebuild
        if taken in seen:
            return False
        seen.add(taken)
        return True

    def _publish(self, result: RoundResult) -> None:
        self.last = result
        self.rounds.append(result.step_s)
        rep = result.report
        now = rep.time_s
        logged = self._history_len
        for tid, t in result.state.pool.tasks.items():  # (the pool is keyed by task id)
            seen = logged.get(tid, 0)
            if seen == len(t.history):
                continue  # nothing new
            if seen == 0 and t.info.arrival_s > now:
                continue  # not arrived yet: its history starts when it does
            for ev in t.history[seen:]:
                if seen == 0 and ev.reason == "added":
                    continue  # the task_added event said it
                if ev.attempt is not None:
                    self._attempt(t, ev, now)
                self._emit(  # at the round's time (the log is in time order); when the change
                    TaskStateEvent(  # was reported earlier (an agent's progress), that time too
                        task=t.id,
                        state=ev.state.value,
                        agent=ev.agent,
                        reason=ev.reason,
                        reported_s=ev.time_s if ev.time_s < now - 1e-9 else None,
                    )
                )
            logged[tid] = len(t.history)
        for msg in result.progress_problems:
            self._emit(WarningEvent(message=msg))
        for w in result.withdrawn:
            self._emit(WithdrawnEvent(agent=w.agent, task=w.task, by=w.by, reason=w.reason))
        for x in result.excluded:
            self._emit(AgentExcludedEvent(agent=x.agent, tasks=list(x.tasks), reason=x.reason))
        changed = dict(rep.assignments) != self._last_assignments
        if changed:
            self._last_assignments = dict(rep.assignments)
        self._emit(
            RoundEvent(
                round=rep.round,
                announced=rep.announced,
                agents=len(rep.agents),
                method=rep.method,
                bids=rep.bids,
                step_ms=result.step_s * 1000,
                assignments=dict(self._last_assignments) if changed else None,  # when they changed,
                dropped=list(rep.dropped) if rep.dropped else None,  # and the others when any
                late_bids=rep.late_bids or None,
                stale_bids=rep.stale_bids or None,
            )
        )
        self.link.assign(
            Assignment(now, rep.round, result.assignments, result.announcement, self._clock())
        )
        acks, self._acks = self._acks, {}
        for agent, keys in acks.items():
            self.link.acknowledge(ProgressAck(agent, tuple(keys)))

    def _attempt(self, t: PoolTask, entry: TaskEvent, now: float) -> None:
        """The ``attempt`` event of the history entry that ended one (logged before its
        ``task`` event; once, a restart included: :attr:`_attempts_len`)."""
        attempt = entry.attempt
        assert attempt is not None
        n = 1 + next(i for i, a in enumerate(t.attempts) if a is attempt)
        if n <= self._attempts_len.get(t.id, 0):
            return  # logged by the coordinator this one continues from
        self._attempts_len[t.id] = n
        until = self.state.cooldown.get((attempt.agent, t.id))
        self._emit(
            AttemptEvent(
                task=t.id,
                agent=attempt.agent,
                attempt=n,
                max_attempts=t.info.max_attempts,
                reason=attempt.reason,
                gave_up=attempt.gave_up,
                state=entry.state.value,
                cooldown_until=until if attempt.gave_up and entry.state is TaskState.OPEN else None,
                reported_s=attempt.time_s if attempt.time_s < now - 1e-9 else None,
            )
        )

    # ---------------------------------------------------------------- queries
    def open_tasks(self) -> list[str]:
        return [t.id for t in self.state.pool if not t.state.terminal]

    def settled(self, now: float) -> bool:
        """Nothing left to allocate: every arrived task is done, failed or unreachable, nothing
        is held and no task is still to arrive. (The run asks every step: the pool's first
        open task answers it, before the arrivals are looked at. A task queued to enter the
        pool is the command port's: :func:`~btmission.runtime.ending.why_finished` asks it.)"""
        if self._open is not None:
            return False
        for t in self.state.pool:
            if t.state.terminal:
                continue
            if t.state is not TaskState.UNREACHABLE:
                return False
        return self.state.pool.next_arrival(now) is None
