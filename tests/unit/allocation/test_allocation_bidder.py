"""Agent-side bids: cost expressions, k_bt (seed 003 eq. 8-10), participation, providers."""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from btmission.allocation.auction import Announcement
from btmission.allocation.bidder import (
    AgentState,
    Bidder,
    BidError,
    CostProvider,
    Point,
    StraightLine,
    bids_for,
    k_bt,
)
from btmission.allocation.tasks import TaskInfo
from btmission.missions import load_mission, load_mission_text
from btmission.runtime.mission_auction import bidder_for_agent, task_info

ROOT = Path(__file__).resolve().parents[3]
PICK = ROOT / "missions" / "pick_and_deliver.yaml"


def announcement(*tasks: TaskInfo) -> Announcement:
    return Announcement(1, 0.0, tasks)


P1 = TaskInfo("P1", "pick_and_deliver", {"pickup": [9, 2, 0], "dropoff": [2, 7, 0]}, 1, 0, True)
I1 = TaskInfo("I1", "inspect", {"location": [4, 3, 0]})
I2 = TaskInfo("I2", "inspect", {"location": [10, 6, 0]})


@dataclass
class CountingProvider:
    """A provider that records its queries and makes a wall at x = 50 impassable."""

    calls: list[tuple[Point, Point]] = field(default_factory=list)

    def path_cost(self, start: Point, goal: Point) -> float:
        self.calls.append((start, goal))
        if (start[0] < 50) != (goal[0] < 50):
            return math.inf
        return 2.0 * math.dist(start, goal)


def test_costs_follow_eq_9_and_10() -> None:
    m = load_mission(PICK)
    b = bidder_for_agent(m, "G1")
    ann = announcement(P1, I1)
    at = (1.0, 1.0, 0.0)
    c = b.costs(ann, AgentState("G1", at))
    gamma2 = math.dist(at, (9, 2, 0)) + math.dist((9, 2, 0), (2, 7, 0))
    assert c.tolist() == pytest.approx([gamma2, math.dist(at, (4, 3, 0))])
    bid = b.bid(ann, AgentState("G1", at), 2.5)
    assert bid.tasks is ann.ids and bid.time_s == 2.5 and bid.committed_to is None
    assert bid.cost_of("I1") == pytest.approx(math.dist(at, (4, 3, 0)))
    assert math.isnan(bid.cost_of("nope"))


def test_k_bt_zero_after_the_commit_point() -> None:
    """Once the pick is done the agent bids 0 on its task (eq. 8 with k_bt = 0) and nothing
    else, and says so in the bid."""
    m = load_mission(PICK)
    b = bidder_for_agent(m, "G1")
    ann = announcement(P1, I1, I2)
    busy = AgentState("G1", (9, 2, 0), task="P1", committed=True)
    assert k_bt(busy, "P1") == 0.0 and k_bt(busy, "I1") == 1.0
    assert k_bt(AgentState("G1", (0, 0, 0), task="P1"), "P1") == 1.0
    c = b.costs(ann, busy)
    assert c[0] == 0.0 and np.isnan(c[1:]).all()
    assert b.bid(ann, busy, 1.0).committed_to == "P1"
    # a committed agent whose task is no longer announced bids on nothing
    assert np.isnan(b.costs(announcement(I1), busy)).all()


def test_switch_cost_is_added_to_other_tasks_only_while_busy() -> None:
    m = load_mission(PICK)
    ann = announcement(P1, I1, I2)
    at = (1.0, 1.0, 0.0)
    plain = Bidder(m.task_types).costs(ann, AgentState("G1", at, task="I1"))
    sticky = Bidder(m.task_types, switch_cost=5.0)
    np.testing.assert_allclose(
        sticky.costs(ann, AgentState("G1", at, task="I1")), plain + np.array([5.0, 0.0, 5.0])
    )
    np.testing.assert_allclose(sticky.costs(ann, AgentState("G1", at)), plain)  # idle: no cost
    with pytest.raises(ValueError, match="switch_cost"):
        Bidder(m.task_types, switch_cost=-1.0)


@dataclass
class BatchProvider:
    """Answers single queries and batches; counts the batches."""

    batches: int = 0

    def path_cost(self, start: Point, goal: Point) -> float:
        return 1.5 * math.dist(start, goal) + 1.0

    def path_costs(self, start: Point, goals: list[Point]) -> np.ndarray:
        self.batches += 1
        return np.array([self.path_cost(start, g) for g in goals])


def test_a_batch_provider_gives_the_same_bids() -> None:
    """Types whose cost is exactly path_cost(field) go through path_costs in one call per
    type; the others are evaluated task by task; the bids are the same either way."""
    m = load_mission(PICK)
    tasks = [P1, I1, I2, TaskInfo("I3", "inspect", {"location": [7, 7, 0]})]
    ann = announcement(*tasks)

    class Single:
        def path_cost(self, start: Point, goal: Point) -> float:
            return BatchProvider().path_cost(start, goal)

    batch = BatchProvider()
    for state in (AgentState("G1", (1.0, 2.0, 0.0)), AgentState("G1", (1.0, 2.0, 0.0), "I2")):
        a = Bidder(m.task_types, Single(), switch_cost=2.0).costs(ann, state)
        b = Bidder(m.task_types, batch, switch_cost=2.0).costs(ann, state)
        np.testing.assert_allclose(a, b)
    assert batch.batches == 2  # one call per round for the three inspections


class KeepsItsRow(BatchProvider):
    """A batch provider that hands out the same array every call (its own memory)."""

    def __init__(self) -> None:
        super().__init__()
        self.row: np.ndarray | None = None

    def path_costs(self, start: Point, goals: list[Point]) -> np.ndarray:
        self.row = super().path_costs(start, goals)
        return self.row


def test_a_batch_of_every_task_is_the_bid_row_and_stays_the_providers() -> None:
    """When one path_costs batch covers every announced task, its answer is the bid row (no
    row to fill): the same bids as task by task, with the switch cost and participation, and
    the provider's array is not changed (the bidder works on a copy)."""
    m = load_mission(PICK)
    rng = np.random.default_rng(3)
    tasks = [
        TaskInfo(f"I{i}", "inspect", {"location": [float(x) for x in rng.uniform(0, 20, 3)]})
        for i in range(9)
    ]
    ann = announcement(*tasks)

    class Single:
        def path_cost(self, start: Point, goal: Point) -> float:
            return BatchProvider().path_cost(start, goal)

    for participation in (1.0, 0.4):
        for state in (AgentState("G1", (1.0, 2.0, 0.0)), AgentState("G1", (3.0, 2.0, 0.0), "I4")):
            kept = KeepsItsRow()
            a = Bidder(m.task_types, Single(), participation, switch_cost=2.0).costs(ann, state)
            b = Bidder(m.task_types, kept, participation, switch_cost=2.0).costs(ann, state)
            np.testing.assert_array_equal(a, b)
            assert kept.batches == 1 and kept.row is not None and b is not kept.row
            np.testing.assert_array_equal(
                kept.row,
                [kept.path_cost(state.position, tuple(t.fields["location"])) for t in tasks],
            )


def test_participation_bids_on_the_k_cheapest_plus_the_current_task() -> None:
    m = load_mission(PICK)
    tasks = [TaskInfo(f"I{i}", "inspect", {"location": [float(i), 0, 0]}) for i in range(10)]
    ann = announcement(*tasks)
    b = Bidder(m.task_types, participation=0.3)
    c = b.costs(ann, AgentState("G1", (0.0, 0.0, 0.0)))
    assert np.flatnonzero(np.isfinite(c)).tolist() == [0, 1, 2]
    c = b.costs(ann, AgentState("G1", (0.0, 0.0, 0.0), task="I8"))
    assert np.flatnonzero(np.isfinite(c)).tolist() == [0, 1, 2, 8]


def test_pluggable_provider_unreachable_and_cache() -> None:
    m = load_mission(PICK)
    prov = CountingProvider()
    assert isinstance(prov, CostProvider) and isinstance(StraightLine(), CostProvider)
    b = Bidder(m.task_types, prov)
    far = TaskInfo("F", "inspect", {"location": [80, 0, 0]})
    ann = announcement(P1, far)
    c = b.costs(ann, AgentState("G1", (1.0, 1.0, 0.0)))
    assert c[0] == pytest.approx(
        2 * (math.dist((1, 1, 0), (9, 2, 0)) + math.dist((9, 2, 0), (2, 7, 0)))
    )
    assert c[1] == math.inf
    n = len(prov.calls)
    b.costs(ann, AgentState("G1", (2.0, 1.0, 0.0)))
    # pickup → dropoff does not depend on the agent: served from the cache the second time
    assert len(prov.calls) == n + 2
    assert ((9.0, 2.0, 0.0), (2.0, 7.0, 0.0)) in prov.calls
    assert prov.calls.count(((9.0, 2.0, 0.0), (2.0, 7.0, 0.0))) == 1


def test_cache_is_bounded() -> None:
    m = load_mission(PICK)
    prov = CountingProvider()
    b = Bidder(m.task_types, prov, cache_size=2)
    tasks = [
        TaskInfo(f"P{i}", "pick_and_deliver", {"pickup": [i, 0, 0], "dropoff": [0, i, 0]})
        for i in range(4)
    ]
    b.costs(announcement(*tasks), AgentState("G1", (0.0, 0.0, 0.0)))
    assert len(b._cache) == 2


def test_task_types_the_agent_cannot_do_get_no_bid() -> None:
    text = textwrap.dedent(
        """
        mission: mixed
        version: 1
        world: {map: {generate: empty, size: [20, 20, 5]}}
        agents:
          - {id: D1, library: aerial, start: [0, 0, 0]}
          - {id: G1, library: ground, start: [1, 0, 0]}
        tasks:
          - {id: I1, type: inspect, location: [5, 5, 1]}
          - {id: P1, type: deliver, pickup: [3, 0, 0], dropoff: [6, 0, 0]}
        task_types:
          inspect: {goal: at_goal(location), cost: path_cost(location)}
          deliver:
            goal: delivered(pickup, dropoff)
            commit_after: holding(pickup)
            cost: path_cost(pickup) + path_cost(pickup, dropoff)
        """
    )
    m = load_mission_text(text, "mixed.yaml")
    drone, rover = bidder_for_agent(m, "D1"), bidder_for_agent(m, "G1")
    assert set(drone.task_types) == {"inspect"} and set(rover.task_types) == {"inspect", "deliver"}
    ann = announcement(*(task_info(t, m) for t in m.tasks))
    agents = [AgentState("D1", (0.0, 0.0, 0.0)), AgentState("G1", (1.0, 0.0, 0.0))]
    d, g = bids_for({"D1": drone, "G1": rover}, agents, ann, 0.0)
    assert math.isnan(d.cost_of("P1")) and d.cost_of("I1") > 0
    assert g.cost_of("P1") == pytest.approx(2.0 + 3.0)
    assert set(bidder_for_agent(m, "G1", types=["deliver"]).task_types) == {"deliver"}


def test_distance_function_and_constants() -> None:
    m = load_mission(PICK)
    from btmission.spec.costexpr import parse_cost
    from btmission.spec.mission import TaskType

    tt = TaskType(
        "t", (), parse_cost("2 * distance(location) + distance(location, base) - 1"), None, 1.0, ()
    )
    b = Bidder({**m.task_types, "t": tt})
    task = TaskInfo("X", "t", {"location": [3, 4, 0], "base": [3, 0, 0]})
    assert b.f_cost(task, AgentState("A", (0.0, 0.0, 0.0))) == pytest.approx(2 * 5 + 4 - 1)


def test_bad_task_fields_are_reported() -> None:
    m = load_mission(PICK)
    b = Bidder(m.task_types)
    a = AgentState("G1", (0.0, 0.0, 0.0))
    with pytest.raises(BidError, match=r"task 'X' \(inspect\): cost functions need positions"):
        b.f_cost(TaskInfo("X", "inspect", {"location": "bay3"}), a)
    with pytest.raises(BidError, match="task 'Y' \\(inspect\\) has no field 'location'"):
        b.f_cost(TaskInfo("Y", "inspect", {}), a)
    from btmission.spec.costexpr import parse_cost
    from btmission.spec.mission import TaskType

    neg = TaskType("n", (), parse_cost("distance(location) - 100"), None, 1.0, ())
    with pytest.raises(BidError, match="bids must be ≥ 0"):
        Bidder({"n": neg}).f_cost(TaskInfo("Z", "n", {"location": [1, 0, 0]}), a)
    with pytest.raises(ValueError, match="participation"):
        Bidder(m.task_types, participation=0.0)
