"""The MAVLink provider against the MAVLink vehicle simulator (in this process, on loopback).

Each test flies a mavsim vehicle through the provider's Backend and checks what a drone engineer
would: the refusals name the autopilot's result and reason, the offboard rules hold, ArduCopter
takes off on NAV_TAKEOFF, the link's health is seen, signing keeps strangers out."""

from __future__ import annotations

import re
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from btmission.backends.mavlink import MavlinkError, MavlinkProvider
from btmission.backends.mavlink_modes import Autopilot
from btmission.backends.mavlink_url import MavlinkAddress
from btmission.mavsim import MavSim
from btmission.spec.vehicleref import VehicleRef
from btmission.vehicles.base import Backend, Mode, VehicleKind
from tests.mavlink_helpers import SIMS, SPEED, answer, free_port, mavsim, provider, spec

# Timed against mavsim's clock (scaled real time): `make test` runs these alone, after the tests
# it spreads over the CPUs, so that no other test's load decides an arming or a link timeout.
pytestmark = pytest.mark.serial

PX4, ARDUPILOT = Autopilot.PX4, Autopilot.ARDUPILOT
START = (5.0, 5.0, 0.0)


def wait_for(
    p: MavlinkProvider,
    seconds: float,
    what: Callable[[], bool],
    every: Callable[[], object] | None = None,
) -> bool:
    """Let up to ``seconds`` of vehicle time pass until ``what()`` (calling ``every`` each
    0.05 s). Vehicle time is the simulator's own when one runs (a loaded machine slows it below
    its speed-up), else the provider's clock."""
    sim = SIMS[-1] if SIMS else None
    now = (lambda: sim.simulator.time_s) if sim is not None else p.clock.now
    end = now() + seconds
    wall_end = time.monotonic() + 10 * seconds / SPEED + 5.0
    while now() < end and time.monotonic() < wall_end:
        if every is not None:
            every()
        if what():
            return True
        time.sleep(0.05 / SPEED)
    return what()


def hold_here(b: Backend) -> Callable[[], None]:
    here = b.telemetry().position.copy()
    return lambda: b.set_position_setpoint(here)


def attach(
    p: MavlinkProvider, sim: MavSim, agent: str = "R1", kind: VehicleKind = VehicleKind.MULTIROTOR
) -> Backend:
    ep = next(e for e in sim.endpoints if e.agent_id == agent)
    start = sim.autopilots[agent].spec.start
    return p.attach(agent, kind, start, VehicleRef.parse(ep.url)).backend


# ------------------------------------------------------------------------------ connecting
def test_a_px4_vehicle_reports_where_it_stands() -> None:
    with mavsim(PX4) as sim, provider() as p:
        v = p.attach("R1", VehicleKind.MULTIROTOR, START, VehicleRef.parse(sim.endpoints[0].url))
        assert v.odometer_m is None and v.clearance_m is None and v.link_ok is not None
        assert wait_for(
            p, 1.0, lambda: v.backend.telemetry().ground_z == pytest.approx(0.0, abs=0.05)
        )
        tel = v.backend.telemetry()
        np.testing.assert_allclose(tel.position, START, atol=0.05)  # local NED origin = start
        assert tel.mode is Mode.MANUAL and not tel.armed and tel.landed
        assert tel.battery == pytest.approx(1.0, abs=0.02)
        assert v.link_ok()


def test_a_vehicle_of_the_wrong_type_is_refused() -> None:
    with mavsim(PX4) as sim, provider() as p:
        with pytest.raises(
            MavlinkError, match="MAV_TYPE_QUADROTOR, but the agent's library drives a ground robot"
        ):
            p.attach("G1", VehicleKind.GROUND, START, VehicleRef.parse(sim.endpoints[0].url))


def test_no_heartbeat_names_the_url_and_waits_only_as_long_as_asked() -> None:
    port = free_port()
    with provider(connect_timeout_s=0.5) as p:
        t0 = time.monotonic()
        with pytest.raises(
            MavlinkError,
            match=f"no heartbeat from an autopilot at mavlink\\+udp://127.0.0.1:{port} within 0.5 s",
        ):
            p.attach(
                "R1",
                VehicleKind.MULTIROTOR,
                START,
                VehicleRef.parse(f"mavlink+udp://127.0.0.1:{port}"),
            )
        assert time.monotonic() - t0 < 3.0


def test_a_udp_port_another_ground_station_holds_is_refused() -> None:
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as pymavlink binds
    holder.bind(("127.0.0.1", 0))
    port = holder.getsockname()[1]
    try:
        with provider(connect_timeout_s=0.5) as p:
            with pytest.raises(
                MavlinkError, match="another ground station or btmission run holds the port"
            ):
                p.attach(
                    "R1",
                    VehicleKind.MULTIROTOR,
                    START,
                    VehicleRef.parse(f"mavlink+udp://127.0.0.1:{port}"),
                )
    finally:
        holder.close()


# ------------------------------------------------------------------------------ PX4
def test_px4_offboard_rules_and_a_flight() -> None:
    with mavsim(PX4) as sim, provider() as p:
        b = attach(p, sim)
        offboard = lambda: b.telemetry().mode is Mode.OFFBOARD  # noqa: E731
        # disarmed, nothing streamed yet: PX4 v1.16 takes OFFBOARD, then refuses to arm
        assert answer(lambda: b.set_mode(Mode.OFFBOARD), offboard)
        ack = answer(b.arm)  # (sent again twice after TEMPORARILY_REJECTED, then refused)
        assert not ack and ack.reason.startswith(  # (STATUSTEXT holds 50 characters)
            "MAV_CMD_COMPONENT_ARM_DISARM: MAV_RESULT_TEMPORARILY_REJECTED "
            "(Arming denied: Resolve system health failures"
        )
        keep = hold_here(b)
        wait_for(p, 1.3, lambda: False, keep)
        assert answer(b.arm, every=keep) and b.telemetry().armed
        ack = answer(lambda: b.set_mode(Mode.OFFBOARD), offboard, keep)
        assert ack, ack.reason
        assert b.telemetry().mode is Mode.OFFBOARD
        goal = np.array([7.0, 5.0, 2.0])
        assert wait_for(p, 8.0, lambda: float(np.linalg.norm(b.telemetry().position - goal)) < 0.2,
                        lambda: b.set_position_setpoint(goal))  # fmt: skip
        assert not b.telemetry().landed and sim.vehicle_state("R1")["mode"] is Mode.OFFBOARD
        ack = b.disarm()
        assert not ack and "air" in ack.reason
        assert answer(b.land)  # (from 2 m: ON_GROUND after 7.5 s, disarmed 2 s later)
        assert wait_for(p, 15.0, lambda: b.telemetry().landed and not b.telemetry().armed)


@pytest.mark.slow  # the conformance suite covers it too (slow selection)
def test_px4_offboard_loss_holds_where_it_was() -> None:
    with mavsim(PX4) as sim, provider() as p:
        b = attach(p, sim)
        keep = hold_here(b)
        wait_for(p, 1.3, lambda: False, keep)
        assert answer(b.arm, every=keep)
        assert answer(lambda: b.set_mode(Mode.OFFBOARD), every=keep)
        goal = np.array([5.0, 5.0, 2.0])
        assert wait_for(p, 6.0, lambda: abs(b.telemetry().position[2] - 2.0) < 0.15,
                        lambda: b.set_position_setpoint(goal))  # fmt: skip
        # the mission stops renewing its setpoint: the provider stops streaming it after 1 s
        # (wall), the autopilot holds after COM_OF_LOSS_T
        assert wait_for(p, 2.0 + 1.5 * SPEED, lambda: b.telemetry().mode is Mode.HOLD)
        assert sim.vehicle_state("R1")["failsafe"].startswith("offboard setpoints lost")
        assert b.telemetry().position[2] == pytest.approx(2.0, abs=0.3)


# ------------------------------------------------------------------------------ ArduPilot
def test_ardupilot_guided_climbs_on_nav_takeoff_sent_by_the_provider() -> None:
    with mavsim(ARDUPILOT) as sim, provider() as p:
        b = attach(p, sim)
        assert answer(b.arm)
        ack = b.set_mode(Mode.OFFBOARD)  # GUIDED would take it: the backend keeps PX4's rule
        assert not ack and ack.reason.startswith("offboard refused: stream setpoints")
        keep = hold_here(b)
        wait_for(p, 1.3, lambda: False, keep)
        assert answer(
            lambda: b.set_mode(Mode.OFFBOARD), lambda: b.telemetry().mode is Mode.OFFBOARD, keep
        )
        assert sim.vehicle_state("R1")["mode"] is Mode.OFFBOARD  # GUIDED
        goal = np.array([5.0, 5.0, 2.5])
        assert wait_for(
            p, 8.0, lambda: abs(b.telemetry().position[2] - 2.5) < 0.15,
            lambda: b.set_position_setpoint(goal),
        )  # fmt: skip
        # the targets stop: ArduPilot keeps the last position target (GUIDED), seen as HOLD
        assert wait_for(p, 3.0, lambda: b.telemetry().mode is Mode.HOLD)
        assert sim.vehicle_state("R1")["mode"] is Mode.OFFBOARD
        wait_for(p, 3.0, lambda: False)  # (the climb overshoots a little, then settles)
        assert b.telemetry().position[2] == pytest.approx(2.5, abs=0.1)


def test_ardupilot_takeoff_shows_as_takeoff_then_hold() -> None:
    with mavsim(ARDUPILOT) as sim, provider() as p:
        b = attach(p, sim)
        ack = b.takeoff(2.0)
        assert not ack and ack.reason == "takeoff refused: not armed"
        assert answer(b.arm) and answer(lambda: b.takeoff(2.0))
        assert wait_for(p, 1.0, lambda: b.telemetry().mode is Mode.TAKEOFF)
        assert wait_for(p, 8.0, lambda: b.telemetry().mode is Mode.HOLD)
        assert b.telemetry().height_above_ground == pytest.approx(2.0, abs=0.2)


def test_an_arducopter_that_landed_in_land_is_armed_from_guided_and_flies_again() -> None:
    with mavsim(ARDUPILOT) as sim, provider() as p:
        b = attach(p, sim)
        assert answer(b.arm) and answer(lambda: b.takeoff(2.0))
        assert wait_for(p, 8.0, lambda: b.telemetry().mode is Mode.HOLD)
        assert answer(b.land, lambda: b.telemetry().mode is Mode.LAND)
        assert wait_for(p, 15.0, lambda: not b.telemetry().armed)  # landed, then disarmed
        assert sim.vehicle_state("R1")["mode"] is Mode.LAND  # ArduCopter stays in LAND
        assert wait_for(p, 1.0, lambda: b.telemetry().mode is Mode.LAND)
        ack = answer(b.arm)  # (LAND is not armable: the provider asks for GUIDED first)
        assert ack, ack.reason
        assert wait_for(p, 1.0, lambda: sim.vehicle_state("R1")["armed"])  # (mavsim's next step)
        assert sim.vehicle_state("R1")["mode"] is Mode.OFFBOARD  # GUIDED
        assert answer(lambda: b.takeoff(2.0))
        assert wait_for(p, 8.0, lambda: b.telemetry().height_above_ground > 1.8)


def test_arducopter_hold_is_brake_and_holds_its_altitude() -> None:
    with mavsim(ARDUPILOT) as sim, provider() as p:
        b = attach(p, sim)
        assert answer(b.arm) and answer(lambda: b.takeoff(3.0))
        assert wait_for(p, 8.0, lambda: b.telemetry().mode is Mode.HOLD)
        assert answer(lambda: b.set_mode(Mode.HOLD))
        assert sim.autopilots["R1"].custom_mode() == 17  # BRAKE, not LOITER
        wait_for(p, 10.0, lambda: False)
        assert b.telemetry().mode is Mode.HOLD
        assert b.telemetry().height_above_ground == pytest.approx(3.0, abs=0.2)


def test_arming_waits_for_the_ekf_with_the_autopilots_reason_and_a_back_off() -> None:
    with mavsim(ARDUPILOT, ekf_delay_s=20.0) as sim, provider(connect_timeout_s=1.0) as p:
        # a local position already (an EKF origin), its estimator not yet ready to arm (mavsim
        # sends no LOCAL_POSITION_NED before the estimator is ready, as the firmwares do)
        sim.autopilots["R1"].position_known = lambda: True  # type: ignore[method-assign]
        b = attach(p, sim)  # waits for the EKF as long as it may (1 s, 10 s at 10x), then goes on
        ack = answer(b.arm)
        assert not ack
        assert ack.reason == (
            "MAV_CMD_COMPONENT_ARM_DISARM: MAV_RESULT_FAILED (PreArm: EKF3 waiting for GPS config data)"
        )
        sent = b.commands_sent  # type: ignore[attr-defined]
        assert b.arm() == ack and b.commands_sent == sent  # type: ignore[attr-defined]  # backing off
        assert wait_for(p, 12.0, lambda: bool(b.arm()))
        assert b.telemetry().armed or wait_for(p, 1.5, lambda: b.telemetry().armed)


@pytest.mark.parametrize("autopilot", [PX4, ARDUPILOT], ids=lambda a: a.value)
def test_attaching_waits_for_a_usable_estimate(autopilot: Autopilot) -> None:
    with mavsim(autopilot, ekf_delay_s=10.0) as sim, provider() as p:
        b = attach(p, sim)
        assert b.estimator_ready()  # type: ignore[attr-defined]
        assert sim.simulator.time_s >= 10.0
        assert answer(b.arm)  # at once: nothing left to refuse


def test_a_failing_pre_arm_check_is_reported_by_px4() -> None:
    with mavsim(PX4, refuse_arm="Accel #0 inconsistent") as sim, provider() as p:
        b = attach(p, sim)
        ack = answer(b.arm)
        assert ack.reason == (
            "MAV_CMD_COMPONENT_ARM_DISARM: MAV_RESULT_DENIED (Preflight Fail: Accel #0 inconsistent)"
        )
        assert ack.transient  # a pre-arm check may pass later: the run retries it
        assert not sim.vehicle_state("R1")["armed"]


# ------------------------------------------------------------------------------ link health
def test_a_dropped_link_is_seen_and_streaming_resumes() -> None:
    # (the timeout is wall time: 0.2 s is 2 s of these vehicles', whose heartbeats come each 0.1 s)
    with mavsim(PX4) as sim, provider(heartbeat_timeout_s=0.2) as p:
        v = p.attach("R1", VehicleKind.MULTIROTOR, START, VehicleRef.parse(sim.endpoints[0].url))
        link_ok = v.link_ok
        assert link_ok is not None and link_ok()
        sim.drop_link("R1", 6.0)
        keep = hold_here(v.backend)
        assert wait_for(p, 4.0, lambda: not link_ok(), keep)
        heard = sim.vehicle_state("R1")["received"]
        assert wait_for(p, 6.0, link_ok, keep)
        assert wait_for(p, 1.0, lambda: sim.vehicle_state("R1")["received"] > heard + 3, keep)


# ------------------------------------------------------------------------------ signing
KEY = bytes(range(32))


def test_signed_links_fly_and_a_wrong_key_is_refused_and_counted() -> None:
    with mavsim(PX4, signing_key=KEY) as sim:
        with provider(signing_key=KEY) as p:
            b = attach(p, sim)
            assert answer(b.arm)
            assert p.rejected() == {}
        with provider(signing_key=bytes(32), connect_timeout_s=1.0, ack_timeout_s=0.3) as p:
            with pytest.raises(MavlinkError, match="its messages are signed with another key"):
                attach(p, sim)  # (at the 1 s deadline: not "no heartbeat")
            assert p.rejected().get("bad_signature", 0) > 0
            said: list[str] = []
            p._progress = said.append  # type: ignore[assignment]
        assert said and said[-1].startswith("MAVLink messages refused: bad signature ")
        with provider(connect_timeout_s=1.0, ack_timeout_s=0.3) as p:  # unsigned: dropped
            with pytest.raises(
                MavlinkError,
                match="is heard but does not answer commands \\(if it requires MAVLink 2 signing",
            ):
                attach(p, sim)
        counts = sim.counters()["R1"]
        assert counts["bad_signature"] + counts["unsigned_refused"] > 0


@pytest.mark.parametrize("vehicle_key", [bytes(32), None], ids=["another-key", "unsigned"])
def test_a_wrong_signing_key_is_named_within_seconds(vehicle_key: bytes | None) -> None:
    # the connect timeout is far longer than the few seconds the verdict takes: waiting it out
    # ended in "no heartbeat ... (is the vehicle on ...?)"
    with (
        mavsim(ARDUPILOT, signing_key=vehicle_key) as sim,
        provider(signing_key=KEY, connect_timeout_s=30.0) as p,
    ):
        url = sim.endpoints[0].url
        with pytest.raises(MavlinkError) as caught:
            attach(p, sim)
    said = str(caught.value)
    assert said.startswith(f"R1 ({url}): its messages are ")
    if vehicle_key is None:
        assert re.search(r"are not signed \(\d+ refused in \d+ s\), and a signing key is "
                         r"given \(--mavlink-key-file\)", said)  # fmt: skip
    else:
        assert re.search(r"are signed with another key \(\d+ rejected in \d+ s\); "
                         r"check --mavlink-key-file / the vehicle's key", said)  # fmt: skip
    # "in N s": the verdict, seconds in (at the deadline it would say "within 30 s")


@pytest.mark.slow  # the conformance suite covers it too (slow selection)
def test_two_vehicles_on_two_links_fly_independently() -> None:
    a = spec(PX4, "R1", (5.0, 5.0, 0.0))
    b_ = spec(PX4, "R2", (9.0, 5.0, 0.0), sysid=2)
    with mavsim(PX4, a, b_) as sim, provider() as p:
        r1, r2 = attach(p, sim, "R1"), attach(p, sim, "R2")
        np.testing.assert_allclose(r2.telemetry().position, (9.0, 5.0, 0.0), atol=0.05)
        hold1, hold2 = hold_here(r1), hold_here(r2)

        def both() -> None:
            hold1()
            hold2()

        wait_for(p, 1.3, lambda: False, both)
        assert answer(r1.arm, every=both)
        assert answer(lambda: r1.set_mode(Mode.OFFBOARD), every=both)
        goal = np.array([5.0, 5.0, 1.5])

        def climb() -> None:
            r1.set_position_setpoint(goal)
            hold2()

        wait_for(p, 5.0, lambda: abs(r1.telemetry().position[2] - 1.5) < 0.15, climb)
        assert r1.telemetry().position[2] == pytest.approx(1.5, abs=0.15)
        assert r2.telemetry().landed and not r2.telemetry().armed


def test_the_sysid_in_the_url_picks_the_vehicle_behind_a_shared_port() -> None:
    port = free_port()
    shared = MavlinkAddress("udp", "127.0.0.1", port)
    from btmission.mavsim import VehicleSpec

    specs = (
        VehicleSpec("A", VehicleKind.MULTIROTOR, (5.0, 5.0, 0.0), shared, 7),
        VehicleSpec("B", VehicleKind.MULTIROTOR, (12.0, 5.0, 0.0), shared, 9),
    )
    with mavsim(PX4, *specs), provider() as p:
        v9 = p.attach(
            "B",
            VehicleKind.MULTIROTOR,
            (12.0, 5.0, 0.0),
            VehicleRef.parse(f"mavlink+udp://127.0.0.1:{port}?sysid=9"),
        )
        v7 = p.attach(
            "A",
            VehicleKind.MULTIROTOR,
            (5.0, 5.0, 0.0),
            VehicleRef.parse(f"mavlink+udp://127.0.0.1:{port}?sysid=7"),
        )
        assert v9.backend.state.sysid == 9 and v7.backend.state.sysid == 7  # type: ignore[attr-defined]
        with pytest.raises(MavlinkError, match=r"sysid 7 .* is already another agent's vehicle"):
            p.attach(
                "C",
                VehicleKind.MULTIROTOR,
                (5.0, 5.0, 0.0),
                VehicleRef.parse(f"mavlink+udp://127.0.0.1:{port}?sysid=7"),
            )


# ------------------------------------------------------------------------------ from a mission
def factory_provider(tmp_path: Path, url: str, extra_world: str = "", mavlink: str = "") -> Any:
    """The ``mavlink`` provider as ``run`` builds it, for a one-drone mission at ``url``."""
    from btmission.missions import load_mission_text
    from btmission.vehicles.provider import provider_factory
    from btmission.world.build import world_from_spec

    text = (
        "mission: m\nversion: 1\n"
        f"world: {{map: {{generate: empty, size: [30, 30, 8]}}, resolution: 0.5{extra_world}}}\n"
        f"agents:\n  - {{id: R1, library: aerial, start: [5, 5, 0], backend: '{url}'}}\n"
        "tasks: []\ntask_types: {}\n"
        f"runtime: {{mavlink: {{time_scale: {SPEED}, connect_timeout_s: 5{mavlink}}}}}\n"
    )
    mission = load_mission_text(text, str(tmp_path / "m.yaml"))
    return provider_factory("mavlink")(mission, world_from_spec(mission.spec.world, tmp_path), 0)


def test_map_sensors_look_from_the_reported_pose(tmp_path: Path) -> None:
    from btmission.backends.mapsensors import MapSensors

    with mavsim(PX4) as sim:
        p = factory_provider(tmp_path, sim.endpoints[0].url, mavlink=", map_sensors: true")
        try:
            v = p.attach(
                "R1", VehicleKind.MULTIROTOR, START, VehicleRef.parse(sim.endpoints[0].url)
            )
            assert isinstance(v.sensors, MapSensors)
            frame = v.sensors.camera()
            np.testing.assert_allclose(
                frame.translation, v.backend.telemetry().position + np.array([0, 0, 0.1]), atol=0.05
            )
        finally:
            p.close()
        p = factory_provider(tmp_path, sim.endpoints[0].url)  # default: none
        try:
            assert (
                p.attach(
                    "R1", VehicleKind.MULTIROTOR, START, VehicleRef.parse(sim.endpoints[0].url)
                ).sensors
                is None
            )
        finally:
            p.close()


def test_a_vehicle_without_a_global_origin_gets_the_worlds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from btmission.backends.mavlink_frames import GeodeticOrigin, world_to_geodetic

    with mavsim(PX4) as sim:
        p = factory_provider(
            tmp_path,
            sim.endpoints[0].url,
            extra_world=", origin: {lat: -35.36, lon: 149.16, alt: 584}",
        )
        try:
            v = p.attach(
                "R1", VehicleKind.MULTIROTOR, START, VehicleRef.parse(sim.endpoints[0].url)
            )
            lat, lon, alt = world_to_geodetic(START, GeodeticOrigin(-35.36, 149.16, 584.0))
            got = v.backend.state.global_origin  # type: ignore[attr-defined]
            assert got == pytest.approx((lat, lon, alt), abs=1e-6)
            assert got[0] != -35.36  # the drone's own origin, 5 m from the world's
        finally:
            p.close()
    assert (
        f"R1: global origin set to {lat:.7f}, {lon:.7f}, {alt:.1f} m (confirmed)"
        in capsys.readouterr().err
    )


def test_a_tcp_vehicle_that_restarts_is_reconnected_without_spinning() -> None:
    first = spec(ARDUPILOT)
    with provider(heartbeat_timeout_s=0.2) as p:  # (wall time)
        with mavsim(ARDUPILOT, first) as sim:
            v = p.attach(
                "R1", VehicleKind.MULTIROTOR, START, VehicleRef.parse(sim.endpoints[0].url)
            )
        link = v.backend.link  # type: ignore[attr-defined]
        deadline = time.monotonic() + 3.0
        while not link.down and time.monotonic() < deadline:
            time.sleep(0.05)
        assert link.down  # the peer closed it: no busy loop on the dead socket
        cpu0 = time.process_time()
        time.sleep(0.5)
        assert time.process_time() - cpu0 < 0.25  # idle, not spinning
        assert v.link_ok is not None and not v.link_ok()
        with mavsim(ARDUPILOT, first) as sim:  # the vehicle comes back on the same port
            end = time.monotonic() + 5.0
            while not v.link_ok() and time.monotonic() < end:
                time.sleep(0.05)
            assert v.link_ok() and not link.down
