"""The place database (btmission.localization.database): where places go, files, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from btmission.localization.database import (
    DB_FORMAT,
    DatabaseError,
    PlaceDatabase,
    build_database,
    load_database,
    positions_from_trajectory,
    random_poses,
    sample_positions,
    save_database,
)
from btmission.localization.descriptor import DescriptorParams
from btmission.world.io import save_map
from btmission.world.voxel import FREE, OCCUPIED, VoxelMap
from tests.reloc_helpers import small_database, small_mine


def test_places_stand_on_floors_with_free_space_up_to_the_sensor() -> None:
    vm = small_mine().map
    pos, floor_z = sample_positions(vm, spacing_m=1.0, height_m=2.0, clearance_m=0.5)
    assert len(pos) > 100
    np.testing.assert_allclose(pos[:, 2] - floor_z, 2.0)
    res = vm.resolution
    for p, f in zip(pos, floor_z):
        assert vm.state_at([p[0], p[1], f - res / 2]) == OCCUPIED  # rock under the floor
        for z in np.arange(f + res / 2, p[2], res):
            assert vm.state_at([p[0], p[1], z]) == FREE
    # a lattice of 1 m: x and y of every place are voxel centres 2 voxels apart
    ix = vm.world_to_index(pos)[:, :2]
    assert len(np.unique(ix % 2, axis=0)) == 1


def test_clearance_keeps_places_off_the_walls() -> None:
    from scipy import ndimage

    vm = small_mine().map
    pos, _ = sample_positions(vm, 1.0, 2.0, clearance_m=1.5)
    dist = ndimage.distance_transform_edt(vm.state != OCCUPIED) * vm.resolution
    idx = vm.world_to_index(pos)
    assert np.all(dist[tuple(idx.T)] >= 1.5)
    fewer, _ = sample_positions(vm, 1.0, 2.0, clearance_m=0.0)
    assert len(fewer) > len(pos)


def test_a_map_without_floors_has_no_places() -> None:
    rock = VoxelMap(np.full((10, 10, 10), OCCUPIED, dtype=np.uint8), 0.5)
    with pytest.raises(DatabaseError, match="no place"):
        sample_positions(rock)
    with pytest.raises(DatabaseError, match="spacing"):
        sample_positions(small_mine().map, spacing_m=0.0)
    with pytest.raises(DatabaseError, match="high"):
        sample_positions(VoxelMap(np.zeros((5, 5, 3), dtype=np.uint8), 0.5), height_m=2.0)


def test_places_along_a_trajectory() -> None:
    mine = small_mine()
    t = mine.tunnels[0]
    a, b = np.array(t.point(0.0, 2.0)), np.array(t.point(1.0, 2.0))
    traj = np.stack([a, b])
    pos, floor_z = positions_from_trajectory(mine.map, traj, spacing_m=2.0)
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    np.testing.assert_allclose(steps, 2.0, atol=1e-9)
    np.testing.assert_allclose(pos[:, 2] - floor_z, 2.0, atol=0.3)
    with pytest.raises(DatabaseError, match="trajectory"):
        positions_from_trajectory(mine.map, np.zeros((0, 3)))
    with pytest.raises(DatabaseError, match="free space"):
        positions_from_trajectory(mine.map, [[-10.0, -10.0, 0.0]])


def test_random_poses_are_in_free_space() -> None:
    vm = small_mine().map
    poses = random_poses(vm, 30, rng=3)
    assert len(poses) == 30
    for t in poses:
        assert vm.state_at(t[:3, 3]) == FREE
    again = random_poses(vm, 30, rng=3)
    np.testing.assert_array_equal(np.stack(poses), np.stack(again))
    with pytest.raises(DatabaseError, match="heights"):
        random_poses(vm, 3, heights_m=(2.0, 1.0))


def test_database_round_trips_through_a_file(tmp_path: Path) -> None:
    db = small_database()
    path = save_database(db, tmp_path / "db.npz")
    back = load_database(path)
    for name in ("positions", "floor_z", "ring_keys", "polar", "cloud"):
        np.testing.assert_array_equal(getattr(back, name), getattr(db, name))
    np.testing.assert_array_equal(back.voxel_map.state, db.voxel_map.state)
    assert back.voxel_map.origin == db.voxel_map.origin
    assert back.params == db.params and back.sensor == db.sensor
    assert "places" in back.describe()


def test_building_from_given_places_and_cloud() -> None:
    vm = small_mine().map
    pos, floor_z = sample_positions(vm, 4.0)
    cloud = np.random.default_rng(0).uniform(0, 10, size=(50, 3))
    db = build_database(vm, cloud, (pos, floor_z), params=DescriptorParams(rings=8))
    assert len(db) == len(pos) and db.polar.shape == (len(pos), 8, 60)
    np.testing.assert_allclose(db.cloud, cloud.astype(np.float32))
    with pytest.raises(DatabaseError, match="surface points"):
        build_database(vm, np.zeros((0, 3)), (pos, floor_z))


def _write_npz(path: Path, **fields: object) -> Path:
    with path.open("wb") as fh:
        np.savez(fh, **fields)  # type: ignore[arg-type]
    return path


def test_bad_database_files_are_named_with_the_problem(tmp_path: Path) -> None:
    with pytest.raises(DatabaseError, match="no such file"):
        load_database(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    with pytest.raises(DatabaseError, match=r"junk\.npz: not a readable"):
        load_database(junk)
    other = _write_npz(tmp_path / "other.npz", format=np.array("something"))
    with pytest.raises(DatabaseError, match="not a btmission place database"):
        load_database(other)
    vm_path = save_map(small_mine().map, tmp_path / "map.npz")
    with pytest.raises(DatabaseError, match="reloc build"):
        load_database(vm_path)
    future = _write_npz(tmp_path / "future.npz", format=np.array(DB_FORMAT), version=np.array(9))
    with pytest.raises(DatabaseError, match="version 9"):
        load_database(future)
    partial = _write_npz(tmp_path / "partial.npz", format=np.array(DB_FORMAT), version=np.array(1))
    with pytest.raises(DatabaseError, match="lacks positions"):
        load_database(partial)
    with pytest.raises(DatabaseError, match=r"\.npz"):
        save_database(small_database(), tmp_path / "db.ply")


def test_an_inconsistent_database_is_refused(tmp_path: Path) -> None:
    db = small_database()
    path = save_database(db, tmp_path / "db.npz")
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    data["ring_keys"] = data["ring_keys"][:-1]
    bad = _write_npz(tmp_path / "bad.npz", **data)
    with pytest.raises(DatabaseError, match="ring_keys"):
        load_database(bad)
    data = {k: v for k, v in data.items()}
    data["descriptor"] = np.array(json.dumps({"rings": -1}))
    bad = _write_npz(tmp_path / "bad2.npz", **data)
    with pytest.raises(DatabaseError, match=r"bad2\.npz"):
        load_database(bad)
    with pytest.raises(DatabaseError, match="no places"):
        PlaceDatabase(
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros((0, 20), np.float32),
            np.zeros((0, 20, 60), np.float32),
            db.cloud,
            db.voxel_map,
        )
