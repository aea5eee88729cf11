"""Give-ups in the auction (issue #36 item 4), as pure functions: a task an agent gives back is
open again with the attempt recorded, fails for good at ``max_attempts`` with every reason; the
agent is cooled down for it (its bid left out, the reason says so); an agent that gives up
``exclude_after`` different tasks in a row is taken out, unless it is the last one bidding."""

from __future__ import annotations

import pytest

from btmission.allocation.auction import AuctionConfig, AuctionState, Bid, auction_round
from btmission.allocation.loop import Exclusion, Progress, apply_progress
from btmission.allocation.tasks import PoolError, TaskInfo, TaskPool, TaskState


def start(*ids: str, max_attempts: int = 3, **cfg: object) -> AuctionState:
    infos = [TaskInfo(t, "inspect", {}, max_attempts=max_attempts) for t in ids]
    return AuctionState(AuctionConfig(**cfg), TaskPool().add_all(infos))  # type: ignore[arg-type]


def rnd(s: AuctionState, now: float, **bids: dict[str, float]) -> AuctionState:
    _, s, _ = auction_round(s, [Bid.of(a, now, c) for a, c in bids.items()], now)
    return s


def gave_up(
    s: AuctionState, agent: str, task: str, now: float, why: str = "arm: refused"
) -> tuple[AuctionState, list[Exclusion]]:
    out: list[Exclusion] = []
    s, problems = apply_progress(s, [Progress(agent, task, "gave_up", now, why)], None, out)
    assert problems == []
    return s, out


def test_a_task_given_up_is_open_again_and_fails_for_good_at_max_attempts() -> None:
    pool = TaskPool().add(TaskInfo("T1", "inspect", {}, max_attempts=2))
    pool = pool.assign("T1", "R1", 1.0, "won").give_up("T1", "R1", 5.0, "arm: PreArm: no GPS")
    t = pool["T1"]
    assert (t.state, t.agent) == (TaskState.OPEN, None)
    assert t.note == "R1 gave up (attempt 1 of 2): arm: PreArm: no GPS"
    assert [(a.agent, a.time_s, a.reason, a.gave_up) for a in t.attempts] == [
        ("R1", 5.0, "arm: PreArm: no GPS", True)
    ]
    pool = pool.assign("T1", "R2", 6.0, "won").give_up("T1", "R2", 9.0, "set_offboard: denied")
    t = pool["T1"]
    assert (t.state, t.agent) == (TaskState.FAILED, "R2")
    assert t.note == (
        "failed after 2 attempt(s): R1: arm: PreArm: no GPS; R2: set_offboard: denied"
    )
    with pytest.raises(PoolError, match="cannot give up task 'T1': it is already failed"):
        pool.give_up("T1", "R2", 10.0)


def test_a_failure_is_the_tasks_last_attempt() -> None:
    pool = TaskPool().add(TaskInfo("T1", "inspect", {})).assign("T1", "R1", 0.0, "won")
    t = pool.fail("T1", "R1", 3.0, "update_path: no path")["T1"]
    assert t.state is TaskState.FAILED
    assert [(a.agent, a.gave_up) for a in t.attempts] == [("R1", False)]


def test_max_attempts_below_one_is_refused() -> None:
    with pytest.raises(ValueError, match="max_attempts must be ≥ 1, got 0"):
        TaskInfo("T1", "inspect", {}, max_attempts=0)


def test_the_agent_that_gave_up_is_cooled_down_then_offered_the_task_again() -> None:
    s = rnd(start("T1", cooldown_s=10.0), 0.0, R1={"T1": 1.0}, R2={"T1": 5.0})
    assert s.holders() == {"R1": "T1"}
    s, _ = gave_up(s, "R1", "T1", 2.0)
    assert s.cooldown == {("R1", "T1"): 12.0}
    s = rnd(s, 2.1, R1={"T1": 1.0}, R2={"T1": 5.0})
    assert s.holders() == {"R2": "T1"}  # R1 bid less, but is cooling down
    # alone, the task waits for the cool-down to end, saying so
    s = rnd(start("T1", cooldown_s=10.0), 0.0, R1={"T1": 1.0})
    s, _ = gave_up(s, "R1", "T1", 2.0)
    s = rnd(s, 2.1, R1={"T1": 1.0})
    assert s.holders() == {} and s.pool["T1"].note == (
        "cooling down: given up by R1 (until t=12.0s)"
    )
    s = rnd(s, 12.1, R1={"T1": 1.0})
    assert s.holders() == {"R1": "T1"} and s.cooldown == {}  # expired: dropped


def test_a_last_attempt_starts_no_cool_down_and_zero_turns_it_off() -> None:
    s = rnd(start("T1", max_attempts=1), 0.0, R1={"T1": 1.0})
    s, _ = gave_up(s, "R1", "T1", 2.0)
    assert s.pool["T1"].state is TaskState.FAILED and s.cooldown == {}
    s = rnd(start("T1", cooldown_s=0.0), 0.0, R1={"T1": 1.0})
    s, _ = gave_up(s, "R1", "T1", 2.0)
    assert s.cooldown == {} and rnd(s, 2.1, R1={"T1": 1.0}).holders() == {"R1": "T1"}


def test_an_agent_giving_up_different_tasks_in_a_row_is_taken_out() -> None:
    s = start("T1", "T2", "T3", exclude_after=2)
    s = rnd(s, 0.0, R1={"T1": 1.0, "T2": 2.0, "T3": 3.0}, R2={"T1": 9.0, "T2": 9.0, "T3": 9.0})
    s, out = gave_up(s, "R1", "T1", 1.0)
    assert out == [] and s.streaks == {"R1": ("T1",)}
    s = rnd(s, 1.1, R1={"T1": 1.0, "T2": 2.0, "T3": 3.0}, R2={"T1": 9.0, "T2": 9.0, "T3": 9.0})
    held = s.holders()["R1"]
    s, out = gave_up(s, "R1", held, 2.0)
    assert out == [Exclusion("R1", ("T1", held))] and "R1" in s.excluded
    assert out[0].reason.startswith(f"gave up 2 different tasks in a row (T1, {held})")
    assert "R1" not in s.streaks  # a clean slate if the operator includes it again
    s = rnd(s, 2.1, R1={"T1": 1.0, "T2": 2.0, "T3": 3.0}, R2={"T1": 9.0, "T2": 9.0, "T3": 9.0})
    assert "R1" not in s.holders()


def test_the_same_task_twice_and_a_task_done_do_not_make_a_streak() -> None:
    s = rnd(start("T1", "T2", exclude_after=2, cooldown_s=0.0), 0.0, R1={"T1": 1.0}, R2={})
    s, _ = gave_up(s, "R1", "T1", 1.0)
    s = rnd(s, 1.1, R1={"T1": 1.0}, R2={})
    s, out = gave_up(s, "R1", "T1", 2.0)  # the same task again
    assert out == [] and s.streaks == {"R1": ("T1",)}
    s = rnd(s, 2.1, R1={"T2": 1.0}, R2={})
    s, _ = apply_progress(s, [Progress("R1", "T2", "done", 3.0)])
    assert s.streaks == {}


def test_the_last_agent_bidding_stays_in_the_auction() -> None:
    s = rnd(start("T1", "T2", exclude_after=1), 0.0, R1={"T1": 1.0, "T2": 2.0})
    s, out = gave_up(s, "R1", "T1", 1.0)
    assert out == [] and s.excluded == frozenset()


def test_a_give_up_of_a_task_the_agent_no_longer_holds_changes_nothing() -> None:
    s = rnd(start("T1"), 0.0, R2={"T1": 1.0})
    after, out = gave_up(s, "R1", "T1", 1.0)  # (it lost T1 while its link was down)
    assert after.pool["T1"] == s.pool["T1"] and out == [] and after.streaks == {}
