"""The planner's search after issue 19 gives, bit for bit, what the previous search gave: the same
costs, lengths and paths (parents) for one-to-all fields, single queries, costs_to and incremental
replanning, on random maps (resolutions whose bucket width is and is not a power of two) and on a
generated mine. The previous kernel is kept in ``tests/planner_before.py``."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btmission.planning.dstar import CostField, IncrementalPlanner, Planner, PlanResult
from btmission.planning.risk import CostMap, RiskParams
from btmission.world.voxel import FREE, OCCUPIED, UNKNOWN, VoxelMap
from tests.planner_before import PreviousPlanner

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@st.composite
def maps(draw: st.DrawFn, max_side: int = 10) -> CostMap:
    shape = (
        draw(st.integers(2, max_side)),
        draw(st.integers(2, max_side)),
        draw(st.integers(1, 5)),
    )
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    p_occ = draw(st.floats(0.0, 0.45))
    p_unk = draw(st.floats(0.0, 0.25))
    u = rng.random(shape)
    state = np.where(u < p_occ, OCCUPIED, np.where(u < p_occ + p_unk, UNKNOWN, FREE))
    # 0.3 and 0.7: bucket widths that are not powers of two, where rounding can re-open voxels
    res = draw(st.sampled_from([0.25, 0.3, 0.5, 0.7, 1.0]))
    vm = VoxelMap(state.astype(np.uint8), res, (draw(st.floats(-5, 5)), 0.0, -1.0))
    params = RiskParams(
        draw(st.sampled_from([0.0, 0.6, 1.5])), draw(st.sampled_from([0.0, 3.0, 10.0]))
    )
    return CostMap(vm, params)


def _free_points(cm: CostMap) -> np.ndarray:
    return cm.map.index_to_world(np.argwhere(cm.map.state != OCCUPIED))


def _same_field(a: CostField, b: CostField, probes: np.ndarray) -> None:
    assert (a.reached, a.expanded) == (b.reached, b.expanded)
    np.testing.assert_array_equal(a.cost, b.cost)
    np.testing.assert_array_equal(a.length_m, b.length_m)
    for p in probes:
        assert a.at(p) == b.at(p)
        np.testing.assert_array_equal(a.path_to(p), b.path_to(p))


def _same_plan(a: PlanResult, b: PlanResult) -> None:
    assert (a.cost, a.length_m, a.expanded) == (b.cost, b.length_m, b.expanded)
    np.testing.assert_array_equal(a.voxels, b.voxels)


@SETTINGS
@given(cm=maps(), data=st.data())
def test_searches_are_bit_identical_to_the_previous_kernel(
    cm: CostMap, data: st.DataObject
) -> None:
    pts = _free_points(cm)
    if len(pts) == 0:
        return
    pick = st.integers(0, len(pts) - 1)
    new, old = Planner(cm), PreviousPlanner(cm)
    probes = pts[data.draw(st.lists(pick, min_size=1, max_size=6))]
    for _ in range(2):  # twice: the second search resets what the first one reached
        start = pts[data.draw(pick)]
        for reverse in (False, True):
            _same_field(
                new.one_to_all(start, reverse=reverse),
                old.one_to_all(start, reverse=reverse),
                probes,
            )
        several = pts[data.draw(st.lists(pick, min_size=2, max_size=4))]
        _same_field(new.one_to_all(several), old.one_to_all(several), probes)
        goal = pts[data.draw(pick)]
        _same_plan(new.plan(start, goal), old.plan(start, goal))
        for x, y in zip(new.costs_to(start, probes), old.costs_to(start, probes)):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("method", IncrementalPlanner.METHODS)
@SETTINGS
@given(cm=maps(), data=st.data())
def test_incremental_replanning_is_bit_identical(
    method: str, cm: CostMap, data: st.DataObject
) -> None:
    pts = _free_points(cm)
    if len(pts) < 2:
        return
    gi, si = data.draw(st.lists(st.integers(0, len(pts) - 1), min_size=2, max_size=2))
    goal, start = pts[gi], pts[si]
    new = IncrementalPlanner(cm, goal, method=method)
    old = IncrementalPlanner(cm, goal, method=method)
    old._planner = PreviousPlanner(cm)
    keep = {tuple(cm.map.world_to_index(goal)), tuple(cm.map.world_to_index(start))}
    for _ in range(data.draw(st.integers(1, 4))):
        _same_plan(new.plan(start), old.plan(start))
        assert new.stats == old.stats
        lo = [data.draw(st.integers(0, s - 1)) for s in cm.map.shape]
        hi = [min(s - 1, a + data.draw(st.integers(0, 2))) for a, s in zip(lo, cm.map.shape)]
        box = np.mgrid[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1].reshape(3, -1).T
        box = np.array([b for b in box if tuple(b) not in keep]).reshape(-1, 3)
        changed = cm.set_states(box, data.draw(st.sampled_from([FREE, OCCUPIED, UNKNOWN])))
        new.notify(*changed)
        old.notify(*changed)
    _same_plan(new.plan(start), old.plan(start))


def test_mine_one_to_all_and_queries_are_bit_identical() -> None:
    from btmission.world.minegen import generate_mine

    mine = generate_mine(7, (60.0, 40.0, 8.0))
    cm = CostMap(mine.map)
    new, old = Planner(cm), PreviousPlanner(cm)
    start = np.array([mine.launch[0], mine.launch[1], 2.0])
    pts = _free_points(cm)
    probes = pts[np.random.default_rng(0).integers(0, len(pts), 20)]
    kept = new.one_to_all(start)  # kept while the planner searches on: copied out, still equal
    for reverse in (False, True):
        _same_field(
            new.one_to_all(start, reverse=reverse), old.one_to_all(start, reverse=reverse), probes
        )
    for a, b in zip(probes[::2], probes[1::2]):
        _same_plan(new.plan(a, b), old.plan(a, b))
    _same_field(kept, old.one_to_all(start), probes)


def test_a_full_bucket_pool_grows_and_the_search_starts_again() -> None:
    vm = VoxelMap(np.zeros((30, 30, 6), dtype=np.uint8), 0.5)
    cm = CostMap(vm)
    new, old = Planner(cm), PreviousPlanner(cm)
    new._work()
    new._pool = (new._pool[0][:40], new._pool[1][:40])  # room for about one expansion
    start = vm.index_to_world((3, 4, 2))
    probes = _free_points(cm)[::97]
    _same_field(new.one_to_all(start), old.one_to_all(start), probes)
    assert len(new._pool[1]) > 1000
