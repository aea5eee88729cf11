"""Shared pieces of the MAVLink tests: free loopback ports, an in-process mavsim, a provider."""

from __future__ import annotations

import re
import socket
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from btmission.backends.mavlink import MavlinkOptions, MavlinkProvider
from btmission.backends.mavlink_modes import Autopilot
from btmission.backends.mavlink_url import MavlinkAddress
from btmission.mavsim import MavSim, MavSimConfig, VehicleSpec
from btmission.vehicles.base import Ack, VehicleKind
from btmission.world.minegen import empty_world
from tests.load import margin

SPEED = 10.0

SIMS: list[MavSim] = []
"""The mavsim instances running now (the innermost last): tests wait on their clock."""
"""mavsim's speed-up in these tests (every rule is in simulated time, so they stay honest)."""


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    s = socket.socket(socket.AF_INET, kind)
    try:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
    finally:
        s.close()


def address(autopilot: Autopilot) -> MavlinkAddress:
    """A free loopback endpoint in the firmware's SITL style (PX4: UDP, ArduPilot: TCP)."""
    if autopilot is Autopilot.PX4:
        return MavlinkAddress("udp", "127.0.0.1", free_port(socket.SOCK_DGRAM))
    return MavlinkAddress("tcp", "127.0.0.1", free_port(socket.SOCK_STREAM))


def spec(
    autopilot: Autopilot,
    agent: str = "R1",
    start: tuple[float, float, float] = (5.0, 5.0, 0.0),
    kind: VehicleKind = VehicleKind.MULTIROTOR,
    sysid: int = 1,
) -> VehicleSpec:
    return VehicleSpec(agent, kind, start, address(autopilot), sysid)


@contextmanager
def mavsim(
    autopilot: Autopilot, *specs: VehicleSpec, speed: float = SPEED, **config: Any
) -> Iterator[MavSim]:
    """Simulated vehicles (default: one drone R1 at (5, 5, 0)) in a 30 x 30 x 8 m open world."""
    vehicles = specs or (spec(autopilot),)
    sim = MavSim(
        MavSimConfig(
            vehicles, empty_world((30, 30, 8), 0.5), autopilot=autopilot, speed=speed, **config
        )
    )
    sim.start()
    SIMS.append(sim)
    try:
        yield sim
    finally:
        SIMS.remove(sim)
        sim.stop()


@contextmanager
def provider(speed: float = SPEED, **options: Any) -> Iterator[MavlinkProvider]:
    made = MavlinkProvider(
        MavlinkOptions(
            time_scale=speed,
            connect_timeout_s=options.pop("connect_timeout_s", 5.0 * margin()),
            telemetry_hz=options.pop("telemetry_hz", 20.0),
            **options,
        )
    )
    try:
        yield made
    finally:
        made.close()


def mission_on_free_ports(shipped: Path, into: Path, time_scale: float | None = None) -> Path:
    """A copy of a shipped MAVLink mission in ``into`` whose agents' loopback ports are free
    ones (a SITL or another run may hold the shipped ports), at ``time_scale`` if given."""
    text = shipped.read_text()
    if time_scale is not None:
        text, n = re.subn(
            r"mavlink: \{time_scale: [0-9.]+\}", f"mavlink: {{time_scale: {time_scale:g}}}", text
        )
        assert n == 1, shipped
    for url in re.findall(r"mavlink\+(?:udp|tcp)://127\.0\.0\.1:\d+", text):
        kind = socket.SOCK_DGRAM if url.startswith("mavlink+udp") else socket.SOCK_STREAM
        text = text.replace(url, url.rsplit(":", 1)[0] + f":{free_port(kind)}")
    out = into / shipped.name
    out.write_text(text)
    return out


def answer(
    call: Callable[[], Ack],
    shown: Callable[[], bool] | None = None,
    every: Callable[[], object] | None = None,
    timeout_s: float = 5.0,
) -> Ack:
    """Call a MAVLink vehicle's command until its answer is in (its commands never wait: the
    first call sends and returns a pending Ack, later calls return the answer) and, when
    accepted, until ``shown()`` (its effect in the telemetry); ``every`` is called between the
    calls (setpoints to keep streaming). Wall time, up to ``timeout_s`` × the load margin."""
    end = time.monotonic() + timeout_s * margin()
    while True:
        if every is not None:
            every()
        ack = call()
        if not ack.pending and (not ack.accepted or shown is None or shown()):
            return ack
        if time.monotonic() > end:
            return ack
        time.sleep(0.05 / SPEED)
