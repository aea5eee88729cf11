"""The embedded simulator: multirotors and ground robots in a voxel world, with PX4-like rules.

One :class:`Simulator` holds the world (a :class:`~btmission.world.voxel.VoxelMap`) and every
vehicle, and advances them all by a fixed step (:meth:`Simulator.step`); it owns no clock and
never sleeps, so it runs as fast as the machine allows, and the same seed gives the same run.
Each vehicle is driven through a :class:`SimVehicle`, which implements the
:class:`~btmission.vehicles.base.Backend` and :class:`~btmission.vehicles.base.Sensors`
interfaces.

This module holds the simulator, its settings (:class:`SimConfig`) and its vehicles. The static
world it queries (rock faces, ground heights, ray casting, the mission's artifacts) is
:class:`~btmission.backends.simworld.SimWorld`; the simulator as the run's vehicle provider (the
``sim`` entry point, :func:`~btmission.backends.sim_provider.sim_provider`) is
:mod:`btmission.backends.sim_provider`.

**Vehicle models.** A multirotor is the seed 002 eight-state model
(:mod:`btmission.control.mav_model`: x = [p, v, φ, θ], u = [T, φ_ref, θ_ref], attitude as a
first-order lag) integrated with RK4, plus a yaw that follows the commanded yaw rate. A ground
robot is the seed 003 unicycle (eq. 11, :func:`~btmission.control.unicycle_nmpc.unicycle_step`)
on the floor, driven by [u_v, u_ω] like a TurtleBot's cmd_vel.

**Autopilot rules** (PX4 offboard semantics, DESIGN.md §8), so behaviour written against the
simulator carries over to a real autopilot:

* OFFBOARD is refused until setpoints have been streaming at more than 2 Hz for at least 1 s;
* arming is refused in the air, and with the battery below 10 %; an armed vehicle that has not
  taken off within 10 s disarms (COM_DISARM_PRFLT), and one that has landed disarms after 2 s
  (COM_DISARM_LAND);
* take-off (AUTO.TAKEOFF) is refused unless armed; LAND descends at 0.7 m/s and disarms after
  touch-down;
* in OFFBOARD, setpoints that stop for more than 1 s (COM_OF_LOSS_T) switch the vehicle to HOLD;
* position and velocity setpoints go through a cascaded position → velocity → attitude
  controller (what PX4 runs on board); attitude setpoints (the NMPC's output) go straight to the
  attitude loop. Tilt is limited to 0.35 rad, as in the NMPC.

**Sensors** are :class:`~btmission.backends.mapsensors.MapSensors` at the vehicle's true pose,
with the simulator's generator and the other vehicles' body spheres: the LiDAR returns points on
the rock surfaces within range (the centres of the faces between rock voxels and open voxels; no
occlusion), plus optional dust outliers near the vehicle (seed 002 §3.2.3's reason for the dust
rule); the depth camera is a low-resolution pinhole camera ray-cast through the voxel map (for
DPHR); artifacts listed in the mission are rendered into the depth image as spheres and detected
with noisy boxes and probabilities (for the COMPRA object localiser). The full-range 3D LiDAR scan
(``lidar_scan``, for global relocalization) casts every beam of an OS1-32-like sensor through the
voxel map, gravity-aligned, with range noise from the simulator's seeded generator.

**Noise** (off unless the mission sets it; ``runtime.sim``, docs/running.md). Seed 003's
TurtleBots took their pose from a Vicon motion-capture system, so what set a real run apart from
its model was mostly the robots not driving exactly what they were told (wheel slip, the motors'
speed loops, the floor) plus a millimetre-level pose estimate. So a ground robot drives its
command scaled by (1 + e): e = [e_v, e_ω] is a first-order Gauss-Markov process per robot
(stationary standard deviation ``velocity_noise``, correlation time ``velocity_noise_tau_s``:
``e ← a·e + √(1−a²)·σ·ξ``, a = exp(−dt/τ)), the result clipped to the motors' limits; and every
vehicle's telemetry reports its x-y position and heading with white Gaussian errors
(``pose_noise_m``, ``heading_noise_rad``), drawn once per step, while collisions, clearances,
the odometer and the sensors use the true pose (a LiDAR scan is taken where the vehicle is and
read where it thinks it is). Each vehicle draws from its own generator, seeded by the run's seed
and the vehicle's id, so turning noise on changes neither the dust nor the detections, a
vehicle's noise does not depend on the others, and a run is still the same for the same seed.

**Collisions.** A vehicle is a sphere of radius ``body_radius_m`` whose bottom touches the
ground when landed. It collides with rock when the sphere reaches a wall or roof face, when its
centre enters a rock voxel, or when it hits the ground faster than 2 m/s; with another vehicle
when the spheres overlap. ``clearance_m`` is the smallest distance from the sphere to a wall or
roof face (the floor under a vehicle is where it lands, so it is not counted).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from btmission.backends.autopilot import (
    _OFFBOARD,
    DISARM_LAND_S,
    AutopilotFields,
    G,
    OffboardCommands,
    autopilot_rules,
    landed_state_of,
)
from btmission.backends.mapsensors import Bodies, MapSensors, SensorPose
from btmission.backends.simworld import Artifact, SimWorld
from btmission.control.mav_model import MavParams
from btmission.localization.scan import LidarSensor
from btmission.types import FloatArray, recorder
from btmission.vehicles.base import (
    CameraFrame,
    LidarScan,
    Mode,
    Telemetry,
    VehicleKind,
)
from btmission.vehicles.provider import VehicleEvent
from btmission.world.voxel import VoxelMap

LAND_SPEED = 0.7
TILT_MAX = 0.35
IMPACT_SPEED = 2.0
YAW_RATE_MAX = 0.8
"""Heading-loop rate limit (rad/s), about PX4's MPC_YAWRAUTO_MAX."""
CONTACT_GAP_S = 0.5
SMALL_FLEET = 6
"""Up to this many vehicles the contact test loops over the pairs (numpy's set-up costs more)."""
POSITION_GAIN = 1.0
"""The autopilot's position loop: velocity command (m/s) per metre of position error."""
VELOCITY_GAIN = 1.2
"""The autopilot's velocity loop: acceleration command (m/s²) per m/s of velocity error."""
HEADING_P = 1.0
"""Heading loop gain (rad/s per rad) for position setpoints with a yaw."""
CMD_VEL_TIMEOUT_S = 0.5
NOISE_STREAM = 3
"""Mixed into each vehicle's noise generator seed (with the run's seed and the id's CRC-32), so
its stream is unrelated to the simulator's own (dust, detections, scans)."""

_new_telemetry = recorder(Telemetry)
"""Builds a :class:`Telemetry` (every vehicle, every step: :func:`~btmission.types.recorder`)."""

# (members read every step, for every vehicle: on Python 3.11 reading an Enum member through its
# class costs about five times reading a module global; _OFFBOARD is the autopilot's)
_MULTIROTOR, _GROUND = VehicleKind.MULTIROTOR, VehicleKind.GROUND
_TAKEOFF, _HOLD, _LAND, _MANUAL = Mode.TAKEOFF, Mode.HOLD, Mode.LAND, Mode.MANUAL


@dataclass(frozen=True)
class SimConfig:
    """Simulator settings (a mission's ``runtime.sim`` section, plus vehicle constants)."""

    step_s: float = 0.05
    lidar_range_m: float = 2.0
    dust_points: int = 0
    detection_noise_px: float = 2.0
    body_radius_m: float = 0.25
    ground_radius_m: float = 0.15
    max_speed_m_s: float = 3.0
    """Horizontal speed limit of the on-board position controller (PX4 MPC_XY_VEL_MAX)."""
    max_climb_m_s: float = 1.5
    land_speed_m_s: float = LAND_SPEED
    """AUTO.LAND's descent speed (PX4 MPC_LAND_SPEED; mavsim's PX4 vehicles land at PX4 SIH's
    ~0.8 m/s, its ArduCopters at LAND_SPEED's 0.5 m/s)."""
    land_crawl_m_s: float | None = None
    """Below :attr:`land_crawl_alt_m` above the ground AUTO.LAND descends this slowly (PX4
    ``MPC_LAND_CRWL`` with a distance sensor, below ``MPC_LAND_ALT3``: mavsim's PX4 vehicles,
    0.3 m/s); None, the embedded simulator's, lands at :attr:`land_speed_m_s` all the way."""
    land_crawl_alt_m: float = 1.0
    disarm_land_s: float = DISARM_LAND_S
    """A vehicle that has landed disarms this long after touching down (PX4 COM_DISARM_LAND,
    2 s; mavsim's ArduCopters disarm 0.5 s after, as ArduCopter SITL did)."""
    ground_v_max: float = 0.4
    ground_v_min: float = -0.1
    ground_omega_max: float = 1.5
    battery_s: float = 1200.0
    """Flight time on a full battery (s)."""
    camera_size: tuple[int, int] = (64, 48)
    camera_hfov_deg: float = 86.0
    camera_range_m: float = 6.0
    velocity_noise: float = 0.0
    """Ground robots: standard deviation of the relative error between the commanded and the
    driven speed and turn rate (0.05: 5 %; module docstring)."""
    velocity_noise_tau_s: float = 1.0
    """Correlation time of that error (s)."""
    pose_noise_m: float = 0.0
    """Standard deviation of the telemetry's x and y about the true position (m)."""
    heading_noise_rad: float = 0.0
    """Standard deviation of the telemetry's heading about the true one (rad)."""

    def __post_init__(self) -> None:
        if not 0 < self.step_s <= 0.2:
            raise ValueError(f"step_s must be in (0, 0.2], got {self.step_s}")
        if self.lidar_range_m <= 0 or self.dust_points < 0:
            raise ValueError("lidar_range_m must be positive and dust_points >= 0")
        if not 0 <= self.velocity_noise <= 0.5 or self.velocity_noise_tau_s <= 0:
            raise ValueError(
                "velocity_noise must be in [0, 0.5] and velocity_noise_tau_s positive, got "
                f"{self.velocity_noise}, {self.velocity_noise_tau_s}"
            )
        if not (math.isfinite(self.land_speed_m_s) and self.land_speed_m_s > 0):
            raise ValueError(f"land_speed_m_s must be positive, got {self.land_speed_m_s}")
        crawl = self.land_crawl_m_s
        if crawl is not None and not (math.isfinite(crawl) and crawl > 0):
            raise ValueError(f"land_crawl_m_s must be positive or None, got {crawl}")
        if not (math.isfinite(self.disarm_land_s) and self.disarm_land_s >= 0):
            raise ValueError(f"disarm_land_s must be >= 0, got {self.disarm_land_s}")
        if self.pose_noise_m < 0 or self.heading_noise_rad < 0:
            raise ValueError("pose_noise_m and heading_noise_rad must be >= 0")

    @property
    def noisy(self) -> bool:
        """Whether any per-vehicle noise is on (then every vehicle gets a noise generator)."""
        return self.velocity_noise > 0 or self.pose_noise_m > 0 or self.heading_noise_rad > 0


SimEvent = VehicleEvent
"""Something the simulator detected: a collision (with ``rock`` or another vehicle's id)."""


@dataclass
class _Vehicle(AutopilotFields):
    """A simulated vehicle's state (its autopilot's part: :class:`AutopilotFields`)."""

    id: str
    kind: VehicleKind
    x: FloatArray
    """Multirotor: [p(3), v(3), φ, θ]; ground robot: [p_x, p_y, ψ]."""
    z: float = 0.0
    """Ground robot height (its floor)."""
    yaw: float = 0.0
    yaw_rate: float = 0.0
    odometer_m: float = 0.0
    thrust: float = 0.0
    contact: dict[str, bool] = field(default_factory=dict)
    touching: dict[str, float] = field(default_factory=dict)
    """Other party (rock or a vehicle id) → last time they touched."""
    clearance_min: float = math.inf
    frozen: bool = False

    @property
    def position(self) -> FloatArray:
        if self.kind is VehicleKind.MULTIROTOR:
            return self.x[:3]
        return np.array([self.x[0], self.x[1], self.z])

    @property
    def velocity(self) -> FloatArray:
        if self.kind is VehicleKind.MULTIROTOR:
            return self.x[3:6]
        v = self.sp_vel_body
        return np.array([v * math.cos(self.x[2]), v * math.sin(self.x[2]), 0.0])

    sp_vel_body: float = 0.0
    v_max: float | None = None
    """This ground vehicle's top speed (m/s); None: ``SimConfig.ground_v_max``."""
    noise: np.random.Generator | None = None
    """This vehicle's own noise generator (None: the simulator has no noise on)."""
    drive_error: FloatArray = field(default_factory=lambda: np.zeros(2))
    """[e_v, e_ω]: a ground robot drives (1 + e) times its command (module docstring)."""
    estimate_error: FloatArray = field(default_factory=lambda: np.zeros(3))
    """[δx, δy, δψ]: the telemetry's error about the true pose, drawn every step."""
    stepped: tuple[FloatArray, FloatArray, FloatArray, float, float] | None = None
    """A multirotor's last compiled step, for its telemetry: (``x`` as that step left it, its
    position and velocity as read-only views of one copy for the fleet, roll, pitch). Used
    while ``x`` is still that array (:meth:`SimVehicle._build_telemetry`)."""


@dataclass(frozen=True)
class _BodyTable:
    """Every vehicle's body sphere at one step (:meth:`Simulator.bodies`)."""

    key: tuple[int, int]
    vehicles: list[_Vehicle]
    centres: FloatArray
    radii: FloatArray
    index: dict[str, int]


class Simulator:
    """All vehicles in one world, advanced together by a fixed step (module docstring)."""

    def __init__(
        self,
        voxel_map: VoxelMap,
        config: SimConfig | None = None,
        *,
        seed: int = 0,
        artifacts: Sequence[Artifact] = (),
        params: MavParams | None = None,
    ) -> None:
        self.config = config or SimConfig()
        self.world = SimWorld(voxel_map, artifacts)
        self.params = params or MavParams()
        self._packed = self._pack()
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.time_s = 0.0
        self.steps = 0
        self._vehicles: dict[str, _Vehicle] = {}
        self.backends: dict[str, SimVehicle] = {}
        self._bodies: _BodyTable | None = None

    # ------------------------------------------------------------------ vehicles
    def add_multirotor(self, vid: str, start: Sequence[float], yaw: float = 0.0) -> SimVehicle:
        p = np.asarray(start, dtype=float)
        x = np.zeros(8)
        x[:3] = p
        g = self.world.ground_z(p + np.array([0.0, 0.0, 0.01]))
        x[2] = max(p[2], g)
        v = _Vehicle(vid, VehicleKind.MULTIROTOR, x, yaw=yaw, ground=g)
        v.hold = x[:3].copy()
        return self._add(v)

    def add_ground(
        self, vid: str, start: Sequence[float], yaw: float = 0.0, *, v_max: float | None = None
    ) -> SimVehicle:
        """A differential-drive robot (unicycle); ``v_max`` overrides the configured top speed
        (a haul truck is not a TurtleBot)."""
        if v_max is not None and not v_max > 0:
            raise ValueError(f"v_max must be > 0 m/s, got {v_max}")
        p = np.asarray(start, dtype=float)
        g = self.world.ground_z(p + np.array([0.0, 0.0, 0.01]))
        v = _Vehicle(
            vid,
            VehicleKind.GROUND,
            np.array([p[0], p[1], yaw]),
            z=g,
            yaw=yaw,
            ground=g,
            v_max=v_max,
        )
        v.armed = True  # a ground robot has no arming: it drives when commanded
        return self._add(v)

    def _add(self, v: _Vehicle) -> SimVehicle:
        if v.id in self._vehicles:
            raise ValueError(f"vehicle '{v.id}' exists already")
        if self.config.noisy:
            v.noise = np.random.default_rng([self.seed, NOISE_STREAM, zlib.crc32(v.id.encode())])
            if v.kind is VehicleKind.GROUND and self.config.velocity_noise > 0:
                v.drive_error = v.noise.normal(0.0, self.config.velocity_noise, 2)  # stationary
            self._draw_estimate(v)
        self._vehicles[v.id] = v
        backend = SimVehicle(self, v)
        self.backends[v.id] = backend
        return backend

    def vehicle(self, vid: str) -> _Vehicle:
        return self._vehicles[vid]

    @property
    def vehicle_ids(self) -> list[str]:
        return list(self._vehicles)

    # ------------------------------------------------------------------ stepping
    def step(self) -> list[SimEvent]:
        """Advance every vehicle by one step; returns the collisions that began in it."""
        dt = self.config.step_s
        t = self.time_s
        drones = []
        for v in self._vehicles.values():  # (vehicles do not interact within a step)
            if v.kind is _MULTIROTOR:
                self._autopilot(v, t)
                if not v.frozen:
                    drones.append(v)
            else:
                self._step_ground(v, t, dt)
        if drones:
            self._step_multirotors(drones, dt)
        if self.config.noisy:
            for v in self._vehicles.values():
                self._draw_noise(v, dt)
        self.time_s = round(t + dt, 9)
        self.steps += 1
        return self._collisions()

    # ---- noise (module docstring)
    def _draw_noise(self, v: _Vehicle, dt: float) -> None:
        """Advance ``v``'s drive error one step and draw its next pose-estimate error."""
        cfg = self.config
        assert v.noise is not None
        if v.kind is VehicleKind.GROUND and cfg.velocity_noise > 0:
            a = math.exp(-dt / cfg.velocity_noise_tau_s)
            v.drive_error = a * v.drive_error + math.sqrt(1.0 - a * a) * v.noise.normal(
                0.0, cfg.velocity_noise, 2
            )
        self._draw_estimate(v)

    def _draw_estimate(self, v: _Vehicle) -> None:
        cfg = self.config
        assert v.noise is not None
        if cfg.pose_noise_m > 0 or cfg.heading_noise_rad > 0:
            v.estimate_error = v.noise.normal(0.0, 1.0, 3) * np.array(
                [cfg.pose_noise_m, cfg.pose_noise_m, cfg.heading_noise_rad]
            )

    # ---- multirotor
    def _autopilot(self, v: _Vehicle, t: float) -> None:
        """PX4-like mode logic: failsafes and automatic disarming."""
        autopilot_rules(v, t, lambda: v.x[:3].copy(), self.config.disarm_land_s)

    def _pack(self) -> FloatArray:
        """The model's, autopilot's and simulator's parameters for the compiled step."""
        from btmission.backends._multirotor_kernels import pack_params

        mp, cfg = self.params, self.config
        return pack_params(
            mp.g,
            mp.drag,
            mp.gain_roll,
            mp.tau_roll_s,
            mp.gain_pitch,
            mp.tau_pitch_s,
            cfg.max_speed_m_s,
            cfg.max_climb_m_s,
            cfg.body_radius_m,
            TILT_MAX,
            HEADING_P,
            YAW_RATE_MAX,
            cfg.land_speed_m_s,
            IMPACT_SPEED,
            POSITION_GAIN,
            VELOCITY_GAIN,
        )

    @staticmethod
    def _command(v: _Vehicle, kernels: Any) -> tuple[int, FloatArray, int, float]:
        """What ``v``'s attitude command follows this step (the compiled step's CMD_*), its
        target, and the yaw loop's mode and setpoint (YAW_*): from the mode and the setpoint
        streamed (``kernels``: :mod:`btmission.backends._multirotor_kernels`)."""
        mode, armed, kind = v.mode, v.armed, v.sp_kind
        offboard = mode is _OFFBOARD
        command = kernels.CMD_NONE
        target = v.hold
        if not armed:
            pass
        elif offboard and kind == "attitude":
            command = kernels.CMD_ATTITUDE
        elif offboard and kind == "position":
            command, target = kernels.CMD_POSITION, v.sp_pos
        elif offboard and kind == "velocity":
            command = kernels.CMD_VELOCITY
        elif mode is _TAKEOFF or mode is _HOLD:
            command = kernels.CMD_HOLD
        elif mode is _LAND:
            command = kernels.CMD_LAND
        # yaw: the commanded rate, or a P loop on the heading setpoint
        yaw_mode, yaw_sp = kernels.YAW_NONE, 0.0
        if offboard and kind in ("velocity", "attitude"):
            yaw_mode, yaw_sp = kernels.YAW_RATE, float(v.sp_yaw_rate)
        elif offboard and v.sp_yaw is not None:
            yaw_mode, yaw_sp = kernels.YAW_HEADING, float(v.sp_yaw)
        return command, target, yaw_mode, yaw_sp

    def _crawl(
        self, v: _Vehicle, command: tuple[int, FloatArray, int, float], kernels: Any
    ) -> tuple[int, FloatArray, int, float]:
        """AUTO.LAND below :attr:`SimConfig.land_crawl_alt_m`: the hold point's x, y and a
        height the position loop descends to at :attr:`SimConfig.land_crawl_m_s` (only with a
        crawl configured: mavsim's PX4)."""
        cfg = self.config
        if command[0] != kernels.CMD_LAND or v.x[2] - v.ground >= cfg.land_crawl_alt_m:
            return command
        crawl = float(cfg.land_crawl_m_s or 0.0)
        target = np.array([v.hold[0], v.hold[1], v.x[2] - crawl / POSITION_GAIN])
        return kernels.CMD_HOLD, target, command[2], command[3]

    def _step_multirotors(self, vs: list[_Vehicle], dt: float) -> None:
        """One step of the seed 002 model (RK4 in the yaw frame), the yaw loop, rock and
        ground contact and landing for every drone in one compiled call
        (:func:`~btmission.backends._multirotor_kernels.step_all`, row by row the single
        drone's :func:`~btmission.backends._multirotor_kernels.step`: Python's per-call cost on
        a dozen floats was most of the simulator's time at fleet scale); then each drone's
        mode, battery and odometer."""
        from btmission.backends import _multirotor_kernels as kernels

        command = self._command
        commands = [command(v, kernels) for v in vs]
        if self.config.land_crawl_m_s is not None:
            commands = [self._crawl(v, c, kernels) for v, c in zip(vs, commands)]
        out = kernels.step_all(
            np.array([v.x for v in vs]),
            np.array([v.yaw for v in vs], dtype=float),
            np.array([c[0] for c in commands], dtype=np.int64),
            np.array([c[1] for c in commands], dtype=float),
            np.array([v.sp_vel for v in vs], dtype=float),
            np.array([v.sp_att for v in vs], dtype=float),
            np.array([v.armed and v.mode is not _MANUAL for v in vs], dtype=np.bool_),
            np.array([c[2] for c in commands], dtype=np.int64),
            np.array([c[3] for c in commands], dtype=float),
            np.array([v.landed for v in vs], dtype=np.bool_),
            dt,
            self._packed,
            self.world._occ,
            self.world._grid,
        )
        states = out[:, :8].copy()
        shown = out[:, :6].copy()  # (the telemetry's position and velocity: read-only views)
        shown.flags.writeable = False
        positions, velocities = shown[:, :3], shown[:, 3:]
        t = self.time_s
        battery_s = self.config.battery_s
        for i, (v, rest) in enumerate(zip(vs, out[:, 6:].tolist())):
            x = states[i]
            v.x = x
            roll, pitch, v.yaw, v.yaw_rate, v.thrust, ground, rock, impact, landed, flown = rest
            v.stepped = (x, positions[i], velocities[i], roll, pitch)
            v.ground = ground
            if rock:
                v.contact["rock"] = True  # bumped into rock: stopped at the last free position
            if impact:
                v.contact["impact"] = True
            was_landed = v.landed
            v.landed = landed > 0
            if v.landed and not was_landed:
                v.landed_at = t
            if not v.landed:
                v.took_off = True
            if v.mode is _TAKEOFF and abs(float(x[2]) - v.hold[2]) < 0.1:
                v.mode = _HOLD
            if v.armed:
                v.battery = max(0.0, v.battery - dt / battery_s)
            v.odometer_m += flown

    # ---- ground robot
    def _step_ground(self, v: _Vehicle, t: float, dt: float) -> None:
        from btmission.control.unicycle_nmpc import unicycle_step

        if v.frozen:
            return
        cfg = self.config
        if t - v.sp_time > CMD_VEL_TIMEOUT_S or v.sp_kind != "velocity":
            uv, uw = 0.0, 0.0
        else:
            uv = float(np.dot(v.sp_vel[:2], [math.cos(v.x[2]), math.sin(v.x[2])]))
            v_max = cfg.ground_v_max if v.v_max is None else v.v_max
            uv = float(np.clip(uv, cfg.ground_v_min, v_max))
            uw = float(np.clip(v.sp_yaw_rate, -cfg.ground_omega_max, cfg.ground_omega_max))
            if cfg.velocity_noise > 0:  # the wheels do not quite drive the command
                scale = np.maximum(1.0 + v.drive_error, 0.0)
                uv = float(np.clip(uv * scale[0], cfg.ground_v_min, v_max))
                uw = float(np.clip(uw * scale[1], -cfg.ground_omega_max, cfg.ground_omega_max))
        new = unicycle_step(v.x, np.array([uv, uw]), dt)
        p_new = np.array([new[0], new[1], v.z + cfg.ground_radius_m])
        if self.world.occupied(p_new):
            v.contact["rock"] = True  # a wall stops the robot
            v.sp_vel_body = 0.0
            v.yaw_rate = 0.0
            return
        v.odometer_m += float(math.hypot(new[0] - v.x[0], new[1] - v.x[1]))
        v.x = new
        v.yaw = float(new[2])
        v.yaw_rate = uw
        v.sp_vel_body = uv
        v.landed = True

    # ---- collisions
    def _radius(self, v: _Vehicle) -> float:
        return (
            self.config.body_radius_m
            if v.kind is VehicleKind.MULTIROTOR
            else self.config.ground_radius_m
        )

    def bodies(self) -> _BodyTable:
        """Every vehicle with its body sphere at this step (built once per step and shared by
        the collision check and every vehicle's LiDAR)."""
        key = (self.steps, len(self._vehicles))
        table = self._bodies
        if table is None or table.key != key:
            if table is not None and table.key[1] == key[1]:  # the same vehicles (never removed)
                vs, radii, index = table.vehicles, table.radii, table.index
            else:
                vs = list(self._vehicles.values())
                radii = np.array([self._radius(v) for v in vs], dtype=float)
                radii.flags.writeable = False
                index = {v.id: i for i, v in enumerate(vs)}
            centres = np.array([v.position for v in vs]).reshape(-1, 3)
            centres[:, 2] += radii  # (the body's centre: its radius above the reference point)
            table = self._bodies = _BodyTable(key, vs, centres, radii, index)
        return table

    def other_bodies(self, vid: str) -> Bodies:
        """The body spheres of every vehicle but ``vid`` (for its LiDAR): the whole table, with
        ``vid``'s row to skip."""
        table = self.bodies()
        return Bodies(table.centres, table.radii, table.index[vid])

    def _collisions(self) -> list[SimEvent]:
        out: list[SimEvent] = []
        t = self.time_s
        table = self.bodies()
        vs, centres, radii = table.vehicles, table.centres, table.radii
        if not vs:
            return out
        gaps = (self.world.wall_distances(centres) - radii).tolist()
        inside = self.world.occupied_rows(centres)
        for i, v in enumerate(vs):
            gap = gaps[i]
            measured = not v.landed or v.kind is _GROUND
            if measured and math.isfinite(gap):
                v.clearance_min = min(v.clearance_min, gap)
            contact = v.contact
            hit = gap < -0.02 or inside[i] or contact.pop("impact", False)
            if hit or contact.pop("rock", False):
                self._episode(v, "rock", True, out, t, centres[i])
        if len(vs) < 2:
            return out
        if len(vs) <= SMALL_FLEET:  # a few vehicles: every pair, in the pair loop's order
            near: list[list[int]] = [[i, j] for i in range(len(vs)) for j in range(i + 1, len(vs))]
        else:
            # pairs in touch: the few that come near it in one compiled pass, then the exact
            # test of the vector form (‖c_a − c_b‖ < r_a + r_b) on them
            from btmission.backends._multirotor_kernels import near_pairs

            near = near_pairs(centres, radii, 1e-6).tolist()
        for i, j in near:  # (row-major: the order of the pair loop)
            delta = centres[i] - centres[j]
            if math.sqrt(float(delta @ delta)) < float(radii[i]) + float(radii[j]):
                a, b = vs[i], vs[j]
                self._episode(a, b.id, True, out, t, centres[i])
                self._episode(b, a.id, True, out, t, centres[j])
        return out

    def _episode(
        self, v: _Vehicle, other: str, hit: bool, out: list[SimEvent], t: float, c: FloatArray
    ) -> None:
        """Report a collision when a contact begins: once, however long it lasts (a contact
        counts as over after ``CONTACT_GAP_S`` without touching)."""
        if not hit:
            return
        last = v.touching.get(other)
        if last is None or t - last > CONTACT_GAP_S:
            p = v.position
            out.append(
                SimEvent(t, v.id, "collision", other, (float(p[0]), float(p[1]), float(p[2])))
            )
        v.touching[other] = t

    def take_clearance(self, vid: str) -> float | None:
        """Smallest clearance of ``vid`` since the last call (None if nothing was measured)."""
        v = self._vehicles[vid]
        c = v.clearance_min
        v.clearance_min = math.inf
        return c if math.isfinite(c) else None


def thrust_attitude(acc: FloatArray, yaw: float, g: float = G) -> FloatArray:
    """[T, φ, θ] giving the world acceleration ``acc`` in the seed 002 model.

    In the yaw frame the model's acceleration is [T cos φ sin θ, −T sin φ, T cos φ cos θ − g], so
    with t = R_z(−ψ)(acc + g e_z): T = ‖t‖, φ = asin(−t_y / T), θ = atan2(t_x, t_z). The thrust
    vector is first tilted back inside the tilt limit (keeping its vertical part); the
    simulator's autopilot does this every step
    (:func:`~btmission.backends._multirotor_kernels.thrust_attitude`).
    """
    from btmission.backends._multirotor_kernels import thrust_attitude as compiled

    return np.array(
        compiled(float(acc[0]), float(acc[1]), float(acc[2]), float(yaw), float(g), TILT_MAX)
    )


class SimVehicle(OffboardCommands):
    """One simulated vehicle as its agent sees it: :class:`Backend` and :class:`Sensors` (the
    commands and setpoints, with PX4's rules, are :class:`~btmission.backends.autopilot.
    OffboardCommands`)."""

    def __init__(self, sim: Simulator, vehicle: _Vehicle) -> None:
        self._sim = sim
        self._v = vehicle
        self._ap = vehicle
        self.id = vehicle.id
        self.kind = vehicle.kind
        self.sensors = MapSensors(sim.world, sim.config, sim.rng, self._pose, self._other_bodies)
        """The vehicle's LiDAR and camera, ray-cast at its true pose."""
        self._telemetry: tuple[tuple[object, ...], Telemetry] | None = None

    @property
    def sim(self) -> Simulator:
        """The simulator the vehicle is in."""
        return self._sim

    @property
    def vehicle(self) -> _Vehicle:
        """Its true state in the simulator."""
        return self._v

    @property
    def owns_sensors(self) -> bool:
        """Its sensors are still the simulator's at its true pose (none replaced)."""
        s = self.sensors
        return (
            type(s) is MapSensors
            and s.world is self._sim.world
            and s.config is self._sim.config
            and s.pose == self._pose
            and s.others == self._other_bodies
        )

    # ---------------------------------------------- commands and setpoints: OffboardCommands
    def _ap_time(self) -> float:
        return self._sim.time_s

    def _ap_here(self) -> FloatArray:
        return self._v.x[:3].copy()

    # ------------------------------------------------------------------ telemetry
    def telemetry(self) -> Telemetry:
        """The vehicle's state as it estimates it: the true state, plus the pose-estimate
        error when the simulator has pose noise on (module docstring).

        Built once per simulation step and autopilot state — mode and arming, what a command
        changes between two steps; everything else in it changes only in a step — (its agent,
        tree leaves, neighbours and the run's snapshot each ask several times a step); its
        arrays are read-only, as the record is shared."""
        v = self._v
        key = (self._sim.steps, v.mode, v.armed)
        cached = self._telemetry
        if cached is not None and cached[0] == key:
            return cached[1]
        tel = self._build_telemetry(v)
        self._telemetry = (key, tel)
        return tel

    def _build_telemetry(self, v: _Vehicle) -> Telemetry:
        stepped = v.stepped
        if stepped is not None and stepped[0] is v.x and v.noise is None:
            _, position, velocity, roll, pitch = stepped  # (the usual case: from the step)
            yaw = float(v.yaw)
        else:
            if v.kind is VehicleKind.MULTIROTOR:
                x = v.x
                roll, pitch = float(x[6]), float(x[7])
                state = x[:6].copy()  # position and velocity: one copy, read-only
            else:
                roll = pitch = 0.0
                state = np.concatenate([v.position, v.velocity])
            yaw = float(v.yaw)
            if v.noise is not None:
                err = v.estimate_error
                state[:2] += err[:2]
                yaw += float(err[2])
            state.flags.writeable = False
            position, velocity = state[:3], state[3:]  # (views of a read-only array: read-only)
        return _new_telemetry(
            time_s=self._sim.time_s,
            position=position,
            velocity=velocity,
            yaw=yaw,
            roll=roll,
            pitch=pitch,
            yaw_rate=float(v.yaw_rate),
            mode=v.mode,
            armed=v.armed,
            landed=v.landed,
            landed_state=landed_state_of(v.landed, v.mode),
            battery=v.battery,
            ground_z=v.ground if v.kind is _MULTIROTOR else v.z,
            failsafe=False,  # (its offboard-loss HOLD is one the agent takes back)
        )

    @property
    def failsafe(self) -> str:
        """The last failsafe the autopilot triggered ("" if none)."""
        return self._v.failsafe

    # ------------------------------------------------------------------ sensors
    @property
    def scan_sensor(self) -> LidarSensor:
        """The 3D LiDAR of :meth:`lidar_scan` (seed 000's platforms carry an Ouster OS1-32)."""
        return self.sensors.scan_sensor

    @property
    def lidar_mount_m(self) -> float:
        """Height of that LiDAR above the vehicle's reference point (the bottom of its body)."""
        return self.sensors.lidar_mount_m

    def lidar_scan(self) -> LidarScan:
        """A full turn of the 3D LiDAR at the vehicle's true pose
        (:meth:`MapSensors.lidar_scan <btmission.backends.mapsensors.MapSensors.lidar_scan>`,
        noise from the simulator's generator). One scan per simulation step."""
        return self.sensors.lidar_scan()

    def lidar(self) -> FloatArray:
        """Rock faces and the other vehicles' bodies within range, plus dust
        (:meth:`MapSensors.lidar <btmission.backends.mapsensors.MapSensors.lidar>`)."""
        return self.sensors.lidar()

    def camera(self) -> CameraFrame:
        """Depth image from a forward-looking level camera with the artifacts in view detected
        (:meth:`MapSensors.camera <btmission.backends.mapsensors.MapSensors.camera>`); one frame
        per simulation step."""
        return self.sensors.camera()

    def _pose(self) -> SensorPose:
        v = self._v
        return SensorPose(self._sim.time_s, v.position, v.yaw)

    def _other_bodies(self) -> Bodies:
        return self._sim.other_bodies(self._v.id)
