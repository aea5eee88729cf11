"""Repeated bids (issue 19): an agent that has not moved to another voxel and sees the same
announcement sends its previous costs again. Every bid of a running mission — agents moving,
tasks arriving, finishing, re-prioritised and cancelled, rock appearing — must equal the bid
computed from scratch, task by task."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from btmission.allocation.auction import Bid
from btmission.allocation.bidder import AgentState, Bidder, Point
from btmission.allocation.tasks import PoolTask, TaskInfo, TaskPool, TaskState
from btmission.bench.sim import scale_mission_text
from btmission.missions import load_mission_text
from btmission.runtime.paths import PathCosts
from btmission.runtime.runner import MissionRun
from btmission.world.voxel import OCCUPIED, VoxelMap


class OneByOne:
    """The D*+ service seen through ``path_cost`` alone: no batches, no start keys, so a
    bidder on it evaluates every task's cost expression for itself every round."""

    def __init__(self, paths: PathCosts) -> None:
        self.paths = paths

    def path_cost(self, start: Point, goal: Point) -> float:
        return self.paths.path_cost(start, goal)


def mission_text() -> str:
    """The scaling floor, small: 6 ground robots, 30 inspections, two more of another type
    arriving later, a switch cost (bids depend on the task each agent holds)."""
    text = scale_mission_text(6, 30, 0.3, seed=3)
    text = text.replace("  inspect: {goal:", "  late: {goal:").replace(
        "task_types:\n",
        "task_types:\n  inspect: {goal: at_goal(location), cost: path_cost(location)}\n",
    )
    text = text.replace(
        "task_types:",
        "  - {id: L1, type: late, location: [50, 50, 0], at: 2.5}\n"
        "  - {id: L2, type: late, location: [20, 70, 0], at: 5.2}\n"
        "task_types:",
    )
    return text.replace("participation: 0.3}", "participation: 0.3, switch_cost: 2.0}")


def test_every_repeated_bid_equals_the_bid_computed_from_scratch() -> None:
    m = load_mission_text(mission_text(), "bids.yaml")
    run = MissionRun(m)
    checked: list[tuple[float, str]] = []
    changed_by_rock: list[str] = []
    rock_at = 4.0

    def state_of(agent_id: str) -> AgentState:
        agent = run.agents[agent_id]
        p = agent.ctx.telemetry().position
        return AgentState(
            agent.id,
            (float(p[0]), float(p[1]), float(p[2])),
            agent.task.id if agent.task is not None else None,
            agent.committed,
        )

    def from_scratch(agent_id: str) -> np.ndarray:
        b = run.agents[agent_id].bidder
        fresh = Bidder(
            b.task_types, OneByOne(run.paths), b.participation, switch_cost=b.switch_cost
        )
        ann = run.agents[agent_id].last_announcement
        assert ann is not None
        return fresh.costs(ann, state_of(agent_id))

    def rock(run: MissionRun) -> None:
        """An 80 m wall of rock across the floor: some agents' costs change where they stand."""
        vm = run.paths.map
        new = type(vm)(vm.state.copy(), vm.resolution, vm.origin, dict(vm.meta))
        new.state[10:90, 50, :] = OCCUPIED
        before = {a: from_scratch(a) for a in run.agents}
        run.paths.set_map(new)
        for a, costs in before.items():
            if not np.array_equal(costs, from_scratch(a), equal_nan=True):
                changed_by_rock.append(a)

    run.at(rock_at, rock)
    run.at(3.0, lambda run: run.set_priority("T5", 3.0))
    run.at(6.0, lambda run: run.cancel_task("T7"))
    send = run.bus.send_bid

    def spy(bid: Bid) -> None:
        ann = run.agents[bid.agent].last_announcement
        assert ann is not None and bid.serial == ann.serial
        np.testing.assert_array_equal(bid.costs, from_scratch(bid.agent))
        checked.append((run.now(), bid.agent))
        send(bid)

    run.bus.send_bid = spy  # type: ignore[method-assign]
    res = run.run(until=8.0)

    bidders = [a.bidder for a in run.agents.values()]
    repeated = sum(b.repeated for b in bidders)
    assert len(checked) == 6 * 80  # every agent bid in every round, each bid checked
    assert repeated > len(checked) // 2  # most bids were repeats …
    assert repeated < len(checked) - 6  # … not all: agents moved and the tasks changed
    assert res.done  # tasks finished (the announcement shrank)
    # the wall changed what agents bid from where they stood: a repeated bid that ignored the
    # map would have differed from the one computed from scratch after it
    assert changed_by_rock and any(t >= rock_at for t, _ in checked)


def floor_with_wall() -> VoxelMap:
    vm = VoxelMap.empty((16, 10, 2), 0.5)
    vm.state[8, 0:8, :] = OCCUPIED  # a wall at x = 4 m with a gap at the far side
    return vm


GOALS = (
    (7.25, 1.25, 0.25),
    (1.25, 4.25, 0.75),
    (4.25, 1.25, 0.25),  # in the wall
    (40.0, 1.0, 0.0),  # outside the map
    (6.75, 4.75, 0.75),
    (7.25, 1.25, 0.25),  # twice
)
STARTS = ((0.25, 0.25, 0.25), (3.0, 2.0, 0.5), (7.9, 4.9, 0.9), (4.25, 3.25, 0.25), (-5.0, 0, 0))


def one_by_one(pc: PathCosts, start: Point, goals: tuple[Point, ...]) -> np.ndarray:
    return np.array([pc.path_cost(start, g) for g in goals])


def test_path_costs_are_path_cost_to_each_goal_however_many_fields_fit() -> None:
    """The stacked fields' gather gives each goal's own path_cost, bit for bit, also when the
    memory bound evicts fields between and during calls (then goals are taken one at a time)."""
    ref = PathCosts(floor_with_wall())
    per = ref.cost_map.padded.size * 4
    for max_bytes in (1 << 30, 3 * per, per):
        pc = PathCosts(floor_with_wall(), max_bytes=max_bytes)
        for _ in range(2):  # the second time, the tuple's rows are remembered (or stale)
            for s in STARTS:
                np.testing.assert_array_equal(pc.path_costs(s, GOALS), one_by_one(ref, s, GOALS))
                np.testing.assert_array_equal(
                    pc.path_costs(s, list(GOALS[::-1])), one_by_one(ref, s, GOALS[::-1])
                )
        assert np.isinf(pc.path_costs(STARTS[0], GOALS)[[2, 3]]).all()
        assert np.isfinite(pc.path_costs(STARTS[0], GOALS)[[0, 1, 4, 5]]).all()
    assert ref.searches == 3  # one per goal voxel with a path


def test_a_new_map_drops_the_fields_and_changes_the_start_keys() -> None:
    pc = PathCosts(floor_with_wall())
    before = pc.path_costs(STARTS[0], GOALS)
    key = pc.start_key(STARTS[0])
    walled = floor_with_wall()
    walled.state[8, 8:, :] = OCCUPIED  # the gap closes: the far side is cut off
    pc.set_map(walled)
    after = pc.path_costs(STARTS[0], GOALS)
    np.testing.assert_array_equal(after, one_by_one(PathCosts(walled), STARTS[0], GOALS))
    assert not np.array_equal(before, after) and pc.start_key(STARTS[0]) != key


def test_the_start_voxel_found_in_line_is_the_one_flat_and_open_find() -> None:
    """PathCosts._start does _flat and _open's common case itself: for starts inside the map,
    on voxel boundaries, in rock (snapped), less than half a voxel outside (the edge voxel) and
    further out (none: then _escape's nearest free voxel), it finds what they find — also after
    the map changes."""
    rng = np.random.default_rng(7)
    pc = PathCosts(floor_with_wall())
    res = pc.map.resolution
    lo = np.array(pc.map.origin, dtype=float)
    hi = lo + np.array(pc.map.shape) * res
    for _ in range(2):
        points = [lo, hi, hi - 1e-9, lo - 0.49 * res, hi + 0.49 * res, lo - 0.51 * res]
        points += list(rng.uniform(lo - res, hi + res, size=(400, 3)))
        points += list(lo + rng.integers(0, 17, size=(200, 3)) * res / 2)  # on boundaries
        for p in points:
            start = (float(p[0]), float(p[1]), float(p[2]))
            pc._last_start = None
            found = pc._open(pc._flat(start))
            if found < 0:
                found = pc._escape(start)
                assert found >= 0  # at most a voxel outside: in reach
            assert pc._start(start) == found, start
            assert pc._start(start) == found  # (remembered)
        walled = floor_with_wall()
        walled.state[2:6, 2:6, :] = OCCUPIED
        pc.set_map(walled)
    assert (
        pc._start((2.0, 2.0, 0.5))
        == pc._open(pc._flat((2.0, 2.0, 0.5)))
        != pc._flat((2.0, 2.0, 0.5))
    )  # in the new rock: snapped out of it


def plain_announced(pool: TaskPool, now: float) -> list[PoolTask]:
    """What TaskPool.announced returned before it kept its order: a sort every call."""
    live = [t for t in pool if not t.state.terminal and t.arrived(now)]
    return sorted(live, key=lambda t: (t.info.arrival_s, t.id))


def plain_holders(pool: TaskPool) -> dict[str, str]:
    """What AuctionState.holders returned before the pool kept it: a pass over the pool."""
    return {
        t.agent: t.id
        for t in pool
        if t.agent is not None and t.state in (TaskState.ASSIGNED, TaskState.COMMITTED)
    }


def test_the_announced_order_kept_by_the_pool_is_a_fresh_sort() -> None:
    """The pool keeps its (arrival, id) order, its announced infos and its holders across the
    changes a round makes; every change that could alter one of them (a new task, another
    arrival, a task finished or re-prioritised, an agent won or lost) computes it again."""
    rng = np.random.default_rng(5)
    pool = TaskPool()
    for i in rng.permutation(40):
        arrival = float(rng.integers(0, 6))  # ties on arrival: the id decides
        pool = pool.add(TaskInfo(f"T{i}", "inspect", {"location": [1, 2, 0]}, 1.0, arrival))
    agents = [f"A{i}" for i in range(5)]
    handed_on = 0
    for step in range(400):
        now = step * 0.05
        ids = [t.id for t in pool if not t.state.terminal]
        tid = ids[int(rng.integers(len(ids)))]
        t, a = pool[tid], agents[int(rng.integers(len(agents)))]
        before = pool.announced_infos(now)
        op = int(rng.integers(10))
        if op == 0:
            pool = pool.with_tasks({tid: t.moved(now, TaskState.ASSIGNED, a, "won")})
        elif op == 1 and t.agent is not None:
            pool = pool.complete(tid, t.agent, now)
        elif op == 2:
            pool = pool.release(tid, now, "lost")
        elif op == 3 and len(ids) > 10:
            pool = pool.cancel(tid, now, "operator")
        elif op == 4:
            pool = pool.reprioritised(tid, float(rng.integers(1, 4)))
        elif op == 5:  # another arrival: the order must be sorted again
            info = replace(t.info, arrival_s=float(rng.integers(0, 12)))
            pool = pool.with_tasks({tid: replace(t, info=info)})
        elif op == 6:
            pool = pool.add(TaskInfo(f"N{step}", "inspect", {"location": [1, 2, 0]}, 1.0, now))
        elif op == 7:  # a note (the round's reasons): everything is handed on
            pool = pool.with_tasks({tid: replace(t, note=f"outbid {step}")})
        elif op == 8 and t.agent is not None and t.info.multi_stage is False:
            pool = pool.with_tasks({tid: t.moved(now, TaskState.COMMITTED, t.agent, "commit")})
        elif op == 9:
            pool = pool.unreachable(tid, now, "no path")
        for at in (now, now + 3):
            assert pool.announced(at) == plain_announced(pool, at)
            infos = pool.announced_infos(at)
            assert infos == tuple(t.info for t in plain_announced(pool, at))
            assert all(x is t.info for x, t in zip(infos, plain_announced(pool, at)))
        pool.holders().clear()  # (a copy: the round's own to change)
        assert list(pool.holders().items()) == list(plain_holders(pool).items())
        handed_on += pool.announced_infos(now) is before and op in (0, 2, 7, 8, 9)
    assert handed_on > 100  # most changes kept the announced infos
