"""The fixed-rate auction loop on a simulated clock (seed 003 §IV, §VII-B: 9 Hz)."""

from __future__ import annotations

import pytest

from btmission.allocation.auction import Announcement, AuctionConfig, AuctionState, Bid
from btmission.allocation.loop import (
    AuctionLoop,
    Inbox,
    ManualClock,
    Progress,
    RoundResult,
    WallClock,
    apply_progress,
)
from btmission.allocation.tasks import TaskInfo, TaskPool, TaskState


def make_state(rate_hz: float = 10.0, *tasks: TaskInfo) -> AuctionState:
    return AuctionState(AuctionConfig(rate_hz=rate_hz), TaskPool().add_all(tasks))


def test_rounds_run_on_a_fixed_schedule() -> None:
    clock = ManualClock(2.0)
    seen: list[float] = []

    def collect(ann: Announcement, now: float) -> list[Bid]:
        seen.append(now)
        return []

    loop = AuctionLoop(make_state(9.0), clock, collect)
    loop.run(rounds=5)
    assert seen == pytest.approx([2.0 + k / 9.0 for k in range(5)])
    assert loop.stats.rounds == 5 and loop.stats.missed_slots == 0
    assert loop.state.round == 5 and loop.period_s == pytest.approx(1 / 9)


def test_an_overrun_skips_to_the_next_free_slot_without_drift() -> None:
    clock = ManualClock()
    seen: list[float] = []

    def slow(ann: Announcement, now: float) -> list[Bid]:
        seen.append(now)
        if len(seen) == 2:
            clock.advance(0.25)  # this round takes 2.5 periods
        return []

    loop = AuctionLoop(make_state(10.0), clock, slow)
    loop.run(rounds=4)
    assert seen == pytest.approx([0.0, 0.1, 0.4, 0.5])
    assert loop.stats.missed_slots == 2


def test_a_task_added_mid_mission_is_allocated_within_one_period() -> None:
    """The operator adds T7 at t = 116.03 s; the loop at 10 Hz allocates it at 116.1 s."""
    clock = ManualClock(115.5)
    state = make_state(10.0, TaskInfo("T7", "inspect", {}, arrival_s=116.03))
    published: list[RoundResult] = []

    def collect(ann: Announcement, now: float) -> list[Bid]:
        return [Bid.aligned("R1", now, ann, [1.0] * len(ann))]

    loop = AuctionLoop(state, clock, collect, published.append)
    loop.run(stop=lambda r: r.assignments.get("R1") == "T7")
    assert published[-1].report.time_s == pytest.approx(116.1)
    assert published[-1].report.time_s - 116.03 <= loop.period_s
    assert all(r.assignments["R1"] is None for r in published[:-1])
    assert published[-1].step_s >= 0 and published[-1].announcement.ids == ("T7",)


def test_progress_reports_are_applied_before_the_round() -> None:
    clock = ManualClock()
    tasks = (TaskInfo("T1", "inspect", {}), TaskInfo("T2", "inspect", {}))
    inboxes = [
        Inbox([Bid.of("R1", 0.0, {"T1": 1.0, "T2": 2.0})]),
        Inbox(
            [Bid.of("R1", 0.1, {"T2": 2.0})],
            [
                Progress("R1", "T1", "done", 0.1),
                Progress("R2", "T2", "done", 0.1),
                Progress("R1", "T1", "bogus", 0.1),  # type: ignore[arg-type]
            ],
        ),
    ]
    loop = AuctionLoop(make_state(10.0, *tasks), clock, lambda ann, now: inboxes.pop(0))
    first = loop.step()
    assert first.assignments == {"R1": "T1"}
    clock.advance(0.1)
    second = loop.step()
    assert second.assignments == {"R1": "T2"}
    assert loop.state.pool["T1"].state is TaskState.DONE
    assert len(second.progress_problems) == 2
    assert "cannot complete task 'T2'" in second.progress_problems[0]
    assert "unknown progress event 'bogus'" in second.progress_problems[1]


def test_apply_progress_commit_and_fail() -> None:
    from btmission.allocation.auction import auction_round

    s = make_state(10.0, TaskInfo("P", "pick", {}, multi_stage=True), TaskInfo("Q", "inspect", {}))
    _, s, _ = auction_round(s, [Bid.of("A", 0, {"P": 1.0}), Bid.of("B", 0, {"Q": 1.0})], 0.0)
    s, problems = apply_progress(
        s,
        [
            Progress("A", "P", "committed", 1.0),
            Progress("B", "Q", "failed", 1.0, "blocked tunnel"),
        ],
    )
    assert problems == []
    assert s.pool["P"].state is TaskState.COMMITTED
    assert s.pool["Q"].state is TaskState.FAILED and s.pool["Q"].note == "blocked tunnel"


def test_until_and_argument_checks() -> None:
    clock = ManualClock()
    loop = AuctionLoop(make_state(4.0), clock, lambda ann, now: Inbox())
    loop.run(until=1.0)
    assert loop.stats.rounds == 5  # t = 0, 0.25, 0.5, 0.75, 1.0
    with pytest.raises(ValueError, match="never ends"):
        loop.run()
    with pytest.raises(ValueError, match="rate_hz"):
        AuctionLoop(make_state(), clock, lambda ann, now: [], rate_hz=0)


def test_wall_clock_is_monotonic() -> None:
    clock = WallClock()
    t = clock.now()
    clock.sleep_until(t - 1.0)  # in the past: returns at once
    clock.sleep_until(clock.now() + 0.001)
    assert clock.now() >= t + 0.001
