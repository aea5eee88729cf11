"""The backend's setpoints as MAVLink offboard / GUIDED targets (pure: fields, not a link).

The :class:`~btmission.vehicles.base.Backend` takes setpoints in the mission world (ENU, z up,
yaw counter-clockwise from +x); PX4 OFFBOARD and ArduPilot GUIDED take them in the vehicle's
local NED frame (:class:`~btmission.backends.mavlink_frames.LocalFrame`):

* a **position** setpoint (with optional velocity feed-forward and yaw) and a **velocity**
  setpoint (with a yaw rate) become ``SET_POSITION_TARGET_LOCAL_NED`` in ``MAV_FRAME_LOCAL_NED``,
  its ``type_mask`` ignoring what is not given (PX4 and ArduPilot both read the mask);
* an **attitude** setpoint — the seed 002 NMPC's mass-less thrust T and roll/pitch references in
  the yaw frame — becomes ``SET_ATTITUDE_TARGET``. Seed 002's model accelerates by
  ``[T cos φ sin θ, −T sin φ, T cos φ cos θ − g]`` in the yaw frame (x forward, z up): a positive
  φ pushes right and a positive θ forward (nose down), so in the autopilot's FRD body frame the
  roll is φ and the pitch −θ; the quaternion's yaw is the vehicle's current heading (the NMPC
  steers yaw by rate), and the thrust is normalised as ``hover · T / g`` (``hover``: the
  vehicle's hover throttle, PX4's MPC_THR_HOVER / ArduPilot's MOT_THST_HOVER), clipped to 0-1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from btmission.backends.autopilot import G
from btmission.backends.mavlink_frames import LocalFrame
from btmission.types import FloatArray, Vec3

X_IGNORE, Y_IGNORE, Z_IGNORE = 1, 2, 4
VX_IGNORE, VY_IGNORE, VZ_IGNORE = 8, 16, 32
AX_IGNORE, AY_IGNORE, AZ_IGNORE = 64, 128, 256
YAW_IGNORE, YAW_RATE_IGNORE = 1024, 2048
"""POSITION_TARGET_TYPEMASK bits (MAVLink common dialect)."""
POSITION_IGNORE = X_IGNORE | Y_IGNORE | Z_IGNORE
VELOCITY_IGNORE = VX_IGNORE | VY_IGNORE | VZ_IGNORE
ACCEL_IGNORE = AX_IGNORE | AY_IGNORE | AZ_IGNORE

ATTITUDE_ALL_RATES = 0
"""ATTITUDE_TARGET_TYPEMASK of our attitude setpoints: nothing ignored (roll and pitch rates 0,
the yaw rate commanded). ArduCopter refuses a mask that ignores some body rates but not all
(seen on SITL: a mask of 3 was discarded); PX4 reads the attitude and the yaw rate."""


@dataclass(frozen=True)
class PositionTarget:
    """The fields of SET_POSITION_TARGET_LOCAL_NED (``coordinate_frame`` MAV_FRAME_LOCAL_NED)."""

    type_mask: int
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0
    yaw_rate: float = 0.0


@dataclass(frozen=True)
class AttitudeTarget:
    """The fields of SET_ATTITUDE_TARGET."""

    type_mask: int
    q: tuple[float, float, float, float]
    """Attitude quaternion (w, x, y, z), FRD body in NED."""
    body_yaw_rate: float
    thrust: float
    """Normalised 0-1."""


def _triple(v: FloatArray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def position_target(
    frame: LocalFrame,
    position: Vec3 | FloatArray,
    velocity: Vec3 | FloatArray | None = None,
    yaw: float | None = None,
) -> PositionTarget:
    """A world position setpoint (with optional velocity feed-forward and world yaw)."""
    mask = ACCEL_IGNORE | YAW_RATE_IGNORE
    vel = (0.0, 0.0, 0.0)
    if velocity is None:
        mask |= VELOCITY_IGNORE
    else:
        vel = _triple(frame.vector_to_local(velocity))
    heading = 0.0
    if yaw is None:
        mask |= YAW_IGNORE
    else:
        heading = frame.yaw_to_local(float(yaw))
    return PositionTarget(mask, _triple(frame.to_local(position)), vel, heading, 0.0)


def velocity_target(
    frame: LocalFrame, velocity: Vec3 | FloatArray, yaw_rate: float = 0.0
) -> PositionTarget:
    """A world velocity setpoint with a world yaw rate (counter-clockwise positive)."""
    mask = POSITION_IGNORE | ACCEL_IGNORE | YAW_IGNORE
    v = _triple(frame.vector_to_local(velocity))
    return PositionTarget(mask, (0.0, 0.0, 0.0), v, 0.0, frame.yaw_rate_to_local(yaw_rate))


def euler_to_quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the ZYX (yaw, pitch, roll) rotation."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def attitude_target(
    frame: LocalFrame,
    thrust: float,
    roll: float,
    pitch: float,
    yaw: float,
    yaw_rate: float = 0.0,
    *,
    hover: float = 0.5,
) -> AttitudeTarget:
    """The seed 002 attitude setpoint (mass-less thrust m/s², roll/pitch in the yaw frame,
    world yaw rate) for a vehicle heading ``yaw`` (world), as SET_ATTITUDE_TARGET (module
    docstring)."""
    if not 0.0 < hover <= 1.0:
        raise ValueError(f"hover throttle must be in (0, 1], got {hover}")
    q = euler_to_quaternion(roll, -pitch, frame.yaw_to_local(yaw))
    throttle = min(1.0, max(0.0, hover * thrust / G))
    return AttitudeTarget(ATTITUDE_ALL_RATES, q, frame.yaw_rate_to_local(yaw_rate), throttle)


def quaternion_to_euler(q: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of a (w, x, y, z) quaternion, ZYX order (the inverse of
    :func:`euler_to_quaternion` for pitch within ±π/2)."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def attitude_from_target(
    frame: LocalFrame, target: AttitudeTarget, *, hover: float = 0.5
) -> tuple[float, float, float, float]:
    """What an autopilot reads from a SET_ATTITUDE_TARGET (the inverse of
    :func:`attitude_target`): the mass-less thrust (m/s²), the roll φ and pitch θ in the yaw
    frame (seed 002's convention) and the world yaw rate. The heading in ``q`` is not needed:
    the autopilot steers yaw by rate."""
    if not 0.0 < hover <= 1.0:
        raise ValueError(f"hover throttle must be in (0, 1], got {hover}")
    roll, pitch_frd, _ = quaternion_to_euler(target.q)
    thrust = G * target.thrust / hover
    return thrust, roll, -pitch_frd, frame.yaw_rate_to_world(target.body_yaw_rate)
