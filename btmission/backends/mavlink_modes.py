"""Flight modes and command results on MAVLink autopilots, as the backend's :class:`Mode` and
:class:`Ack` (pure functions over pymavlink's tables; no link).

The backend speaks PX4's vocabulary (:class:`~btmission.vehicles.base.Mode`: MANUAL, HOLD,
TAKEOFF, OFFBOARD, LAND). On the wire, a mode is a HEARTBEAT's ``base_mode`` and
``custom_mode``, whose meaning depends on the autopilot (``HEARTBEAT.autopilot``) and, for
ArduPilot, on the vehicle type:

==========  =====================================  ==========================  =================
``Mode``    PX4 (``custom_mode`` = main << 16 |     ArduCopter                  ArduRover
            sub << 24)
==========  =====================================  ==========================  =================
MANUAL      MANUAL (1)                             STABILIZE (0)               MANUAL (0)
HOLD        AUTO.LOITER (4, 3)                     BRAKE (17)                  HOLD (4)
TAKEOFF     AUTO.TAKEOFF (4, 2)                    GUIDED (4) + NAV_TAKEOFF    —
OFFBOARD    OFFBOARD (6)                           GUIDED (4)                  GUIDED (15)
LAND        AUTO.LAND (4, 6)                       LAND (9)                    —
==========  =====================================  ==========================  =================

**HOLD on ArduCopter is BRAKE**, not LOITER. LOITER is a pilot's mode: it takes its climb rate
from the throttle stick, and with no RC (a companion computer, SITL, whose default RC throttle is
1000 µs: the stick at the bottom) that is full descent at ``PILOT_SPEED_DN`` (0: then
``PILOT_SPEED_UP``, 2.5 m/s) — the drone the mission told to hold sinks to the ground. BRAKE
ignores the pilot's sticks: it stops as fast as it can and holds that position and altitude for
as long as it is left there (no timeout when a ground station asks for it), and its number in the
HEARTBEAT says "holding" to the ground station and to an operator, where GUIDED at the current
position (the other way to hold without RC) would read as OFFBOARD and hold only as long as the
provider keeps track of why it sent that target. Like LAND and RTL, BRAKE refuses to arm
(:func:`armable`), which the provider handles by switching to GUIDED before it arms.

A COMMAND_ACK's ``MAV_RESULT`` becomes an :class:`~btmission.vehicles.base.Ack`: accepted, or
refused with the result's name and the autopilot's last STATUSTEXT (the reason a pre-arm check
gave), transient or final (:data:`TRANSIENT_RESULTS`); TEMPORARILY_REJECTED and IN_PROGRESS are
worth waiting for (:func:`retry_wanted`).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from btmission.errors import BtmissionError
from btmission.vehicles.base import ACCEPTED, Ack, Mode, VehicleKind


class Autopilot(str, Enum):
    PX4 = "px4"
    ARDUPILOT = "ardupilot"


def autopilot_of(heartbeat_autopilot: int) -> Autopilot | None:
    """The autopilot family of a HEARTBEAT's ``autopilot`` field (None: neither, e.g. a GCS)."""
    if heartbeat_autopilot == mavlink.MAV_AUTOPILOT_PX4:
        return Autopilot.PX4
    if heartbeat_autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return Autopilot.ARDUPILOT
    return None


_PX4_NAMES = {
    Mode.MANUAL: "MANUAL",
    Mode.HOLD: "LOITER",
    Mode.TAKEOFF: "TAKEOFF",
    Mode.OFFBOARD: "OFFBOARD",
    Mode.LAND: "LAND",
}
_COPTER_NAMES = {
    Mode.MANUAL: "STABILIZE",
    Mode.HOLD: "BRAKE",  # not LOITER: it sinks without RC throttle (module docstring)
    Mode.TAKEOFF: "GUIDED",
    Mode.OFFBOARD: "GUIDED",
    Mode.LAND: "LAND",
}
_ROVER_NAMES = {Mode.MANUAL: "MANUAL", Mode.HOLD: "HOLD", Mode.OFFBOARD: "GUIDED"}


@dataclass(frozen=True)
class ModeRequest:
    """How to ask an autopilot for a mode: MAV_CMD_DO_SET_MODE with these parameters, and
    whether MAV_CMD_NAV_TAKEOFF must follow (ArduPilot takes off from GUIDED)."""

    base_mode: int
    custom_mode: int
    name: str
    """The autopilot's own name of the mode (``AUTO.LOITER``, ``GUIDED`` ...)."""
    then_takeoff: bool = False


def set_mode_params(autopilot: Autopilot, request: ModeRequest) -> tuple[float, float, float]:
    """Parameters 1-3 of MAV_CMD_DO_SET_MODE for ``request``: the base mode, then ArduPilot's
    mode number, or PX4's main and sub mode (the HEARTBEAT packs them into ``custom_mode``;
    the command takes them apart, as pymavlink's ``set_mode_px4`` and MAVSDK send them)."""
    if autopilot is Autopilot.PX4:
        main, sub = (request.custom_mode >> 16) & 0xFF, (request.custom_mode >> 24) & 0xFF
        return float(request.base_mode), float(main), float(sub)
    return float(request.base_mode), float(request.custom_mode), 0.0


def custom_mode_of_command(autopilot: Autopilot, param2: float, param3: float) -> int:
    """The HEARTBEAT ``custom_mode`` a DO_SET_MODE command asks for (the vehicle's side of
    :func:`set_mode_params`)."""
    if autopilot is Autopilot.PX4:
        return _px4_custom(int(param2), int(param3))
    return int(param2)


class UnsupportedMode(BtmissionError, ValueError):
    """A mode this autopilot and vehicle type do not have (e.g. LAND on a rover)."""


def _px4_custom(main: int, sub: int) -> int:
    return (main << 16) | (sub << 24)


def _ardupilot(kind: VehicleKind) -> tuple[dict[Mode, str], dict[int, str], str]:
    """Our modes → ArduPilot's names, its number → name table, and the firmware's name."""
    if kind is VehicleKind.MULTIROTOR:
        return _COPTER_NAMES, mavutil.mode_mapping_acm, "ArduCopter"
    return _ROVER_NAMES, mavutil.mode_mapping_rover, "ArduRover"


def _mode_by_name(names: dict[Mode, str], name: str) -> Mode | str:
    """The backend mode an autopilot's mode name stands for (OFFBOARD before TAKEOFF: both are
    ArduPilot's GUIDED), else the name itself."""
    for mode in (Mode.OFFBOARD, Mode.MANUAL, Mode.HOLD, Mode.LAND, Mode.TAKEOFF):
        if names.get(mode) == name:
            return mode
    return name


def mode_request(autopilot: Autopilot, kind: VehicleKind, mode: Mode) -> ModeRequest:
    """The DO_SET_MODE parameters for ``mode`` (module docstring's table). Raises
    :class:`UnsupportedMode`."""
    custom = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if autopilot is Autopilot.PX4:
        name = _PX4_NAMES[mode]
        _, main, sub = mavutil.px4_map[name]
        shown = f"AUTO.{name}" if main == mavutil.PX4_CUSTOM_MAIN_MODE_AUTO else name
        return ModeRequest(custom, _px4_custom(main, sub), shown)
    names, table, firmware = _ardupilot(kind)
    if mode not in names:
        raise UnsupportedMode(f"{firmware} has no {mode.value} mode")
    name = names[mode]
    number = next(n for n, m in table.items() if m == name)
    return ModeRequest(custom, number, name, then_takeoff=mode is Mode.TAKEOFF)


def mode_of(autopilot: Autopilot, kind: VehicleKind, custom_mode: int) -> Mode | str:
    """The backend :class:`Mode` a HEARTBEAT's ``custom_mode`` means, or the autopilot's own
    name of a mode that is none of them (``ALTCTL``, ``RTL`` ...; ``custom mode 99`` if
    unknown). ArduPilot's GUIDED reads as OFFBOARD (a take-off is GUIDED too)."""
    if autopilot is Autopilot.PX4:
        main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        for name, (_, m, s) in mavutil.px4_map.items():
            if m == main and (s == sub or main != mavutil.PX4_CUSTOM_MAIN_MODE_AUTO):
                return _mode_by_name(_PX4_NAMES, str(name))
        return f"custom mode {custom_mode}"
    names, table, _ = _ardupilot(kind)
    name = table.get(custom_mode)
    return f"custom mode {custom_mode}" if name is None else _mode_by_name(names, str(name))


COPTER_NOT_ARMABLE = frozenset(
    number
    for number, name in mavutil.mode_mapping_acm.items()
    if name
    in (
        "AUTO", "RTL", "CIRCLE", "LAND", "FLIP", "AUTOTUNE", "BRAKE", "AVOID_ADSB", "SMART_RTL",
        "FOLLOW", "SYSTEMID", "AUTOROTATE", "AUTO_RTL",
    )
)  # fmt: skip
"""ArduCopter's modes that refuse to arm ("Arm: Mode not armable"): their ``allows_arming`` is
false in ArduCopter's ``mode.h`` (AUTO unless ``AUTO_OPTIONS`` allows it; TURTLE, which arms on
its own terms, is left out). A copter that landed in LAND or RTL stays in that mode."""


def armable(autopilot: Autopilot, kind: VehicleKind, custom_mode: int) -> bool:
    """Whether the autopilot accepts an arming command in the mode of HEARTBEAT ``custom_mode``
    (False only for an ArduCopter in a mode of :data:`COPTER_NOT_ARMABLE`; PX4 and ArduRover
    check their own conditions, which the refusal names)."""
    return not (
        autopilot is Autopilot.ARDUPILOT
        and kind is VehicleKind.MULTIROTOR
        and custom_mode in COPTER_NOT_ARMABLE
    )


def result_name(result: int) -> str:
    """``MAV_RESULT_DENIED`` ... for a COMMAND_ACK's ``result``."""
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT {result}"


def command_name(command: int) -> str:
    """``MAV_CMD_COMPONENT_ARM_DISARM`` ... for a command id."""
    entry = mavlink.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else f"MAV_CMD {command}"


TRANSIENT_RESULTS = frozenset(
    (
        mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
        mavlink.MAV_RESULT_DENIED,
        mavlink.MAV_RESULT_FAILED,
        mavlink.MAV_RESULT_IN_PROGRESS,
    )
)
"""The refusals that may be taken back (:attr:`Ack.transient <btmission.vehicles.base.Ack>`):
TEMPORARILY_REJECTED (busy, not ready), DENIED (not in this state: PX4's pre-arm checks and
"Switching to Offboard is currently not available"), FAILED (ArduPilot's pre-arm checks, "Mode
change failed: requires position"), an IN_PROGRESS that never ended. Every other result
(UNSUPPORTED, CANCELLED, COMMAND_INT_ONLY ...) is final: the autopilot will not run that command
whatever its state. (docs/mavlink.md, "Refusals and retries")"""


def ack_of(command: int, result: int, statustext: str = "") -> Ack:
    """A COMMAND_ACK as an :class:`Ack`: accepted, or refused naming the command, the result
    and the autopilot's reason (its last STATUSTEXT), e.g. ``MAV_CMD_COMPONENT_ARM_DISARM:
    MAV_RESULT_DENIED (PreArm: EKF3 waiting for GPS config data)``, transient or final by the
    result (:data:`TRANSIENT_RESULTS`)."""
    if result == mavlink.MAV_RESULT_ACCEPTED:
        return ACCEPTED
    reason = f"{command_name(command)}: {result_name(result)}"
    if statustext:
        reason += f" ({statustext})"
    return Ack.refused(reason, transient=result in TRANSIENT_RESULTS)


def retry_wanted(result: int) -> bool:
    """Whether a command answered with ``result`` should be sent again after a while
    (TEMPORARILY_REJECTED: e.g. the EKF is not ready yet) or waited for (IN_PROGRESS)."""
    return result in (mavlink.MAV_RESULT_TEMPORARILY_REJECTED, mavlink.MAV_RESULT_IN_PROGRESS)
