"""Simulated LiDAR scans (btmission.localization.scan) against exact geometry."""

from __future__ import annotations

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from btmission.localization.scan import (
    OS1_32,
    VLP16,
    LidarSensor,
    add_dust,
    as_pose,
    cast,
    drop_see_through,
    from_record,
    pose_matrix,
    range_image,
    record,
    simulate_scan,
    transform_points,
    with_obstacle,
    yaw_of,
)
from btmission.world.voxel import FREE, OCCUPIED, MapError, VoxelMap

EXACT = replace(OS1_32, range_noise_m=0.0, azimuths=256)


def room(size: tuple[int, int, int] = (40, 30, 12), res: float = 0.5) -> VoxelMap:
    """A closed box: free inside, one voxel of rock on every side (inner faces at 0.5 m from the
    map's corner (0, 0, 0) and at size·res − 0.5 m)."""
    st_ = np.full(size, OCCUPIED, dtype=np.uint8)
    st_[1:-1, 1:-1, 1:-1] = FREE
    return VoxelMap(st_, res)


def box_ranges(origin: np.ndarray, dirs: np.ndarray, lo: float, hi: np.ndarray) -> np.ndarray:
    """Exact distance from ``origin`` inside the box [lo, hi] to its walls along ``dirs``."""
    with np.errstate(divide="ignore"):
        t_hi = np.where(dirs > 0, (hi - origin) / dirs, np.inf)
        t_lo = np.where(dirs < 0, (lo - origin) / dirs, np.inf)
    out: np.ndarray = np.minimum(t_hi, t_lo).min(axis=1)
    return out


def test_scan_of_a_box_room_matches_the_exact_distances() -> None:
    vm = room()
    pose = pose_matrix(7.3, 5.1, 2.2, 0.4)
    r = range_image(vm, pose, EXACT, rng=None).ravel()
    d_world = EXACT.directions().reshape(-1, 3) @ pose[:3, :3].T
    ref = box_ranges(pose[:3, 3], d_world, 0.5, np.array([19.5, 14.5, 5.5]))
    assert np.all(np.isfinite(r))
    np.testing.assert_allclose(r, ref, atol=1e-9)


def test_points_are_in_the_sensor_frame_and_lie_on_the_walls() -> None:
    vm = room()
    pose = pose_matrix(10.0, 7.0, 3.0, -2.0)
    pts = simulate_scan(vm, pose, EXACT, rng=None)
    assert pts.shape == (EXACT.beams, 3)
    world = transform_points(pose, pts)
    on_wall = np.isclose(world, 0.5, atol=1e-7) | np.isclose(world, [19.5, 14.5, 5.5], atol=1e-7)
    assert np.all(on_wall.any(axis=1))


def first_hit(state: np.ndarray, start: np.ndarray, d: np.ndarray) -> float:
    """Exact first entry into an occupied voxel (voxel units): every crossing of a grid plane
    along the ray, sorted; each stretch between two crossings lies in one voxel (its midpoint
    tells which), stretches of zero length (through an edge or corner) enter no voxel."""
    ts = [0.0]
    for a in range(3):
        if d[a] != 0:
            k = np.arange(0, state.shape[a] + 1)
            t = (k - start[a]) / d[a]
            ts.extend(t[t > 0])
    ts = np.unique(ts)
    for t0, t1 in itertools.pairwise(ts):
        if t1 - t0 < 1e-9:
            continue
        idx = np.floor(start + 0.5 * (t0 + t1) * d).astype(int)
        if np.any(idx < 0) or np.any(idx >= state.shape):
            return np.inf
        if state[tuple(idx)] == OCCUPIED:
            return float(t0)
    return np.inf


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    ox=st.floats(0.1, 5.9),
    oy=st.floats(0.1, 4.9),
    oz=st.floats(0.1, 3.9),
)
@example(seed=0, ox=1.0, oy=1.0, oz=2.0)  # on a voxel corner: rays leave it diagonally
@example(seed=58, ox=1.0, oy=2.0, oz=1.0)
@example(seed=0, ox=0.99999, oy=0.5, oz=0.5)  # a 10 µm sliver of a voxel before the next
def test_voxel_traversal_agrees_with_exact_plane_crossings(
    seed: int, ox: float, oy: float, oz: float
) -> None:
    """The DDA's first hit equals the exact one from sorted plane crossings (random rock, rays)."""
    rng = np.random.default_rng(seed)
    state = (rng.random((12, 10, 8)) < 0.15).astype(np.uint8)
    vm = VoxelMap(state, 0.5)
    origin = np.array([ox, oy, oz])
    if vm.state_at(origin) == OCCUPIED:
        return
    dirs = rng.normal(size=(20, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    got = cast(vm, origin, dirs, 50.0)
    for d, g in zip(dirs, got):
        ref = first_hit(state, origin / 0.5, d) * 0.5
        if np.isinf(ref):
            assert np.isinf(g)
        else:
            assert g == pytest.approx(ref, abs=1e-9)


def test_max_range_and_leaving_the_map_give_no_return() -> None:
    vm = room()
    origin = np.array([10.0, 7.0, 3.0])
    assert np.isinf(cast(vm, origin, [[1.0, 0.0, 0.0]], 5.0)[0])  # wall at 9.5 m
    assert cast(vm, origin, [[1.0, 0.0, 0.0]], 9.6)[0] == pytest.approx(9.5)
    open_room = VoxelMap(np.zeros((10, 10, 10), dtype=np.uint8), 1.0)
    assert np.isinf(cast(open_room, [5.0, 5.0, 5.0], [[0.0, 1.0, 0.0]], 100.0)[0])


def test_range_noise_has_the_sensor_sigma_and_the_seed_repeats() -> None:
    vm = room()
    pose = pose_matrix(10.0, 7.0, 3.0)
    sensor = replace(OS1_32, range_noise_m=0.05)
    exact = range_image(vm, pose, sensor, rng=None)
    noisy = range_image(vm, pose, sensor, rng=3)
    assert np.nanstd(noisy - exact) == pytest.approx(0.05, rel=0.05)
    np.testing.assert_array_equal(noisy, range_image(vm, pose, sensor, rng=3))
    assert not np.array_equal(noisy, range_image(vm, pose, sensor, rng=4))


def test_dropout_and_min_range_remove_returns() -> None:
    vm = room()
    pose = pose_matrix(10.0, 7.0, 3.0)
    lossy = replace(EXACT, dropout=0.3)
    r = range_image(vm, pose, lossy, rng=0)
    assert np.isnan(r).mean() == pytest.approx(0.3, abs=0.03)
    near = replace(EXACT, min_range_m=7.0)
    r = range_image(vm, pose, near, rng=None)
    assert np.nanmin(r) >= 7.0 and np.isnan(r).any()


def test_sensor_outside_the_map_is_an_error() -> None:
    with pytest.raises(MapError, match="outside the map"):
        simulate_scan(room(), pose_matrix(-1.0, 2.0, 2.0))


def test_a_sensor_inside_rock_sees_nothing() -> None:
    assert len(simulate_scan(room(), pose_matrix(0.2, 0.2, 0.2), EXACT, rng=None)) == 0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"channels": 0}, "at least 1"),
        ({"elevation_deg": (10.0, -10.0)}, "elevation_deg"),
        ({"min_range_m": 5.0, "max_range_m": 1.0}, "ranges"),
        ({"dropout": 1.0}, "dropout"),
    ],
)
def test_bad_sensors_are_refused(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LidarSensor(**kwargs)  # type: ignore[arg-type]


def test_sensor_round_trips_through_a_record() -> None:
    assert from_record(LidarSensor, json.loads(json.dumps(record(VLP16)))) == VLP16
    with pytest.raises(TypeError):
        from_record(LidarSensor, {"beams": 3})


@given(x=st.floats(-50, 50), y=st.floats(-50, 50), z=st.floats(-5, 5), yaw=st.floats(-3.1, 3.1))
def test_pose_matrix_is_rigid_and_keeps_the_yaw(x: float, y: float, z: float, yaw: float) -> None:
    t = as_pose(pose_matrix(x, y, z, yaw, roll=0.1, pitch=-0.05))
    assert yaw_of(pose_matrix(x, y, z, yaw)) == pytest.approx(yaw, abs=1e-12)
    np.testing.assert_allclose(t[:3, 3], [x, y, z])


def test_as_pose_refuses_non_rigid_transforms() -> None:
    with pytest.raises(ValueError, match="4×4"):
        as_pose(np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="orthonormal"):
        as_pose(bad)


def test_dust_shortens_a_fraction_of_the_beams() -> None:
    vm = room()
    pts = simulate_scan(vm, pose_matrix(10.0, 7.0, 3.0), EXACT, rng=None)
    dusty = add_dust(pts, 0.05, rng=1)
    moved = np.linalg.norm(dusty - pts, axis=1) > 1e-9
    assert moved.sum() == round(0.05 * len(pts))
    r0, r1 = np.linalg.norm(pts[moved], axis=1), np.linalg.norm(dusty[moved], axis=1)
    assert np.all(r1 <= r0 + 1e-9) and np.all(r1 <= 8.0 + 1e-9)
    cos = np.sum(pts[moved] * dusty[moved], axis=1) / (r0 * r1)
    np.testing.assert_allclose(cos, 1.0)  # same beams
    with pytest.raises(ValueError, match="fraction"):
        add_dust(pts, 1.5)


def test_see_through_filter_drops_dust_in_front_of_walls() -> None:
    vm = room()
    pts = simulate_scan(
        vm, pose_matrix(10.0, 7.0, 3.0), replace(OS1_32, range_noise_m=0.0), rng=None
    )
    dusty = add_dust(pts, 0.05, rng=2)
    is_dust = np.linalg.norm(dusty - pts, axis=1) > 1.0  # dust more than 1 m before the wall
    kept = drop_see_through(dusty)
    kept_set = {tuple(p) for p in np.round(kept, 9)}
    dust_kept = sum(tuple(p) in kept_set for p in np.round(dusty[is_dust], 9))
    clean_kept = sum(tuple(p) in kept_set for p in np.round(dusty[~is_dust], 9))
    assert dust_kept <= 0.05 * is_dust.sum()
    assert clean_kept >= 0.99 * (~is_dust).sum()
    assert len(drop_see_through(pts)) == len(pts)  # a clean room keeps every point


def test_an_obstacle_blocks_part_of_the_view() -> None:
    vm = room()
    pose = pose_matrix(6.0, 7.0, 2.0, 0.0)
    blocked = with_obstacle(vm, pose, distance_m=2.0, bearing=0.0, size_m=(1.0, 2.0, 2.0))
    assert blocked.counts()["occupied"] > vm.counts()["occupied"]
    assert vm.state_at([8.5, 7.0, 1.0]) == FREE and blocked.state_at([8.5, 7.0, 1.0]) == OCCUPIED
    ahead = cast(blocked, pose[:3, 3], [[1.0, 0.0, 0.0]], 50.0)[0]
    assert ahead == pytest.approx(2.0, abs=0.5)
    behind = cast(blocked, pose[:3, 3], [[-1.0, 0.0, 0.0]], 50.0)[0]
    assert behind == pytest.approx(5.5)
