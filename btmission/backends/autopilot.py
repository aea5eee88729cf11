"""The PX4-like autopilot rules every simulated vehicle obeys (the simulator's and the fake one's).

:mod:`btmission.backends.sim` integrates physics and :mod:`btmission.backends.fake` moves
vehicles kinematically, but both answer commands and take setpoints the way PX4's offboard
interface does (DESIGN.md §8), so a behaviour that works on one works on the other and, later,
on a real autopilot (the backend conformance suite, ``tests/unit/vehicles/test_backend_conformance.py``, holds
them all to it):

* arming is refused in the air and with the battery below 10 %; disarming in the air is refused;
  every refusal is typed (:class:`~btmission.vehicles.base.Ack`): a state that can change (in
  the air, not armed, not streaming yet) is transient, what will not (a battery too low, a
  ground robot asked to fly, an altitude out of range) is final;
* OFFBOARD is refused until setpoints have been streaming at more than ``STREAM_MIN_HZ`` for
  ``STREAM_MIN_S``; TAKEOFF and LAND need the vehicle armed; a ground robot takes any mode and
  cannot take off or land;
* in OFFBOARD, setpoints that stop for more than ``OFFBOARD_LOSS_S`` switch to HOLD (the
  failsafe), and back to OFFBOARD once they have streamed again for ``STREAM_MIN_S`` (PX4's
  failsafe ends when its condition clears), unless another mode was asked for meanwhile; an
  armed vehicle that does not take off within ``DISARM_PREFLIGHT_S`` disarms, and
  one that has landed disarms after ``DISARM_LAND_S``.

:class:`OffboardCommands` is the command and setpoint half of the
:class:`~btmission.vehicles.base.Backend` interface on a vehicle's :class:`AutopilotState`;
:func:`autopilot_rules` is the per-step half (failsafe and automatic disarming).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from btmission.types import FloatArray, Vec3
from btmission.vehicles.base import ACCEPTED, Ack, LandedState, Mode, VehicleKind

STREAM_MIN_HZ = 2.0
STREAM_MIN_S = 1.0
OFFBOARD_LOSS_S = 1.0
DISARM_PREFLIGHT_S = 10.0
DISARM_LAND_S = 2.0
G = 9.81
"""Gravity (m/s²): the hover thrust of the mass-less models, and the default attitude setpoint."""


_OFFBOARD = Mode.OFFBOARD
"""(read every step for every vehicle: a global costs a fifth of an Enum member on Python 3.11)"""

_ON_GROUND, _IN_AIR, _LANDING, _TAKING_OFF = (
    LandedState.ON_GROUND,
    LandedState.IN_AIR,
    LandedState.LANDING,
    LandedState.TAKEOFF,
)
_LAND, _TAKEOFF = Mode.LAND, Mode.TAKEOFF


def landed_state_of(landed: bool, mode: Mode) -> LandedState:
    """A simulated vehicle's landed state as PX4's land detector reports it
    (EXTENDED_SYS_STATE): on the ground, else landing in LAND, taking off in TAKEOFF, else in
    the air."""
    if landed:
        return _ON_GROUND
    if mode is _LAND:
        return _LANDING
    if mode is _TAKEOFF:
        return _TAKING_OFF
    return _IN_AIR


_NO_VELOCITY = np.zeros(3)
_NO_VELOCITY.flags.writeable = False
"""The feed-forward velocity of a position setpoint given none (shared: read-only)."""


@dataclass(kw_only=True)
class AutopilotFields:
    """The autopilot's part of a simulated vehicle's state (base of the simulator's and the fake
    provider's vehicle records, keyword-only so they keep their own positional fields)."""

    armed: bool = False
    mode: Mode = Mode.MANUAL
    landed: bool = True
    battery: float = 1.0
    ground: float = 0.0
    """Height of the ground under the vehicle (world z)."""
    # setpoints
    sp_kind: str = ""
    sp_pos: FloatArray = field(default_factory=lambda: np.zeros(3))
    sp_vel: FloatArray = field(default_factory=lambda: np.zeros(3))
    sp_yaw: float | None = None
    sp_yaw_rate: float = 0.0
    sp_att: FloatArray = field(default_factory=lambda: np.array([G, 0.0, 0.0]))
    sp_time: float = -math.inf
    stream_since: float = math.inf
    # mode logic
    hold: FloatArray = field(default_factory=lambda: np.zeros(3))
    armed_at: float = -math.inf
    landed_at: float = -math.inf
    took_off: bool = False
    failsafe: str = ""
    offboard_lost: bool = False
    """In HOLD by the offboard-loss failsafe: OFFBOARD comes back with the stream."""


class AutopilotState(Protocol):
    """What the rules read and write of a vehicle (its provider keeps more)."""

    kind: VehicleKind
    armed: bool
    mode: Mode
    landed: bool
    battery: float
    ground: float
    sp_kind: str
    sp_pos: FloatArray
    sp_vel: FloatArray
    sp_yaw: float | None
    sp_yaw_rate: float
    sp_att: FloatArray
    sp_time: float
    stream_since: float
    hold: FloatArray
    armed_at: float
    landed_at: float
    took_off: bool
    failsafe: str
    offboard_lost: bool


class OffboardCommands:
    """Commands and setpoints with PX4's offboard rules (module docstring), for a vehicle class
    that sets ``_ap`` (its :class:`AutopilotState`) and implements :meth:`_ap_time` and
    :meth:`_ap_here`."""

    _ap: AutopilotState

    def _ap_time(self) -> float:
        """The provider's time now (s)."""
        raise NotImplementedError

    def _ap_here(self) -> FloatArray:
        """A copy of where the vehicle is (the point HOLD, TAKEOFF and LAND start from)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ commands
    def arm(self) -> Ack:
        v = self._ap
        if v.kind is VehicleKind.GROUND:
            return ACCEPTED
        if v.armed:
            return ACCEPTED
        if not v.landed:
            return Ack.refused("cannot arm in the air", transient=True)
        if v.battery < 0.1:
            return Ack.refused(f"battery too low ({v.battery:.0%})", transient=False)
        v.armed = True
        v.armed_at = self._ap_time()
        v.took_off = False
        v.failsafe = ""
        return ACCEPTED

    def disarm(self) -> Ack:
        v = self._ap
        if v.kind is VehicleKind.GROUND:
            return ACCEPTED
        if not v.landed:
            return Ack.refused("cannot disarm in the air", transient=True)
        v.armed = False
        v.mode = Mode.MANUAL
        return ACCEPTED

    def set_mode(self, mode: Mode) -> Ack:
        v = self._ap
        t = self._ap_time()
        v.offboard_lost = False  # a mode asked for ends the failsafe's
        if v.kind is VehicleKind.GROUND:
            v.mode = mode
            return ACCEPTED
        if mode is Mode.OFFBOARD:
            streaming = t - v.sp_time <= 1.0 / STREAM_MIN_HZ and t - v.stream_since >= STREAM_MIN_S
            if not streaming:
                return Ack.refused(
                    f"offboard refused: stream setpoints at > {STREAM_MIN_HZ:g} Hz for "
                    f"{STREAM_MIN_S:g} s first",
                    transient=True,
                )
        if mode is Mode.TAKEOFF:
            return self.takeoff(2.0)
        if mode is Mode.LAND:
            return self.land()
        if mode is Mode.HOLD:
            v.hold = self._ap_here()
        v.mode = mode
        return ACCEPTED

    def takeoff(self, altitude_m: float) -> Ack:
        v = self._ap
        if v.kind is VehicleKind.GROUND:
            return Ack.refused("a ground robot cannot take off", transient=False)
        if not v.armed:
            return Ack.refused("takeoff refused: not armed", transient=True)
        if not altitude_m > 0:
            return Ack.refused(f"takeoff altitude must be > 0, got {altitude_m:g}", transient=False)
        v.hold = self._ap_here()
        v.hold[2] = v.ground + altitude_m
        v.mode = Mode.TAKEOFF
        v.offboard_lost = False
        return ACCEPTED

    def land(self) -> Ack:
        v = self._ap
        if v.kind is VehicleKind.GROUND:
            return Ack.refused("a ground robot cannot land", transient=False)
        if not v.armed:
            return Ack.refused("land refused: not armed", transient=True)
        v.hold = self._ap_here()
        v.mode = Mode.LAND
        v.offboard_lost = False
        return ACCEPTED

    # ------------------------------------------------------------------ setpoints
    def _stream(self, kind: str) -> None:
        v = self._ap
        t = self._ap_time()
        if t - v.sp_time > 1.0 / STREAM_MIN_HZ:
            v.stream_since = t
        v.sp_time = t
        v.sp_kind = kind

    def set_position_setpoint(
        self,
        position: Vec3 | FloatArray,
        velocity: Vec3 | FloatArray | None = None,
        yaw: float | None = None,
    ) -> None:
        v = self._ap
        self._stream("position")
        v.sp_pos = np.array(position, dtype=float)  # (a copy)
        v.sp_vel = _NO_VELOCITY if velocity is None else np.array(velocity, dtype=float)
        v.sp_yaw = yaw

    def set_velocity_setpoint(self, velocity: Vec3 | FloatArray, yaw_rate: float = 0.0) -> None:
        v = self._ap
        self._stream("velocity")
        v.sp_vel = np.asarray(velocity, dtype=float).copy()
        v.sp_yaw_rate = float(yaw_rate)

    def set_attitude_setpoint(
        self, thrust: float, roll: float, pitch: float, yaw_rate: float = 0.0
    ) -> None:
        v = self._ap
        if v.kind is VehicleKind.GROUND:
            raise ValueError("a ground robot takes velocity setpoints, not attitude setpoints")
        self._stream("attitude")
        v.sp_att = np.array([float(thrust), float(roll), float(pitch)])
        v.sp_yaw_rate = float(yaw_rate)


def autopilot_rules(
    v: AutopilotState,
    t: float,
    here: Callable[[], FloatArray],
    disarm_land_s: float = DISARM_LAND_S,
) -> None:
    """One step of the mode logic at time ``t``: the offboard-loss failsafe (HOLD at ``here()``)
    and automatic disarming (module docstring; a landed vehicle disarms ``disarm_land_s`` after
    touching down)."""
    if v.mode is _OFFBOARD and t - v.sp_time > OFFBOARD_LOSS_S:
        v.mode = Mode.HOLD if not v.landed else Mode.MANUAL
        v.hold = here()
        v.failsafe = f"offboard setpoints lost for more than {OFFBOARD_LOSS_S:g} s"
        v.offboard_lost = v.mode is Mode.HOLD
    elif v.offboard_lost:
        # as PX4's failsafe framework (seen on PX4 v1.16 SITL): the offboard-loss HOLD ends
        # when its condition clears — setpoints stream again for STREAM_MIN_S — and the vehicle
        # returns to the mode the user asked for, OFFBOARD; any mode asked for meanwhile ends it
        if v.mode is not Mode.HOLD or not v.armed:
            v.offboard_lost = False
        elif t - v.sp_time <= 1.0 / STREAM_MIN_HZ and t - v.stream_since >= STREAM_MIN_S:
            v.mode = _OFFBOARD
            v.offboard_lost = False
    if v.armed and v.landed:
        if not v.took_off and t - v.armed_at > DISARM_PREFLIGHT_S:
            v.armed = False
            v.failsafe = f"disarmed: no take-off within {DISARM_PREFLIGHT_S:g} s of arming"
        elif v.took_off and t - v.landed_at > disarm_land_s:
            v.armed = False
            v.took_off = False
            if v.mode in (Mode.LAND, Mode.HOLD, Mode.TAKEOFF):
                v.mode = Mode.MANUAL
