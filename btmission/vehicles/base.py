"""The interface between an agent and its vehicle: what PX4 offboard (or a ground robot) offers.

An agent's leaves never touch a vehicle directly: they go through its :class:`Backend` — the
embedded simulator (:mod:`btmission.backends.sim`) or, later, a MAVLink autopilot. The calls
mirror PX4's offboard interface so that behaviour written against the simulator carries over
(DESIGN.md §6, §8):

* commands — :meth:`Backend.arm`, :meth:`Backend.disarm`, :meth:`Backend.set_mode`,
  :meth:`Backend.takeoff`, :meth:`Backend.land` — are answered with an :class:`Ack`, like
  MAVLink's COMMAND_ACK: accepted, or refused with the reason, and whether the refusal is
  *transient* (the vehicle may accept later: not ready, busy, no answer; the run retries it)
  or *final* (it will not as things are: unsupported, out of range);
* setpoints — position, velocity, or attitude + thrust (what the seed 002 NMPC outputs) — are
  streamed, and OFFBOARD is only accepted once they have been streaming for a while; a vehicle
  in OFFBOARD whose setpoints stop falls back to a failsafe mode;
* :meth:`Backend.telemetry` returns pose, velocity, attitude, mode, armed state and battery.

Exteroceptive sensors (LiDAR, depth camera, object detections) are a separate
:class:`Sensors` interface: on a real robot they come from drivers, not from the autopilot.
Positions are world-frame metres, z up; yaw is counter-clockwise from +x, in radians.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Protocol, runtime_checkable

from btmission.types import CameraIntrinsics, Detection, FloatArray, Vec3


class Mode(str, Enum):
    """Flight modes, named after PX4's."""

    MANUAL = "MANUAL"  # on the ground, nothing commanded (the power-on mode)
    HOLD = "HOLD"  # hold position (PX4 AUTO.LOITER); the offboard-loss failsafe
    TAKEOFF = "TAKEOFF"  # PX4 AUTO.TAKEOFF: climb to the commanded altitude, then HOLD
    OFFBOARD = "OFFBOARD"  # follow the streamed setpoints
    LAND = "LAND"  # PX4 AUTO.LAND: descend, touch down, disarm


class LandedState(str, Enum):
    """Where the autopilot says the vehicle is (MAVLink's MAV_LANDED_STATE, PX4's land
    detector, ArduPilot's EXTENDED_SYS_STATE): a descent is told from a flight by LANDING,
    which no speed threshold can (PX4 lands at ~0.8 m/s)."""

    UNDEFINED = "undefined"  # the vehicle does not say (then ``landed`` follows its arming)
    ON_GROUND = "on_ground"
    IN_AIR = "in_air"
    TAKEOFF = "takeoff"
    LANDING = "landing"


class VehicleKind(str, Enum):
    MULTIROTOR = "multirotor"
    GROUND = "ground"

    @classmethod
    def of(cls, vehicle: str | None) -> VehicleKind:
        """What a capability library's implementations ask for (their ``vehicle``:
        ``"ground"`` for a ground robot; anything else flies a multirotor)."""
        return cls.GROUND if vehicle == "ground" else cls.MULTIROTOR


@dataclass(frozen=True)
class Ack:
    """The answer to a command (MAVLink COMMAND_ACK): accepted or refused, why, and whether the
    refusal is transient.

    The provider, which knows its vehicle, types the refusal, so the run never reads its reason
    text: a **transient** refusal is one the same vehicle may take back if asked again later
    (arming refused by a pre-arm check or an estimator not ready yet, a mode change denied for
    now, TEMPORARILY_REJECTED, a command nobody answered, "cannot arm in the air"): a leaf
    retries it with a back-off (:class:`btmission.runtime.actions.Command`), then hands the
    task back. A **final** one (``transient`` false: a command or mode the vehicle does not
    have, a value out of range, a battery too low to fly) is not retried: the leaf fails at
    once and the task goes to another agent. ``transient`` is meaningless on an accepted Ack.

    A provider whose commands travel (MAVLink) does not wait for the answer: the first call
    sends the command and returns a **pending** Ack (not accepted, transient, ``pending``: the
    answer is not in yet); the caller calls again on a later tick and gets the answer once it
    came (:meth:`waiting`).
    """

    accepted: bool
    reason: str = ""
    transient: bool = False
    """The refusal may be taken back later (class docstring); False: final."""
    pending: bool = False
    """Sent, its answer not in yet: ask again later (class docstring)."""

    def __bool__(self) -> bool:
        return self.accepted

    @classmethod
    def refused(cls, reason: str, *, transient: bool) -> Ack:
        """A refusal, typed: ``transient`` (asking again later may work) or final."""
        return cls(False, reason, transient)

    @classmethod
    def waiting(cls, reason: str) -> Ack:
        """Not answered yet (``reason``: what it waits for): transient and pending."""
        return cls(False, reason, True, True)


ACCEPTED = Ack(True)


@dataclass(frozen=True)
class Telemetry:
    """The vehicle's state as its autopilot reports it. Read-only: a backend may hand the same
    record (and arrays) to every caller within a step."""

    time_s: float
    position: FloatArray
    velocity: FloatArray
    yaw: float
    roll: float
    pitch: float
    yaw_rate: float
    mode: Mode
    armed: bool
    landed: bool
    """On the ground (PX4's land detector)."""
    landed_state: LandedState
    """The autopilot's landed state (:class:`LandedState`): ``ON_GROUND`` when ``landed``;
    ``LANDING`` while it descends to land."""
    battery: float
    """Remaining charge, 1.0 = full."""
    ground_z: float
    """Height of the ground under the vehicle (its range-finder reading, world z)."""
    failsafe: bool = False
    """The autopilot has taken a failsafe action of its own (MAVLink: HEARTBEAT's
    ``system_status`` CRITICAL or EMERGENCY, which PX4 and ArduPilot report while a failsafe is
    active). The agent stands down on it (docs/mavlink.md, "When the autopilot takes over")."""

    @property
    def height_above_ground(self) -> float:
        return float(self.position[2] - self.ground_z)


@runtime_checkable
class Backend(Protocol):
    """Commands and setpoints to one vehicle, and its telemetry (see the module docstring)."""

    kind: VehicleKind

    def arm(self) -> Ack: ...

    def disarm(self) -> Ack: ...

    def set_mode(self, mode: Mode) -> Ack: ...

    def takeoff(self, altitude_m: float) -> Ack:
        """Climb to ``altitude_m`` above the ground (PX4 AUTO.TAKEOFF). Needs the vehicle armed."""
        ...

    def land(self) -> Ack: ...

    def set_position_setpoint(
        self,
        position: Vec3 | FloatArray,
        velocity: Vec3 | FloatArray | None = None,
        yaw: float | None = None,
    ) -> None:
        """Go to ``position`` (world), with an optional velocity feed-forward and heading."""
        ...

    def set_velocity_setpoint(self, velocity: Vec3 | FloatArray, yaw_rate: float = 0.0) -> None:
        """Fly (drive) at ``velocity`` (world frame) turning at ``yaw_rate``. A ground robot
        drives at the component along its heading (its cmd_vel)."""
        ...

    def set_attitude_setpoint(
        self, thrust: float, roll: float, pitch: float, yaw_rate: float = 0.0
    ) -> None:
        """Mass-less thrust (m/s²) and roll/pitch references in the yaw frame — the output of
        the seed 002 NMPC — plus a yaw-rate command. Multirotors only."""
        ...

    def telemetry(self) -> Telemetry: ...


@dataclass(frozen=True)
class CameraFrame:
    """A depth image with the camera's intrinsics and pose, and the object detections in it
    (the inputs of DPHR and of the seed 002 object localiser)."""

    time_s: float
    depth_m: FloatArray
    """(H, W) metres along the optical axis, 0 = no return."""
    intrinsics: CameraIntrinsics
    rotation: FloatArray
    """^W R_C: optical frame (x right, y down, z forward) → world."""
    translation: FloatArray
    """Camera position (world)."""
    detections: tuple[Detection, ...] = ()


@dataclass(frozen=True)
class LidarScan:
    """One full turn of a 3D LiDAR (the input of global relocalization, seed 000 §IV-C1).

    ``points`` are in the **sensor frame, gravity-aligned**: origin at the LiDAR, x along the
    vehicle's heading, z up (roll and pitch taken out with the IMU attitude, as a LiDAR-inertial
    driver such as FAST-LIO gives them). ``robot_from_sensor`` is where the LiDAR sits on the
    vehicle (4×4), so that a pose found for the sensor gives the vehicle's."""

    time_s: float
    points: FloatArray
    """(N, 3) returns, metres."""
    robot_from_sensor: FloatArray
    """4×4 mounting of the LiDAR in the vehicle frame (x forward, z up, origin at the vehicle's
    reference point — for the simulator, the bottom of the body, on the ground when landed)."""
    sensor: str = ""
    """Sensor model name (e.g. ``os1-32``)."""


@runtime_checkable
class Sensors(Protocol):
    """Exteroceptive sensors of one vehicle."""

    def lidar(self) -> FloatArray:
        """(N, 3) points relative to the vehicle, in its yaw frame (x forward, z up)."""
        ...

    def lidar_scan(self) -> LidarScan | None:
        """The latest full-range 3D LiDAR scan (:class:`LidarScan`), or None while the driver
        has no complete one yet. :meth:`lidar` is the short-range view for obstacle avoidance;
        this is the whole turn of the sensor (tens of thousands of returns out to its maximum
        range), what relocalization matches against the map. On a real robot the LiDAR driver
        supplies it; the simulator ray-casts its voxel map from the vehicle's true pose."""
        ...

    def camera(self) -> CameraFrame:
        """The latest depth frame (with detections)."""
        ...
