"""mavsim seen by a plain pymavlink ground station: the firmware rules a ground station must keep,
the failsafes, the CLI. Independent of btmission's provider: a client that breaks PX4's offboard
rules fails against it."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from btmission.backends._pymavlink import mavlink, mavutil
from btmission.backends.mavlink_modes import Autopilot, mode_request, set_mode_params
from btmission.cli.main import cli
from btmission.mavsim import MavSim
from btmission.vehicles.base import Mode, VehicleKind
from tests.mavlink_helpers import SPEED, mavsim, mission_on_free_ports

ROOT = Path(__file__).resolve().parents[3]


class Client:
    """A bare pymavlink ground station on a mavsim endpoint (sysid 255)."""

    def __init__(self, sim: MavSim) -> None:
        url = sim.endpoints[0].url
        transport, rest = url.split("://")
        device = ("udpin:" if transport.endswith("udp") else "tcp:") + rest
        self.sim = sim
        self.conn = mavutil.mavlink_connection(device, source_system=255, source_component=190)
        self.ap = sim.config.autopilot
        self.wait("HEARTBEAT")

    def wait(self, kind: str, seconds: float = 3.0, **fields: Any) -> Any:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            m = self.conn.recv_match(type=kind, blocking=True, timeout=0.1)
            if m is not None and all(getattr(m, k) == v for k, v in fields.items()):
                return m
        return None

    def command(self, command: int, *params: float) -> Any:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(1, 1, command, 0, *p)
        ack = self.wait("COMMAND_ACK", command=command)
        if ack is not None and command == mavlink.MAV_CMD_DO_SET_MODE and self.ap is Autopilot.PX4:
            # PX4 answers a mode change twice: ACCEPTED at once, then the real result
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED
            ack = self.wait("COMMAND_ACK", command=command)
        return ack

    def set_mode(self, mode: Mode) -> Any:
        req = mode_request(self.ap, VehicleKind.MULTIROTOR, mode)
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(self.ap, req))

    def setpoint(self, z_up: float = 0.0) -> None:
        self.conn.mav.set_position_target_local_ned_send(
            0,
            1,
            1,
            mavlink.MAV_FRAME_LOCAL_NED,
            0b110111111000,
            0,
            0,
            -z_up,
            0,
            0,
            0,
            0,
            0,
            0,
            0,
            0,
        )

    def stream(self, seconds: float, hz: float, z_up: float = 0.0, gcs: bool = True) -> None:
        """Setpoints at ``hz`` (vehicle time) for ``seconds`` (vehicle time), GCS heartbeats."""
        end = time.monotonic() + seconds / SPEED
        while time.monotonic() < end:
            self.setpoint(z_up)
            if gcs:
                self.heartbeat()
            time.sleep(1.0 / hz / SPEED)

    def heartbeat(self) -> None:
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def close(self) -> None:
        self.conn.close()


@contextmanager
def client(autopilot: Autopilot, **config: Any) -> Iterator[Client]:
    with mavsim(autopilot, **config) as sim:
        c = Client(sim)
        try:
            yield c
        finally:
            c.close()


@pytest.mark.slow
def test_heartbeats_say_the_firmware_and_streams_come_only_when_asked() -> None:
    with client(Autopilot.PX4) as c:
        hb = c.wait("HEARTBEAT")
        assert (hb.autopilot, hb.type) == (mavlink.MAV_AUTOPILOT_PX4, mavlink.MAV_TYPE_QUADROTOR)
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert c.wait("LOCAL_POSITION_NED", 0.5) is None  # not asked yet
        ack = c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 32, 1e5)  # 10 Hz
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        t0, n = time.monotonic(), 0
        while time.monotonic() - t0 < 1.0:
            n += c.wait("LOCAL_POSITION_NED", 0.5) is not None
        assert 10 * SPEED * 0.7 < n < 10 * SPEED * 1.3  # 10 Hz of vehicle time
        assert c.command(4242).result == mavlink.MAV_RESULT_UNSUPPORTED


def test_px4_refuses_offboard_below_2_hz_and_accepts_it_above() -> None:
    with client(Autopilot.PX4) as c:
        arm = c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)  # (disarmed, PX4 takes it)
        assert arm.result == mavlink.MAV_RESULT_ACCEPTED
        c.stream(2.0, hz=1.5)
        ack = c.set_mode(Mode.OFFBOARD)
        assert ack.result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        c.stream(1.2, hz=10)
        assert c.set_mode(Mode.OFFBOARD).result == mavlink.MAV_RESULT_ACCEPTED


@pytest.mark.slow
def test_px4_lands_when_the_ground_station_goes_silent() -> None:
    with client(Autopilot.PX4, datalink_loss_s=10.0) as c:  # NAV_DLL_ACT = land (default off)
        c.stream(1.2, hz=10)
        assert c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
        assert c.set_mode(Mode.OFFBOARD).result == 0
        c.stream(4.0, hz=10, z_up=2.0)
        c.stream(11.0, hz=10, z_up=2.0, gcs=False)  # setpoints, but no GCS heartbeat
        state = c.sim.vehicle_state("R1")
        assert state["mode"] is Mode.LAND and state["failsafe"] == "data link lost: landing"


@pytest.mark.slow
def test_ardupilot_velocity_targets_stop_after_3_s_and_gcs_loss_lands() -> None:
    with client(Autopilot.ARDUPILOT, gcs_failsafe_s=5.0) as c:  # FS_GCS_ENABLE = land
        c.heartbeat()
        assert c.set_mode(Mode.OFFBOARD).result == 0  # GUIDED, no stream needed
        assert c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
        assert c.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0).result == 0
        end = time.monotonic() + 4.0 / SPEED
        while time.monotonic() < end:
            c.heartbeat()
            time.sleep(0.02)
        c.conn.mav.set_position_target_local_ned_send(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0b110111000111, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0
        )  # 1 m/s north, once
        end = time.monotonic() + 4.0 / SPEED
        while time.monotonic() < end:
            c.heartbeat()
            time.sleep(0.02)
        assert c.sim.autopilots["R1"].guided.kind == "hold"  # the velocity target timed out
        time.sleep(6.0 / SPEED)  # no GCS heartbeat for > 5 s
        state = c.sim.vehicle_state("R1")
        assert state["mode"] is Mode.LAND and state["failsafe"] == "GCS failsafe: landing"


def test_a_landed_arducopter_climbs_on_nav_takeoff_and_targets_cancel_it() -> None:
    """As ArduCopter SITL does: GUIDED targets never lift a landed copter, and a target sent
    while a NAV_TAKEOFF is still spooling up cancels it (the copter stays on the ground)."""
    with client(Autopilot.ARDUPILOT) as c:
        c.heartbeat()
        assert c.set_mode(Mode.OFFBOARD).result == 0
        assert c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
        c.stream(2.0, hz=10, z_up=2.0)
        assert c.sim.vehicle_state("R1")["landed"]
        ack = c.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        c.stream(3.0, hz=10, z_up=2.0)  # targets at once: the take-off is cancelled
        assert c.sim.vehicle_state("R1")["landed"]
        ack = c.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        end = time.monotonic() + 5.0 / SPEED
        while time.monotonic() < end:  # nothing but heartbeats: it climbs
            c.heartbeat()
            time.sleep(0.02)
        state = c.sim.vehicle_state("R1")
        assert not state["landed"] and state["position"][2] > 1.0


def test_arming_during_the_ekf_delay_is_refused_with_a_statustext() -> None:
    with client(Autopilot.PX4, ekf_delay_s=30.0) as c:
        c.conn.mav.command_long_send(
            1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
        )
        text = c.wait("STATUSTEXT", 1.0)  # the reason comes first, then the ack
        assert text is not None and text.text == "Arming denied: Preflight: estimator not ready"
        ack = c.wait("COMMAND_ACK", 1.0)
        assert ack.result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED


# ------------------------------------------------------------------------------ the CLI
def test_the_cli_refuses_bad_input_with_exit_2(tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(cli, ["mavsim"])
    assert result.exit_code == 2 and "give either --mission FILE or --count N" in result.output
    result = runner.invoke(cli, ["mavsim", "--count", "1", "--speed", "nan"])
    assert result.exit_code == 2 and "--speed" in result.output
    missing = tmp_path / "none.key"
    result = runner.invoke(cli, ["mavsim", "--count", "1", "--signing-key-file", str(missing)])
    assert result.exit_code == 2
    assert f"{missing}: no such file (the MAVLink signing key)" in result.output
    sim_mission = ROOT / "missions" / "pick_and_deliver.yaml"
    result = runner.invoke(cli, ["mavsim", "--mission", str(sim_mission)])
    assert result.exit_code == 2
    assert "no agent has a mavlink+udp:// or mavlink+tcp:// backend to serve" in result.output


@pytest.mark.slow
def test_the_cli_serves_until_sigterm_and_says_what_it_did() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "btmission", "mavsim", "--count", "1", "--port", "26540"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert first.startswith("V1  mavlink+udp://127.0.0.1:26540  sysid 1  px4 multirotor")
        assert proc.stdout.readline().startswith("ready (1 vehicle(s), px4, speed 1x)")
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0
    assert "stopped after" in out and "Traceback" not in out


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_the_cli_serves_a_missions_agents_at_their_urls(autopilot: str, tmp_path: Path) -> None:
    shipped = ROOT / "missions" / f"mine_inspection_{autopilot}.yaml"
    mission = mission_on_free_ports(shipped, tmp_path)
    text = mission.read_text()
    result = CliRunner().invoke(cli, ["mavsim", "--mission", str(mission), "--duration", "0.2"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    for agent, line in zip(("R1", "R2", "R3"), lines, strict=False):
        url = line.split()[1]
        assert line.startswith(f"{agent}  {url}  sysid ") and f"'{url}'" in text
        assert line.endswith(f"{autopilot} multirotor")
    assert lines[3] == f"ready (3 vehicle(s), {autopilot}, speed 4x)"
