"""The embedded simulator: PX4-like rules, vehicle models, sensors, collisions."""

from __future__ import annotations

import functools
import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btmission.backends.autopilot import DISARM_LAND_S, OFFBOARD_LOSS_S
from btmission.backends.sim import SimConfig, Simulator, thrust_attitude
from btmission.backends.simworld import WALL_QUERY_M, Artifact, SimWorld
from btmission.control.mav_model import MavParams, mav_dynamics, world_to_yaw_frame
from btmission.vehicles.base import Backend, Mode, Sensors
from btmission.world.voxel import OCCUPIED, VoxelMap


def room(size: tuple[float, float, float] = (20, 10, 6), res: float = 0.5) -> VoxelMap:
    """A closed box: floor, walls and roof of rock around open space; floor top at z = 0."""
    vm = VoxelMap.empty(size, res, origin=(0.0, 0.0, -res))
    st_ = vm.state
    st_[0, :, :] = st_[-1, :, :] = OCCUPIED
    st_[:, 0, :] = st_[:, -1, :] = OCCUPIED
    st_[:, :, 0] = st_[:, :, -1] = OCCUPIED
    return vm


def stream(sim: Simulator, vid: str, seconds: float, hz: float = 20.0) -> None:
    """Stream hold setpoints at ``hz`` for ``seconds`` while the simulator runs."""
    veh = sim.backends[vid]
    every = max(1, round(1.0 / (hz * sim.config.step_s)))
    for k in range(round(seconds / sim.config.step_s)):
        if k % every == 0:
            veh.set_position_setpoint(veh.telemetry().position)
        sim.step()


def flying(sim: Simulator, vid: str = "R1") -> None:
    """Arm, switch to OFFBOARD and climb to 2 m with position setpoints."""
    veh = sim.backends[vid]
    stream(sim, vid, 1.2)
    assert veh.arm() and veh.set_mode(Mode.OFFBOARD)
    p = veh.telemetry().position
    for _ in range(120):
        veh.set_position_setpoint((p[0], p[1], 2.0))
        sim.step()
    assert not veh.telemetry().landed


def test_sim_vehicle_implements_the_interfaces() -> None:
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    assert isinstance(veh, Backend) and isinstance(veh, Sensors)
    tel = veh.telemetry()
    assert tel.landed and not tel.armed and tel.mode is Mode.MANUAL
    assert tel.ground_z == pytest.approx(0.0) and tel.position[2] == pytest.approx(0.0)


def test_offboard_is_refused_until_setpoints_have_streamed() -> None:
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    ack = veh.set_mode(Mode.OFFBOARD)
    assert not ack and "stream" in ack.reason
    stream(sim, "R1", 0.5)
    assert not veh.set_mode(Mode.OFFBOARD)  # streaming, but not for a second yet
    stream(sim, "R1", 0.7)
    assert veh.set_mode(Mode.OFFBOARD)
    assert veh.telemetry().mode is Mode.OFFBOARD


def test_offboard_needs_more_than_2_hz() -> None:
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    stream(sim, "R1", 3.0, hz=1.0)
    assert not veh.set_mode(Mode.OFFBOARD)


def test_takeoff_is_refused_unarmed_and_climbs_when_armed() -> None:
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    ack = veh.takeoff(2.0)
    assert not ack and "not armed" in ack.reason
    assert veh.arm()
    assert veh.takeoff(2.0)
    assert veh.telemetry().mode is Mode.TAKEOFF
    for _ in range(300):
        sim.step()
    tel = veh.telemetry()
    assert tel.mode is Mode.HOLD and not tel.landed
    assert tel.position[2] == pytest.approx(2.0, abs=0.15)


def test_arm_is_refused_in_the_air_and_land_disarms() -> None:
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    flying(sim)
    ack = veh.arm()
    assert ack  # already armed: accepted
    assert not veh.disarm()  # cannot disarm in the air
    assert veh.land()
    for _ in range(round((4.0 + DISARM_LAND_S + 0.5) / sim.config.step_s)):
        sim.step()
    tel = veh.telemetry()
    assert tel.landed and not tel.armed
    assert tel.position[2] == pytest.approx(0.0, abs=0.05)


def test_offboard_loss_switches_to_hold() -> None:
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    flying(sim)
    for _ in range(round((OFFBOARD_LOSS_S + 0.2) / sim.config.step_s)):
        sim.step()  # no setpoints
    tel = veh.telemetry()
    assert tel.mode is Mode.HOLD and tel.armed and not tel.landed
    assert "offboard" in veh.failsafe


def test_an_armed_vehicle_that_never_takes_off_disarms() -> None:
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    assert veh.arm()
    for _ in range(round(11 / sim.config.step_s)):
        sim.step()
    assert not veh.telemetry().armed


def test_flying_into_a_wall_is_a_collision() -> None:
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    flying(sim)
    events = []
    for _ in range(400):
        veh.set_position_setpoint((30.0, 5.0, 2.0))  # beyond the wall at x = 19.5
        events += sim.step()
    hits = [e for e in events if e.other == "rock"]
    assert len(hits) == 1 and hits[0].vehicle == "R1"
    assert veh.telemetry().position[0] < 19.5  # it never goes through the rock


def test_two_vehicles_meeting_collide_once() -> None:
    sim = Simulator(room())
    a = sim.add_multirotor("A", (5, 5, 0))
    b = sim.add_multirotor("B", (8, 5, 0))
    for vid in ("A", "B"):
        flying(sim, vid)
    events = []
    for _ in range(200):
        a.set_position_setpoint((5.0, 5.0, 2.0))  # A hovers (it has been since it took off)
        b.set_position_setpoint((6.0, 5.0, 2.0))  # B flies into it
        events += sim.step()
    pairs = {(e.vehicle, e.other) for e in events}
    assert pairs == {("A", "B"), ("B", "A")} and len(events) == 2


def test_clearance_is_the_gap_to_the_nearest_wall() -> None:
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    flying(sim)
    for _ in range(100):
        veh.set_position_setpoint((5.0, 2.0, 2.0))
        sim.step()
    sim.take_clearance("R1")
    sim.step()
    gap = sim.take_clearance("R1")
    p = veh.telemetry().position
    # the wall face is y = 0.5; the body sphere (radius 0.25) is centred 0.25 above p
    assert gap == pytest.approx(p[1] - 0.5 - sim.config.body_radius_m, abs=0.2)


@settings(max_examples=60, deadline=None)
@given(st.floats(-3, 3), st.floats(-3, 3), st.floats(-3, 3), st.floats(-math.pi, math.pi))
def test_thrust_attitude_inverts_the_model(ax: float, ay: float, az: float, yaw: float) -> None:
    """The [T, φ, θ] returned gives back the requested acceleration (inside the tilt limit)."""
    acc = np.array([ax, ay, az])
    u = thrust_attitude(acc, yaw)
    x = np.zeros(8)
    x[6], x[7] = u[1], u[2]  # attitude settled at the reference
    a_yaw = mav_dynamics(x, u, MavParams(drag=(0.0, 0.0, 0.0)))[3:6]
    want = world_to_yaw_frame(acc, yaw)
    tilt = math.hypot(want[0], want[1]) / (want[2] + 9.81)
    if want[2] + 9.81 > 0.2 * 9.81 and tilt <= math.tan(0.35):
        np.testing.assert_allclose(a_yaw, want, atol=1e-9)
    assert abs(u[1]) <= 0.35 + 1e-9 and abs(u[2]) <= 0.35 + 1e-9


def test_ground_robot_drives_its_cmd_vel_and_stops_at_walls() -> None:
    sim = Simulator(room())
    g = sim.add_ground("G1", (5, 5, 0))
    assert g.arm() and not g.takeoff(1.0)
    for _ in range(40):  # 2 s at 0.4 m/s along +x
        g.set_velocity_setpoint((0.4, 0.0, 0.0), 0.0)
        sim.step()
    assert g.telemetry().position[0] == pytest.approx(5.8, abs=0.02)
    for _ in range(40):  # no command: a cmd_vel timeout stops it
        sim.step()
    assert g.telemetry().position[0] == pytest.approx(5.8 + 0.4 * 0.5, abs=0.05)
    events = []
    for _ in range(1000):
        g.set_velocity_setpoint((0.4, 0.0, 0.0), 0.0)
        events += sim.step()
    assert g.telemetry().position[0] < 19.5 and any(e.other == "rock" for e in events)


def test_lidar_sees_rock_within_range_other_vehicles_and_dust() -> None:
    sim = Simulator(room(), SimConfig(lidar_range_m=2.0, dust_points=3), seed=1)
    a = sim.add_multirotor("A", (5, 1.5, 0))
    pts = a.lidar()
    assert len(pts) and np.all(np.linalg.norm(pts[:-3], axis=1) <= 2.0 + 1e-9)
    sim.add_multirotor("B", (6, 1.5, 0))
    with_b = a.lidar()
    assert len(with_b) > len(pts)  # B's body appears in the scan
    sim2 = Simulator(room(), SimConfig(lidar_range_m=2.0, dust_points=3), seed=1)
    sim2.add_multirotor("A", (5, 1.5, 0))
    np.testing.assert_array_equal(sim2.backends["A"].lidar(), pts)  # seeded


def test_depth_camera_sees_the_wall_and_detects_an_artifact() -> None:
    vm = room()
    art = np.array([9.0, 5.0, 2.0])
    sim = Simulator(
        vm, SimConfig(detection_noise_px=0.0), artifacts=[Artifact("survivor", (9, 5, 2), 0.6)]
    )
    veh = sim.add_multirotor("R1", (5, 5, 0))
    flying(sim)
    frame = veh.camera()
    assert frame.depth_m.max() <= sim.config.camera_range_m
    assert len(frame.detections) == 1 and frame.detections[0].label == "survivor"
    x0, y0, bw, bh = frame.detections[0].bbox
    rel = frame.rotation.T @ (art - frame.translation)  # optical frame
    u = frame.intrinsics.fx * rel[0] / rel[2] + frame.intrinsics.cx
    v = frame.intrinsics.fy * rel[1] / rel[2] + frame.intrinsics.cy
    assert x0 + bw / 2 == pytest.approx(u) and y0 + bh / 2 == pytest.approx(v)
    # the localiser's 3×3 window at the box centre reads the artifact's front surface
    centre = frame.depth_m[round(v), round(u)]
    assert centre == pytest.approx(rel[2] - 0.3, abs=0.1)


def test_world_surfaces_and_ground_heights() -> None:
    vm = room()
    world = SimWorld(vm)
    assert world.ground_z(np.array([5.0, 5.0, 3.0])) == pytest.approx(0.0)
    assert world.occupied(np.array([5.0, 5.0, -0.2]))
    # faces are sampled at their centres: the nearest lies up to half a voxel (diagonally) aside
    assert world.wall_distance(np.array([5.0, 5.0, 2.0])) == pytest.approx(3.0, abs=0.03)
    assert world.wall_distance(np.array([5.0, 1.5, 3.0])) == pytest.approx(1.0, abs=0.12)


# ------------------------------------------------------------------------------------- noise
def _drive(seed: int, config: SimConfig, steps: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """A ground robot on a constant cmd_vel: (true states, reported [x, y, ψ]) per step."""
    sim = Simulator(room(), config, seed=seed)
    g = sim.add_ground("G1", (2, 5, 0))
    truth, told = [], []
    for _ in range(steps):
        g.set_velocity_setpoint((0.3, 0.0, 0.0), 0.1)
        sim.step()
        tel = g.telemetry()
        truth.append(sim.vehicle("G1").x.copy())
        told.append([tel.position[0], tel.position[1], tel.yaw])
    return np.array(truth), np.array(told)


NOISY = SimConfig(velocity_noise=0.05, pose_noise_m=0.002, heading_noise_rad=0.01)


def test_noise_is_the_same_for_a_seed_and_differs_across_seeds() -> None:
    a, told_a = _drive(0, NOISY)
    b, told_b = _drive(0, NOISY)
    c, _ = _drive(1, NOISY)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(told_a, told_b)
    assert np.abs(a - c).max() > 0.01  # another seed drives another path
    quiet, told = _drive(0, SimConfig())  # off by default: exactly the command, told the truth
    np.testing.assert_array_equal(quiet, told)
    assert np.array_equal(quiet, _drive(5, SimConfig())[0])  # and no seed changes it


def test_velocity_noise_is_a_gauss_markov_error_of_the_command() -> None:
    """e ← a·e + √(1−a²)·σ·ξ with a = exp(−dt/τ): standard deviation σ, lag-one correlation a;
    the robot drives (1 + e) times its command."""
    cfg = SimConfig(velocity_noise=0.1, velocity_noise_tau_s=0.5)
    sim = Simulator(room(), cfg, seed=3)
    g = sim.add_ground("G1", (5, 5, 0))
    v = sim.vehicle("G1")
    errors, speeds = [], []
    for _ in range(20_000):
        g.set_velocity_setpoint((0.2, 0.0, 0.0), 0.0)
        before = v.drive_error.copy()
        sim.step()
        errors.append(before)
        speeds.append(v.sp_vel_body)
        v.x[:2] = (5.0, 5.0)  # keep it in the room
    e = np.array(errors)
    assert e.std(axis=0) == pytest.approx([0.1, 0.1], rel=0.15)
    a = math.exp(-cfg.step_s / cfg.velocity_noise_tau_s)
    lag1 = [np.corrcoef(e[:-1, k], e[1:, k])[0, 1] for k in range(2)]
    assert lag1 == pytest.approx([a, a], abs=0.02)
    np.testing.assert_allclose(speeds, 0.2 * (1 + e[:, 0]), atol=1e-12)


def test_telemetry_is_one_read_only_record_per_step_and_autopilot_state() -> None:
    """The simulator builds a vehicle's telemetry once per step: asked again within the step it
    is the same record, with read-only arrays; a command that changes the autopilot's state
    (arm, take-off) shows at once, and the next step gives a new record."""
    sim = Simulator(room(), SimConfig())
    d = sim.add_multirotor("D1", (5, 5, 0))
    first = d.telemetry()
    assert d.telemetry() is first and not first.armed
    with pytest.raises(ValueError, match="read-only"):
        first.position[0] = 1.0
    assert d.arm().accepted
    armed = d.telemetry()
    assert armed is not first and armed.armed and armed.time_s == first.time_s
    assert d.takeoff(2.0).accepted
    assert d.telemetry().mode is Mode.TAKEOFF
    for _ in range(20):
        sim.step()
    later = d.telemetry()
    assert later.time_s > first.time_s and later.position[2] > 0.1
    assert later.position[2] == sim.vehicle("D1").x[2]  # the state now, not a stale copy


def test_telemetry_after_a_step_is_the_stepped_state_and_follows_a_replaced_state() -> None:
    """After a compiled step a drone's telemetry takes its position and velocity from the step
    (read-only views of one copy for the fleet): equal to the state, not aliasing it; a state
    replaced since (e.g. by a test) is read afresh."""
    sim = Simulator(room(), SimConfig())
    drones = [sim.add_multirotor(f"D{i}", (3.0 + i, 5.0, 0.0)) for i in range(3)]
    for d in drones:
        assert d.arm().accepted and d.takeoff(2.0).accepted
    for _ in range(10):
        sim.step()
    for i, d in enumerate(drones):
        v = sim.vehicle(f"D{i}")
        tel = d.telemetry()
        assert tel.position.tolist() == v.x[:3].tolist()
        assert tel.velocity.tolist() == v.x[3:6].tolist()
        assert (tel.roll, tel.pitch) == (float(v.x[6]), float(v.x[7]))
        assert not np.shares_memory(tel.position, v.x)
        with pytest.raises(ValueError, match="read-only"):
            tel.velocity[0] = 1.0
    v = sim.vehicle("D1")
    v.x = v.x.copy()
    v.x[:3] = (4.0, 6.0, 1.0)
    assert drones[1].land().accepted  # (a mode change: the record is built again)
    assert drones[1].telemetry().position.tolist() == [4.0, 6.0, 1.0]


def test_pose_noise_is_in_the_telemetry_only() -> None:
    """The vehicle reports its pose with the configured error; it moves, collides and senses
    at its true pose, and turning the noise on changes neither the dust nor the detections
    (each vehicle has its own generator)."""
    truth, told = _drive(2, SimConfig(pose_noise_m=0.01, heading_noise_rad=0.02), steps=2000)
    err = told - truth
    assert err[:, :2].std() == pytest.approx(0.01, rel=0.1)
    assert err[:, 2].std() == pytest.approx(0.02, rel=0.1)
    assert abs(err.mean(axis=0)).max() < 0.002
    quiet, _ = _drive(2, SimConfig(), steps=2000)
    np.testing.assert_array_equal(truth, quiet)  # pose noise alone does not move it
    scans = []
    for cfg in (
        SimConfig(dust_points=3),
        SimConfig(dust_points=3, pose_noise_m=0.01, velocity_noise=0.1),
    ):
        sim = Simulator(room(), cfg, seed=4)
        sim.add_ground("G1", (5, 1.5, 0))
        sim.step()
        scans.append(sim.backends["G1"].lidar())
    np.testing.assert_array_equal(scans[0], scans[1])


def test_a_vehicles_noise_does_not_depend_on_the_others() -> None:
    def errors(ids: list[str], of: str = "G1") -> np.ndarray:
        sim = Simulator(room(), SimConfig(pose_noise_m=0.01), seed=7)
        for k, vid in enumerate(ids):
            sim.add_ground(vid, (2 + 2 * k, 5, 0))
        out = []
        for _ in range(20):
            sim.step()
            out.append(sim.vehicle(of).estimate_error.copy())
        return np.array(out)

    np.testing.assert_array_equal(errors(["G1"]), errors(["G0", "G1", "G2"]))
    assert not np.array_equal(errors(["G1"]), errors(["G2"], of="G2"))  # its own stream


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"velocity_noise": 0.8}, "velocity_noise must be in [0, 0.5]"),
        ({"velocity_noise": -0.1}, "velocity_noise must be in [0, 0.5]"),
        ({"velocity_noise_tau_s": 0.0}, "velocity_noise_tau_s positive"),
        ({"pose_noise_m": -1.0}, "pose_noise_m and heading_noise_rad must be >= 0"),
        ({"heading_noise_rad": -1.0}, "pose_noise_m and heading_noise_rad must be >= 0"),
    ],
)
def test_bad_noise_settings_are_refused(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        SimConfig(**kwargs)  # type: ignore[arg-type]


# ---- the fast paths of a step give the vector forms' results, to the bit (issue 19)
@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-5, 5), min_size=8, max_size=8),
    st.floats(0, 20),
    st.floats(-0.4, 0.4),
    st.floats(-0.4, 0.4),
)
def test_the_compiled_rk4_step_is_the_vector_one(
    x: list[float], thrust: float, phi: float, theta: float
) -> None:
    from btmission.backends import _multirotor_kernels as kernels
    from btmission.backends.sim import Simulator
    from btmission.control.mav_model import rk4_step

    p = MavParams()
    u = [thrust, phi, theta]
    vec = rk4_step(lambda s, w: mav_dynamics(s, w, p), np.array(x), np.array(u), 0.05)
    packed = Simulator(VoxelMap.empty((4, 4, 4), 1.0), params=p)._packed
    assert np.array_equal(kernels.rk4(np.array(x), np.array(u), 0.05, packed), vec)


@settings(max_examples=300, deadline=None)
@given(st.floats(-2, 62), st.floats(-2, 42), st.floats(-2, 10))
def test_the_compiled_ground_and_rock_queries_are_the_worlds(x: float, y: float, z: float) -> None:
    """The multirotor step's own ``occupied`` and ``ground_z`` (a column scan) answer as the
    world's (its ground table, and ``VoxelMap.ground_z``) do, in and around the map."""
    from btmission.backends import _multirotor_kernels as kernels

    world = _shared_mine_world()
    assert kernels.occupied(world._occ, world._grid, x, y, z) == world.occupied((x, y, z))
    assert kernels.ground_z(world._occ, world._grid, x, y, z) == world.ground_z((x, y, z))
    assert kernels.ground_z(world._occ, world._grid, x, y, z) == world.map.ground_z((x, y, z))


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-3, 3), min_size=5, max_size=5),
    st.floats(-3.1, 3.1),
    st.floats(5, 15),
    st.floats(-0.3, 0.3),
    st.floats(-0.3, 0.3),
)
def test_the_compiled_step_flies_the_model_in_the_yaw_frame(
    v: list[float], yaw: float, thrust: float, phi: float, theta: float
) -> None:
    """In open air, under an attitude setpoint, one step is an RK4 step of the vector model in
    the yaw frame, rotated back to the world (seed 002 §3.2.2), and the distance flown."""
    from btmission.backends import _multirotor_kernels as kernels
    from btmission.backends.sim import Simulator
    from btmission.control.mav_model import rk4_step, world_to_yaw_frame, yaw_frame_to_world

    sim = Simulator(VoxelMap.empty((40, 40, 40), 1.0))
    x = np.array([20.0, 20.0, 20.0, *v])
    out = np.zeros(kernels.N_OUT)
    att = np.array([thrust, phi, theta])
    kernels.step(
        x, yaw, kernels.CMD_ATTITUDE, np.zeros(3), np.zeros(3), att, True,
        kernels.YAW_NONE, 0.0, False, 0.05, sim._packed, sim.world._occ, sim.world._grid, out,
    )  # fmt: skip
    body = np.concatenate([[0.0, 0.0, 0.0], world_to_yaw_frame(x[3:6], yaw), x[6:]])
    p = MavParams()
    ref = rk4_step(lambda s, w: mav_dynamics(s, w, p), body, att, 0.05)
    want = np.concatenate(
        [x[:3] + yaw_frame_to_world(ref[:3], yaw), yaw_frame_to_world(ref[3:6], yaw), ref[6:]]
    )
    assert np.allclose(out[:8], want, rtol=0, atol=1e-12)
    assert out[kernels.OUT_ROCK] == 0 and out[kernels.OUT_YAW] == pytest.approx(yaw, abs=1e-12)
    assert out[kernels.OUT_ODOMETER] == pytest.approx(float(np.linalg.norm(want[:3] - x[:3])))


def _mine_world() -> SimWorld:
    from btmission.world.minegen import generate_mine

    return SimWorld(generate_mine(seed=3, size=(60.0, 40.0, 8.0), resolution=0.5).map)


_shared_mine_world = functools.cache(_mine_world)
"""One mine for the property tests that only query it."""


def test_the_world_queries_agree_with_the_voxel_map() -> None:
    world = _mine_world()
    vm = world.map
    rng = np.random.default_rng(0)
    lo, hi = vm.bounds
    pts = rng.uniform(np.asarray(lo) - 2.0, np.asarray(hi) + 2.0, (3000, 3))
    for p in pts:
        idx = vm.world_to_index(p)
        inside = bool(vm.in_bounds(idx))
        assert world.occupied(p) == (inside and vm.state[tuple(idx)] == OCCUPIED)
        assert world.ground_z(p) == vm.ground_z(p)
    assert not world.occupied((math.nan, 1.0, 1.0))
    assert not world.occupied((math.inf, 1.0, 1.0))
    batched = world.wall_distances(pts[:500])
    assert np.array_equal(batched, [world.wall_distance(p) for p in pts[:500]])
    assert any(np.isfinite(batched)) and any(np.isinf(batched))


def test_the_surface_ball_query_is_the_brute_force_one() -> None:
    """The cell-sorted face points give, for balls anywhere (inside, at the edge, outside the
    map, of several radii), exactly the points within the radius, each once; the LiDAR's scan
    is those points relative to the vehicle, rotated into its yaw frame."""
    from btmission.backends.mapsensors import _SPHERE, Bodies

    world = _mine_world()
    surf = world.surface
    rng = np.random.default_rng(5)
    lo, hi = world.map.bounds
    none = Bodies(np.zeros((0, 3)), np.zeros(0))
    counts = []
    for _ in range(300):
        p = rng.uniform(np.asarray(lo) - 1.0, np.asarray(hi) + 1.0)
        r = float(rng.choice([0.4, 2.0, 3.7]))
        got = world.surface_points(p, r)
        d2 = np.einsum("ij,ij->i", surf - p, surf - p)
        want = surf[d2 <= r * r]
        counts.append(len(want))
        assert len(got) == len(want)
        key = lambda a: a[np.lexsort(a.T[::-1])]  # noqa: E731
        assert np.array_equal(key(got), key(want))
        yaw = float(rng.uniform(-math.pi, math.pi))
        scan = world.scan_points(p, r, yaw, none, _SPHERE)
        assert np.allclose(scan, world_to_yaw_frame(got - p, yaw), atol=1e-12)
    assert max(counts) > 50 and min(counts) == 0
    # the nearest wall face, as a brute-force minimum (inf from WALL_QUERY_M on)
    queries = rng.uniform(np.asarray(lo) - 3.0, np.asarray(hi) + 3.0, (400, 3))
    d = np.array(
        [np.sqrt(np.einsum("ij,ij->i", world.walls - q, world.walls - q).min()) for q in queries]
    )
    want = np.where(d < WALL_QUERY_M, d, np.inf)
    got = world.wall_distances(queries)
    assert np.allclose(got, want, rtol=0, atol=1e-12) and np.array_equal(
        np.isinf(got), np.isinf(want)
    )
    assert 0 < np.isinf(want).sum() < 300


def test_the_nearest_wall_in_open_air_is_the_brute_force_minimum_to_the_bit() -> None:
    """Where drones fly — free voxels 0.2-5 m from rock, so the search grows its cube from the
    nearest face found — the clearance is exactly the brute-force minimum of the same formula
    (the clearances in a run's log depend on it)."""
    world = _shared_mine_world()
    vm = world.map
    rng = np.random.default_rng(8)
    lo, hi = vm.bounds
    pts = rng.uniform(lo, hi, (6000, 3))
    free = np.array([vm.state_at(p) not in (None, OCCUPIED) for p in pts])
    queries = pts[free][:400]
    walls = world.walls
    want = []
    for q in queries:
        dx, dy, dz = walls[:, 0] - q[0], walls[:, 1] - q[1], walls[:, 2] - q[2]
        d = float(np.sqrt((dx * dx + dy * dy + dz * dz).min()))
        want.append(d if d < WALL_QUERY_M else math.inf)
    got = world.wall_distances(queries)
    assert got.tolist() == want
    finite = np.isfinite(got)
    assert finite.sum() > 300 and (got[finite] > 2.0).sum() > 20  # (cubes grown past 2 m)


def test_a_fleet_sees_and_touches_each_other_as_before() -> None:
    """LiDAR returns of other vehicles and vehicle-vehicle contacts, computed for all at once,
    are the per-pair vector tests: 25 vehicles at random spots, some touching, some in range."""
    from btmission.backends.mapsensors import _SPHERE, VEHICLE_POINTS, Bodies

    sim = Simulator(VoxelMap.empty((40, 40, 6), 0.5, origin=(0.0, 0.0, -0.5)), SimConfig())
    rng = np.random.default_rng(1)
    for i in range(25):
        sim.add_multirotor(f"V{i}", [*rng.uniform(5, 12, 2), 0.0])
    table = sim.bodies()
    r = sim.config.body_radius_m
    for k, v in enumerate(table.vehicles):
        p = v.position
        others = sim.other_bodies(v.id)
        assert others.skip == k and len(others.radii) == 25
        want = [
            o.position + np.array([0.0, 0.0, r]) - p
            for o in table.vehicles
            if o is not v and float(np.linalg.norm(o.position - p)) < 4.0
        ]
        seen = sim.world.scan_points(p, 4.0, 0.0, others, _SPHERE)  # yaw 0: world axes
        unskipped = sim.world.scan_points(
            p, 4.0, 0.0, Bodies(others.centres, others.radii), _SPHERE
        )
        assert len(unskipped) == len(seen) + VEHICLE_POINTS  # itself, when not skipped
        got = seen.reshape(-1, VEHICLE_POINTS, 3)
        assert 0 < len(got) == len(want) < 24
        assert all(np.allclose(g.mean(axis=0), w, atol=0.05) for g, w in zip(got, want))
        assert all(
            np.allclose(np.linalg.norm(g - g.mean(axis=0), axis=1), r, atol=0.02) for g in got
        )
    touching = []
    vs = table.vehicles
    for i, a in enumerate(vs):
        for b in vs[i + 1 :]:
            if float(np.linalg.norm(a.position - b.position)) < 2 * r:
                touching += [(a.id, b.id), (b.id, a.id)]
    assert touching, "the layout should put some vehicles in touch"
    assert [(e.vehicle, e.other) for e in sim._collisions()] == touching


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.floats(-3, 63), st.floats(-3, 43), st.floats(-3, 11)), max_size=20))
def test_the_vectorised_rock_test_is_the_pointwise_one(
    points: list[tuple[float, float, float]],
) -> None:
    """SimWorld.occupied_rows (every body at once, for the contact test) answers as
    SimWorld.occupied does point by point, in the map, at its edges and outside it."""
    world = _shared_mine_world()
    pts = np.array(points, dtype=float).reshape(-1, 3)
    if len(pts):
        pts[0] = (np.nan, 1.0, 1.0)  # a non-finite point is not in rock
    assert world.occupied_rows(pts) == [world.occupied(p) for p in pts]


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(0, 4), st.floats(0, 4), st.floats(0, 2), st.sampled_from([0.25, 0.3])),
        min_size=2,
        max_size=25,
    )
)
def test_the_contact_tests_candidate_pairs_hold_every_touching_pair(
    bodies: list[tuple[float, float, float, float]],
) -> None:
    """near_pairs (a fleet's contact test) keeps, in row-major order, every pair whose spheres
    touch (the exact test the simulator then applies), and only pairs near touching."""
    from btmission.backends._multirotor_kernels import near_pairs

    centres = np.array([b[:3] for b in bodies], dtype=float)
    radii = np.array([b[3] for b in bodies], dtype=float)
    got = near_pairs(centres, radii, 1e-6).tolist()
    assert got == sorted(got) and all(i < j for i, j in got)
    n = len(bodies)
    touching = [
        [i, j]
        for i in range(n)
        for j in range(i + 1, n)
        if math.sqrt(float((centres[i] - centres[j]) @ (centres[i] - centres[j])))
        < radii[i] + radii[j]
    ]
    assert all(pair in got for pair in touching)
    for i, j in got:
        assert float(np.linalg.norm(centres[i] - centres[j])) < radii[i] + radii[j] + 1e-5


def test_a_fast_built_telemetry_record_is_the_dataclass_it_stands_for() -> None:
    import dataclasses

    from btmission.types import record
    from btmission.vehicles.base import LandedState, Mode, Telemetry

    fields = dict(time_s=1.5, position=np.array([1.0, 2.0, 3.0]), velocity=np.zeros(3), yaw=0.1,
                  roll=0.0, pitch=0.0, yaw_rate=0.2, mode=Mode.HOLD, armed=True, landed=False,
                  landed_state=LandedState.IN_AIR, battery=0.9, ground_z=0.5,
                  failsafe=False)  # fmt: skip
    fast, slow = record(Telemetry, **fields), Telemetry(**fields)  # type: ignore[arg-type]
    assert type(fast) is Telemetry and dataclasses.asdict(fast).keys() == fields.keys()
    assert fast.height_above_ground == slow.height_above_ground == 2.5
    assert dataclasses.replace(fast, yaw=0.3).yaw == 0.3
    with pytest.raises(dataclasses.FrozenInstanceError):
        fast.yaw = 0.3  # type: ignore[misc]
    del fields["ground_z"]
    with pytest.raises(TypeError, match="ground_z"):
        record(Telemetry, **fields)


def test_a_recorder_builds_the_dataclass_and_refuses_what_the_dataclass_refuses() -> None:
    """recorder(cls) builds records equal to cls(...); a missing or unknown field is the
    dataclass's TypeError; a class with __post_init__ (whose check a record would skip) is
    built by the class itself."""
    import dataclasses

    from btmission.types import CameraIntrinsics, recorder

    @dataclasses.dataclass(frozen=True)
    class Pair:
        a: int
        b: str = "x"

    new = recorder(Pair)
    assert recorder(Pair) is new and new(a=1, b="y") == Pair(1, "y")
    assert type(new(a=1, b="y")) is Pair and vars(new(a=1, b="y")) == {"a": 1, "b": "y"}
    with pytest.raises(TypeError, match="'b'"):
        new(a=1)  # (every field by name, its default too)
    with pytest.raises(TypeError, match="'c'"):
        new(a=1, b="y", c=2)
    assert recorder(CameraIntrinsics) is CameraIntrinsics

    @dataclasses.dataclass(frozen=True)
    class Derived:
        a: int
        b: int = dataclasses.field(init=False, default=0)

    assert recorder(Derived) is Derived  # (a field out of __init__: the class builds it)
    with pytest.raises(ValueError, match="focal"):
        recorder(CameraIntrinsics)(fx=0.0, fy=1.0, cx=0.0, cy=0.0)


def test_a_simulated_vehicles_telemetry_arrays_are_read_only() -> None:
    sim = Simulator(VoxelMap.empty((4.0, 4.0, 3.0), 0.5), SimConfig())
    tel = sim.add_multirotor("A", (1.0, 1.0, 0.5)).telemetry()
    assert not tel.position.flags.writeable and not tel.velocity.flags.writeable
    assert tel.position.tolist() == [1.0, 1.0, 0.5] and tel.velocity.tolist() == [0.0, 0.0, 0.0]


def test_the_fleet_step_is_the_single_drone_step_row_by_row() -> None:
    """step_all on a fleet — every command, yaw mode, landed or not, near rock — gives each row
    exactly what step gives that drone alone."""
    from btmission.backends import _multirotor_kernels as kernels
    from btmission.backends.sim import Simulator

    world = _shared_mine_world()
    sim = Simulator(world.map)
    rng = np.random.default_rng(11)
    lo, hi = world.map.bounds
    m = 40
    xs = np.concatenate(
        [rng.uniform(lo, hi, (m, 3)), rng.normal(0, 1.5, (m, 3)), rng.normal(0, 0.2, (m, 2))],
        axis=1,
    )
    yaws = rng.uniform(-3.1, 3.1, m)
    commands = rng.integers(0, 6, m).astype(np.int64)
    targets = xs[:, :3] + rng.normal(0, 3.0, (m, 3))
    velocities = rng.normal(0, 1.0, (m, 3))
    attitudes = np.column_stack([rng.uniform(5, 15, m), rng.normal(0, 0.2, (m, 2))])
    clamps = rng.integers(0, 2, m).astype(np.bool_)
    yaw_modes = rng.integers(0, 3, m).astype(np.int64)
    yaw_sps = rng.uniform(-3, 3, m)
    landed = rng.integers(0, 2, m).astype(np.bool_)
    args = (sim._packed, world._occ, world._grid)
    out = kernels.step_all(xs, yaws, commands, targets, velocities, attitudes, clamps,
                           yaw_modes, yaw_sps, landed, 0.05, *args)  # fmt: skip
    assert out.shape == (m, kernels.N_OUT)
    for i in range(m):
        one = np.zeros(kernels.N_OUT)
        kernels.step(xs[i], float(yaws[i]), int(commands[i]), targets[i], velocities[i],
                     attitudes[i], bool(clamps[i]), int(yaw_modes[i]), float(yaw_sps[i]),
                     bool(landed[i]), 0.05, *args, one)  # fmt: skip
        assert one.tobytes() == out[i].tobytes(), i
    assert {kernels.CMD_NONE, kernels.CMD_POSITION, kernels.CMD_LAND} <= set(commands.tolist())


def test_the_offboard_loss_hold_ends_when_the_setpoints_stream_again() -> None:
    """PX4's failsafe framework (seen on PX4 v1.16 SITL, issue #36): setpoints late for more
    than COM_OF_LOSS_T put the drone in HOLD; once they have streamed again for a second it
    returns to OFFBOARD by itself — unless a mode was asked for meanwhile."""
    sim = Simulator(room())
    veh = sim.add_multirotor("R1", (5, 5, 0))
    flying(sim)
    for _ in range(round(1.5 / sim.config.step_s)):  # no setpoint for 1.5 s
        sim.step()
    assert veh.telemetry().mode is Mode.HOLD and veh.failsafe.startswith("offboard")
    modes = []
    for _ in range(round(1.5 / sim.config.step_s)):
        veh.set_position_setpoint((5.0, 5.0, 2.0))
        sim.step()
        modes.append(veh.telemetry().mode)
    assert modes[0] is Mode.HOLD and modes[-1] is Mode.OFFBOARD  # back, after the stream's second
    assert modes.index(Mode.OFFBOARD) * sim.config.step_s == pytest.approx(1.0, abs=0.15)
    # a HOLD asked for is not the failsafe's: the stream does not end it
    assert veh.set_mode(Mode.HOLD)
    for _ in range(round(1.5 / sim.config.step_s)):
        veh.set_position_setpoint((5.0, 5.0, 2.0))
        sim.step()
    assert veh.telemetry().mode is Mode.HOLD
