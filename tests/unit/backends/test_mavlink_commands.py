"""The MAVLink vehicle's commands never wait (issue #36 item 7): on real PX4 a
TEMPORARILY_REJECTED made ``command()`` sleep 0.5 s then 1 s inside the mission loop, stalling
every vehicle's setpoints; PX4 acknowledges a mode change twice (ACCEPTED at once, then the real
result) and the first was taken; HEARTBEAT cannot be sped up on PX4, so modes are read from
CURRENT_MODE too.

The wall clock here is the test's (``time.monotonic`` replaced, as in
test_mavlink_link_timeout.py) and the vehicle's answers are filed by the I/O thread's own code
(:meth:`_LinkIO._file`): nothing sleeps, and what is asserted is what each call returns and how
many commands went out, never how long a call took."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from btmission.backends._pymavlink import CurrentMode, mavlink
from btmission.backends.mavlink import MavlinkProvider
from btmission.backends.mavlink_frames import LocalFrame
from btmission.backends.mavlink_link import MavlinkOptions, _Link
from btmission.backends.mavlink_modes import Autopilot, mode_request
from btmission.backends.mavlink_url import MavlinkAddress
from btmission.backends.mavlink_vehicle import ACCEPTED_HOLD_S, MavlinkVehicle
from btmission.vehicles.base import Mode, VehicleKind
from tests.wallclock import WallClock

SCALE = 1.0
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
SET_MODE = mavlink.MAV_CMD_DO_SET_MODE
OFFBOARD = mode_request(Autopilot.PX4, VehicleKind.MULTIROTOR, Mode.OFFBOARD).custom_mode


class Wire:
    """What the vehicle sends (its link's ``mav``): the COMMAND_LONGs, in order."""

    def __init__(self) -> None:
        self.commands: list[tuple[int, int]] = []
        """(command, confirmation) of each COMMAND_LONG sent."""

    def command_long_send(self, _sys: int, _comp: int, command: int, confirmation: int,
                          *_params: float) -> None:  # fmt: skip
        self.commands.append((command, confirmation))

    def sent(self, command: int) -> int:
        return sum(c == command for c, _ in self.commands)


class Conn:
    def __init__(self) -> None:
        self.mav = Wire()


@pytest.fixture
def provider(wall: WallClock) -> Iterator[MavlinkProvider]:
    p = MavlinkProvider(MavlinkOptions(time_scale=SCALE, ack_timeout_s=1.0, command_retries=2))
    yield p
    p.close()


def _packed(msg: Any) -> Any:
    msg.pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))  # (sets its source)
    return msg


def heartbeat(
    custom_mode: int = 0, armed: bool = False, status: int = mavlink.MAV_STATE_STANDBY
) -> Any:
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if armed:
        base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    return _packed(
        mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, custom_mode, status, 3,
        )
    )  # fmt: skip


def ack(command: int, result: int) -> Any:
    return _packed(mavlink.MAVLink_command_ack_message(command, result, 0, 0, 255, 190))


def text(said: str) -> Any:
    return _packed(mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_CRITICAL, said.encode()))


class Px4:
    """R1, a PX4 drone on the ground, as the provider sees it once connected; ``tell`` files
    what it sends as the I/O thread would."""

    def __init__(self, p: MavlinkProvider, wall: WallClock) -> None:
        self.p = p
        self.link = wall.read_on(_Link(MavlinkAddress("udp", "127.0.0.1", 14540), conn=Conn()))
        self.tell(heartbeat())
        self.vehicle = MavlinkVehicle(
            "R1", VehicleKind.MULTIROTOR, self.link, self.link.vehicles[1],
            LocalFrame((0.0, 0.0, 0.0)), p.clock, p.options,
        )  # fmt: skip
        self.wire: Wire = self.link.conn.mav

    def tell(self, *msgs: Any) -> None:
        for msg in msgs:
            self.p._io._file(self.link, msg)


@pytest.fixture
def px4(provider: MavlinkProvider, wall: WallClock) -> Px4:
    return Px4(provider, wall)


def test_a_temporarily_rejected_command_returns_at_once_and_is_sent_again_on_a_later_call(
    px4: Px4, wall: WallClock
) -> None:
    v = px4.vehicle
    first = v.arm()
    assert first.pending and first.transient and not first.accepted
    assert first.reason == "waiting for COMMAND_ACK of MAV_CMD_COMPONENT_ARM_DISARM"
    assert px4.wire.sent(ARM) == 1
    px4.tell(text("Arming denied: Preflight: estimator not ready"))
    px4.tell(ack(ARM, mavlink.MAV_RESULT_TEMPORARILY_REJECTED))
    waiting = v.arm()  # (the old command() slept 0.5 s here, in the mission loop)
    assert waiting.pending and not waiting.accepted
    assert waiting.reason == (
        "MAV_CMD_COMPONENT_ARM_DISARM: MAV_RESULT_TEMPORARILY_REJECTED (Arming denied: Preflight: "
        "estimator not ready): sending it again"
    )
    assert px4.wire.sent(ARM) == 1  # not yet: its back-off runs
    wall.t += 0.49
    assert v.arm().pending and px4.wire.sent(ARM) == 1
    wall.t += 0.02
    assert v.arm().pending and px4.wire.sent(ARM) == 2  # after the back-off, on a later call
    assert px4.wire.commands[-1] == (ARM, 1)  # its confirmation counts the sends
    px4.tell(ack(ARM, mavlink.MAV_RESULT_ACCEPTED))
    assert v.arm()
    assert v.telemetry().armed  # an accepted arming shows until the next heartbeat says
    assert px4.wire.sent(ARM) == 2


def test_an_answer_read_after_its_effect_showed_is_not_taken_for_a_later_request(
    px4: Px4, wall: WallClock
) -> None:
    """The HEARTBEAT showed the drone armed before the arming's COMMAND_ACK was read, so arm()
    was done without it. The drone flew, landed and was disarmed; the next arm() took that
    old ACCEPTED, still unread, for its own answer and sent nothing (seen on mavsim: the tree
    then waited for a drone that never armed)."""
    v = px4.vehicle
    assert v.arm().pending and px4.wire.sent(ARM) == 1
    px4.tell(heartbeat(armed=True))  # its effect shows first
    assert v.arm() and px4.wire.sent(ARM) == 1
    px4.tell(ack(ARM, mavlink.MAV_RESULT_ACCEPTED))  # then its answer, which nobody reads
    wall.t += 30.0
    px4.tell(heartbeat(armed=False))  # landed and disarmed by the autopilot
    again = v.arm()
    assert again.pending and px4.wire.sent(ARM) == 2  # asked anew
    assert not v.telemetry().armed
    px4.tell(ack(ARM, mavlink.MAV_RESULT_DENIED))
    assert not v.arm().accepted  # the answer to this request, not the old one


def test_an_unanswered_command_is_sent_again_after_its_deadline_then_refused_transiently(
    px4: Px4, wall: WallClock
) -> None:
    v = px4.vehicle
    assert v.set_mode(Mode.HOLD).pending and px4.wire.sent(SET_MODE) == 1
    wall.t += 0.9
    assert v.set_mode(Mode.HOLD).pending and px4.wire.sent(SET_MODE) == 1
    wall.t += 0.2  # ack_timeout_s (1 s) passed without an answer
    assert v.set_mode(Mode.HOLD).pending and px4.wire.sent(SET_MODE) == 2
    wall.t += 1.1
    assert v.set_mode(Mode.HOLD).pending and px4.wire.sent(SET_MODE) == 3
    wall.t += 1.1  # command_retries (2) spent
    gave_up = v.set_mode(Mode.HOLD)
    assert not gave_up.accepted and not gave_up.pending and gave_up.transient
    assert gave_up.reason == (
        "MAV_CMD_DO_SET_MODE: no COMMAND_ACK from sysid 1 within 1 s (3 tries); "
        "the vehicle's link is lost"
    )
    assert v.set_mode(Mode.HOLD) == gave_up and px4.wire.sent(SET_MODE) == 3  # kept a while
    wall.t += 0.5  # its back-off (0.5 s): asked anew, saying what it said last time
    again = v.set_mode(Mode.HOLD)
    assert again.pending and px4.wire.sent(SET_MODE) == 4
    assert again.reason == gave_up.reason + "; asked again"


def test_px4s_second_answer_to_a_mode_change_overrides_its_first(px4: Px4) -> None:
    """PX4: ACCEPTED from its MAVLink module at once, then the commander's refusal. Neither the
    first answer nor anything else shows OFFBOARD before the telemetry does."""
    v = px4.vehicle
    assert v.set_mode(Mode.OFFBOARD).pending
    px4.tell(ack(SET_MODE, mavlink.MAV_RESULT_ACCEPTED))
    assert v.set_mode(Mode.OFFBOARD).accepted
    assert v.telemetry().mode is not Mode.OFFBOARD  # accepted is not set: the telemetry says
    px4.tell(text("Switching to Offboard is currently not available"))
    px4.tell(ack(SET_MODE, mavlink.MAV_RESULT_DENIED))
    refused = v.set_mode(Mode.OFFBOARD)
    assert not refused.accepted and not refused.pending and refused.transient
    assert refused.reason == (
        "MAV_CMD_DO_SET_MODE: MAV_RESULT_DENIED (Switching to Offboard is currently not available)"
    )
    assert v.telemetry().mode is not Mode.OFFBOARD
    assert px4.wire.sent(SET_MODE) == 1


def test_an_accepted_mode_that_does_not_show_is_asked_again(px4: Px4, wall: WallClock) -> None:
    v = px4.vehicle
    v.set_mode(Mode.OFFBOARD)
    px4.tell(ack(SET_MODE, mavlink.MAV_RESULT_ACCEPTED))
    assert v.set_mode(Mode.OFFBOARD).accepted and px4.wire.sent(SET_MODE) == 1
    wall.t += ACCEPTED_HOLD_S / SCALE + 0.01  # accepted, kept, never seen: sent anew
    assert v.set_mode(Mode.OFFBOARD).pending and px4.wire.sent(SET_MODE) == 2


def test_an_accepted_mode_the_vehicle_left_is_asked_again_at_once(px4: Px4) -> None:
    """OFFBOARD accepted and shown, then PX4's offboard-loss failsafe holds (a link drop): the
    agent's next OFFBOARD is sent, not answered with the old ACCEPTED (at time_scale 10 the
    answer's hold, at least ``ack_timeout_s`` of wall time, outlasted the agent's 5 s of trying
    to take OFFBOARD back)."""
    v = px4.vehicle
    v.set_mode(Mode.OFFBOARD)
    px4.tell(ack(SET_MODE, mavlink.MAV_RESULT_ACCEPTED))
    assert v.set_mode(Mode.OFFBOARD).accepted
    px4.tell(_packed(CurrentMode(0, OFFBOARD, OFFBOARD)))
    assert v.telemetry().mode is Mode.OFFBOARD
    px4.tell(_packed(CurrentMode(0, LOITER, LOITER)))  # the failsafe (no wall time passed)
    assert v.set_mode(Mode.OFFBOARD).pending and px4.wire.sent(SET_MODE) == 2


def test_land_on_the_ground_asks_nothing(px4: Px4) -> None:
    """Landed, disarmed and out of LAND, seen from CURRENT_MODE and EXTENDED_SYS_STATE before
    the next 1 Hz HEARTBEAT says disarmed: no LAND is sent (mavsim's PX4 refused it, and the
    navigator abandoned the landing it had finished)."""
    v = px4.vehicle
    px4.tell(heartbeat(custom_mode=LAND_MODE, armed=True))
    on_ground = mavlink.MAVLink_extended_sys_state_message(0, mavlink.MAV_LANDED_STATE_ON_GROUND)
    px4.tell(_packed(on_ground), _packed(CurrentMode(0, 0, 0)))
    tel = v.telemetry()
    assert tel.armed and tel.landed and tel.mode is not Mode.LAND
    assert v.land() and px4.wire.sent(SET_MODE) == 0


def test_the_mode_is_read_from_current_mode_before_the_next_heartbeat(px4: Px4) -> None:
    v = px4.vehicle
    v.set_mode(Mode.OFFBOARD)
    px4.tell(ack(SET_MODE, mavlink.MAV_RESULT_ACCEPTED))
    beats = v.state.heartbeats
    px4.tell(_packed(CurrentMode(0, OFFBOARD, OFFBOARD)))
    assert v.state.heartbeats == beats  # no heartbeat came
    assert v.telemetry().mode is Mode.OFFBOARD
    assert v.set_mode(Mode.OFFBOARD) and px4.wire.sent(SET_MODE) == 1  # in it: not asked again
    px4.tell(heartbeat(custom_mode=0))  # a newer message says otherwise: that is the mode
    assert v.telemetry().mode is Mode.MANUAL


def test_wait_calls_until_the_answer_and_the_telemetry_are_in(
    px4: Px4, wall: WallClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The blocking variant (the stop sequence): the vehicle answers while it waits."""
    v = px4.vehicle
    script = iter(
        [
            [ack(SET_MODE, mavlink.MAV_RESULT_ACCEPTED)],
            [],
            [_packed(CurrentMode(0, LOITER, LOITER))],
        ]
    )

    def sleep(_s: float) -> None:  # the vehicle's side, one step per wait
        wall.t += 0.01
        px4.tell(*next(script, []))

    monkeypatch.setattr("time.sleep", sleep)
    assert v.set_mode_and_wait(Mode.HOLD)
    assert v.telemetry().mode is Mode.HOLD
    assert px4.wire.sent(SET_MODE) == 1


LOITER = mode_request(Autopilot.PX4, VehicleKind.MULTIROTOR, Mode.HOLD).custom_mode
LAND_MODE = mode_request(Autopilot.PX4, VehicleKind.MULTIROTOR, Mode.LAND).custom_mode


def test_px4s_default_offboard_loss_action_reads_as_the_hold_the_agent_takes_back(
    px4: Px4,
) -> None:
    """PX4's offboard-loss failsafe with its default action (COM_OBL_RC_ACT 0) is Position mode,
    reported with system status CRITICAL (PX4 v1.16 SITL after btmission was stopped 2 s: custom
    mode 196608); PX4 returns to OFFBOARD by itself once the setpoints stream. Read as MANUAL,
    the agent stood down for good: it is the offboard-loss HOLD, which the agent takes back. A
    pilot's Position mode (no failsafe) and a failsafe's RTL stay MANUAL: taken over."""
    v = px4.vehicle
    posctl, altctl, rtl = 3 << 16, 2 << 16, (4 << 16) | (5 << 24)
    critical = mavlink.MAV_STATE_CRITICAL
    px4.tell(heartbeat(posctl, armed=True, status=critical))
    tel = v.telemetry()
    assert tel.mode is Mode.HOLD and tel.failsafe
    px4.tell(heartbeat(altctl, armed=True, status=critical))
    assert v.telemetry().mode is Mode.HOLD
    px4.tell(heartbeat(posctl, armed=True, status=mavlink.MAV_STATE_ACTIVE))  # the pilot's
    assert v.telemetry().mode is Mode.MANUAL
    px4.tell(heartbeat(rtl, armed=True, status=critical))  # e.g. a battery failsafe's return
    tel = v.telemetry()
    assert tel.mode is Mode.MANUAL and tel.failsafe
