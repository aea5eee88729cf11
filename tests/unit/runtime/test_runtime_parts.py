"""Runtime building blocks: D*+ path costs for bids, the navigator's polyline, the bus, the
warehouse world, COMPRA on a small mine."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from btmission.links.bus import InMemoryBus
from btmission.missions import load_mission_text
from btmission.planning.dstar import Planner
from btmission.planning.risk import CostMap, RiskParams
from btmission.runtime.events import Recorder
from btmission.runtime.navcontrol import Polyline, ground_obstacle_points
from btmission.runtime.paths import START_ESCAPE_M, PathCosts, inflate
from btmission.runtime.runner import MissionRun
from btmission.world.minegen import warehouse_world
from btmission.world.voxel import OCCUPIED, MapError, VoxelMap


def corridor() -> VoxelMap:
    vm = VoxelMap.empty((12, 6, 3), 0.5)
    vm.state[:, 0, :] = vm.state[:, -1, :] = OCCUPIED
    vm.state[6:8, 1:7, :] = OCCUPIED  # a wall at x 3-4 m with a 2 m gap at the far side
    return vm


def test_path_costs_are_the_planners_lengths_to_each_goal() -> None:
    """One backward search per goal gives, for every start, the length of the optimal path
    the planner finds from that start (seed 000 §IV-B2: bids are D*+ path lengths)."""
    vm = corridor()
    pc = PathCosts(vm, RiskParams(1.0, 5.0))
    planner = Planner(CostMap(vm, RiskParams(1.0, 5.0)))
    goal = (10.25, 2.25, 1.25)
    for start in [(1.25, 1.25, 0.25), (1.25, 4.25, 2.25), (5.25, 2.25, 1.25)]:
        _, length = planner.one_to_all(start).at(goal)
        assert pc.path_cost(start, goal) == pytest.approx(length, rel=1e-6)
    assert pc.searches == 1  # one search served every start
    route = pc.route((1.25, 1.25, 0.25), goal)
    assert route is not None
    np.testing.assert_allclose(route.waypoints[0], (1.25, 1.25, 0.25))
    np.testing.assert_allclose(route.waypoints[-1], goal)
    assert route.length_m == pytest.approx(pc.path_cost((1.25, 1.25, 0.25), goal), rel=1e-6)


def test_goals_in_rock_or_outside_have_no_path() -> None:
    pc = PathCosts(corridor())
    assert math.isinf(pc.path_cost((1.25, 1.25, 0.25), (3.25, 1.25, 1.25)))
    assert pc.problem((3.25, 1.25, 1.25)) == "inside rock"
    assert "outside the map" in str(pc.problem((50, 1, 1)))
    assert pc.route((1.25, 1.25, 0.25), (50.0, 1.0, 1.0)) is None


def test_a_start_a_hair_outside_the_map_counts_as_its_edge_voxel() -> None:
    """A real vehicle resting on a map whose floor is the map's edge reports z a few mm below
    it (estimator noise, seen on ArduCopter SITL): it still has a path from its edge voxel; a
    start further out plans from the nearest voxel within START_ESCAPE_M, and none beyond."""
    pc = PathCosts(corridor())
    goal = (10.25, 2.25, 1.25)
    on_floor = pc.path_cost((1.25, 1.25, 0.0), goal)
    assert math.isfinite(on_floor)
    assert pc.path_cost((1.25, 1.25, -0.006), goal) == pytest.approx(on_floor)
    assert pc.path_cost((1.25, 1.25, 3.1), goal) == pytest.approx(
        pc.path_cost((1.25, 1.25, 2.9), goal)
    )
    # more than half a voxel out: planned from the nearest voxel it may enter (a drone pushed
    # out of the map by a failsafe, #36 item 7), within START_ESCAPE_M of the start, not beyond
    assert math.isfinite(pc.path_cost((1.25, 1.25, -0.3), goal))
    assert math.isfinite(pc.path_cost((-0.3, 1.25, 0.25), goal))
    assert math.isinf(pc.path_cost((1.25, 1.25, -START_ESCAPE_M - 0.5), goal))
    assert math.isinf(pc.path_cost((-START_ESCAPE_M - 0.5, 1.25, 0.25), goal))


def test_inflation_keeps_paths_off_the_rock() -> None:
    vm = corridor()
    inflated = inflate(vm, 0.5)
    d_free = np.argwhere(inflated.state != OCCUPIED)
    occ = np.argwhere(vm.state == OCCUPIED)
    # every voxel left open is at least 0.5 m (centre to rock surface) from rock
    gaps = (
        np.min(np.linalg.norm(d_free[:, None, :] - occ[None, :, :], axis=2), axis=1) * vm.resolution
        - vm.resolution / 2
    )
    assert gaps.min() >= 0.5 - 1e-9
    assert inflate(vm, 0.0) is vm
    # a start in the inflated margin (a drone on the floor) is moved to the nearest open voxel
    pc = PathCosts(vm, clearance_m=0.5)
    assert math.isfinite(pc.path_cost((1.25, 0.75, 0.25), (10.25, 2.75, 1.25)))


def test_polyline_projection_and_arc_length() -> None:
    line = Polyline(np.array([[0.0, 0, 0], [4, 0, 0], [4, 3, 0]]))
    assert line.length == 7.0
    seg, s = line.project(np.array([2.0, 1.0, 0.0]))
    assert (seg, s) == (0, 2.0)
    np.testing.assert_allclose(line.at(s + 3.0), [4.0, 1.0, 0.0])
    np.testing.assert_allclose(line.at(100.0), [4.0, 3.0, 0.0])
    np.testing.assert_allclose(line.at(-1.0), [0.0, 0.0, 0.0])
    seg, s = line.project(np.array([5.0, 2.0, 0.0]), start=1)
    assert (seg, s) == (1, 6.0)
    # the first of equally close segments; a start past the end is clamped to the last
    assert line.project(np.array([4.0, 0.0, 0.0])) == (0, 4.0)
    assert line.project(np.array([0.0, 0.0, 0.0]), start=9) == (1, 4.0)
    np.testing.assert_allclose(line.at(4.0), [4.0, 0.0, 0.0])  # a vertex: the next segment's start
    one = Polyline(np.array([[1.0, 2.0, 3.0]]))  # a route to where it is
    assert one.length == 0.0 and one.project(np.zeros(3)) == (0, 0.0)
    np.testing.assert_allclose(one.at(0.5), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="at least one point"):
        Polyline(np.zeros((0, 3)))


def test_the_carrots_are_the_projection_and_the_points_ahead_of_it() -> None:
    """Polyline.carrots (one compiled call per control step) gives, to the bit, what project
    then at(arc + d1) and at(arc + d2) give, on random routes, positions and starts (a one-point
    route, the ends and past them included)."""
    rng = np.random.default_rng(5)
    for trial in range(300):
        n = int(rng.integers(1, 8))
        line = Polyline(np.cumsum(rng.normal(0.0, 2.0, (n, 3)), axis=0))
        p = rng.normal(0.0, 5.0, 3)
        start = int(rng.integers(0, n + 2))
        d1 = float(rng.uniform(0.0, 3.0)) if trial % 7 else 100.0
        seg, arc, c1, c2 = line.carrots(p, start, d1, 2 * d1)
        assert (seg, arc) == line.project(p, start)
        assert np.array_equal(c1, line.at(arc + d1)) and np.array_equal(c2, line.at(arc + 2 * d1))


def test_bus_predictions_are_shifted_and_ordered() -> None:
    bus = InMemoryBus()
    bus.share_prediction("A", 0.0, np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]))
    bus.share_prediction("B", 0.2, np.array([[5.0, 0.0]]))
    out = bus.predictions("C", 0.2, 0.1, near=np.array([4.0, 0.0]))
    assert [p[0].tolist() for p in out] == [[5.0, 0.0], [2.0, 0.0]]  # nearest first, A moved on
    assert bus.predictions("C", 0.2, 0.1, near=np.array([4.0, 0.0]), within_m=1.5)[0].shape == (
        1,
        2,
    )
    assert [len(p) for p in bus.predictions("A", 0.0, 0.1)] == [1]  # never one's own


def test_a_fleet_bus_finds_the_same_neighbours_as_the_pure_function() -> None:
    """Past SMALL_FLEET agents the bus picks neighbours with one vectorised test; the answer is
    advance_predictions' to the bit: the same arrays in the same order (ties too), own left out,
    multi-row predictions shifted."""
    from btmission.links.bus import SMALL_FLEET, advance_predictions, first_points

    rng = np.random.default_rng(4)
    bus = InMemoryBus()
    n = 5 * SMALL_FLEET
    for i in range(n):
        rows = 1 if i % 3 else 4
        pos = rng.uniform(0.0, 20.0, (rows, 2 if i % 2 else 3)).round(1)  # ties in distance
        bus.share_prediction(f"A{i}", float(rng.choice([0.0, 0.1, 0.3])), pos)
    bus.share_prediction("A0", 0.2, np.array([[10.0, 10.0, 1.0]]))  # again: keeps its row
    checked = 0
    for k in range(200):
        near = rng.uniform(0.0, 20.0, 3).round(1)
        within = float(rng.choice([0.0, 2.0, 6.0, 100.0]))
        me = f"A{k % n}"
        got = bus.predictions(me, 0.4, 0.1, near=near, within_m=within)
        want = advance_predictions(bus._predictions, me, 0.4, 0.1, near, within)
        assert len(got) == len(want)
        assert all(np.array_equal(g, w) for g, w in zip(got, want))
        # where they are now: the first point of each, stacked, z NaN for a 2D one
        now = bus.neighbour_positions(me, 0.4, 0.1, near, within)
        assert np.array_equal(now, first_points(want), equal_nan=True)
        assert now.shape == (len(want), 3)
        assert all(np.array_equal(r[: w.shape[1]], w[0]) for r, w in zip(now, want))
        checked += len(want)
    assert checked > 500
    # every agent back to a single 3D point (one leaves the bus): no trajectory is left, and
    # the compiled query that skips them gives the same answer
    assert bus._trajectories > 0
    for i in range(n):
        bus.share_prediction(f"A{i}", 0.5, rng.uniform(0.0, 20.0, (1, 3)).round(1))
    bus.disconnect("A1")
    assert bus._trajectories == 0
    for k in range(50):
        near = rng.uniform(0.0, 20.0, 3).round(1)
        me = f"A{k % n}"
        want = advance_predictions(bus._predictions, me, 0.6, 0.1, near, 6.0)
        got = bus.neighbour_positions(me, 0.6, 0.1, near, 6.0)
        assert np.array_equal(got, first_points(want), equal_nan=True)
    bus.share_prediction("A2", 0.6, np.array([[1.0, 1.0], [2.0, 1.0]]))  # a trajectory again
    assert bus._trajectories == 1
    small = InMemoryBus()  # a small fleet: the same through advance_predictions
    small.share_prediction("A", 0.0, np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]))
    small.share_prediction("B", 0.2, np.array([[5.0, 0.0, 1.5]]))
    np.testing.assert_array_equal(
        small.neighbour_positions("C", 0.2, 0.1, np.array([4.0, 0.0]), 10.0),
        [[5.0, 0.0, 1.5], [2.0, 0.0, np.nan]],
    )


def test_ground_obstacle_points_keep_what_the_robot_can_hit() -> None:
    """The ground NMPC's obstacle points from a LiDAR scan (yaw frame, relative to the base):
    a shelf face at the body's height is kept (rotated into the world), the floor, a shelf
    edge above the body and the points on a robot that shares its predictions are not."""
    body = [
        [1.0, 0.0, 0.125],  # shelf face 1 m ahead, at the robot's height
        [1.0, 0.0, 0.125],  # the same point twice
        [0.5, 0.5, 0.0],  # floor
        [1.0, 0.0, 0.625],  # the same shelf, above the robot
        [0.0, 1.0, 0.15],  # on another robot, 1 m to the left
        [0.0, 1.1, 0.2],
    ]
    pts = ground_obstacle_points(body, [2.0, 3.0, 0.0], math.pi / 2, [[1.0, 3.0]])
    np.testing.assert_allclose(pts, [[2.0, 4.0]], atol=1e-9)  # ahead = +y at ψ = 90°
    alone = ground_obstacle_points(body, [2.0, 3.0, 0.0], math.pi / 2)
    np.testing.assert_allclose(alone, [[0.9, 3.0], [1.0, 3.0], [2.0, 4.0]], atol=1e-9)
    assert ground_obstacle_points(np.zeros((0, 3)), [0.0, 0.0, 0.0], 0.0).shape == (0, 2)


def test_warehouse_world() -> None:
    a = warehouse_world((24, 16, 1), 0.25, seed=3)
    b = warehouse_world((24, 16, 1), 0.25, seed=3)
    assert np.array_equal(a.state, b.state)
    assert not np.array_equal(a.state, warehouse_world((24, 16, 1), 0.25, seed=4).state)
    occ = a.state == OCCUPIED
    assert occ.any() and (occ.all(axis=2) == occ.any(axis=2)).all()  # shelves are full height
    # the 2.5 m strips along the walls are open (docks, drop-off)
    assert not occ[:, :10].any() and not occ[:, -10:].any()
    assert not occ[:10].any() and not occ[-10:].any()
    with pytest.raises(MapError, match="at least 8"):
        warehouse_world((6, 16, 1), 0.25)


COMPRA = """
mission: sar
version: 1
world:
  map: {generate: mine, seed: 3, size: [80, 50, 8]}
  resolution: 0.5
agents:
  - {id: M1, library: compra, start: [4, 5, 0]}
tasks:
  - {id: S1, type: search}
task_types:
  search: {goal: [stop_handled, mission_complete], cost: 0}
runtime:
  controller: track
  settings: {explore_time_s: 12}
  sim:
    artifacts:
      - {label: survivor, position: [11.5, 7.5, 0.4], size_m: 0.6}
"""


def test_compra_explores_localises_returns_and_lands(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(COMPRA).lstrip(), str(tmp_path / "m.yaml"))
    rec = Recorder()
    run = MissionRun(m, observers=[rec])
    result = run.run(until=120)
    assert result.reason == "completed" and result.collisions == 0
    poses = [e.get("p") for e in rec.of("pose") if e.get("agent") == "M1"]
    start = np.array([4.0, 5.0, 0.0])
    far = max(float(np.linalg.norm(np.array(p) - start)) for p in poses)
    assert far > 6.0  # it explored...
    assert float(np.linalg.norm(np.array(poses[-1][:2]) - start[:2])) < 1.5  # ...and came back
    tel = run.vehicles["M1"].backend.telemetry()
    assert tel.landed and not tel.armed
    objects = rec.of("objects")[0].get("objects")
    assert [o["label"] for o in objects] == ["survivor"]
    assert math.dist(objects[0]["p"], (11.5, 7.5, 0.4)) < 0.3


def test_compra_stop_lands_and_holds_until_cleared(tmp_path: Path) -> None:
    text = textwrap.dedent(COMPRA).lstrip().replace("explore_time_s: 12", "explore_time_s: 60")
    run = MissionRun(load_mission_text(text, str(tmp_path / "m.yaml")))
    run.at(6.0, lambda r: r.signal("M1", "stop", True))
    run.run(until=16.0)
    tel = run.vehicles["M1"].backend.telemetry()
    assert tel.landed and run.agents["M1"].action == "emergency_land"
    run.signal("M1", "stop", False)
    run.run(until=24.0)
    assert not run.vehicles["M1"].backend.telemetry().landed  # back in the air, exploring again
