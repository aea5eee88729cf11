"""A vehicle the map puts inside rock plans out to the nearest free voxel (issue #36 item 7): on
real PX4 a failsafe descent left a drone where the map has rock, and planning home from there
failed on every tick (1,471 times in one run)."""

from __future__ import annotations

import math

import numpy as np

from btmission.runtime.paths import START_ESCAPE_M, PathCosts
from btmission.world.voxel import OCCUPIED, VoxelMap


def slab() -> VoxelMap:
    """10 x 10 x 6 m at 0.5 m: rock from the floor up to z = 3 m, open above it."""
    vm = VoxelMap.empty((10.0, 10.0, 6.0), 0.5)
    vm.state[:, :, 0:6] = OCCUPIED
    return vm


def test_a_start_inside_rock_plans_from_the_nearest_free_voxel() -> None:
    pc = PathCosts(slab(), clearance_m=0.5)
    goal = (8.0, 8.0, 4.75)
    inside = (2.0, 2.0, 1.0)  # 2 m deep in the rock, beyond snap_m (1.5 m) of open space
    route = pc.route(inside, goal)
    assert route is not None
    first = route.waypoints[0]
    assert first[2] > 3.0 and math.hypot(first[0] - 2.0, first[1] - 2.0) < 0.5  # straight up
    assert pc.start_problem(inside) is None
    assert math.isfinite(pc.path_cost(inside, goal))
    np.testing.assert_allclose(route.waypoints[-1], goal, atol=0.3)


def test_no_free_voxel_within_the_bound_is_said_clearly() -> None:
    vm = VoxelMap.empty((20.0, 20.0, 20.0), 0.5)
    vm.state[:, :, 0:30] = OCCUPIED  # rock up to z = 15 m
    pc = PathCosts(vm)
    deep = (10.0, 10.0, 1.0)  # 14 m under the surface: more than START_ESCAPE_M
    assert pc.route(deep, (10.0, 10.0, 17.0)) is None
    assert math.isinf(pc.path_cost(deep, (10.0, 10.0, 17.0)))
    why = pc.start_problem(deep)
    assert why == (
        "the vehicle is inside rock at [10.00, 10.00, 1.00] and no free voxel is within "
        f"{START_ESCAPE_M:g} m to plan from"
    )
    far = (10.0, 10.0, 15.0 - START_ESCAPE_M + 1.0)  # 4 m under the surface: within the bound
    assert pc.route(far, (10.0, 10.0, 17.0)) is not None


def test_a_start_far_outside_the_map_has_no_path() -> None:
    pc = PathCosts(VoxelMap.empty((10.0, 10.0, 4.0), 0.5))
    assert pc.route((-2.0, 5.0, 1.0), (5.0, 5.0, 1.0)) is not None  # 2 m outside: in reach
    assert pc.route((-20.0, 5.0, 1.0), (5.0, 5.0, 1.0)) is None
    assert "outside the map" in (pc.start_problem((-20.0, 5.0, 1.0)) or "")
