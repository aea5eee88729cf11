"""A fake vehicle provider (scheme ``fake``): kinematic vehicles for behaviour tests.

Tests of the auction, the commands or a library's tree check what the agents decide, not how they
fly. The ``fake`` provider gives them vehicles that cost next to nothing to step:

* a **multirotor** moves at the velocity its setpoint asks for, capped (horizontal
  ``max_speed_m_s``, vertical ``max_climb_m_s``): no attitude dynamics, no RK4. A position
  setpoint asks for ``velocity + (position − p)`` (the autopilot's position loop, gain 1/s),
  a velocity setpoint for itself; an attitude setpoint (the NMPC's output) is turned into the
  acceleration it would give and integrated once per step;
* a **ground robot** is a unicycle driven by its ``cmd_vel`` (the component of the velocity
  setpoint along its heading, and the yaw rate), like the simulator's, stopping 0.5 s after its
  last command; like the simulator's, it stays at the height of the floor it started on;
* the **autopilot rules** are the simulator's — the same code, :mod:`btmission.backends.autopilot`
  — so leaves behave the same: OFFBOARD only after setpoints have streamed at > 2 Hz for 1 s, HOLD when they stop
  for 1 s, no arming change in the air, take-off only when armed, LAND descends at 0.7 m/s and
  disarms 2 s after touch-down, an armed vehicle that never takes off disarms after 10 s;
* **no sensors** (``Vehicle.sensors`` is None: no LiDAR, camera or detections), **no
  collisions** (vehicles pass through rock and each other; :meth:`FakeProvider.step` reports
  nothing). The floor under a vehicle is the map's ground, so it lands where the simulator's would.

Its time is simulated like the simulator's (:class:`~btmission.vehicles.clock.SimClock`; a run
goes as fast as the machine allows) and it keeps the odometer as ground truth (the clearance
is never measured: ``None``). For tests, :meth:`FakeVehicle.teleport` puts a vehicle anywhere
(e.g. from a :class:`~btmission.runtime.substitution.TestLeaf` effect), and
:meth:`FakeVehicle.refuse_arming` makes it refuse to arm a number of times, or always, with a
reason and a transient or final refusal (a vehicle whose pre-arm checks fail).

Use it in a mission with ``backend: fake`` on every agent, or with
:func:`fake_provider` / :class:`FakeProvider` directly (docs/providers.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from btmission.backends.autopilot import (
    AutopilotFields,
    G,
    OffboardCommands,
    autopilot_rules,
    landed_state_of,
)
from btmission.backends.sim import (
    CMD_VEL_TIMEOUT_S,
    HEADING_P,
    LAND_SPEED,
    YAW_RATE_MAX,
    SimConfig,
)
from btmission.spec.vehicleref import SIM, VehicleRef
from btmission.types import FloatArray, Vec3
from btmission.vehicles.base import Ack, Mode, Telemetry, VehicleKind
from btmission.vehicles.provider import AttachOptions, ProviderBase, Vehicle, VehicleEvent

if TYPE_CHECKING:
    from btmission.spec.mission import Mission
    from btmission.world.voxel import VoxelMap

VELOCITY_GAIN = 1.2
"""1/s: the velocity approaches the commanded one as in the simulator's velocity loop."""

SAME_REQUEST_S = 1.0
"""Arming calls less than this apart are one request (:meth:`FakeVehicle.refuse_arming`)."""


@dataclass
class _State(AutopilotFields):
    """A fake vehicle's state (its autopilot's part, as in the simulator: AutopilotFields)."""

    id: str
    kind: VehicleKind
    p: FloatArray
    yaw: float = 0.0
    v: FloatArray = field(default_factory=lambda: np.zeros(3))
    yaw_rate: float = 0.0
    odometer_m: float = 0.0
    v_max: float | None = None
    refuse_arm: int | None = 0
    """Arming requests still to refuse (None: every one; :meth:`FakeVehicle.refuse_arming`)."""
    arm_refusal: Ack | None = None
    """The refusal (None: arming is never refused)."""
    arm_asked_s: float = -math.inf
    """When arming was last asked for."""
    refusing: bool = False
    """The arming request being asked for now is refused."""
    failsafe_active: bool = False
    """A failsafe of :meth:`FakeVehicle.take_over` is under way (until the vehicle disarms)."""


class FakeProvider(ProviderBase):
    """Kinematic vehicles (module docstring): a
    :class:`~btmission.vehicles.provider.VehicleProvider` with simulated time."""

    realtime = False

    def __init__(self, voxel_map: VoxelMap | None = None, config: SimConfig | None = None) -> None:
        from btmission.vehicles.clock import SimClock

        self.map = voxel_map
        self.config = config or SimConfig()
        self.time_s = 0.0
        self.clock = SimClock(self)
        self.vehicles: dict[str, FakeVehicle] = {}

    def ground_z(self, p: FloatArray) -> float:
        """The floor under ``p`` (0 without a map)."""
        return 0.0 if self.map is None else float(self.map.ground_z(p))

    def attach(
        self,
        agent_id: str,
        kind: VehicleKind,
        start: Vec3,
        ref: VehicleRef = SIM,
        options: AttachOptions = AttachOptions(),
    ) -> Vehicle:
        """A vehicle at ``start`` (on the ground under it), heading ``options.yaw`` (a ground
        robot at most at ``options.v_max``)."""
        if agent_id in self.vehicles:
            raise ValueError(f"vehicle '{agent_id}' exists already")
        p = np.asarray(start, dtype=float).copy()
        g = self.ground_z(p + np.array([0.0, 0.0, 0.01]))
        p[2] = max(float(p[2]), g) if kind is VehicleKind.MULTIROTOR else g
        v_max = options.v_max
        state = _State(agent_id, kind, p, yaw=float(options.yaw), ground=g,
                       v_max=None if v_max is None else float(v_max))  # fmt: skip
        state.hold = p.copy()
        state.armed = kind is VehicleKind.GROUND  # a ground robot drives when commanded
        vehicle = self.vehicles[agent_id] = FakeVehicle(self, state)
        return Vehicle(agent_id, kind, vehicle, None, lambda: state.odometer_m, lambda: None)

    def step(self, dt: float) -> list[VehicleEvent]:
        """Move every vehicle by ``dt`` seconds; nothing ever collides."""
        if not dt > 0:
            raise ValueError(f"dt must be > 0 s, got {dt}")
        t = self.time_s
        for vehicle in self.vehicles.values():
            vehicle._step(t, dt)
        self.time_s = round(t + dt, 9)
        return []

    def close(self) -> None:
        """Nothing to release."""


class FakeVehicle(OffboardCommands):
    """One fake vehicle: the :class:`~btmission.vehicles.base.Backend` interface, plus
    :meth:`teleport` for tests."""

    def __init__(self, provider: FakeProvider, state: _State) -> None:
        self._provider = provider
        self._s = state
        self._ap = state
        self.id = state.id
        self.kind = state.kind

    # ---------------------------------------------- commands and setpoints: OffboardCommands
    def arm(self) -> Ack:
        """:meth:`OffboardCommands.arm`, unless :meth:`refuse_arming` says to refuse this
        request."""
        s = self._s
        if s.arm_refusal is not None and not s.armed and s.kind is VehicleKind.MULTIROTOR:
            now = self._provider.time_s
            if now - s.arm_asked_s > SAME_REQUEST_S:  # a new request
                s.refusing = s.refuse_arm is None or s.refuse_arm > 0
                if s.refuse_arm:
                    s.refuse_arm -= 1
            s.arm_asked_s = now
            if s.refusing:
                return s.arm_refusal
        return super().arm()

    def refuse_arming(
        self,
        requests: int | None = None,
        reason: str = "PreArm: estimator not ready",
        *,
        transient: bool = True,
    ) -> None:
        """Refuse the next ``requests`` arming requests (None: every one from now on; 0: stop
        refusing) with ``reason``, a transient or a final refusal (a test's vehicle whose
        pre-arm checks fail). A leaf asks again every tick while it waits: calls that follow
        the previous one within :data:`SAME_REQUEST_S` are the same request (as the MAVLink
        provider answers them from its back-off without asking the autopilot again)."""
        if requests is not None and requests < 0:
            raise ValueError(f"requests must be ≥ 0 or None, got {requests}")
        s = self._s
        s.refuse_arm = requests
        s.arm_refusal = Ack.refused(reason, transient=transient)
        s.refusing = False
        s.arm_asked_s = -math.inf

    def _ap_time(self) -> float:
        return self._provider.time_s

    def _ap_here(self) -> FloatArray:
        return self._s.p.copy()

    # ------------------------------------------------------------------ telemetry
    def telemetry(self) -> Telemetry:
        s = self._s
        return Telemetry(
            time_s=self._provider.time_s,
            position=s.p.copy(),
            velocity=s.v.copy(),
            yaw=s.yaw,
            roll=0.0,
            pitch=0.0,
            yaw_rate=s.yaw_rate,
            mode=s.mode,
            armed=s.armed,
            landed=s.landed,
            landed_state=landed_state_of(s.landed, s.mode),
            battery=s.battery,
            ground_z=s.ground,
            failsafe=s.failsafe_active and s.armed,
        )

    def take_over(self, mode: Mode = Mode.LAND, reason: str = "data link lost: landing") -> None:
        """The autopilot's own failsafe switches the vehicle to ``mode`` where it is (a test's
        fault: PX4's data-link-loss landing); the telemetry says ``failsafe`` until it
        disarms."""
        s = self._s
        s.mode = mode
        s.hold = s.p.copy()
        s.failsafe = reason
        s.failsafe_active = True

    @property
    def failsafe(self) -> str:
        """The last failsafe the autopilot triggered ("" if none)."""
        return self._s.failsafe

    def teleport(self, position: Vec3 | FloatArray, yaw: float | None = None) -> None:
        """Put the vehicle at ``position`` at rest (a test's shortcut; the odometer does not
        count it). A multirotor in the air holds there."""
        s = self._s
        s.p = np.array(position, dtype=float)
        s.ground = self._provider.ground_z(s.p + np.array([0.0, 0.0, 0.05]))
        if s.kind is VehicleKind.GROUND:
            s.p[2] = s.ground  # (it stays on this floor, as in the simulator)
        s.p[2] = max(float(s.p[2]), s.ground)
        s.v = np.zeros(3)
        s.hold = s.p.copy()
        if yaw is not None:
            s.yaw = float(yaw)
        if s.kind is VehicleKind.MULTIROTOR:
            s.landed = s.p[2] - s.ground < 0.05
            s.took_off = s.took_off or not s.landed

    # ------------------------------------------------------------------ stepping
    def _step(self, t: float, dt: float) -> None:
        if self._s.kind is VehicleKind.MULTIROTOR:
            self._step_multirotor(t, dt)
        else:
            self._step_ground(t, dt)

    def _autopilot(self, t: float) -> None:
        """The simulator's mode logic: the offboard-loss failsafe and automatic disarming."""
        autopilot_rules(self._s, t, self._ap_here)

    def _velocity_command(self, dt: float) -> FloatArray | None:
        """The velocity the active mode and setpoint ask for (None: none, at rest)."""
        s = self._s
        if s.mode is Mode.OFFBOARD and s.sp_kind == "position":
            return s.sp_vel + (s.sp_pos - s.p)
        if s.mode is Mode.OFFBOARD and s.sp_kind == "velocity":
            return s.sp_vel.copy()
        if s.mode is Mode.OFFBOARD and s.sp_kind == "attitude":
            thrust, roll, pitch = s.sp_att
            c, sn = math.cos(s.yaw), math.sin(s.yaw)
            ax = thrust * math.cos(roll) * math.sin(pitch)
            ay = -thrust * math.sin(roll)
            acc = np.array([c * ax - sn * ay, sn * ax + c * ay,
                            thrust * math.cos(roll) * math.cos(pitch) - G])  # fmt: skip
            return s.v + acc * dt
        if s.mode in (Mode.TAKEOFF, Mode.HOLD):
            return s.hold - s.p
        if s.mode is Mode.LAND:
            v = np.zeros(3)
            v[:2] = s.hold[:2] - s.p[:2]
            v[2] = -LAND_SPEED
            return v
        return None

    def _step_multirotor(self, t: float, dt: float) -> None:
        s = self._s
        cfg = self._provider.config
        self._autopilot(t)
        v = self._velocity_command(dt) if s.armed else None
        if v is None:
            v = np.zeros(3) if s.landed else np.array([0.0, 0.0, -LAND_SPEED])  # unpowered
        h = math.hypot(v[0], v[1])
        if h > cfg.max_speed_m_s:
            v[:2] *= cfg.max_speed_m_s / h
        v[2] = min(max(v[2], -cfg.max_climb_m_s), cfg.max_climb_m_s)
        if not (s.mode is Mode.OFFBOARD and s.sp_kind == "attitude"):
            v = s.v + (v - s.v) * min(1.0, VELOCITY_GAIN * dt)  # the velocity loop's lag
        if s.landed and v[2] <= 0.0:
            v[:] = 0.0  # resting on the ground
        old = s.p.copy()
        s.p = s.p + v * dt
        s.ground = self._provider.ground_z(s.p + np.array([0.0, 0.0, 0.05]))
        if s.p[2] <= s.ground:
            s.p[2] = s.ground
            v[2] = max(v[2], 0.0)
        s.v = v
        # yaw: the commanded rate, or the heading loop on a position setpoint's yaw
        if s.mode is Mode.OFFBOARD and s.sp_kind in ("velocity", "attitude"):
            rate = s.sp_yaw_rate
        elif s.mode is Mode.OFFBOARD and s.sp_yaw is not None:
            err = (s.sp_yaw - s.yaw + math.pi) % (2 * math.pi) - math.pi
            rate = min(max(HEADING_P * err, -YAW_RATE_MAX), YAW_RATE_MAX)
        else:
            rate = 0.0
        s.yaw_rate = 0.0 if s.landed else rate
        s.yaw = (s.yaw + s.yaw_rate * dt + math.pi) % (2 * math.pi) - math.pi
        was_landed = s.landed
        s.landed = s.p[2] - s.ground < 0.05 and v[2] <= 0.0
        if s.landed and not was_landed:
            s.landed_at = t
        if not s.landed:
            s.took_off = True
        if s.mode is Mode.TAKEOFF and abs(s.p[2] - s.hold[2]) < 0.1:
            s.mode = Mode.HOLD
        if s.armed:
            s.battery = max(0.0, s.battery - dt / cfg.battery_s)
        s.odometer_m += float(np.linalg.norm(s.p - old))

    def _step_ground(self, t: float, dt: float) -> None:
        s = self._s
        cfg = self._provider.config
        if t - s.sp_time > CMD_VEL_TIMEOUT_S or s.sp_kind != "velocity":
            uv = uw = 0.0
        else:
            heading = (math.cos(s.yaw), math.sin(s.yaw))
            uv = float(s.sp_vel[0] * heading[0] + s.sp_vel[1] * heading[1])
            v_max = cfg.ground_v_max if s.v_max is None else s.v_max
            uv = min(max(uv, cfg.ground_v_min), v_max)
            uw = min(max(s.sp_yaw_rate, -cfg.ground_omega_max), cfg.ground_omega_max)
        old = s.p.copy()
        s.p[0] += uv * math.cos(s.yaw) * dt
        s.p[1] += uv * math.sin(s.yaw) * dt
        s.yaw = (s.yaw + uw * dt + math.pi) % (2 * math.pi) - math.pi
        s.v = np.array([uv * math.cos(s.yaw), uv * math.sin(s.yaw), 0.0])
        s.yaw_rate = uw
        s.odometer_m += float(math.hypot(s.p[0] - old[0], s.p[1] - old[1]))


def fake_provider(mission: Mission, voxel_map: VoxelMap, seed: int) -> FakeProvider:
    """The ``fake`` entry point of ``btmission.providers``: fake vehicles on the mission's
    map (its ground), with the speed limits of the simulator's defaults."""
    return FakeProvider(voxel_map)


__all__ = ["FakeProvider", "FakeVehicle", "fake_provider"]
