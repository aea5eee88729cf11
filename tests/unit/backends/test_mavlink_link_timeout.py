"""The MAVLink provider's clocks (issue #36 item 3): a vehicle's link is lost after
``heartbeat_timeout_s`` of wall time whatever ``time_scale`` (at ×4, a 0.75 s pause of a busy
machine was 3 s of the vehicles' time and flapped the link: 45 ``vehicle_link`` events in one
run), and what the vehicles told while they connected is stamped at the mission's start.

The wall clock here is the test's (``time.monotonic`` replaced for the test's duration: the
run's clock, the link's stamps and the timeout all read it), so nothing sleeps."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from btmission.backends._pymavlink import mavlink
from btmission.backends.mavlink import MavlinkProvider
from btmission.backends.mavlink_frames import LocalFrame
from btmission.backends.mavlink_link import MavlinkOptions, _Link
from btmission.backends.mavlink_url import MavlinkAddress
from btmission.backends.mavlink_vehicle import MavlinkVehicle
from btmission.vehicles.base import VehicleKind
from tests.wallclock import WallClock

SCALE = 4.0
"""The vehicles run four times faster than real time (a simulator's speed-up)."""


@pytest.fixture
def provider(wall: WallClock) -> Iterator[MavlinkProvider]:
    p = MavlinkProvider(MavlinkOptions(time_scale=SCALE, heartbeat_timeout_s=3.0))
    yield p
    p.close()


def _packed(msg: Any) -> Any:
    msg.pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))  # (sets its source)
    return msg


def heartbeat() -> Any:
    return _packed(
        mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR,
            mavlink.MAV_AUTOPILOT_PX4,
            0,
            0,
            mavlink.MAV_STATE_STANDBY,
            3,
        )
    )


def position() -> Any:
    return _packed(mavlink.MAVLink_local_position_ned_message(0, 1.0, 2.0, -3.0, 0.0, 0.0, 0.0))


def connected(p: MavlinkProvider) -> tuple[MavlinkVehicle, _Link]:
    """R1 heard on a link (what ``attach`` leaves): its heartbeat filed by the I/O thread's code."""
    link = _Link(MavlinkAddress("udp", "127.0.0.1", 14540), conn=None)
    p._io._file(link, heartbeat())
    vehicle = MavlinkVehicle(
        "R1",
        VehicleKind.MULTIROTOR,
        link,
        link.vehicles[1],
        LocalFrame((0.0, 0.0, 0.0)),
        p.clock,
        p.options,
    )
    p.vehicles["R1"] = vehicle
    return vehicle, link


def test_a_wall_pause_shorter_than_the_timeout_keeps_the_link_whatever_time_scale(
    provider: MavlinkProvider, wall: WallClock
) -> None:
    vehicle, link = connected(provider)
    wall.read_on(link)  # (the I/O thread reads the link to its end all along)
    provider.start()
    for _ in range(8):  # heartbeats at 1 Hz of the vehicle's time: every 0.25 s of wall time
        wall.t += 0.25
        provider._io._file(link, heartbeat())
        assert vehicle.link_ok()
    wall.t += 0.9  # a 0.75 s pause, and the heartbeat that was due: 3.6 s of the vehicle's time
    assert provider.clock.now() - link.vehicles[1].heartbeat_at == pytest.approx(3.6)
    assert vehicle.link_ok()  # (in the vehicle's time, 3.6 s > 3 s: the link flapped)
    provider._io._file(link, heartbeat())
    wall.t += 2.9
    assert vehicle.link_ok()
    wall.t += 0.2  # 3.1 s of wall time without a heartbeat: lost
    assert not vehicle.link_ok()
    provider._io._file(link, heartbeat())
    assert vehicle.link_ok()


def test_btmission_stopped_itself_is_no_lost_link(
    provider: MavlinkProvider, wall: WallClock
) -> None:
    """btmission stopped 8 s (``kill -STOP``, or a machine too busy to run it): the vehicle's
    heartbeats of those 8 s wait in the socket. Until the I/O thread has read them the silence
    is unknown, not a loss: before, the first step after the stall logged a loss and the next
    one, 0.025 s later, its recovery."""
    vehicle, link = connected(provider)
    provider.start()
    link.read_wall = wall.t
    wall.t += 8.0  # stopped: nothing was read
    assert vehicle.link_ok()
    provider._io._file(link, heartbeat())  # the backlog read: heartbeats came all along
    link.read_wall = wall.t
    assert vehicle.link_ok()
    wall.t += 3.1  # read to its end since, and nothing came: a vehicle that went silent
    link.read_wall = wall.t
    assert not vehicle.link_ok()
    link.down = True  # a closed TCP link is silent up to now, read or not
    link.read_wall = -1.0
    assert not vehicle.link_ok()


def test_what_came_while_connecting_is_stamped_at_the_start(
    provider: MavlinkProvider, wall: WallClock
) -> None:
    """Connecting took 100 s of wall time (400 s of the vehicles'): the telemetry it heard is
    the start's (t = 0), not 400 s, a time the mission's clock never shows."""
    vehicle, link = connected(provider)
    wall.t += 100.0
    provider._io._file(link, position())
    assert vehicle.telemetry().time_s == pytest.approx(400.0)  # the connecting clock's
    provider.start()
    assert provider.clock.now() == 0.0
    assert vehicle.telemetry().time_s == 0.0
    assert link.vehicles[1].heartbeat_at == 0.0
    wall.t += 0.5
    provider._io._file(link, position())
    assert vehicle.telemetry().time_s == pytest.approx(2.0)  # the mission's time from then on


def position_at(boot_s: float) -> Any:
    return _packed(
        mavlink.MAVLink_local_position_ned_message(
            int(boot_s * 1000), 1.0, 2.0, -3.0, 0.0, 0.0, 0.0
        )
    )


def test_a_vehicle_that_stood_still_while_its_link_was_down_is_told_apart(
    provider: MavlinkProvider, wall: WallClock
) -> None:
    """A SITL stopped 8 s of wall time (``kill -STOP``): its clock stopped too (lockstep) while
    the mission's ran on 32 s (×4). Heard again, its clock says so, and the run warns that its
    times include it; a vehicle whose link was lost but which flew on gets no such warning."""
    _, link = connected(provider)
    wall.read_on(link)
    provider.start()

    def heard(boot_s: float) -> None:
        provider._io._file(link, heartbeat())
        provider._io._file(link, position_at(boot_s))

    heard(100.0)
    assert provider.step(0.02) == []
    wall.t += 8.0  # stopped: nothing came, the I/O thread read on
    assert provider.step(0.02) == []  # (the loss: the agent logs it)
    heard(100.1)  # its clock went on 0.1 s in 8 s of wall time (32 s of the mission's)
    (event,) = provider.step(0.02)
    assert event.kind == "warning" and event.vehicle == "R1"
    assert event.message == (
        "R1: its autopilot's clock stood still for 31.9 s of the 32.0 s its link was down (a "
        "stopped or paused vehicle: a frozen SITL, a debugger); the mission's clock ran on, so "
        "this run's times include 31.9 s of it standing still"
    )
    assert provider.step(0.02) == []  # said once
    wall.t += 8.0  # lost again, and this time it flew on: its clock went on 32 s
    assert provider.step(0.02) == []
    heard(100.1 + 32.0)
    assert provider.step(0.02) == []
    wall.t += 5.0
    provider.step(0.02)
    heard(3.0)  # back with its clock at 3 s: it restarted
    (event,) = provider.step(0.02)
    assert "clock went back from 132.1 s to 3.0 s" in event.message
