"""The simulator's full-range 3D LiDAR scan (``Sensors.lidar_scan``), the input of relocalization."""

from __future__ import annotations

import numpy as np
import pytest

from btmission.backends.sim import Simulator
from btmission.localization.scan import pose_matrix, transform_points
from btmission.vehicles.base import LidarScan, Sensors
from tests.unit.backends.test_sim import flying, room

# the room of tests.unit.backends.test_sim: open space x ∈ [0.5, 19.5], y ∈ [0.5, 9.5], z ∈ [0, 5]
PLANES = ((0, 0.5), (0, 19.5), (1, 0.5), (1, 9.5), (2, 0.0), (2, 5.0))


def distance_to_room(points: np.ndarray) -> np.ndarray:
    """Distance of each world point to the nearest wall, floor or roof plane of the room."""
    return np.min(np.stack([np.abs(points[:, axis] - c) for axis, c in PLANES]), axis=0)


@pytest.mark.parametrize("yaw", [0.0, 0.9, -2.5])
def test_scan_points_lie_on_the_rock_seen_from_the_mounted_lidar(yaw: float) -> None:
    sim = Simulator(room(), seed=1)
    veh = sim.add_multirotor("R1", (5.0, 4.0, 0.0), yaw=yaw)
    assert isinstance(veh, Sensors)
    scan = veh.lidar_scan()
    assert isinstance(scan, LidarScan) and scan.sensor == "os1-32" and scan.time_s == 0.0
    np.testing.assert_allclose(scan.robot_from_sensor, pose_matrix(0.0, 0.0, veh.lidar_mount_m))
    assert len(scan.points) > 0.9 * veh.scan_sensor.beams  # a closed room: nearly every beam
    world_from_sensor = pose_matrix(5.0, 4.0, veh.lidar_mount_m, yaw)
    world = transform_points(world_from_sensor, scan.points)
    assert np.max(distance_to_room(world)) < 0.15  # 3 cm range noise, 5 σ
    # the wrong heading would put the points off the walls
    wrong = transform_points(pose_matrix(5.0, 4.0, veh.lidar_mount_m, yaw + 0.3), scan.points)
    assert np.mean(distance_to_room(wrong) > 0.15) > 0.2


def test_scan_follows_the_vehicle_in_flight() -> None:
    sim = Simulator(room(), seed=2)
    veh = sim.add_multirotor("R1", (5.0, 4.0, 0.0))
    flying(sim)
    tel = veh.telemetry()
    scan = veh.lidar_scan()
    p = tel.position
    pose = pose_matrix(p[0], p[1], p[2] + veh.lidar_mount_m, tel.yaw)
    # gravity-aligned: roll and pitch of the flying body are not in the scan
    assert np.max(distance_to_room(transform_points(pose, scan.points))) < 0.15
    assert scan.time_s == pytest.approx(sim.time_s)


def test_scans_are_deterministic_for_a_seed_and_one_per_step() -> None:
    def first_two(seed: int) -> tuple[LidarScan, LidarScan, LidarScan]:
        sim = Simulator(room(), seed=seed)
        veh = sim.add_multirotor("R1", (5.0, 4.0, 0.0))
        a = veh.lidar_scan()
        again = veh.lidar_scan()
        sim.step()
        return a, again, veh.lidar_scan()

    a, again, b = first_two(7)
    a2, _, b2 = first_two(7)
    assert again is a  # same step: the same scan
    np.testing.assert_array_equal(a.points, a2.points)
    np.testing.assert_array_equal(b.points, b2.points)
    assert b.time_s > a.time_s and not np.array_equal(a.points, b.points)  # fresh noise
    c, _, _ = first_two(8)
    assert not np.array_equal(a.points, c.points)
