"""The auctioneer's step function and the task pool (seed 003 §IV-V, seed 000 §IV-B)."""

from __future__ import annotations

import math
import random
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btmission.allocation.auction import (
    Announcement,
    AuctionConfig,
    AuctionState,
    Bid,
    _matrix,
    announce,
    auction_round,
    cheapest,
    costs_in_range,
    participation_k,
)
from btmission.allocation.bidder import AgentState
from btmission.allocation.tasks import PoolError, TaskInfo, TaskPool, TaskState
from btmission.missions import load_mission
from btmission.runtime.mission_auction import bidder_for_agent, pool_from_mission

ROOT = Path(__file__).resolve().parents[3]
PICK = ROOT / "missions" / "pick_and_deliver.yaml"
MINE = ROOT / "missions" / "mine_inspection.yaml"


def info(tid: str, **kw: object) -> TaskInfo:
    return TaskInfo(tid, str(kw.pop("type", "inspect")), {}, **kw)  # type: ignore[arg-type]


def state(*tasks: TaskInfo, **cfg: object) -> AuctionState:
    return AuctionState(AuctionConfig(**cfg), TaskPool().add_all(tasks))  # type: ignore[arg-type]


def step(
    s: AuctionState, now: float, **bids: dict[str, float]
) -> tuple[dict[str, str | None], AuctionState, object]:
    return auction_round(s, [Bid.of(a, now, c) for a, c in bids.items()], now)


# --------------------------------------------------------------------------------------------
# The paper's scenarios
# --------------------------------------------------------------------------------------------
def test_fig7_inspection_steals_the_agent_before_the_pick_not_after() -> None:
    """Seed 003 Fig. 7 / scenario 1 with the mission file, the bidder and straight-line costs:
    (a) G1 gets the pick-and-deliver P1; (b) inspection I1 arrives before the pick and G1 switches
    to it; (c) after the pick (commit point, k_bt = 0) inspection I2 arrives and G1 stays."""
    m = load_mission(PICK)
    s = AuctionState(AuctionConfig.from_spec(m.spec.coordination), pool_from_mission(m))
    bidder = bidder_for_agent(m, "G1")

    def rnd(s: AuctionState, agent: AgentState, now: float) -> tuple[str | None, AuctionState]:
        s = announce(s, now)
        a, s, _ = auction_round(s, [bidder.bid(s.announcement, agent, now)], now)
        return a["G1"], s

    got, s = rnd(s, AgentState("G1", (1, 1, 0)), 0.0)  # (a)
    assert got == "P1"
    got, s = rnd(s, AgentState("G1", (3, 1.5, 0), task="P1"), 3.0)  # (b) I1 arrived at t = 3
    assert got == "I1"
    assert s.pool["P1"].state is TaskState.OPEN and "reassigned to I1" in s.pool["P1"].note
    s = s.complete("I1", "G1", 8.0)
    got, s = rnd(s, AgentState("G1", (4, 3, 0)), 8.0)
    assert got == "P1"
    # G1 picks the object: its tree reports the commit point with its bid (k_bt = 0)
    got, s = rnd(s, AgentState("G1", (9, 2, 0), task="P1", committed=True), 20.0)
    assert got == "P1" and s.pool["P1"].state is TaskState.COMMITTED
    got, s = rnd(s, AgentState("G1", (8, 3, 0), task="P1", committed=True), 40.0)  # (c)
    assert got == "P1"
    assert s.pool["I2"].state is TaskState.OPEN
    assert "G1 (committed to P1)" in s.pool["I2"].note
    states = [e.state.value for e in s.pool["P1"].history]
    assert states == ["open", "assigned", "open", "assigned", "committed"]
    # (c) again, but with I2 much cheaper than the rest of P1: still no switch
    got, s = rnd(s, AgentState("G1", (10, 6, 0), task="P1", committed=True), 41.0)
    assert got == "P1"


def test_committed_agent_keeps_its_task_whatever_the_bids() -> None:
    s = state(info("P", type="pick", multi_stage=True), info("Q"))
    _, s, _ = step(s, 0.0, A={"P": 5.0}, B={"Q": 5.0})
    s = s.commit("P", "A", 1.0)
    # B bids 0 on P and nothing else; A (committed) bids only 0 on P (k_bt = 0)
    a, s, r = auction_round(
        s, [Bid.of("A", 2.0, {"P": 0.0}), Bid.of("B", 2.0, {"P": 0.0, "Q": 9.0})], 2.0
    )
    assert a == {"A": "P", "B": "Q"} and r.committed == ("A",)
    # even a committed agent that bids on other tasks cannot be moved
    a, s, _ = auction_round(s, [Bid.of("A", 3.0, {"Q": 0.0}), Bid.of("B", 3.0, {"P": 0.0})], 3.0)
    assert a == {"A": "P", "B": None}
    assert s.pool["P"].state is TaskState.COMMITTED and s.pool["P"].agent == "A"


def test_priority_task_takes_an_agent_from_a_cheaper_one() -> None:
    """Seed 003 scenario 3: all agents busy; a high-priority task arrives and an agent is
    reallocated to it although its bid is higher; with priority_scale 0 nothing moves."""
    for scale, moved in ((1000.0, True), (0.0, False)):
        s = state(info("T1"), info("T2"), info("H", priority=2.0, arrival_s=5.0))
        s = replace_cfg(s, priority_scale=scale)
        a, s, _ = step(s, 0.0, R1={"T1": 10.0, "T2": 30.0}, R2={"T1": 30.0, "T2": 10.0})
        assert a == {"R1": "T1", "R2": "T2"}
        bids = {"R1": {"T1": 9.0, "T2": 30.0, "H": 50.0}, "R2": {"T1": 30.0, "T2": 9.0, "H": 80.0}}
        a, s, r = step(s, 5.0, **bids)
        if moved:
            assert a["R1"] == "H" and a["R2"] == "T2"
            assert (
                s.pool["T1"].state is TaskState.OPEN and "R1 reassigned to H" in s.pool["T1"].note
            )
            assert r.unassigned == {"T1": "outbid: its 2 bidder(s) won other tasks"}
        else:
            assert a == {"R1": "T1", "R2": "T2"} and "H" in r.unassigned


def replace_cfg(s: AuctionState, **kw: object) -> AuctionState:
    from dataclasses import replace

    return replace(s, config=replace(s.config, **kw))  # type: ignore[arg-type]


def test_new_task_is_assigned_in_the_first_round_after_it_arrives() -> None:
    """Seed 000: T7, added at t = 116 s, is announced and allocated at the first round ≥ 116 s."""
    m = load_mission(MINE)
    s = AuctionState(AuctionConfig.from_spec(m.spec.coordination), pool_from_mission(m))
    bidders = {a.id: bidder_for_agent(m, a.id) for a in m.agents}
    where = {a.id: a.start for a in m.agents}
    location = {t.id: tuple(t.fields["location"]) for t in m.tasks}

    def rnd(s: AuctionState, now: float) -> tuple[dict[str, str | None], AuctionState]:
        s = announce(s, now)
        agents = [AgentState(g, p) for g, p in where.items()]
        a, s, _ = auction_round(s, [bidders[g.id].bid(s.announcement, g, now) for g in agents], now)
        return a, s

    a, s = rnd(s, 0.0)
    assert "T7" not in s.announcement.ids and len(s.announcement) == 6
    assert sorted(t for t in a.values() if t) == ["T1", "T2", "T4"]  # the nearest three
    for now in (50.0, 100.0):  # each agent completes its task and takes the next one
        for g, t in a.items():
            assert t is not None
            s = s.complete(t, g, now)
            where[g] = location[t]  # type: ignore[assignment]
        a, s = rnd(s, now)
    assert set(a.values()) == {None}  # T1-T6 done, T7 not there yet
    a, s = rnd(s, 115.9)
    assert set(a.values()) == {None} and len(s.announcement) == 0
    a, s = rnd(s, 116.0)
    assert list(a.values()).count("T7") == 1 and s.pool["T7"].state is TaskState.ASSIGNED


# --------------------------------------------------------------------------------------------
# Agents that stop reporting, stale and invalid bids
# --------------------------------------------------------------------------------------------
def test_a_silent_holder_keeps_its_task_for_its_lease_then_loses_it() -> None:
    s = state(info("T1"), info("T2"), agent_timeout_s=1.0, lease_s=5.0)
    a, s, _ = step(s, 0.0, A={"T1": 1.0, "T2": 5.0}, B={"T1": 2.0, "T2": 3.0})
    assert a == {"A": "T1", "B": "T2"}
    # A goes silent; its last bid (t = 0) stays valid until the timeout
    for now in (0.5, 1.0):
        a, s, r = step(s, now, B={"T1": 2.0, "T2": 3.0})
        assert a == {"A": "T1", "B": "T2"} and r.dropped == ()
    # past the timeout A is dropped from the auction but keeps T1 (its lease): B, which
    # would take T1 at a lower total, is not offered it
    a, s, r = step(s, 1.1, B={"T1": 2.0, "T2": 3.0})
    assert r.dropped == ("A",) and a == {"B": "T2"} and r.agents == ("B",)
    assert s.pool["T1"].agent == "A" and s.pool["T1"].state is TaskState.ASSIGNED
    assert s.silent == {"A": 0.0}
    for now in (2.0, 3.0, 5.0):  # up to the end of the lease (5 s after its last bid)
        a, s, r = step(s, now, B={"T1": 2.0, "T2": 3.0})
        assert a == {"B": "T2"} and r.dropped == ()
        assert s.pool["T1"].agent == "A" and "T1" not in r.unassigned
    # the lease has run out: T1 goes back to the pool and is re-offered
    a, s, r = step(s, 5.1, B={"T1": 2.0, "T2": 3.0})
    assert a == {"B": "T1"} and s.silent == {}
    hist = [(e.state.value, e.agent, e.reason) for e in s.pool["T1"].history]
    assert ("open", None, "lease of A ran out (no word for 5.1 s)") in hist
    assert s.pool["T1"].agent == "B" and s.pool["T2"].state is TaskState.OPEN
    # A comes back with a fresh bid and takes part again
    a, s, r = step(s, 5.2, A={"T1": 1.0, "T2": 5.0}, B={"T1": 2.0, "T2": 3.0})
    assert a == {"A": "T1", "B": "T2"} and r.agents == ("A", "B")


def test_a_silent_holder_heard_again_within_its_lease_keeps_its_task() -> None:
    s = state(info("T1"), info("T2"), agent_timeout_s=1.0, lease_s=5.0)
    _, s, _ = step(s, 0.0, A={"T1": 1.0, "T2": 5.0}, B={"T1": 2.0, "T2": 3.0})
    for now in (1.5, 3.0):
        _, s, _ = step(s, now, B={"T1": 2.0, "T2": 3.0})
    a, s, _ = step(s, 4.0, A={"T1": 1.0, "T2": 5.0}, B={"T1": 2.0, "T2": 3.0})
    assert a == {"A": "T1", "B": "T2"} and s.silent == {}
    assert [e.agent for e in s.pool["T1"].history if e.agent is not None] == ["A"]
    # a new silence starts a new lease (from the bid at t = 4)
    for now in (6.0, 9.0):
        a, s, _ = step(s, now, B={"T1": 2.0, "T2": 3.0})
        assert s.pool["T1"].agent == "A"
    a, s, _ = step(s, 9.1, B={"T1": 2.0, "T2": 3.0})
    assert a == {"B": "T1"}


def test_a_silent_agent_without_a_task_gets_nothing_new() -> None:
    s = state(info("T1"), agent_timeout_s=1.0, lease_s=5.0)
    _, s, _ = step(s, 0.0, A={"T1": 9.0}, B={"T1": 1.0})
    assert s.pool["T1"].agent == "B"
    s = s.complete("T1", "B", 0.5).add_task(info("T2"), 1.0)
    a, s, r = step(s, 1.5, B={})  # A silent (last bid at t = 0): T2 is not for it
    assert r.dropped == ("A",) and a == {"B": None} and s.silent == {}
    assert s.pool["T2"].state is TaskState.OPEN


def test_a_late_completion_within_the_lease_is_the_only_one() -> None:
    s = state(info("T1"), agent_timeout_s=1.0, lease_s=5.0)
    _, s, _ = step(s, 0.0, A={"T1": 1.0}, B={"T1": 2.0})
    for now in (1.5, 3.0):  # A cut off: B bids, T1 stays A's
        a, s, _ = step(s, now, B={"T1": 2.0})
        assert a == {"B": None}
    s = s.complete("T1", "A", 2.5)  # its report, made at 2.5 s, arrives with the link
    a, s, _ = step(s, 4.0, A={}, B={})
    assert s.pool["T1"].state is TaskState.DONE and s.pool["T1"].agent == "A"
    assert all(e.agent in (None, "A") for e in s.pool["T1"].history) and s.silent == {}


def test_stale_committed_agent_keeps_its_task_for_its_lease() -> None:
    s = state(info("P", multi_stage=True), agent_timeout_s=1.0, lease_s=4.0)
    _, s, _ = step(s, 0.0, A={"P": 3.0})
    s = s.commit("P", "A", 0.5)
    a, s, r = step(s, 2.0, B={"P": 7.0})
    assert r.dropped == ("A",) and a == {"B": None}
    assert s.pool["P"].state is TaskState.COMMITTED and s.pool["P"].agent == "A"
    a, s, r = step(s, 4.5, B={"P": 7.0})
    assert a == {"B": "P"} and s.pool["P"].state is TaskState.ASSIGNED


def test_invalid_and_out_of_order_bids_are_ignored_with_reasons() -> None:
    s = state(info("T1"))
    bad = [
        Bid.of("A", 0.0, {"T1": -1.0}),
        Bid("B", 0.0, ("T1",), np.array([1.0, 2.0])),
        Bid.of("", 0.0, {"T1": 1.0}),
        Bid.of("C", math.nan, {"T1": 1.0}),
    ]
    a, s, r = auction_round(s, bad, 0.0)
    assert a == {}
    assert len(r.ignored) == 4
    assert "cost -1 for task 'T1' is out of range" in r.ignored[0]
    assert "(2,) costs for 1 task(s)" in r.ignored[1]
    a, s, r = auction_round(s, [Bid.of("A", 5.0, {"T1": 1.0}), Bid.of("A", 4.0, {"T1": 0.5})], 5.0)
    assert a == {"A": "T1"} and "older than its last one" in r.ignored[0]
    assert s.board["A"].time_s == 5.0


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.floats(-10, 10),
            st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0]),
            st.floats(0.5e12, 2e13),
        ),
        max_size=6,
    )
)
def test_a_bid_is_refused_exactly_when_a_cost_is_out_of_range(costs: list[float]) -> None:
    """Bid.problem's quick test (three reductions) refuses what the definition refuses: a cost
    below 0 (−inf too) or a finite one above MAX_COST; NaN (no bid) and inf (unreachable) pass;
    the message names the first bad one."""
    from btmission.allocation.solvers import MAX_COST

    tasks = tuple(f"T{i}" for i in range(len(costs)))
    bad = [i for i, c in enumerate(costs) if c < 0 or (math.isfinite(c) and c > MAX_COST)]
    own = np.array(costs, dtype=float)  # (the compiled check)
    strided = np.repeat(own, 2)[::2]  # (not contiguous: numpy's)
    for array in (own, strided):
        problem = Bid("A", 0.0, tasks, array).problem()
        if not bad:
            assert problem is None
        else:
            assert problem is not None and f"for task 'T{bad[0]}' is out of range" in problem


COSTS = st.one_of(
    st.floats(0, 10),
    st.sampled_from([math.nan, math.inf, 0.0, -0.0]),
    st.floats(-10, -1e-300),
    st.floats(0.5e12, 2e13),
)


@st.composite
def bid_lists(draw: st.DrawFn) -> list[Bid]:
    """Bids of one round: mostly in range, some with a bad cost, some whose costs do not fit
    their tasks, some not float64 (ints), some not contiguous."""
    bids = []
    for a in range(draw(st.integers(0, 6))):
        n = draw(st.integers(0, 5))
        costs = np.array(draw(st.lists(COSTS, min_size=n, max_size=n)), dtype=np.float64)
        if draw(st.booleans()):  # most bids are in range
            costs[~((costs >= 0) & ((costs <= 1e12) | np.isinf(costs)) | np.isnan(costs))] = 1.0
        kind = draw(st.sampled_from(["own", "own", "strided", "ints", "short", "2d"]))
        if kind == "strided":
            costs = np.repeat(costs, 2)[::2]
        elif kind == "ints":
            costs = np.nan_to_num(costs, posinf=1.0, neginf=-1.0).astype(np.int64)
        elif kind == "2d":
            costs = costs[None, :]
        tasks = tuple(f"T{i}" for i in range(n + (kind == "short")))
        bids.append(Bid(f"A{a}", 0.0, tasks, costs))
    return bids


@settings(max_examples=300, deadline=None)
@given(bid_lists())
def test_the_rounds_range_check_of_all_bids_at_once_is_each_bids(bids: list[Bid]) -> None:
    """costs_in_range (one compiled pass over every bid) says a round may skip each bid's range
    check only when no bid of the round fails it; and it says so whenever every bid's costs are
    1-D float64 and in range."""
    each = [b.problem() for b in bids]
    if costs_in_range(bids):
        assert each == [b._form_problem() for b in bids]
    in_range = all(b._cost_problem() is None for b in bids if b.costs.ndim == 1)
    if in_range and all(b.costs.dtype == np.float64 and b.costs.ndim == 1 for b in bids):
        assert costs_in_range(bids)


def test_a_bad_cost_is_refused_when_the_round_checks_all_bids_at_once() -> None:
    s = state(info("T1"), info("T2"))
    _, s, r = auction_round(
        s,
        [
            Bid.of("A", 1.0, {"T1": 1.0, "T2": 2.0}),
            Bid.of("B", 1.0, {"T1": 1.0, "T2": -2.0}),  # out of range: the one pass sees it
            Bid.of("C", 1.0, {"T1": 3.0, "T2": 1.0}),
        ],
        1.0,
    )
    assert r.agents == ("A", "C") and len(r.ignored) == 1
    assert "cost -2 for task 'T2' is out of range" in r.ignored[0]


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 5), st.integers(0, 6), st.randoms(use_true_random=False))
def test_the_matrix_of_bids_on_this_announcement_is_the_general_one(
    na: int, nt: int, rnd: random.Random
) -> None:
    """Bids that answer the round's announcement (their tasks are its ids) are stacked in one
    array; the general path, which maps each bid's tasks onto the announcement, gives the same
    matrix (a bid with an equal but not identical task tuple takes it)."""
    ann = Announcement(1, 0.0, tuple(info(f"T{j}") for j in range(nt)))
    board: dict[str, Bid] = {}
    for a in range(na):
        costs = [rnd.choice([math.nan, math.inf, rnd.random() * 10]) for _ in range(nt)]
        board[f"A{a}"] = Bid.aligned(f"A{a}", 0.0, ann, costs)
    agents = sorted(board)
    fast, covered = _matrix(ann, agents, board)
    copied = {a: Bid(a, 0.0, tuple(list(ann.ids)), b.costs) for a, b in board.items()}
    slow, covered_slow = _matrix(ann, agents, copied)
    assert fast.shape == slow.shape == (na, nt) and fast.dtype == slow.dtype == np.float64
    np.testing.assert_array_equal(fast, slow)
    np.testing.assert_array_equal(covered, covered_slow)
    assert covered.all()


def test_commit_reports_that_do_not_fit_are_ignored() -> None:
    s = state(info("T1"), info("T2"))
    _, s, _ = step(s, 0.0, A={"T1": 1.0}, B={"T2": 1.0})
    _, s, r = auction_round(
        s,
        [
            Bid.of("A", 1.0, {"T1": 0.0}, committed_to="T1"),  # single-stage: no commit point
            Bid.of("B", 1.0, {"T2": 1.0}, committed_to="T1"),  # not its task
        ],
        1.0,
    )
    assert any("which has none" in m for m in r.ignored)
    assert any("which it does not hold" in m for m in r.ignored)
    assert s.pool["T1"].state is TaskState.ASSIGNED


# --------------------------------------------------------------------------------------------
# Reasons, unreachable tasks, participation, announcements
# --------------------------------------------------------------------------------------------
def test_unassigned_tasks_carry_the_reason() -> None:
    s = state(info("T1"), info("T2"), info("T3"))
    a, s, r = auction_round(s, [], 0.0)
    assert r.unassigned["T1"] == "no agents are bidding" and r.method == "none"
    a, s, r = step(s, 1.0, A={"T1": 1.0, "T2": math.inf}, B={"T1": 2.0, "T2": math.inf})
    assert a == {"A": "T1", "B": None}
    assert r.unassigned["T2"] == "unreachable: no path from A, B"
    assert s.pool["T2"].state is TaskState.UNREACHABLE
    assert r.unassigned["T3"] == "awaiting bids (newly announced)"
    # a later bid that can reach T2 picks it up: unreachable tasks stay announced
    a, s, r = step(s, 2.0, A={"T1": 1.0, "T2": math.inf}, B={"T1": 2.0, "T2": 4.0})
    assert a == {"A": "T1", "B": "T2"}
    assert [e.state.value for e in s.pool["T2"].history] == ["open", "unreachable", "assigned"]


def test_a_reason_names_three_agents_and_counts_the_others() -> None:
    """A task nobody can reach, or every bidder declined, names the first three agents (by id)
    and counts the rest; a committed one says what it is committed to."""
    many = {f"A{i}": {"T1": math.inf, "T2": math.nan, "T3": 1.0 + i} for i in range(5)}
    _, _, r = step(state(info("T1"), info("T2"), info("T3")), 1.0, **many)
    assert r.unassigned["T1"] == "unreachable: no path from A0, A1, A2 and 2 more"
    assert r.unassigned["T2"] == "no bids: declined by A0, A1, A2 and 2 more"
    few = {a: c for a, c in many.items() if a in ("A1", "A3")}
    _, _, r = step(state(info("T1"), info("T2"), info("T3")), 1.0, **few)
    assert r.unassigned["T1"] == "unreachable: no path from A1, A3"
    assert r.unassigned["T2"] == "no bids: declined by A1, A3"
    s = state(info("T2"), info("P", type="pick", multi_stage=True))
    a, s, r = step(s, 1.0, A0={"T2": math.nan, "P": 2.0}, A1={"T2": math.nan, "P": 1.0})
    assert a == {"A0": None, "A1": "P"}
    _, s, r = auction_round(
        s,
        [
            Bid.of("A0", 2.0, {"T2": math.nan, "P": 2.0}),
            Bid.of("A1", 2.0, {"T2": math.nan, "P": 0.0}, committed_to="P"),
        ],
        2.0,
    )
    assert r.committed == ("A1",)
    assert r.unassigned["T2"] == "no bids: declined by A0, A1 (committed to P)"


def test_declined_tasks_and_participation_in_the_reason() -> None:
    s = state(*(info(f"T{i}") for i in range(4)), participation=0.5)
    ann = announce(s, 0.0).announcement
    bid = Bid.aligned("A", 0.0, ann, [1.0, np.nan, 3.0, np.nan])
    a, s, r = auction_round(s, [bid], 0.0)
    assert a == {"A": "T0"}
    assert r.unassigned["T1"] == (
        "no bids: declined by A; each agent bids on its 2 cheapest of 4 (participation 0.5)"
    )
    assert r.unassigned["T2"].startswith("outbid")


def test_participation_guard_trims_an_agent_to_its_k_cheapest() -> None:
    s = state(info("T1"), info("T2"), info("T3"), info("T4"), participation=0.5)
    # A bids on all four; only its 2 cheapest (T3, T4) count, so T1 stays free for B
    a, s, r = step(s, 0.0, A={"T1": 1.0, "T2": 9.0, "T3": 0.5, "T4": 0.7})
    assert a == {"A": "T3"} and r.bids == 2
    # its current task is always kept, even when no longer among the k cheapest
    a, s, r = step(s, 1.0, A={"T1": 0.1, "T2": 0.2, "T3": 5.0, "T4": 9.0})
    assert r.bids == 3
    assert participation_k(0.3, 400) == 120 and participation_k(0.01, 10) == 1
    assert participation_k(1.0, 0) == 0
    keep = cheapest(np.array([3.0, 1.0, np.nan, np.inf, 1.0]), 2, keep=0)
    assert keep.tolist() == [True, True, False, True, True]


def test_bids_on_an_older_announcement_are_remapped() -> None:
    s = state(info("T1"), info("T2", arrival_s=1.0), info("T3"))
    s = announce(s, 0.0)
    old = s.announcement
    assert old.ids == ("T1", "T3") and old.serial == 1
    assert announce(s, 0.5).announcement is old  # unchanged set: same announcement
    bid = Bid.aligned("A", 0.9, old, [5.0, 1.0])
    a, s, r = auction_round(s, [bid], 1.0)  # T2 arrived: new announcement
    assert s.announcement.ids == ("T1", "T3", "T2") and r.serial == 2
    assert a == {"A": "T3"}
    assert r.unassigned["T2"] == "awaiting bids (newly announced)"
    assert r.unassigned["T1"].startswith("outbid")


def test_round_is_pure_and_deterministic() -> None:
    s = state(info("T1"), info("T2"), info("T3"))
    bids = [Bid.of("A", 0.0, {"T1": 1.0, "T2": 1.0}), Bid.of("B", 0.0, {"T1": 1.0, "T2": 1.0})]
    before = (s.pool, s.board, s.round)
    first = auction_round(s, bids, 0.0)
    assert (s.pool, s.board, s.round) == before
    for _ in range(3):
        again = auction_round(s, bids, 0.0)
        assert again[0] == first[0] and again[2] == first[2]
    # order of bids does not matter
    assert auction_round(s, bids[::-1], 0.0)[0] == first[0]


def test_both_solvers_give_the_same_allocation() -> None:
    rng = np.random.default_rng(2)
    tasks = [info(f"T{j:02d}", priority=float(rng.choice([1.0, 2.0]))) for j in range(30)]
    bids = {}
    for i in range(8):
        costs = rng.uniform(0, 100, 30)
        costs[rng.random(30) < 0.4] = np.nan
        bids[f"R{i}"] = {t.id: c for t, c in zip(tasks, costs) if not math.isnan(c)}
    out = {}
    for solver in ("assignment", "ilp-scip", "dense", "sparse", "pruned"):
        s = state(*tasks, solver=solver)
        a, _, r = step(s, 0.0, **bids)
        out[solver] = (a, round(r.total_cost, 6))
        if solver == "pruned":  # (it hands a problem it cannot prove to dense)
            assert r.method in ("pruned", "dense")
        else:
            assert r.method == {"assignment": "dense"}.get(solver, solver)
    assert len({repr(v) for v in out.values()}) == 1


@st.composite
def scripts(draw: st.DrawFn) -> list[tuple[str, object]]:
    """Random sequences of rounds with random bids, commits and completions."""
    events: list[tuple[str, object]] = []
    for _ in range(draw(st.integers(1, 8))):
        kind = draw(st.sampled_from(["round", "round", "round", "commit", "done"]))
        if kind == "round":
            bids = {}
            for a in draw(st.lists(st.sampled_from("ABCD"), unique=True)):
                bids[a] = {
                    t: draw(st.sampled_from([0.0, 1.0, 2.0, 5.0, math.inf]))
                    for t in draw(st.lists(st.sampled_from(["T1", "T2", "T3", "P1", "P2"])))
                }
            events.append(("round", bids))
        else:
            events.append((kind, draw(st.sampled_from("ABCD"))))
    return events


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(script=scripts())
def test_no_task_is_ever_held_twice(script: list[tuple[str, object]]) -> None:
    """Whatever the bids, commits and completions: each agent holds at most one task, each task
    has at most one agent, the published assignment matches the pool (but for silent holders
    within their lease), committed tasks never change agent while their agent is live."""
    s = state(
        info("T1"),
        info("T2"),
        info("T3", arrival_s=2.0),
        info("P1", multi_stage=True),
        info("P2", multi_stage=True, priority=3.0),
        agent_timeout_s=2.5,
    )
    now = 0.0
    for kind, arg in script:
        now += 1.0
        if kind == "round":
            assert isinstance(arg, dict)
            committed = {t.agent: t.id for t in s.pool.in_state(TaskState.COMMITTED)}
            a, s, r = step(s, now, **arg)
            held = [t for t in s.pool if t.state in (TaskState.ASSIGNED, TaskState.COMMITTED)]
            agents = [t.agent for t in held]
            assert len(agents) == len(set(agents))
            live = {t.agent: t.id for t in held if t.agent not in s.silent}
            assert {k: v for k, v in a.items() if v} == live
            assert r.assignments == live
            for ag, last in s.silent.items():  # a silent holder: within its lease, no new task
                assert ag not in a and ag in agents and now - last <= 30.0
            for ag, tid in committed.items():
                if ag in r.agents:
                    assert a[ag] == tid
            for t in s.pool:
                if t.state is TaskState.OPEN or t.state is TaskState.UNREACHABLE:
                    assert t.agent is None
        else:
            held_task = s.holders().get(str(arg))
            if held_task is None:
                continue
            if kind == "commit" and s.pool[held_task].info.multi_stage:
                s = s.commit(held_task, str(arg), now)
            elif kind == "done":
                s = s.complete(held_task, str(arg), now)


# --------------------------------------------------------------------------------------------
# Config and pool
# --------------------------------------------------------------------------------------------
def test_config_from_the_mission_and_validation() -> None:
    m = load_mission(PICK)
    cfg = AuctionConfig.from_spec(m.spec.coordination)
    assert (cfg.rate_hz, cfg.participation, cfg.solver, cfg.method) == (
        9.0,
        1.0,
        "assignment",
        "auto",
    )
    assert AuctionConfig(solver="ilp-scip").method == "ilp-scip"
    for kw, msg in [
        ({"participation": 0.0}, "participation"),
        ({"participation": 1.5}, "participation"),
        ({"priority_scale": -1.0}, "priority_scale"),
        ({"solver": "greedy"}, "unknown solver 'greedy'"),
        ({"agent_timeout_s": 0.0}, "agent_timeout_s"),
        ({"rate_hz": 0.0}, "rate_hz"),
    ]:
        with pytest.raises(ValueError, match=msg):
            AuctionConfig(**kw)  # type: ignore[arg-type]


def test_pool_from_mission_and_task_model() -> None:
    pool = pool_from_mission(load_mission(PICK))
    assert [t.id for t in pool] == ["P1", "I1", "I2"]
    p1 = pool["P1"].info
    assert p1.multi_stage and p1.fields["pickup"] == [9, 2, 0] and p1.priority == 1.0
    assert not pool["I1"].info.multi_stage and pool["I1"].info.arrival_s == 3.0
    assert [t.id for t in pool.announced(3.0)] == ["P1", "I1"]
    assert pool.next_arrival(3.0) == 40.0 and pool.next_arrival(40.0) is None
    assert str(pool["I1"].history[0]) == "t=3.00s open (added)"
    assert len(pool) == 3 and "P1" in pool and pool.get("X") is None


def test_pool_refuses_impossible_transitions() -> None:
    pool = TaskPool().add_all([info("T"), info("P", multi_stage=True)])
    with pytest.raises(PoolError, match="duplicate task id 'T'"):
        pool.add(info("T"))
    with pytest.raises(PoolError, match="unknown task 'X'"):
        pool["X"]
    with pytest.raises(PoolError, match="cannot complete task 'T': it is not assigned"):
        pool.complete("T", "A", 1.0)
    s = state(info("T"), info("P", multi_stage=True))
    _, s, _ = step(s, 0.0, A={"T": 1.0}, B={"P": 1.0})
    pool = s.pool
    with pytest.raises(PoolError, match="agent 'B' cannot complete task 'T': it is held by A"):
        pool.complete("T", "B", 1.0)
    with pytest.raises(PoolError, match="has no commit point"):
        pool.commit("T", "A", 1.0)
    assert pool.held_by("A") is pool["T"] and pool.held_by("C") is None
    pool = pool.commit("P", "B", 1.0)
    assert pool.commit("P", "B", 2.0) is pool  # already committed
    assert pool.held_by("B") is pool["P"]
    pool = pool.fail("P", "B", 3.0, "gripper jammed")
    assert pool["P"].state is TaskState.FAILED and pool["P"].note == "gripper jammed"
    with pytest.raises(PoolError, match="already failed"):
        pool.release("P", 4.0, "x")
    with pytest.raises(PoolError, match="cannot complete task 'P': it is already failed"):
        pool.complete("P", "B", 4.0)
    pool = pool.release("T", 5.0, "operator")
    assert pool["T"].state is TaskState.OPEN and pool["T"].agent is None


@pytest.mark.parametrize(
    ("kw", "msg"),
    [
        ({"priority": 0.0}, "priority must be > 0"),
        ({"priority": math.nan}, "priority must be > 0"),
        ({"arrival_s": -1.0}, "arrival time must be ≥ 0"),
    ],
)
def test_bad_task_info(kw: dict[str, float], msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        TaskInfo("T", "inspect", {}, **kw)
    with pytest.raises(ValueError, match="needs an id"):
        TaskInfo("", "inspect", {})
