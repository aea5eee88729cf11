"""mavsim answers only its own ground station, and steps on time under a flood (issue #36, item
5): a datagram from another address — garbage, unsigned, a command — neither diverts a UDP
vehicle's telemetry nor reaches its autopilot; only a ground station's valid (and, with
signing, correctly signed) HEARTBEAT moves it; a flood of incoming datagrams does not starve its
physics step or its telemetry."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from typing import Any

import pytest

from btmission.backends._pymavlink import mavlink
from btmission.backends.mavlink_modes import Autopilot
from btmission.spec.vehicleref import VehicleRef
from btmission.vehicles.base import VehicleKind
from tests.load import margin
from tests.mavlink_helpers import mavsim, provider
from tests.unit.tools.test_mavsim_gcs import KEY, px4

pytestmark = pytest.mark.serial  # paced by the wall clock

SPEED = 4.0
"""mavsim's speed-up in the flood test: a step every 5 ms of wall time leaves little to spare."""
GARBAGE = b"\x00\x01\x02\x03\x04"


def frame(kind: str, *fields: Any, sysid: int = 255, key: bytes | None = None) -> bytes:
    """One MAVLink 2 frame as a stranger would send it (signed with ``key`` if given)."""
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = int((time.time() - 1420070400) * 100000)
    msg = getattr(mav, f"{kind}_encode")(*fields)
    return bytes(msg.pack(mav))


GCS_HEARTBEAT = ("heartbeat", mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
ARM = ("command_long", 1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)


class Stranger:
    """A UDP socket on another port that writes to a vehicle and records what comes back."""

    def __init__(self, vehicle: tuple[str, int]) -> None:
        self.vehicle = vehicle
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)

    def send(self, data: bytes) -> None:
        self.sock.sendto(data, self.vehicle)

    def heard(self) -> int:
        n = 0
        while True:
            try:
                self.sock.recv(65535)
            except BlockingIOError:
                return n
            n += 1

    def close(self) -> None:
        self.sock.close()


def vehicle_address(sim: Any, agent: str) -> tuple[str, int]:
    return tuple(sim.autopilots[agent].conn.port.getsockname())  # type: ignore[return-value]


def test_a_stray_datagram_before_and_during_a_run_diverts_nothing() -> None:
    """The issue's case: one unsigned 5-byte datagram before the run connects used to make the
    vehicle send everything there, and the run never heard a heartbeat."""
    with mavsim(Autopilot.PX4) as sim, provider() as p:
        stranger = Stranger(vehicle_address(sim, "R1"))
        try:
            stranger.send(GARBAGE)  # before the run connects
            time.sleep(0.2)
            ep = sim.endpoints[0]
            v = p.attach("R1", VehicleKind.MULTIROTOR, (5.0, 5.0, 0.0), VehicleRef.parse(ep.url))
            st = v.backend.state  # type: ignore[attr-defined]
            beats = st.heartbeats
            for data in (GARBAGE, frame(*ARM), frame("heartbeat", 2, 12, 0, 0, 0)):
                stranger.send(data)  # during the run: garbage, a command, a vehicle's heartbeat
            end = time.monotonic() + 3.0 * margin()
            while st.heartbeats < beats + 3 and time.monotonic() < end:
                time.sleep(0.02)
            assert st.heartbeats >= beats + 3  # the run still hears its vehicle
            assert stranger.heard() == 0  # and the stranger hears nothing
            state = sim.vehicle_state("R1")
            assert not state["armed"] and state["strangers"] == 4
        finally:
            stranger.close()


def test_with_signing_only_a_signed_ground_station_heartbeat_moves_the_vehicle() -> None:
    with px4(key=KEY, signing_key=KEY) as (sim, [g]):
        stranger = Stranger(vehicle_address(sim, "V1"))
        try:
            for data in (GARBAGE, frame(*GCS_HEARTBEAT), frame(*ARM)):  # unsigned
                stranger.send(data)
            assert g.wait("HEARTBEAT", 2.0) is not None  # still ours
            assert stranger.heard() == 0 and not sim.vehicle_state("V1")["armed"]
            assert sim.counters()["V1"]["unsigned_refused"] >= 1
            stranger.send(frame(*GCS_HEARTBEAT, key=KEY))  # a ground station restarted there
            end = time.monotonic() + 2.0 * margin()
            heard = 0
            while heard == 0 and time.monotonic() < end:
                time.sleep(0.05)
                heard = stranger.heard()
            assert heard > 0
        finally:
            stranger.close()


FLOOD = """
import socket, sys, time
fd, host, port, seconds = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
data = bytes.fromhex(sys.argv[5])
s = socket.socket(fileno=fd) if fd >= 0 else socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setblocking(False)
end = time.monotonic() + seconds
n = 0
while time.monotonic() < end:
    for _ in range(100):
        try:
            s.sendto(data, (host, port))
            n += 1
        except BlockingIOError:
            pass
print(n)
"""


@pytest.mark.parametrize("sender", ["stranger", "ground station"])
def test_a_flood_of_datagrams_does_not_stop_the_vehicle_stepping(sender: str) -> None:
    """A process floods the vehicle's port with valid setpoint frames — from another address, or
    from its own ground station's — for 3 s; meanwhile the vehicle keeps stepping in real time
    and its position messages (asked at 20 Hz) keep their rate: it reads a bounded share of
    what arrives each step."""
    with px4(speed=SPEED) as (sim, [g]):
        assert g.interval(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20.0) == 0
        host, port = vehicle_address(sim, "V1")
        target = frame(
            "set_position_target_local_ned", 0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 3576,
            0.0, 0.0, 0.0, 0, 0, 0, 0, 0, 0, 0, 0,
        )  # fmt: skip
        fd = g.conn.port.fileno() if sender == "ground station" else -1
        flood = subprocess.Popen(
            [sys.executable, "-S", "-c", FLOOD, str(fd), host, str(port), "3.0", target.hex()],
            pass_fds=(fd,) if fd >= 0 else (),
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            time.sleep(0.5)  # the flood is on
            steps0, sim0, t0 = sim.steps, sim.simulator.time_s, time.monotonic()
            ap = sim.autopilots["V1"]
            read0 = ap.received + ap.strangers
            positions = sum(  # (sent since sim0: not what waited in our socket)
                m.get_type() == "LOCAL_POSITION_NED" and m.time_boot_ms >= 1000 * sim0
                for m in g.pump(2.0, g.heartbeat)
            )
            elapsed = time.monotonic() - t0
            steps, simulated = sim.steps - steps0, sim.simulator.time_s - sim0
            read = ap.received + ap.strangers - read0
        finally:
            sent = flood.communicate(timeout=30)[0]
        print(
            f"\n{sender} flood: {sent.strip()} datagrams sent, {read / elapsed:.0f}/s read; "
            "the vehicle made "
            f"{steps / elapsed:.0f} steps/s and sent {positions / simulated:.1f} positions per "
            f"simulated s ({simulated / elapsed:.2f} simulated s per s)"
        )
        assert int(sent) > 10_000  # a flood
        # (a vehicle that fell behind catches up: more than 50 steps a second for a while)
        assert steps / elapsed >= 0.8 * SPEED / sim.config.step_s / margin()  # 200/s asked
        assert positions / simulated >= 15.0  # 20 asked, in simulated time
        assert sim.vehicle_state("V1")["received"] > 0
