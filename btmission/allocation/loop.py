"""The auctioneer's fixed-rate loop: announce, collect, allocate, publish — every period.

Seed 003 §IV and §VII-B run the auction at a fixed rate (a delay after the announcement gave
9 Hz) so tasks added mid-mission are allocated within one period. :class:`AuctionLoop` calls the
pure step function (:func:`~btmission.allocation.auction.auction_round`) on a schedule
``t0 + k / rate_hz``, with no drift: a round that overruns its slot is followed by the next
free slot (the missed ones are counted, never run late in a burst).

The loop owns no clock and no transport: it takes a :class:`Clock` (:class:`WallClock` for real
time, :class:`ManualClock` for simulation and tests), a ``collect`` function that publishes the
announcement and returns what arrived since the last round (bids and progress reports), and a
``publish`` function that receives each round's result.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal, Protocol

from btmission.allocation.auction import (
    Announcement,
    AuctionState,
    Bid,
    RoundReport,
    announce,
    auction_round,
)
from btmission.allocation.tasks import PoolError, TaskState


class Clock(Protocol):
    """Time in seconds since the mission started."""

    def now(self) -> float: ...

    def sleep_until(self, t: float) -> None: ...


class WallClock:
    """Real time (monotonic), zero when created."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic() - self._t0

    def sleep_until(self, t: float) -> None:
        delay = t - self.now()
        if delay > 0:
            time.sleep(delay)


class ManualClock:
    """Simulated time: ``sleep_until`` jumps forward (never back)."""

    def __init__(self, t: float = 0.0):
        self.t = t

    def now(self) -> float:
        return self.t

    def sleep_until(self, t: float) -> None:
        self.t = max(self.t, t)

    def advance(self, dt: float) -> None:
        self.t += dt


@dataclass(frozen=True)
class Progress:
    """An agent's report on its task: passed the commit point, done, failed (the task cannot
    be done), or gave up (its vehicle kept refusing: the task goes back to the pool)."""

    agent: str
    task: str
    event: Literal["committed", "done", "failed", "gave_up"]
    time_s: float
    reason: str = ""


@dataclass(frozen=True)
class Exclusion:
    """An agent taken out of the auction because it gave up ``tasks`` (different ones, in a
    row, none done between: ``AuctionConfig.exclude_after`` of them)."""

    agent: str
    tasks: tuple[str, ...]

    @property
    def reason(self) -> str:
        return (
            f"gave up {len(self.tasks)} different tasks in a row ({', '.join(self.tasks)}) "
            "without finishing one: out of the auction until the operator includes it again"
        )


@dataclass(frozen=True)
class Withdrawal:
    """A holder loses its task because another agent's report settled it first: ``by`` reported
    it ``event`` (done, or passed its commit point) while it no longer held it (it had been
    released or reassigned while ``by`` was silent). ``agent`` must stop executing it."""

    agent: str
    task: str
    by: str
    event: str

    @property
    def reason(self) -> str:
        what = "completed" if self.event == "done" else "committed to"
        return f"{self.by} {what} '{self.task}' first (reported after its link returned)"


def _take_over(
    state: AuctionState, p: Progress, withdrawn: list[Withdrawal]
) -> AuctionState | None:
    """A report of ``p.agent`` on a task it no longer holds (it lost it while silent): the first
    completion wins, and so does a commit point on a task nobody else has committed to; the
    holder, if any, is withdrawn. None when the report cannot be used that way."""
    t = state.pool.get(p.task)
    if t is None or t.state.terminal or t.agent == p.agent:
        return None
    if not any(e.agent == p.agent for e in t.history):  # it never held it: not a late report
        return None
    late = f"reported late by {p.agent}, which had lost it while silent"
    if t.agent is not None:
        late += f"; {t.agent} withdrawn"
    if p.event == "done":
        st, reason = TaskState.DONE, f"completed ({late})"
    elif p.event == "committed" and t.info.multi_stage and t.state is not TaskState.COMMITTED:
        st, reason = TaskState.COMMITTED, f"commit point ({late})"
    else:
        return None
    if t.agent is not None:
        withdrawn.append(Withdrawal(t.agent, t.id, p.agent, p.event))
    return replace(state, pool=state.pool.take_over(p.task, p.agent, p.time_s, st, reason))


def _gave_up(state: AuctionState, p: Progress, excluded: list[Exclusion]) -> AuctionState:
    """``p.agent`` gave ``p.task`` up: the task's attempt (:meth:`AuctionState.give_up`), and,
    when that makes ``config.exclude_after`` different tasks in a row, the agent out of the
    auction (appended to ``excluded``) — unless no other agent bids, where it stays to try the
    tasks until they fail for good. A give-up of a task the agent no longer holds (taken from
    it while its link was down) changes nothing."""
    t = state.pool.get(p.task)
    if t is None or t.agent != p.agent or t.state.terminal:
        return state
    state = state.give_up(p.task, p.agent, p.time_s, p.reason)
    streak = state.streaks.get(p.agent, ())
    most = state.config.exclude_after
    if not most or len(streak) < most or p.agent in state.excluded:
        return state
    if not any(a != p.agent and a not in state.excluded for a in state.board):
        return state
    excluded.append(Exclusion(p.agent, streak))
    streaks = {a: s for a, s in state.streaks.items() if a != p.agent}
    return replace(state, excluded=state.excluded | {p.agent}, streaks=streaks)


def apply_progress(
    state: AuctionState,
    reports: Iterable[Progress],
    withdrawn: list[Withdrawal] | None = None,
    excluded: list[Exclusion] | None = None,
) -> tuple[AuctionState, list[str]]:
    """Apply progress reports in order; reports the pool refuses are returned as messages.

    A report from an agent that no longer holds the task — it finished (or passed the commit
    point of) a task that was released or reassigned while its link was down — is accepted when
    it comes first: the task becomes done (committed) with that agent and the other holder is
    appended to ``withdrawn``. A later completion of a task already done is refused (it is
    never counted twice). A give-up hands the task back (:func:`_gave_up`; an agent taken out
    of the auction for its give-ups is appended to ``excluded``); a completion ends the agent's
    streak of give-ups."""
    problems: list[str] = []
    taken: list[Withdrawal] = [] if withdrawn is None else withdrawn
    out: list[Exclusion] = [] if excluded is None else excluded
    for p in reports:
        try:
            if p.event == "committed":
                state = state.commit(p.task, p.agent, p.time_s)
            elif p.event == "done":
                state = state.complete(p.task, p.agent, p.time_s).finished(p.agent)
            elif p.event == "failed":
                state = state.fail(p.task, p.agent, p.time_s, p.reason)
            elif p.event == "gave_up":
                state = _gave_up(state, p, out)
            else:
                problems.append(f"unknown progress event '{p.event}' from {p.agent}")
        except PoolError as exc:
            took = _take_over(state, p, taken)
            if took is not None:
                state = took.finished(p.agent) if p.event == "done" else took
                continue
            t = state.pool.get(p.task)
            if p.event == "done" and t is not None and t.state is TaskState.DONE:
                problems.append(
                    f"{p.agent} reports '{p.task}' done (finished at t={p.time_s:.1f}s), but "
                    f"{t.agent}'s completion (finished at t={t.history[-1].time_s:.1f}s) "
                    f"reached the coordinator first: counted once, for {t.agent}"
                )
            else:
                problems.append(str(exc))
    return state, problems


@dataclass
class Inbox:
    """What arrived since the last round."""

    bids: list[Bid] = field(default_factory=list)
    progress: list[Progress] = field(default_factory=list)
    late_bids: int = 0
    """Bids that arrived while no round was collecting them (already left out of ``bids``)."""


@dataclass(frozen=True)
class RoundResult:
    """One round as seen by ``publish``."""

    assignments: dict[str, str | None]
    report: RoundReport
    announcement: Announcement
    state: AuctionState
    step_s: float
    """Wall time of the round (announce, collect, allocate), measured by the loop."""
    progress_problems: tuple[str, ...] = ()
    withdrawn: tuple[Withdrawal, ...] = ()
    """Holders that lost their task this round to another agent's late report."""
    excluded: tuple[Exclusion, ...] = ()
    """Agents taken out of the auction this round for their give-ups (before allocating)."""


Collect = Callable[[Announcement, float], Inbox | Sequence[Bid]]


@dataclass
class LoopStats:
    rounds: int = 0
    missed_slots: int = 0
    step_s: list[float] = field(default_factory=list)


class AuctionLoop:
    """Runs auction rounds at ``state.config.rate_hz`` on ``clock``."""

    def __init__(
        self,
        state: AuctionState,
        clock: Clock,
        collect: Collect,
        publish: Callable[[RoundResult], object] | None = None,
        *,
        rate_hz: float | None = None,
    ):
        self.state = state
        self.clock = clock
        self.collect = collect
        self.publish = publish
        self.rate_hz = rate_hz if rate_hz is not None else state.config.rate_hz
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")
        self.stats = LoopStats()

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    def step(self) -> RoundResult:
        """One round now: announce, collect, allocate, publish."""
        t_start = time.perf_counter()
        now = self.clock.now()
        ann = self.open_round(now)
        got = self.collect(ann, now)
        inbox = got if isinstance(got, Inbox) else Inbox(list(got))
        return self.close_round(inbox, now, ann.serial, t_start)

    def open_round(self, now: float) -> Announcement:
        """Stage 1 of a round whose bids arrive later (a bid window): the announcement to
        publish now. :meth:`close_round` allocates with what arrived."""
        self.state = announce(self.state, now)
        return self.state.announcement

    def close_round(
        self, inbox: Inbox, now: float, serial: int, t_start: float | None = None
    ) -> RoundResult:
        """Stages 2-3: apply the progress reports, then allocate with the bids that answer the
        announcement of ``serial`` (bids for an older one are stale: ignored and counted), and
        publish. ``t_start`` (``time.perf_counter()``) is when the round's work began."""
        t0 = time.perf_counter() if t_start is None else t_start
        fresh = [b for b in inbox.bids if b.serial is None or b.serial >= serial]
        withdrawn: list[Withdrawal] = []
        excluded: list[Exclusion] = []
        state, problems = apply_progress(self.state, inbox.progress, withdrawn, excluded)
        assignments, state, report = auction_round(state, fresh, now)
        stale = len(inbox.bids) - len(fresh)
        if stale or inbox.late_bids:
            report = replace(report, stale_bids=stale, late_bids=inbox.late_bids)
        step_s = time.perf_counter() - t0
        self.state = state
        self.stats.rounds += 1
        self.stats.step_s.append(step_s)
        result = RoundResult(
            assignments,
            report,
            state.announcement,
            state,
            step_s,
            tuple(problems),
            tuple(withdrawn),
            tuple(excluded),
        )
        if self.publish is not None:
            self.publish(result)
        return result

    def run(
        self,
        *,
        rounds: int | None = None,
        until: float | None = None,
        stop: Callable[[RoundResult], bool] | None = None,
    ) -> AuctionState:
        """Run rounds on the fixed schedule until ``rounds`` are done, the clock reaches
        ``until``, or ``stop(result)`` is true (at least one of them must be given)."""
        if rounds is None and until is None and stop is None:
            raise ValueError("give rounds, until or stop, or the loop never ends")
        period = self.period_s
        t0 = self.clock.now()
        slot = 0
        done = 0
        while True:
            if until is not None and self.clock.now() > until:
                break
            result = self.step()
            done += 1
            if (rounds is not None and done >= rounds) or (stop is not None and stop(result)):
                break
            slot += 1
            now = self.clock.now()
            due = t0 + slot * period
            if now > due:  # overran: skip to the next free slot
                nxt = math.floor((now - t0) / period) + 1
                self.stats.missed_slots += nxt - slot
                slot = nxt
                due = t0 + slot * period
            if until is not None and due > until:
                break
            self.clock.sleep_until(due)
        return self.state
