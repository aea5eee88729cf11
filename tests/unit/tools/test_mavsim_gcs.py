"""mavsim, the MAVLink vehicle simulator, seen from raw pymavlink ground stations, beyond
tests/unit/tools/test_mavsim.py: what a PX4 or ArduPilot SITL would send and refuse (heartbeat fields,
stream rates in simulated time, one-shot messages, ACK targets, OFFBOARD entry and loss, frames,
take-off altitudes, attitude targets, estimator and pre-arm refusals, rovers), faults (link drops,
signing), several vehicles, reconnects, the in-process API and more of ``btmission mavsim``'s
options and refusals. Tests that repeat a tests/unit/tools/test_mavsim.py scenario in more detail are slow."""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from btmission.backends._pymavlink import CURRENT_MODE_ID, mavlink, mavutil
from btmission.backends.mavlink_frames import LocalFrame
from btmission.backends.mavlink_modes import Autopilot, mode_of, mode_request, set_mode_params
from btmission.backends.mavlink_setpoints import (
    attitude_target,
    position_target,
    velocity_target,
)
from btmission.backends.mavlink_signing import enable_signing
from btmission.backends.mavlink_url import MavlinkAddress
from btmission.cli.main import cli
from btmission.mavsim import MavSim, MavSimConfig, VehicleSpec, mission_vehicles
from btmission.vehicles.base import Mode, VehicleKind
from btmission.world.minegen import empty_world

ROOT = Path(__file__).resolve().parents[3]
PX4, APM = Autopilot.PX4, Autopilot.ARDUPILOT
ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
KEY = bytes(range(32))


class Gcs:
    """A raw pymavlink ground station on one vehicle's link."""

    def __init__(self, conn: Any, sysid: int, autopilot: Autopilot, start: tuple[float, ...]):
        self.conn = conn
        self.sysid = sysid
        self.autopilot = autopilot
        self.frame = LocalFrame((start[0], start[1], start[2]))
        self.texts: list[str] = []
        self.last: dict[str, Any] = {}

    @property
    def mav(self) -> Any:
        return self.conn.mav

    def recv(self, timeout: float) -> Any:
        msg = self.conn.recv_match(blocking=True, timeout=timeout)
        if msg is not None and msg.get_type() != "BAD_DATA":
            self.last[msg.get_type()] = msg
            if msg.get_type() == "STATUSTEXT":
                self.texts.append(msg.text)
            return msg
        return None

    def wait(
        self, kind: str, timeout: float = 3.0, cond: Callable[[Any], bool] = lambda m: True,
        every: Callable[[], None] | None = None,
    ) -> Any:  # fmt: skip
        """The first ``kind`` message that satisfies ``cond`` (None after ``timeout``), calling
        ``every`` (a setpoint, a GCS heartbeat) every 0.05 s meanwhile."""
        end = time.monotonic() + timeout
        next_call = 0.0
        while (now := time.monotonic()) < end:
            if every is not None and now >= next_call:
                every()
                next_call = now + 0.05
            msg = self.recv(min(0.05, end - now))
            if msg is not None and msg.get_type() == kind and cond(msg):
                return msg
        return None

    def pump(self, seconds: float, every: Callable[[], None] | None = None) -> list[Any]:
        """Everything received for ``seconds`` (wall), calling ``every`` every 0.05 s."""
        out: list[Any] = []
        end = time.monotonic() + seconds
        next_call = 0.0
        while (now := time.monotonic()) < end:
            if every is not None and now >= next_call:
                every()
                next_call = now + 0.05
            msg = self.recv(min(0.02, end - now))
            if msg is not None:
                out.append(msg)
        return out

    def heartbeat(self) -> None:
        self.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def command(
        self, command: int, *params: float, timeout: float = 2.0, target: int | None = None
    ) -> int | None:
        p = list(params) + [0.0] * (7 - len(params))
        self.mav.command_long_send(self.sysid if target is None else target, 1, command, 0, *p)
        ack = self.wait("COMMAND_ACK", timeout, lambda m: m.command == command)
        if ack is not None and command == mavlink.MAV_CMD_DO_SET_MODE and self.autopilot is PX4:
            # PX4 answers a mode change twice: ACCEPTED at once, then the real result
            assert ack.result == ACCEPTED
            ack = self.wait("COMMAND_ACK", timeout, lambda m: m.command == command)
        return None if ack is None else int(ack.result)

    def arm(self, force: bool = False) -> int | None:
        return self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196 if force else 0)

    def set_mode(self, mode: Mode) -> int | None:
        req = mode_request(self.autopilot, VehicleKind.MULTIROTOR, mode)
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(self.autopilot, req))

    def mode(self) -> Mode | str:
        hb = self.wait("HEARTBEAT", 2.5)
        assert hb is not None, "no heartbeat"
        return mode_of(self.autopilot, VehicleKind.MULTIROTOR, hb.custom_mode)

    def interval(self, msg_id: int, hz: float) -> int | None:
        us = -1 if hz < 0 else (0 if hz == 0 else 1e6 / hz)
        return self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, us)

    def position(self, world: tuple[float, float, float], target: int | None = None) -> None:
        t = position_target(self.frame, world)
        self.mav.set_position_target_local_ned_send(
            0, self.sysid if target is None else target, 1, mavlink.MAV_FRAME_LOCAL_NED,
            t.type_mask, *t.position, *t.velocity, 0, 0, 0, t.yaw, t.yaw_rate,
        )  # fmt: skip

    def velocity(self, world: tuple[float, float, float]) -> None:
        t = velocity_target(self.frame, world)
        self.mav.set_position_target_local_ned_send(
            0, self.sysid, 1, mavlink.MAV_FRAME_LOCAL_NED,
            t.type_mask, *t.position, *t.velocity, 0, 0, 0, t.yaw, t.yaw_rate,
        )  # fmt: skip


def _world() -> Any:
    return empty_world((30.0, 20.0, 10.0), 0.5)


def _spec(i: int, address: MavlinkAddress) -> VehicleSpec:
    return VehicleSpec(f"V{i + 1}", VehicleKind.MULTIROTOR, (5.0 + 3 * i, 5.0, 0.0), address, i + 1)


@contextmanager
def px4(n: int = 1, key: bytes | None = None, **config: Any) -> Iterator[tuple[MavSim, list[Gcs]]]:
    """``n`` PX4 vehicles, each sending to its own listening ground station (PX4 SITL's UDP)."""
    with ExitStack() as stack:
        conns = []
        for _ in range(n):
            c = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                           source_component=190)  # fmt: skip
            stack.callback(c.close)
            if key is not None:
                enable_signing(c, key)
            conns.append(c)
        specs = tuple(
            _spec(i, MavlinkAddress("udp", "127.0.0.1", c.port.getsockname()[1]))
            for i, c in enumerate(conns)
        )
        sim = stack.enter_context(MavSim(MavSimConfig(specs, _world(), autopilot=PX4, **config)))
        gcs = [Gcs(c, s.sysid, PX4, s.start) for c, s in zip(conns, specs, strict=True)]
        for g in gcs:  # the vehicle's first heartbeat tells the ground station where it is
            assert g.wait("HEARTBEAT", 3.0) is not None or key is not None
        yield sim, gcs


def _close(g: Gcs) -> None:
    g.conn.close()


@contextmanager
def ardupilot(
    n: int = 1, key: bytes | None = None, **config: Any
) -> Iterator[tuple[MavSim, list[Gcs]]]:
    """``n`` ArduPilot vehicles listening on TCP (free ports), a ground station connected to
    each."""
    with ExitStack() as stack:
        specs = tuple(_spec(i, MavlinkAddress("tcp", "127.0.0.1", 0)) for i in range(n))
        sim = stack.enter_context(MavSim(MavSimConfig(specs, _world(), autopilot=APM, **config)))
        gcs = []
        for ep, spec in zip(sim.endpoints, specs, strict=True):
            port = int(ep.url.rsplit(":", 1)[1])
            assert port > 0
            c = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255,
                                           source_component=190)  # fmt: skip
            if key is not None:
                enable_signing(c, key)
            g = Gcs(c, spec.sysid, APM, spec.start)
            stack.callback(_close, g)  # the test may have reconnected
            gcs.append(g)
        yield sim, gcs


def _takeoff_px4(sim: MavSim, g: Gcs, altitude: float = 2.5) -> None:
    assert g.arm() == ACCEPTED
    assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, altitude) == ACCEPTED
    end = time.monotonic() + 5
    while sim.vehicle_state("V1")["position"][2] < altitude - 0.3 and time.monotonic() < end:
        g.pump(0.05, g.heartbeat)
    assert sim.vehicle_state("V1")["position"][2] > altitude - 0.3


# ------------------------------------------------------------------ heartbeats, streams
def test_px4_heartbeat_fields_and_endpoint() -> None:
    with px4(speed=4.0) as (sim, [g]):
        hb = g.wait("HEARTBEAT")
        assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
        assert hb.type == mavlink.MAV_TYPE_QUADROTOR
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
        assert hb.base_mode == mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert hb.system_status == mavlink.MAV_STATE_STANDBY
        assert mode_of(PX4, VehicleKind.MULTIROTOR, hb.custom_mode) is Mode.MANUAL
        [ep] = sim.endpoints
        assert (ep.agent_id, ep.sysid, ep.autopilot, ep.kind) == (
            "V1", 1, PX4, VehicleKind.MULTIROTOR,
        )  # fmt: skip
        assert ep.url == f"mavlink+udp://127.0.0.1:{g.conn.port.getsockname()[1]}"
        assert g.arm() == ACCEPTED
        hb = g.wait("HEARTBEAT")
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.system_status == mavlink.MAV_STATE_ACTIVE
        assert g.arm() == ACCEPTED  # already armed


def test_ardupilot_heartbeat_over_tcp() -> None:
    with ardupilot(speed=4.0) as (sim, [g]):
        hb = g.wait("HEARTBEAT")
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        assert hb.type == mavlink.MAV_TYPE_QUADROTOR
        assert sim.endpoints[0].url.startswith("mavlink+tcp://127.0.0.1:")
        assert g.set_mode(Mode.OFFBOARD) == ACCEPTED
        assert g.wait("HEARTBEAT", cond=lambda m: m.custom_mode == 4) is not None  # GUIDED
        assert g.set_mode(Mode.OFFBOARD) == ACCEPTED  # already in GUIDED


def test_px4_answers_a_mode_change_twice_the_second_answer_is_the_real_one() -> None:
    """As PX4's MAVLink module and commander: ACCEPTED at once, then the refusal (with its
    STATUSTEXT before it; TEMPORARILY_REJECTED, as PX4 v1.16 SITL armed on the ground without
    setpoints) — a ground station that takes the first answer reads a refused OFFBOARD as
    accepted."""
    with px4() as (_sim, [g]):
        assert g.arm() == ACCEPTED  # (disarmed, PX4 takes OFFBOARD: test_mavsim_firmware)
        req = mode_request(PX4, VehicleKind.MULTIROTOR, Mode.OFFBOARD)
        g.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                                *set_mode_params(PX4, req), 0, 0, 0, 0)  # fmt: skip
        got = [m for m in g.pump(0.5) if m.get_type() in ("COMMAND_ACK", "STATUSTEXT")]
        assert [(m.get_type(), getattr(m, "result", None)) for m in got] == [
            ("COMMAND_ACK", ACCEPTED),
            ("STATUSTEXT", None),
            ("COMMAND_ACK", mavlink.MAV_RESULT_TEMPORARILY_REJECTED),
        ]
        assert got[1].text == "Switching to Offboard is currently not available"
        assert g.mode() is Mode.MANUAL


@pytest.mark.parametrize("autopilot", [PX4, APM], ids=lambda a: a.value)
def test_heartbeat_cannot_be_sped_up_on_px4_and_current_mode_streams(autopilot: Autopilot) -> None:
    """PX4 refuses SET_MESSAGE_INTERVAL for HEARTBEAT (it stays at 1 Hz); CURRENT_MODE is
    accepted at 20 Hz but comes at about 2 Hz (and on each change, test_mavsim_firmware), with
    the heartbeat's ``custom_mode``. ArduCopter is the other way round: a
    faster HEARTBEAT (from now on, not after the next one), and CURRENT_MODE refused as
    ArduCopter SITL refused it (DENIED, "No ap_message for mavlink id (436)"), never sent."""
    with px4() if autopilot is PX4 else ardupilot() as (_sim, [g]):
        result = g.interval(mavlink.MAVLINK_MSG_ID_HEARTBEAT, 10)
        assert result == (mavlink.MAV_RESULT_FAILED if autopilot is PX4 else ACCEPTED)
        result = g.interval(CURRENT_MODE_ID, 20)
        assert result == (ACCEPTED if autopilot is PX4 else mavlink.MAV_RESULT_DENIED)
        if autopilot is APM:
            assert g.texts[-1] == "No ap_message for mavlink id (436)"
            assert g.command(mavlink.MAV_CMD_REQUEST_MESSAGE, CURRENT_MODE_ID) == (
                mavlink.MAV_RESULT_FAILED
            )
        got = g.pump(1.0)
        modes = [m for m in got if m.get_type() == "CURRENT_MODE"]
        beats = [m for m in got if m.get_type() == "HEARTBEAT"]
        if autopilot is APM:
            assert modes == []
            assert len(beats) >= 5, len(beats)  # (10 Hz asked; a loaded machine may lag)
            return
        assert 1 <= len(modes) <= 3, len(modes)  # (20 Hz asked: PX4 sends 2 Hz)
        assert len(beats) <= 2
        assert {m.custom_mode for m in modes} == {beats[-1].custom_mode}


def test_streams_only_when_asked_at_the_asked_rate() -> None:
    with px4() as (_sim, [g]):
        assert "LOCAL_POSITION_NED" not in {m.get_type() for m in g.pump(0.3)}
        assert g.interval(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20) == ACCEPTED
        assert g.interval(mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, 5) == ACCEPTED
        got = g.pump(1.0)
        lpos = [m for m in got if m.get_type() == "LOCAL_POSITION_NED"]
        dist = [m for m in got if m.get_type() == "DISTANCE_SENSOR"]
        assert 15 <= len(lpos) <= 23, len(lpos)
        assert 3 <= len(dist) <= 7, len(dist)
        assert dist[-1].orientation == mavlink.MAV_SENSOR_ROTATION_PITCH_270
        span_ms = lpos[-1].time_boot_ms - lpos[0].time_boot_ms
        assert span_ms == pytest.approx(50 * (len(lpos) - 1), abs=60)  # sim time, 50 ms apart
        assert (lpos[-1].x, lpos[-1].y) == pytest.approx((0.0, 0.0), abs=0.05)  # spawn = origin
        assert g.interval(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, -1) == ACCEPTED
        g.pump(0.1)
        assert "LOCAL_POSITION_NED" not in {m.get_type() for m in g.pump(0.4)}


@pytest.mark.slow  # covered in the fast selection by test_mavlink_provider / test_mavsim
def test_stream_rates_are_in_simulated_time() -> None:
    with px4(speed=4.0) as (_sim, [g]):
        assert g.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 10) == ACCEPTED
        n = sum(m.get_type() == "ATTITUDE" for m in g.pump(1.0))
        assert 30 <= n <= 45, n


def test_one_shot_messages_and_unsupported_commands() -> None:
    with px4() as (_sim, [g]):
        assert g.command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                         mavlink.MAVLINK_MSG_ID_HOME_POSITION) == ACCEPTED  # fmt: skip
        assert "HOME_POSITION" in g.last or g.wait("HOME_POSITION") is not None
        assert g.command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                         mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == ACCEPTED  # fmt: skip
        av = g.last.get("AUTOPILOT_VERSION") or g.wait("AUTOPILOT_VERSION")
        assert av.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        assert g.command(
            mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN
        ) == (
            mavlink.MAV_RESULT_UNSUPPORTED
        )  # fmt: skip  (no GPS: no global origin until one is set)
        g.mav.set_gps_global_origin_send(1, 473977420, 85455940, 488000, 0)
        origin = g.wait("GPS_GLOBAL_ORIGIN")
        assert (origin.latitude, origin.longitude, origin.altitude) == (473977420, 85455940, 488000)
        assert g.command(mavlink.MAV_CMD_DO_FLIGHTTERMINATION, 1) == (
            mavlink.MAV_RESULT_UNSUPPORTED
        )


def test_px4_moves_to_a_ground_station_that_sends_its_heartbeat_from_elsewhere() -> None:
    """A stranger's command gets no answer; once it sends a ground station's HEARTBEAT, the
    vehicle answers there (a ground station restarted at another address)."""
    with px4() as (sim, [g]):
        other = mavutil.mavlink_connection("udpout:127.0.0.1:9", source_system=255)
        try:
            other.port.bind(("127.0.0.1", 0))
            vehicle = g.conn.clients.copy().pop() if g.conn.clients else None
            g.heartbeat()  # the vehicle learns nothing new from the listening station yet
            assert vehicle is not None
            other.destination_addr = vehicle

            def arm() -> Any:
                other.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                            1, 0, 0, 0, 0, 0, 0)  # fmt: skip
                end = time.monotonic() + 1.0
                ack = None
                while ack is None and time.monotonic() < end:
                    ack = other.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.1)
                return ack

            assert arm() is None and not sim.vehicle_state("V1")["armed"]
            assert sim.vehicle_state("V1")["strangers"] >= 1
            other.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            ack = arm()
            assert ack is not None and ack.result == ACCEPTED
            assert ack.target_system == 255
        finally:
            other.close()


# ------------------------------------------------------------------ PX4 offboard
def test_px4_offboard_is_refused_without_a_setpoint_stream() -> None:
    with px4(speed=4.0) as (sim, [g]):
        assert g.arm() == ACCEPTED  # (disarmed, PX4 takes OFFBOARD: test_mavsim_firmware)
        assert g.set_mode(Mode.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        assert any("Offboard" in t for t in g.texts), g.texts
        # one setpoint is not a stream
        g.position((5.0, 5.0, 2.0))
        assert g.set_mode(Mode.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        # nor is a stream in a frame that is not simulated (MAV_FRAME_BODY_NED)
        g.pump(0.4, lambda: g.mav.set_position_target_local_ned_send(
            0, 1, 1, mavlink.MAV_FRAME_BODY_NED, 0b110111111000, 0, 0, -2, 0, 0, 0, 0, 0, 0, 0, 0,
        ))  # fmt: skip
        assert g.set_mode(Mode.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        assert sim.vehicle_state("V1")["ignored_frames"] >= 5


@pytest.mark.slow
def test_px4_offboard_is_refused_for_a_slow_stream() -> None:
    with px4(speed=4.0) as (_sim, [g]):
        assert g.arm() == ACCEPTED  # (disarmed, PX4 takes OFFBOARD: test_mavsim_firmware)
        for _ in range(6):  # 1 Hz of simulated time for 1.5 s
            g.position((5.0, 5.0, 2.0))
            g.pump(0.25)
        g.position((5.0, 5.0, 2.0))
        assert g.set_mode(Mode.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED


@pytest.mark.slow  # covered in the fast selection by test_mavlink_provider / test_mavsim
def test_px4_offboard_after_a_second_of_streaming_then_hold_when_it_stops() -> None:
    # (COM_OBL_RC_ACT = Hold; the default, Position mode: test_mavsim_firmware.py)
    with px4(speed=4.0, offboard_loss_action="hold") as (sim, [g]):
        _takeoff_px4(sim, g)

        def stream() -> None:
            g.heartbeat()
            g.position((5.0, 7.0, 2.5))

        g.pump(0.15, stream)  # 0.6 s simulated: not yet
        assert g.set_mode(Mode.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        g.pump(0.2, stream)
        assert g.set_mode(Mode.OFFBOARD) == ACCEPTED
        assert g.wait("HEARTBEAT", cond=lambda m: (m.custom_mode >> 16) & 0xFF == 6) is not None
        g.pump(0.75, stream)
        assert sim.vehicle_state("V1")["position"][1] > 6.0  # flew 2 m north
        assert sim.vehicle_state("V1")["mode"] is Mode.OFFBOARD
        g.pump(0.4, g.heartbeat)  # 1.6 s simulated without setpoints
        state = sim.vehicle_state("V1")
        assert state["mode"] is Mode.HOLD, state
        assert "offboard" in state["failsafe"]
        assert g.mode() is Mode.HOLD


@pytest.mark.slow
def test_px4_data_link_loss_lands() -> None:
    with px4(speed=8.0, datalink_loss_s=10.0) as (sim, [g]):  # NAV_DLL_ACT = land
        _takeoff_px4(sim, g)
        assert g.interval(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 5) == ACCEPTED
        g.pump(0.6, g.heartbeat)  # 4.8 s simulated with a ground station: still flying
        assert sim.vehicle_state("V1")["mode"] is not Mode.LAND
        landing = g.wait("HEARTBEAT", 3.0,
                         lambda m: mode_of(PX4, VehicleKind.MULTIROTOR, m.custom_mode) is Mode.LAND)  # fmt: skip
        assert landing is not None
        assert any("no GCS link" in t for t in g.texts), g.texts
        assert "data link lost" in sim.vehicle_state("V1")["failsafe"]


def test_px4_takeoff_climbs_to_the_amsl_altitude_once_armed() -> None:
    with px4(speed=4.0, home_amsl_m=100.0) as (sim, [g]):
        # disarmed: accepted (as PX4 v1.16 SITL), nothing moves until armed
        assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, 103.0) == ACCEPTED
        g.pump(0.2, g.heartbeat)
        assert sim.vehicle_state("V1")["position"][2] == pytest.approx(0.0, abs=0.05)
        assert g.arm() == ACCEPTED
        assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, 103.0) == ACCEPTED
        g.pump(1.5, g.heartbeat)
        assert sim.vehicle_state("V1")["position"][2] == pytest.approx(3.0, abs=0.3)


@pytest.mark.slow
def test_px4_attitude_setpoints_fly() -> None:
    with px4(speed=2.0) as (sim, [g]):
        _takeoff_px4(sim, g)
        yaw = sim.vehicle_state("V1")["yaw"]
        heading = np.array([math.cos(yaw), math.sin(yaw), 0.0])

        def stream() -> None:
            g.heartbeat()
            t = attitude_target(g.frame, 9.81, 0.0, 0.15, yaw, hover=0.5)
            g.mav.set_attitude_target_send(0, 1, 1, t.type_mask, t.q, 0, 0, t.body_yaw_rate,
                                           t.thrust)  # fmt: skip

        g.pump(0.6, stream)
        assert g.set_mode(Mode.OFFBOARD) == ACCEPTED
        p0 = sim.vehicle_state("V1")["position"]
        g.pump(0.8, stream)
        state = sim.vehicle_state("V1")
        assert state["velocity"] @ heading > 0.5  # pitched forward (+θ), moving forward
        assert (state["position"] - p0) @ heading > 0.3
        assert state["position"][2] == pytest.approx(2.5, abs=0.5)  # hover thrust holds height


# ------------------------------------------------------------------ ArduPilot GUIDED
@pytest.mark.slow
def test_ardupilot_guided_takeoff_climbs_to_altitude_above_home() -> None:
    with ardupilot(speed=4.0) as (sim, [g]):
        assert g.arm() == ACCEPTED
        assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3.0) == (
            mavlink.MAV_RESULT_FAILED
        )  # not in GUIDED
        assert g.set_mode(Mode.OFFBOARD) == ACCEPTED
        g.position((5.0, 5.0, 3.0))  # a target does not lift a landed copter
        g.pump(0.3, g.heartbeat)
        assert sim.vehicle_state("V1")["landed"]
        assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3.0) == ACCEPTED
        g.pump(1.5, g.heartbeat)
        state = sim.vehicle_state("V1")
        assert state["position"][2] == pytest.approx(3.0, abs=0.3)
        assert state["mode"] is Mode.OFFBOARD and state["armed"]


@pytest.mark.slow
def test_ardupilot_position_targets_hold_and_velocity_targets_stop_after_3_s() -> None:
    with ardupilot(speed=8.0) as (sim, [g]):
        assert g.set_mode(Mode.OFFBOARD) == ACCEPTED
        assert g.arm() == ACCEPTED
        assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == ACCEPTED
        g.pump(0.5, g.heartbeat)
        g.position((5.0, 8.0, 2.0))  # once: position targets do not time out
        g.pump(1.0, g.heartbeat)
        assert sim.vehicle_state("V1")["position"][1] == pytest.approx(8.0, abs=0.3)
        g.velocity((1.0, 0.0, 0.0))  # once: east for 3 s, then stop
        g.pump(0.19, g.heartbeat)
        assert sim.vehicle_state("V1")["velocity"][0] > 0.5
        g.pump(0.56, g.heartbeat)  # 4.5 s simulated since the target
        state = sim.vehicle_state("V1")
        assert np.linalg.norm(state["velocity"]) < 0.2, state
        assert 7.0 < state["position"][0] < 9.5  # about 3 m east, then it stopped


@pytest.mark.slow
def test_ardupilot_gcs_failsafe_lands() -> None:
    with ardupilot(speed=8.0, gcs_failsafe_s=5.0) as (_sim, [g]):  # FS_GCS_ENABLE = land
        assert g.set_mode(Mode.OFFBOARD) == ACCEPTED
        assert g.arm() == ACCEPTED
        assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == ACCEPTED
        g.pump(0.4, g.heartbeat)
        assert g.wait("HEARTBEAT", 2.0, lambda m: mode_of(
            APM, VehicleKind.MULTIROTOR, m.custom_mode) is Mode.LAND) is not None  # fmt: skip
        assert "GCS Failsafe On: LAND" in g.texts


# ------------------------------------------------------------------ faults
def test_px4_arming_is_temporarily_rejected_until_the_estimator_is_ready() -> None:
    with px4(speed=4.0, ekf_delay_s=2.0) as (_sim, [g]):
        assert g.interval(mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS, 4) == ACCEPTED
        status = g.wait("ESTIMATOR_STATUS")
        assert not status.flags & mavlink.ESTIMATOR_POS_HORIZ_REL
        assert g.arm() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        assert g.texts[-1] == "Arming denied: Preflight: estimator not ready"
        assert g.set_mode(Mode.HOLD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # no estimate
        assert g.texts[-1] == "Switching to Hold is currently not available"
        ready = g.wait("ESTIMATOR_STATUS", 2.0, lambda m: m.flags & mavlink.ESTIMATOR_POS_HORIZ_REL)
        assert ready is not None
        assert g.arm() == ACCEPTED


@pytest.mark.slow
def test_ardupilot_arming_and_guided_refused_during_the_ekf_delay() -> None:
    with ardupilot(speed=4.0, ekf_delay_s=2.0) as (_sim, [g]):
        assert g.interval(mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 4) == ACCEPTED
        assert not g.wait("EKF_STATUS_REPORT").flags & mavlink.EKF_POS_HORIZ_REL
        assert g.arm() == mavlink.MAV_RESULT_FAILED
        assert g.texts[-1] == "PreArm: EKF3 waiting for GPS config data"
        assert g.set_mode(Mode.OFFBOARD) == mavlink.MAV_RESULT_FAILED
        assert g.texts[-1] == "Mode change failed: requires position"
        assert g.wait("EKF_STATUS_REPORT", 2.0,
                      lambda m: m.flags & mavlink.EKF_POS_HORIZ_REL) is not None  # fmt: skip
        assert g.arm() == ACCEPTED


@pytest.mark.parametrize(
    ("make", "result", "text"),
    [
        (px4, mavlink.MAV_RESULT_DENIED, "Preflight Fail: Compass Uncalibrated"),
        (ardupilot, mavlink.MAV_RESULT_FAILED, "PreArm: Compass Uncalibrated"),
    ],
)
def test_refuse_arm(make: Any, result: int, text: str) -> None:
    with make(refuse_arm="Compass Uncalibrated") as (sim, [g]):
        assert g.arm() == result
        assert g.texts == [text]
        assert not sim.vehicle_state("V1")["armed"]


def test_refuse_arm_times_refuses_only_the_first_arming_commands() -> None:
    with px4(refuse_arm_times=2) as (sim, [g]):
        assert [g.arm(), g.arm()] == [mavlink.MAV_RESULT_DENIED] * 2
        assert g.texts == ["Preflight Fail: sensors not ready"] * 2
        assert not sim.vehicle_state("V1")["armed"]
        assert g.arm() == ACCEPTED  # the third passes the check
    with pytest.raises(ValueError, match="refuse_arm_times must be ≥ 0"):
        MavSimConfig(sim.config.vehicles, sim.config.voxel_map, refuse_arm_times=-1)


def test_a_dropped_link_neither_sends_nor_hears() -> None:
    with px4(speed=2.0) as (sim, [g]):
        sim.drop_link("V1", 1.0)  # 0.5 s of wall time
        g.heartbeat()
        g.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                1, 0, 0, 0, 0, 0, 0)  # fmt: skip
        assert g.pump(0.4) == []
        assert g.wait("HEARTBEAT", 1.5) is not None  # back
        assert not sim.vehicle_state("V1")["armed"]  # the arm sent meanwhile was lost
        assert g.arm() == ACCEPTED


@pytest.mark.slow  # covered in the fast selection by test_mavlink_provider / test_mavsim
def test_two_vehicles_fly_independently() -> None:
    with px4(n=2, speed=4.0) as (sim, [g1, g2]):
        assert {ep.sysid for ep in sim.endpoints} == {1, 2}
        assert g2.wait("HEARTBEAT").get_srcSystem() == 2
        # a command for vehicle 2 sent on vehicle 1's link is not vehicle 1's
        assert g1.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=2, timeout=0.5) is None
        assert not sim.vehicle_state("V1")["armed"]
        assert g2.arm() == ACCEPTED
        assert g2.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, 2.0) == ACCEPTED
        g2.pump(1.0, g2.heartbeat)
        assert sim.vehicle_state("V2")["position"][2] > 1.5
        assert sim.vehicle_state("V1")["position"][2] < 0.1
        assert not sim.vehicle_state("V1")["armed"]


@pytest.mark.slow  # covered in the fast selection by test_mavlink_provider / test_mavsim
def test_wrong_signing_key_gets_no_answer_and_is_counted() -> None:
    with ardupilot(speed=4.0, key=b"\x07" * 32, signing_key=KEY) as (sim, [g]):
        assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout=0.6) is None
        assert g.wait("HEARTBEAT", 0.6) is None  # its heartbeats are not ours to read either
        counts = sim.counters()["V1"]
        assert counts["bad_signature"] >= 1 and counts["signed_ok"] == 0
        assert not sim.vehicle_state("V1")["armed"]


def test_unsigned_ground_station_is_refused_and_a_signed_one_flies() -> None:
    with ardupilot(signing_key=KEY) as (sim, [g]):
        assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout=0.6) is None
        assert sim.counters()["V1"]["unsigned_refused"] >= 1
    with ardupilot(key=KEY, signing_key=KEY) as (sim, [g]):
        assert g.arm() == ACCEPTED
        assert sim.counters()["V1"]["signed_ok"] >= 1


def test_stop_is_idempotent_and_frees_the_port() -> None:
    specs = (_spec(0, MavlinkAddress("tcp", "127.0.0.1", 0)),)
    sim = MavSim(MavSimConfig(specs, _world(), autopilot=APM)).start()
    port = int(sim.endpoints[0].url.rsplit(":", 1)[1])
    sim.stop()
    sim.stop()
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))


# ------------------------------------------------------------------ config from a mission
def test_a_mission_serves_each_mavlink_agent_at_its_url() -> None:
    from btmission.missions import load_mission

    mission = load_mission(ROOT / "missions/mine_inspection_ardupilot.yaml")
    specs = mission_vehicles(mission)
    agents = {a.id: a for a in mission.agents}
    assert [s.agent_id for s in specs] == list(agents)
    for s in specs:
        assert f"mavlink+{s.address.transport}://{s.address.host}:{s.address.port}" in (
            agents[s.agent_id].backend
        )
        assert s.start == tuple(float(v) for v in agents[s.agent_id].start)


# ------------------------------------------------------------------ CLI
def test_cli_bad_input_exits_2(tmp_path: Path) -> None:
    runner = CliRunner()
    r = runner.invoke(cli, ["mavsim"])
    assert r.exit_code == 2 and "give either --mission FILE or --count N" in r.output
    r = runner.invoke(cli, ["mavsim", "--count", "1", "--signing-key-file", str(tmp_path / "k")])
    assert r.exit_code == 2 and "k: no such file (the MAVLink signing key)" in r.output
    bad = tmp_path / "bad.yaml"
    bad.write_text("agents: [\n")
    r = runner.invoke(cli, ["mavsim", "--mission", str(bad)])
    assert r.exit_code == 2 and "bad.yaml:" in r.output and "Traceback" not in r.output
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        r = runner.invoke(cli, ["mavsim", "--count", "1", "--autopilot", "ardupilot",
                                "--port", str(port)])  # fmt: skip
    assert r.exit_code == 2 and "cannot serve the vehicles" in r.output, r.output


@pytest.mark.slow
def test_cli_serves_until_sigterm(tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "XDG_STATE_HOME": str(tmp_path)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "btmission", "mavsim", "--count", "2",
         "--autopilot", "ardupilot", "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline() for _ in range(3)]
        assert lines[0].split() == ["V1", f"mavlink+tcp://127.0.0.1:{port}", "sysid", "1",
                                    "ardupilot", "multirotor"]  # fmt: skip
        assert lines[1].split()[1] == f"mavlink+tcp://127.0.0.1:{port + 10}"
        assert lines[2].startswith("ready (2 vehicle(s), ardupilot")
        c = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port + 10}", source_system=255)
        try:
            hb = c.recv_match(type="HEARTBEAT", blocking=True, timeout=3)
            assert hb is not None and hb.get_srcSystem() == 1  # as every ArduCopter SITL
        finally:
            c.close()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert out.startswith("stopped after"), out


def test_ardupilot_accepts_a_ground_station_that_reconnects() -> None:
    with ardupilot(speed=4.0) as (sim, [g]):
        assert g.wait("HEARTBEAT") is not None
        port = int(sim.endpoints[0].url.rsplit(":", 1)[1])
        g.conn.close()
        g.conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255,
                                            source_component=190)  # fmt: skip
        assert g.wait("HEARTBEAT", 3.0) is not None
        assert g.arm() == ACCEPTED


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _mission(tmp_path: Path, *backends: str) -> Path:
    agents = "\n".join(
        f"  - {{id: R{i + 1}, library: {'ground' if 'rover' in b else 'aerial'}, "
        f"start: [{2 + 3 * i}, 2, 0], backend: '{b.replace('#rover', '')}'}}"
        for i, b in enumerate(backends)
    )
    path = tmp_path / "m.yaml"
    path.write_text(
        "mission: tiny\nversion: 1\n"
        "world:\n  map: {generate: empty, size: [20, 20, 6]}\n  resolution: 0.5\n"
        f"agents:\n{agents}\n"
        "tasks:\n  - {id: T1, type: inspect, location: [10, 10, 2]}\n"
        "task_types:\n  inspect: {goal: at_goal(location), cost: path_cost(location)}\n"
    )
    return path


def test_cli_serves_a_mission_at_its_agents_urls(tmp_path: Path) -> None:
    p1, p2 = _free_tcp_port(), _free_tcp_port()
    path = _mission(
        tmp_path, f"mavlink+tcp://127.0.0.1:{p1}", f"mavlink+tcp://127.0.0.1:{p2}?sysid=7#rover"
    )
    r = CliRunner().invoke(
        cli, ["mavsim", "--mission", str(path), "--autopilot", "ardupilot", "--duration", "0.3"]
    )
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    assert lines[0].split() == ["R1", f"mavlink+tcp://127.0.0.1:{p1}", "sysid", "1",
                                "ardupilot", "multirotor"]  # fmt: skip
    assert lines[1].split() == ["R2", f"mavlink+tcp://127.0.0.1:{p2}", "sysid", "7",
                                "ardupilot", "ground"]  # fmt: skip
    assert lines[2] == "ready (2 vehicle(s), ardupilot, speed 1x)"
    assert lines[3].startswith("stopped after")


def test_cli_quiet_and_transport(tmp_path: Path) -> None:
    port = _free_tcp_port()
    args = ["mavsim", "--count", "1", "--autopilot", "px4", "--transport", "tcp"]
    r = CliRunner().invoke(cli, [*args, "--port", str(port), "--duration", "0.2", "--quiet"])
    assert r.exit_code == 0, r.output
    assert r.output == "ready (1 vehicle(s), px4, speed 1x)\n"
    r = CliRunner().invoke(cli, [*args, "--port", str(port), "--duration", "0.2"])
    assert r.output.split()[1] == f"mavlink+tcp://127.0.0.1:{port}"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--count", "1", "--host", "localhostx"],
         "--host 'localhostx': expected an IPv4 address such as 127.0.0.1"),
        (["--count", "3", "--port", "65535"],
         "--port 65535: 3 vehicles do not fit below port 65536"),
    ],
)  # fmt: skip
def test_cli_bad_options_exit_2(args: list[str], message: str) -> None:
    r = CliRunner().invoke(cli, ["mavsim", *args])
    assert r.exit_code == 2
    assert f"Error: {message}" in r.output


def test_cli_bad_missions_exit_2(tmp_path: Path) -> None:
    runner = CliRunner()
    path = _mission(tmp_path, "mavlink+tcp://127.0.0.1:5900", "mavlink+tcp://127.0.0.1:5900")
    r = runner.invoke(cli, ["mavsim", "--mission", str(path)])
    assert r.exit_code == 2
    assert f"Error: {path}: R2 and R1 share the TCP port 127.0.0.1:5900" in r.output
    path = _mission(tmp_path, "mavlink+udp://10.1.2.3:14540")
    r = runner.invoke(cli, ["mavsim", "--mission", str(path)])
    assert r.exit_code == 2
    assert (
        f"Error: {path}: agent R1: its backend is at 10.1.2.3, but mavsim serves on 127.0.0.1 "
        "(--host 10.1.2.3 to serve there)" in r.output
    )
    path = _mission(tmp_path, "mavlink+serial:///dev/ttyACM0")
    r = runner.invoke(cli, ["mavsim", "--mission", str(path)])
    assert r.exit_code == 2
    assert "no agent has a mavlink+udp:// or mavlink+tcp:// backend to serve" in r.output
    r = runner.invoke(cli, ["mavsim", "--mission", str(path), "--port", "5000"])
    assert r.exit_code == 2
    assert "--transport and --port go with --count" in r.output


# ------------------------------------------------------------------ ground robots
@contextmanager
def rover(autopilot: Autopilot, **config: Any) -> Iterator[tuple[MavSim, Gcs]]:
    spec = VehicleSpec("V1", VehicleKind.GROUND, (5.0, 5.0, 0.0),
                       MavlinkAddress("tcp", "127.0.0.1", 0), 1)  # fmt: skip
    with MavSim(MavSimConfig((spec,), _world(), autopilot=autopilot, **config)) as sim:
        port = int(sim.endpoints[0].url.rsplit(":", 1)[1])
        c = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255,
                                       source_component=190)  # fmt: skip
        try:
            yield sim, Gcs(c, 1, autopilot, spec.start)
        finally:
            c.close()


def _rover_mode(g: Gcs, mode: Mode) -> int | None:
    req = mode_request(g.autopilot, VehicleKind.GROUND, mode)
    return g.command(mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(g.autopilot, req))


@pytest.mark.slow  # covered in the fast selection by test_mavlink_provider / test_mavsim
def test_px4_rover_offboard_rules() -> None:
    with rover(PX4, speed=4.0) as (sim, g):
        hb = g.wait("HEARTBEAT")
        assert hb.type == mavlink.MAV_TYPE_GROUND_ROVER
        assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        assert _rover_mode(g, Mode.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        g.pump(0.15, lambda: g.velocity((1.0, 0.0, 0.0)))
        assert sim.vehicle_state("V1")["position"][0] == pytest.approx(5.0)  # not in OFFBOARD
        assert _rover_mode(g, Mode.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # 0.6 s
        g.pump(0.2, lambda: g.velocity((1.0, 0.0, 0.0)))
        assert _rover_mode(g, Mode.OFFBOARD) == ACCEPTED
        g.pump(0.3, lambda: g.velocity((1.0, 0.0, 0.0)))
        assert sim.vehicle_state("V1")["position"][0] == pytest.approx(5.0)  # not armed
        assert g.arm() == ACCEPTED
        assert g.wait("HEARTBEAT").base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        g.pump(0.5, lambda: g.velocity((1.0, 0.0, 0.0)))
        assert sim.vehicle_state("V1")["position"][0] > 5.3  # drives east (0.4 m/s)
        g.pump(0.5, g.heartbeat)  # 2 s simulated without setpoints
        state = sim.vehicle_state("V1")
        assert state["mode"] is Mode.HOLD and "offboard" in state["failsafe"]


@pytest.mark.slow  # covered in the fast selection by test_mavlink_provider / test_mavsim
def test_ardurover_guided_velocity_targets() -> None:
    with rover(APM, speed=4.0) as (sim, g):
        assert g.wait("HEARTBEAT").type == mavlink.MAV_TYPE_GROUND_ROVER
        assert _rover_mode(g, Mode.OFFBOARD) == ACCEPTED
        assert g.wait("HEARTBEAT", cond=lambda m: m.custom_mode == 15) is not None  # GUIDED
        assert g.arm() == ACCEPTED
        g.velocity((1.0, 0.0, 0.0))  # once: ahead (east) for 3 s
        g.pump(0.4, g.heartbeat)
        assert sim.vehicle_state("V1")["velocity"][0] > 0.2  # the robot's top speed is 0.4
        g.pump(0.6, g.heartbeat)  # 4 s simulated: stopped
        assert np.linalg.norm(sim.vehicle_state("V1")["velocity"]) < 0.05
        assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == (
            mavlink.MAV_RESULT_UNSUPPORTED
        )
        assert _rover_mode(g, Mode.HOLD) == ACCEPTED
        assert g.wait("HEARTBEAT", cond=lambda m: m.custom_mode == 4) is not None  # HOLD


def test_cli_prints_the_signing_counters_on_exit(tmp_path: Path) -> None:
    key = tmp_path / "key"
    key.write_text("correct horse battery staple\n")
    port = _free_tcp_port()
    r = CliRunner().invoke(
        cli,
        ["mavsim", "--count", "1", "--autopilot", "ardupilot", "--port", str(port),
         "--signing-key-file", str(key), "--duration", "0.2"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    assert r.output.splitlines()[-1] == (
        "V1 signing: signed_ok 0, unsigned_refused 0, bad_signature 0, replay 0"
    )
    r = CliRunner().invoke(
        cli, ["mavsim", "--count", "1", "--port", str(port), "--duration", "0.2"],
        env={"BTMISSION_MAVLINK_KEY": ""},
    )  # fmt: skip
    assert "signing" not in r.output


@pytest.mark.slow
def test_no_link_loss_failsafe_before_a_ground_station_was_heard() -> None:
    with ardupilot(speed=8.0, gcs_failsafe_s=5.0) as (sim, [g]):
        assert g.set_mode(Mode.OFFBOARD) == ACCEPTED
        assert g.arm() == ACCEPTED
        assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == ACCEPTED
        g.pump(1.0)  # 8 s simulated, no GCS heartbeat ever
        state = sim.vehicle_state("V1")
        assert state["mode"] is Mode.OFFBOARD and not state["landed"], state
        assert "GCS Failsafe On: LAND" not in g.texts
