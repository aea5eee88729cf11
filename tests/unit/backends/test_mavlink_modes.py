"""Backend modes and command results on PX4 and ArduPilot (btmission.backends.mavlink_modes)."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import common as mavlink

from btmission.backends.mavlink_modes import (
    Autopilot,
    UnsupportedMode,
    ack_of,
    armable,
    autopilot_of,
    custom_mode_of_command,
    mode_of,
    mode_request,
    retry_wanted,
    set_mode_params,
)
from btmission.vehicles.base import Mode, VehicleKind

MULTI, GROUND = VehicleKind.MULTIROTOR, VehicleKind.GROUND


def test_the_autopilot_comes_from_the_heartbeat() -> None:
    assert autopilot_of(mavlink.MAV_AUTOPILOT_PX4) is Autopilot.PX4
    assert autopilot_of(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA) is Autopilot.ARDUPILOT
    assert autopilot_of(mavlink.MAV_AUTOPILOT_INVALID) is None  # a ground station


@pytest.mark.parametrize(
    ("mode", "custom", "name"),
    [
        (Mode.MANUAL, 1 << 16, "MANUAL"),
        (Mode.HOLD, (4 << 16) | (3 << 24), "AUTO.LOITER"),
        (Mode.TAKEOFF, (4 << 16) | (2 << 24), "AUTO.TAKEOFF"),
        (Mode.OFFBOARD, 6 << 16, "OFFBOARD"),  # main mode 6 in bits 16-23
        (Mode.LAND, (4 << 16) | (6 << 24), "AUTO.LAND"),
    ],
)
def test_px4_modes_are_main_and_sub_modes(mode: Mode, custom: int, name: str) -> None:
    req = mode_request(Autopilot.PX4, MULTI, mode)
    assert (req.custom_mode, req.name, req.then_takeoff) == (custom, name, False)
    assert req.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert mode_of(Autopilot.PX4, MULTI, custom) is mode  # and the heartbeat reads back


@pytest.mark.parametrize(
    ("mode", "custom", "name", "takeoff"),
    [
        (Mode.MANUAL, 0, "STABILIZE", False),
        (Mode.HOLD, 17, "BRAKE", False),  # LOITER would sink without RC throttle
        (Mode.TAKEOFF, 4, "GUIDED", True),  # GUIDED, then MAV_CMD_NAV_TAKEOFF
        (Mode.OFFBOARD, 4, "GUIDED", False),  # GUIDED = custom mode 4
        (Mode.LAND, 9, "LAND", False),
    ],
)
def test_ardupilot_copter_modes(mode: Mode, custom: int, name: str, takeoff: bool) -> None:
    req = mode_request(Autopilot.ARDUPILOT, MULTI, mode)
    assert (req.custom_mode, req.name, req.then_takeoff) == (custom, name, takeoff)
    expected = Mode.OFFBOARD if mode is Mode.TAKEOFF else mode
    assert mode_of(Autopilot.ARDUPILOT, MULTI, custom) is expected


def test_ardurover_modes_and_what_a_rover_cannot_do() -> None:
    assert mode_request(Autopilot.ARDUPILOT, GROUND, Mode.OFFBOARD).custom_mode == 15
    assert mode_request(Autopilot.ARDUPILOT, GROUND, Mode.HOLD).custom_mode == 4
    assert mode_of(Autopilot.ARDUPILOT, GROUND, 15) is Mode.OFFBOARD
    for mode in (Mode.TAKEOFF, Mode.LAND):
        with pytest.raises(UnsupportedMode, match=f"ArduRover has no {mode.value} mode"):
            mode_request(Autopilot.ARDUPILOT, GROUND, mode)


def test_arducopter_refuses_to_arm_in_land_rtl_auto_and_brake() -> None:
    ap = Autopilot.ARDUPILOT
    for custom in (3, 6, 9, 17, 21):  # AUTO, RTL, LAND, BRAKE, SMART_RTL
        assert not armable(ap, MULTI, custom)
    for custom in (0, 2, 4, 5, 16):  # STABILIZE, ALT_HOLD, GUIDED, LOITER, POSHOLD
        assert armable(ap, MULTI, custom)
    assert armable(ap, GROUND, 9)  # (a rover's mode 9 is not LAND)
    land = mode_request(Autopilot.PX4, MULTI, Mode.LAND).custom_mode
    assert armable(Autopilot.PX4, MULTI, land)  # PX4 names its own reasons


def test_other_modes_read_as_the_autopilots_names() -> None:
    assert mode_of(Autopilot.PX4, MULTI, 3 << 16) == "POSCTL"
    assert mode_of(Autopilot.PX4, MULTI, (4 << 16) | (5 << 24)) == "RTL"
    assert mode_of(Autopilot.ARDUPILOT, MULTI, 6) == "RTL"
    assert mode_of(Autopilot.ARDUPILOT, MULTI, 99) == "custom mode 99"


def test_command_acks_become_acks_with_the_reason() -> None:
    arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    assert ack_of(arm, mavlink.MAV_RESULT_ACCEPTED)
    denied = ack_of(arm, mavlink.MAV_RESULT_DENIED, "PreArm: EKF3 waiting for GPS config data")
    assert not denied and denied.reason == (
        "MAV_CMD_COMPONENT_ARM_DISARM: MAV_RESULT_DENIED (PreArm: EKF3 waiting for GPS config data)"
    )
    assert ack_of(400, 99).reason == "MAV_CMD_COMPONENT_ARM_DISARM: MAV_RESULT 99"
    assert retry_wanted(mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
    assert retry_wanted(mavlink.MAV_RESULT_IN_PROGRESS)
    assert not retry_wanted(mavlink.MAV_RESULT_DENIED)


@pytest.mark.parametrize(
    ("result", "transient"),
    [
        (mavlink.MAV_RESULT_TEMPORARILY_REJECTED, True),  # PX4: not ready, busy
        (mavlink.MAV_RESULT_DENIED, True),  # PX4's pre-arm checks, OFFBOARD not available
        (mavlink.MAV_RESULT_FAILED, True),  # ArduPilot's pre-arm checks, GUIDED needs a fix
        (mavlink.MAV_RESULT_IN_PROGRESS, True),  # never finished
        (mavlink.MAV_RESULT_UNSUPPORTED, False),  # whatever its state
        (99, False),  # a result this btmission does not know
    ],
)
def test_a_refusal_is_typed_transient_or_final_by_its_result(result: int, transient: bool) -> None:
    ack = ack_of(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, result, "PreArm: Compass not calibrated")
    assert not ack.accepted and ack.transient is transient


@pytest.mark.parametrize(
    ("autopilot", "kind", "mode", "params"),
    [
        (Autopilot.PX4, VehicleKind.MULTIROTOR, Mode.OFFBOARD, (1.0, 6.0, 0.0)),
        (Autopilot.PX4, VehicleKind.MULTIROTOR, Mode.HOLD, (1.0, 4.0, 3.0)),
        (Autopilot.PX4, VehicleKind.MULTIROTOR, Mode.LAND, (1.0, 4.0, 6.0)),
        (Autopilot.ARDUPILOT, VehicleKind.MULTIROTOR, Mode.OFFBOARD, (1.0, 4.0, 0.0)),
        (Autopilot.ARDUPILOT, VehicleKind.GROUND, Mode.HOLD, (1.0, 4.0, 0.0)),
    ],
)
def test_do_set_mode_parameters_round_trip_to_the_heartbeat_mode(
    autopilot: Autopilot, kind: VehicleKind, mode: Mode, params: tuple[float, float, float]
) -> None:
    request = mode_request(autopilot, kind, mode)
    assert set_mode_params(autopilot, request) == params
    custom = custom_mode_of_command(autopilot, params[1], params[2])
    assert custom == request.custom_mode
    assert mode_of(autopilot, kind, custom) is mode
