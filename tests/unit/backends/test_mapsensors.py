"""Map sensors (btmission.backends.mapsensors): the simulator's LiDAR and camera as a stand-alone
Sensors, ray-cast through the mission map at whatever pose a vehicle reports."""

from __future__ import annotations

import numpy as np
import pytest

from btmission.backends.mapsensors import Body, MapSensors, SensorPose, body_at
from btmission.backends.sim import SimConfig, Simulator
from btmission.backends.sim_provider import mission_artifacts, sim_config
from btmission.backends.simworld import Artifact, SimWorld
from btmission.control.mav_model import yaw_frame_to_world
from btmission.missions import load_mission_text
from btmission.vehicles.base import Sensors
from btmission.world.voxel import VoxelMap
from tests.unit.backends.test_sim import flying, room

ART = Artifact("survivor", (9.0, 5.5, 2.0), 0.6)
CONFIG = SimConfig(dust_points=4, detection_noise_px=1.5)


def test_map_sensors_at_the_vehicles_pose_see_what_the_simulators_vehicle_sees() -> None:
    """Lidar points, scan, depth image and detections: the same numbers, random draws included,
    from a MapSensors that only knows the map and the pose the vehicle reports (its telemetry)."""
    sim = Simulator(room(), CONFIG, seed=3, artifacts=[ART])
    veh = sim.add_multirotor("R1", (6.0, 1.8, 0.0), yaw=0.3)
    flying(sim)
    rng = np.random.default_rng()
    rng.bit_generator.state = sim.rng.bit_generator.state  # the same draws from here on
    own = MapSensors(SimWorld(room(), [ART]), CONFIG, rng, pose=veh.telemetry)
    assert isinstance(own, Sensors)
    a, b = veh.lidar(), own.lidar()
    assert len(a) > CONFIG.dust_points + 10  # the wall 1.3 m aside
    np.testing.assert_array_equal(a, b)
    scan_a, scan_b = veh.lidar_scan(), own.lidar_scan()
    assert len(scan_a.points) > 0.9 * own.scan_sensor.beams  # a closed room
    np.testing.assert_array_equal(scan_a.points, scan_b.points)
    np.testing.assert_array_equal(scan_a.robot_from_sensor, scan_b.robot_from_sensor)
    assert scan_a.time_s == scan_b.time_s == sim.time_s
    cam_a, cam_b = veh.camera(), own.camera()
    assert cam_a.depth_m.max() > 0
    np.testing.assert_array_equal(cam_a.depth_m, cam_b.depth_m)
    np.testing.assert_array_equal(cam_a.translation, cam_b.translation)
    assert len(cam_b.detections) == 1 and cam_a.detections == cam_b.detections


def test_a_pose_away_from_the_truth_sees_the_map_from_there() -> None:
    """The sensors follow the pose given, not any vehicle: 1 m from the +x wall, facing it."""
    p = np.array([18.5, 5.0, 2.0])
    sensors = MapSensors(
        SimWorld(room()), SimConfig(), np.random.default_rng(0), lambda: SensorPose(1.0, p, 0.0)
    )
    pts = sensors.lidar()
    assert len(pts) and np.all(np.linalg.norm(pts, axis=1) <= 2.0 + 1e-9)
    assert pts[:, 0].max() == pytest.approx(1.0)  # the wall face at x = 19.5, straight ahead
    depth = sensors.camera().depth_m
    h, w = depth.shape
    assert depth[h // 2, w // 2] == pytest.approx(1.0, abs=0.13)  # quarter-voxel ray steps


def test_other_vehicles_appear_as_points_on_their_body_spheres() -> None:
    p = np.array([10.0, 5.0, 2.5])  # 2.5 m from floor and roof, 4.5 m from the walls
    yaw = 1.1
    bodies = [
        Body(np.array([11.0, 5.5, 2.75]), 0.25),  # in range
        body_at((10.0, 8.0, 2.5), 0.15),  # its bottom 3 m away: out of range
    ]
    sensors = MapSensors(
        SimWorld(room()),
        SimConfig(lidar_range_m=2.0),
        np.random.default_rng(0),
        lambda: SensorPose(0.0, p, yaw),
        lambda: bodies,
    )
    assert body_at((10.0, 8.0, 2.5), 0.15) == (pytest.approx([10.0, 8.0, 2.65]), 0.15)
    pts = sensors.lidar()
    assert len(pts) == 200
    world = yaw_frame_to_world(pts, yaw) + p
    np.testing.assert_allclose(np.linalg.norm(world - bodies[0].centre, axis=1), 0.25)
    alone = MapSensors(
        SimWorld(room()),
        SimConfig(lidar_range_m=2.0),
        np.random.default_rng(0),
        lambda: SensorPose(0.0, p, yaw),
    )
    assert alone.lidar().shape == (0, 3)


def test_nothing_is_seen_in_open_space_beyond_range() -> None:
    open_space = VoxelMap.empty((30.0, 30.0, 12.0), 0.5)  # no rock at all
    t = [0.0]
    sensors = MapSensors(
        SimWorld(open_space),
        SimConfig(),
        np.random.default_rng(0),
        lambda: SensorPose(t[0], np.array([15.0, 15.0, 6.0]), 0.4),
    )
    assert sensors.lidar().shape == (0, 3)
    scan = sensors.lidar_scan()
    assert scan.points.shape == (0, 3)
    frame = sensors.camera()
    assert not frame.depth_m.any() and frame.detections == ()


def test_one_scan_and_one_frame_per_pose_time() -> None:
    t = [0.0]
    p = np.array([5.0, 5.0, 1.0])
    sensors = MapSensors(
        SimWorld(room(), [ART]),
        SimConfig(),
        np.random.default_rng(0),
        lambda: SensorPose(t[0], p, 0.0),
    )
    scan, frame = sensors.lidar_scan(), sensors.camera()
    assert sensors.lidar_scan() is scan and sensors.camera() is frame
    t[0] = 0.05
    again = sensors.lidar_scan()
    assert again is not scan and again.time_s == 0.05
    assert not np.array_equal(again.points, scan.points)  # fresh range noise
    assert sensors.camera() is not frame


def test_a_missions_sensor_settings_and_artifacts_build_map_sensors() -> None:
    """What a provider other than the simulator does for its opt-in map sensors."""
    m = load_mission_text(
        """\
mission: m
version: 1
world: {map: {generate: empty, size: [20, 10, 6]}}
agents: [{id: R1, library: aerial, start: [5, 5, 0]}]
task_types: {inspect: {goal: at_goal(location), cost: path_cost(location)}}
runtime:
  sim:
    lidar_range_m: 1.5
    dust_points: 2
    detection_noise_px: 0
    max_speed_m_s: 0.2
    velocity_noise: 0.05
    velocity_noise_tau_s: 2
    pose_noise_m: 0.002
    heading_noise_rad: 0.01
    artifacts: [{label: survivor, position: [9, 5, 2], size_m: 0.6}]
""",
        "m.yaml",
    )
    config = sim_config(m)
    assert (config.lidar_range_m, config.dust_points, config.detection_noise_px) == (1.5, 2, 0.0)
    assert config.max_speed_m_s == 0.2
    assert (config.velocity_noise, config.velocity_noise_tau_s) == (0.05, 2.0)
    assert (config.pose_noise_m, config.heading_noise_rad) == (0.002, 0.01)
    sensors = MapSensors(
        SimWorld(room(), mission_artifacts(m)),
        config,
        np.random.default_rng(0),
        lambda: SensorPose(0.0, np.array([5.0, 5.0, 1.9]), 0.0),
    )
    (det,) = sensors.camera().detections
    assert det.label == "survivor" and det.bbox[2] == pytest.approx(
        32 / np.tan(np.radians(43)) * 0.15
    )
    assert len(sensors.lidar()) == 2  # nothing within 1.5 m but the dust
