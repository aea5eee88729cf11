"""A fleet connects concurrently (issue #36, item 2): against mavsim on loopback.

What a ground-station engineer checks when ten drones are powered up at once: every drone is
asked for its telemetry as soon as it is heard, not after the one before it is ready; a drone that
never answers is named with what it lacked while the others connect; a drone switched on after
the ground station is waited for. No timing is asserted: the overlap is seen in the order of what
happened (every first request before any vehicle was connected)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from btmission.backends._pymavlink import CURRENT_MODE_ID, mavlink
from btmission.backends.mavlink import MavlinkError, MavlinkProvider
from btmission.backends.mavlink_connect import NOTE_AFTER_S
from btmission.backends.mavlink_modes import Autopilot
from btmission.mavsim import (
    SITL_EKF_DELAY_S,
    MavSim,
    MavSimConfig,
    VehicleSpec,
    _SimulatedAutopilot,
    mission_vehicles,
)
from btmission.spec.vehicleref import VehicleRef
from btmission.vehicles.base import Mode, VehicleKind
from btmission.vehicles.provider import AttachRequest
from btmission.world.minegen import empty_world
from tests.load import margin
from tests.mavlink_helpers import (
    SPEED,
    address,
    answer,
    free_port,
    mavsim,
    mission_on_free_ports,
    provider,
)

# Paced by the wall clock (mavsim's scaled real time, the connect's deadline): run alone.
pytestmark = pytest.mark.serial

ROOT = Path(__file__).resolve().parents[3]
PX4, ARDUPILOT = Autopilot.PX4, Autopilot.ARDUPILOT


def fleet(autopilot: Autopilot, n: int) -> tuple[VehicleSpec, ...]:
    """``n`` drones 3 m apart, each on its own link (PX4: UDP, ArduPilot: TCP), sysid i + 1."""
    return tuple(
        VehicleSpec(
            f"R{i + 1}",
            VehicleKind.MULTIROTOR,
            (2.0 + 3.0 * i, 5.0, 0.0),
            address(autopilot),
            i + 1,
        )
        for i in range(n)
    )


def requests(sim: MavSim) -> list[AttachRequest]:
    return [
        AttachRequest(ap.spec.agent_id, ap.spec.kind, ap.spec.start, VehicleRef.parse(ap.url))
        for ap in sim.autopilots.values()
    ]


@pytest.mark.parametrize("autopilot", [PX4, ARDUPILOT], ids=lambda a: a.value)
def test_ten_vehicles_connect_concurrently(autopilot: Autopilot) -> None:
    # Their estimators need a few (simulated) seconds, so none can be connected before every
    # one has been heard; one after the other, the second would be asked only once the first
    # was connected.
    specs = fleet(autopilot, 10)
    said: list[str] = []
    with (
        mavsim(autopilot, *specs, ekf_delay_s=5.0 * margin()) as sim,
        provider(connect_timeout_s=30.0 * margin()) as p,
    ):
        p._progress = said.append
        reqs = requests(sim)
        p.prepare([r.ref for r in reqs])
        vehicles = p.attach_all(reqs)
        assert [v.id for v in vehicles] == [s.agent_id for s in specs]
        for v, s in zip(vehicles, specs, strict=True):
            assert v.backend.state.sysid == s.sysid  # type: ignore[attr-defined]
            assert v.backend.estimator_ready()  # type: ignore[attr-defined]
            np.testing.assert_allclose(v.backend.telemetry().position, s.start, atol=0.05)
        times = p.connect_times
        assert set(times) == {s.agent_id for s in specs}
        assert max(t.requested_s for t in times.values()) < min(
            t.connected_s for t in times.values()
        )  # every vehicle asked before any was connected
        assert all(t.heard_s <= t.requested_s <= t.connected_s for t in times.values())
    connected = [line for line in said if " sysid " in line and "MAV_TYPE_QUADROTOR" in line]
    assert len(connected) == 10  # each says so once: "R3: px4 sysid 3 (MAV_TYPE_QUADROTOR) at ..."


def test_a_vehicle_that_never_answers_is_named_with_what_it_lacked() -> None:
    specs = fleet(PX4, 3)
    silent = free_port()
    said: list[str] = []
    with mavsim(PX4, *specs) as sim, provider(connect_timeout_s=3.0 * margin()) as p:
        p._progress = said.append
        reqs = [
            *requests(sim),
            AttachRequest(
                "R4", VehicleKind.MULTIROTOR, (11.0, 5.0, 0.0),
                VehicleRef.parse(f"mavlink+udp://127.0.0.1:{silent}"),
            ),
        ]  # fmt: skip
        with pytest.raises(MavlinkError) as info:
            p.attach_all(reqs)
        assert set(p.connect_times) == {"R1", "R2", "R3"}  # the others connected meanwhile
    assert list(info.value.failures) == ["R4"]
    assert info.value.failures["R4"].startswith(
        f"R4: no heartbeat from an autopilot at mavlink+udp://127.0.0.1:{silent} within "
    )
    assert str(info.value) == info.value.failures["R4"]
    assert said[-1].startswith("connecting: 3 of 4 vehicle(s) connected after ")
    assert said[-1].endswith("; waiting: R4 for a heartbeat")


def test_every_vehicle_that_did_not_connect_is_named() -> None:
    specs = fleet(PX4, 2)
    ports = [free_port(), free_port()]
    with mavsim(PX4, *specs) as sim, provider(connect_timeout_s=1.0 * margin()) as p:
        reqs = [
            *requests(sim),
            *(
                AttachRequest(
                    f"S{i + 1}", VehicleKind.MULTIROTOR, (11.0 + i, 5.0, 0.0),
                    VehicleRef.parse(f"mavlink+udp://127.0.0.1:{port}?sysid=9"),
                )
                for i, port in enumerate(ports)
            ),
        ]  # fmt: skip
        with pytest.raises(MavlinkError) as info:
            p.attach_all(reqs)
    assert list(info.value.failures) == ["S1", "S2"]
    lines = str(info.value).splitlines()
    assert lines[0] == "2 of 4 vehicles could not be connected:"
    assert lines[1].startswith(
        f"S1: no heartbeat from sysid 9 at mavlink+udp://127.0.0.1:{ports[0]}"
    )
    assert lines[2].startswith(
        f"S2: no heartbeat from sysid 9 at mavlink+udp://127.0.0.1:{ports[1]}"
    )


def test_a_vehicle_of_the_wrong_type_stops_the_connect_at_once() -> None:
    specs = fleet(PX4, 2)
    with mavsim(PX4, *specs) as sim, provider(connect_timeout_s=60.0) as p:
        reqs = requests(sim)
        reqs[1] = AttachRequest("R2", VehicleKind.GROUND, specs[1].start, reqs[1].ref)
        with pytest.raises(MavlinkError) as info:
            p.attach_all(reqs)  # not after the 60 s: a drone will not become a rover
    assert list(info.value.failures) == ["R2"]
    assert "is a MAV_TYPE_QUADROTOR, but the agent's library drives a ground robot" in str(
        info.value
    )


@pytest.mark.parametrize("lose", [False, True], ids=["all answered", "one lost"])
def test_answers_sent_together_are_told_apart(monkeypatch: pytest.MonkeyPatch, lose: bool) -> None:
    # Like PX4, the vehicles refuse a faster HEARTBEAT; unlike PX4 v1.16, they have no
    # CURRENT_MODE either. All eight stream requests go out at once and their answers are told
    # apart by their order: the refusals are the HEARTBEAT's and CURRENT_MODE's (one note says
    # how modes are seen) and each stream was asked once. When each vehicle loses the first
    # request for its ATTITUDE stream, seven answers come back and which one was lost is
    # unknown: the eight are asked again one at a time, the refusals are still those two, and
    # ATTITUDE streams.
    heard: dict[tuple[int, int], int] = {}
    real = _SimulatedAutopilot._command

    def command(self: _SimulatedAutopilot, msg: Any) -> int | None:
        if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            key = (self.spec.sysid, int(msg.param1))
            heard[key] = heard.get(key, 0) + 1
            if key[1] in (mavlink.MAVLINK_MSG_ID_HEARTBEAT, CURRENT_MODE_ID):
                return mavlink.MAV_RESULT_DENIED
            if lose and key[1] == mavlink.MAVLINK_MSG_ID_ATTITUDE and heard[key] == 1:
                return None  # lost: no answer
        return real(self, msg)

    monkeypatch.setattr(_SimulatedAutopilot, "_command", command)
    monkeypatch.setattr(_SimulatedAutopilot, "_handle", _answer_unless_none)
    specs = fleet(PX4, 3)
    said: list[str] = []
    with mavsim(PX4, *specs) as sim, provider(ack_timeout_s=0.2 * margin()) as p:
        p._progress = said.append
        p.attach_all(requests(sim))
        for ap in sim.autopilots.values():  # every stream runs
            assert set(ap.intervals) >= {
                mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                mavlink.MAVLINK_MSG_ID_ATTITUDE,
                mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS,
            }
    refused = sorted(line for line in said if "available" in line)
    assert refused == [
        f"R{i}: modes are seen at the autopilot's own HEARTBEAT rate (neither a faster HEARTBEAT "
        "nor CURRENT_MODE is available)"
        for i in (1, 2, 3)
    ]
    sends = 2 if lose else 1
    for s in specs:
        assert heard[(s.sysid, mavlink.MAVLINK_MSG_ID_ATTITUDE)] == sends
        assert heard[(s.sysid, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED)] == sends


def _answer_unless_none(self: _SimulatedAutopilot, msg: Any) -> None:
    """mavsim's COMMAND_LONG handling, but a command whose result is None is not answered."""
    if msg.get_type() != "COMMAND_LONG" or not self._for_me(msg):
        _REAL_HANDLE(self, msg)
        return
    result = self._command(msg)
    if result is None:
        return
    src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
    self.send(lambda mav: mav.command_ack_send(msg.command, result, 0, 0, src_sys, src_comp))


_REAL_HANDLE = _SimulatedAutopilot._handle


@pytest.mark.parametrize("autopilot", [PX4, ARDUPILOT], ids=lambda a: a.value)
def test_vehicles_switched_on_after_the_ground_station_are_waited_for(
    autopilot: Autopilot,
) -> None:
    # PX4: the run listens and the vehicles send once they run; ArduPilot: the run's TCP
    # connects are refused until the vehicles listen, and are tried again meanwhile. The
    # vehicles come after the connect has said who waits for what.
    specs = fleet(autopilot, 2)
    said: list[str] = []
    started: list[MavSim] = []

    def switch_on() -> None:
        world = empty_world((30, 30, 8), 0.5)
        started.append(MavSim(MavSimConfig(specs, world, autopilot=autopilot, speed=SPEED)).start())

    reqs = [
        AttachRequest(s.agent_id, s.kind, s.start, VehicleRef.parse(s.address.url())) for s in specs
    ]
    later = threading.Timer(NOTE_AFTER_S + 0.5 * margin(), switch_on)
    try:
        with provider(connect_timeout_s=20.0 * margin()) as p:
            p._progress = said.append
            p.prepare([r.ref for r in reqs])
            later.start()
            vehicles = p.attach_all(reqs)
            assert started  # connected to the vehicles that came
            for v, s in zip(vehicles, specs, strict=True):
                np.testing.assert_allclose(v.backend.telemetry().position, s.start, atol=0.05)
                assert v.link_ok is not None and v.link_ok()
    finally:
        later.cancel()
        later.join()
        for sim in started:
            sim.stop()
    waited = [line for line in said if line.startswith("connecting: 0 of 2 vehicle(s) connected")]
    assert waited, said
    if autopilot is PX4:  # heard nothing yet
        assert waited[0].endswith("; waiting: R1, R2 for a heartbeat")
    else:  # its TCP connects refused
        assert waited[0].endswith("; waiting: R1, R2 for its link (Connection refused)")


@pytest.fixture(autouse=True)
def _no_leftover_threads() -> Iterator[None]:
    """A connect ends the helper threads it started (a link that never opened stops trying)."""
    yield
    opening = [t for t in threading.enumerate() if t.name.startswith("mavlink-open")]
    for t in opening:
        t.join(timeout=2.0 * margin())
    assert not [t.name for t in opening if t.is_alive()]


def test_an_unused_provider_closes_the_links_it_was_opening() -> None:
    port = free_port()
    p = MavlinkProvider()
    p.prepare([VehicleRef.parse(f"mavlink+tcp://127.0.0.1:{port}")])  # nothing listens there
    p.close()  # the retrying stops (the fixture checks)


def test_an_arducopter_refusing_current_mode_connects_and_reads_modes_from_heartbeat(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # ArduCopter SITL answers SET_MESSAGE_INTERVAL for CURRENT_MODE with DENIED ("No ap_message
    # for mavlink id (436)") and sends HEARTBEAT at 5 Hz when asked: the refusal is taken once,
    # silently, and modes come from HEARTBEAT.
    heard: dict[int, int] = {}
    real = _SimulatedAutopilot._command

    def command(self: _SimulatedAutopilot, msg: Any) -> int | None:
        if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            heard[int(msg.param1)] = heard.get(int(msg.param1), 0) + 1
        return real(self, msg)

    monkeypatch.setattr(_SimulatedAutopilot, "_command", command)
    said: list[str] = []
    with mavsim(ARDUPILOT) as sim, provider() as p:
        p._progress = said.append
        [v] = p.attach_all(requests(sim))
        b = v.backend
        assert b.telemetry().mode is Mode.MANUAL  # STABILIZE
        ack = answer(lambda: b.set_mode(Mode.HOLD), lambda: b.telemetry().mode is Mode.HOLD)
        assert ack.accepted and b.telemetry().mode is Mode.HOLD  # (BRAKE, from HEARTBEAT)
        assert sim.autopilots["R1"].heartbeat_s == pytest.approx(0.2)
        assert CURRENT_MODE_ID not in sim.autopilots["R1"].intervals
        requested = sim.simulator.time_s
        while sim.simulator.time_s < requested + 3.0:  # time for any retry to show
            threading.Event().wait(0.05)
    assert heard[CURRENT_MODE_ID] == 1  # asked once, refused, not asked again
    assert not [line for line in said if "CURRENT_MODE" in line or "not available" in line]


def test_three_arducopters_all_sysid_1_each_agent_gets_its_own(tmp_path: Path) -> None:
    # As three ArduCopter SITLs (every instance is sysid 1, each on its own TCP port):
    # missions/mine_inspection_ardupilot.yaml's three agents, on free ports.
    from btmission.missions import load_mission

    shipped = ROOT / "missions" / "mine_inspection_ardupilot.yaml"
    specs = mission_vehicles(load_mission(mission_on_free_ports(shipped, tmp_path)), ARDUPILOT)
    assert [s.sysid for s in specs] == [1, 1, 1]
    with mavsim(ARDUPILOT, *specs) as sim, provider() as p:
        vehicles = p.attach_all(requests(sim))
        assert [v.id for v in vehicles] == ["R1", "R2", "R3"]
        for v, s in zip(vehicles, specs, strict=True):
            assert v.backend.state.sysid == 1  # type: ignore[attr-defined]
            np.testing.assert_allclose(v.backend.telemetry().position, s.start, atol=0.05)
        # each agent commands its own vehicle: R2's BRAKE reaches R2 alone
        b = vehicles[1].backend
        assert answer(lambda: b.set_mode(Mode.HOLD), lambda: b.telemetry().mode is Mode.HOLD)
        assert [sim.vehicle_state(a)["mode"] for a in ("R1", "R2", "R3")] == [
            Mode.MANUAL, Mode.HOLD, Mode.MANUAL,
        ]  # fmt: skip


@pytest.mark.parametrize("autopilot", [PX4, ARDUPILOT], ids=lambda a: a.value)
def test_a_vehicle_whose_estimator_starts_as_sitls_does_connects_once_it_has_a_position(
    autopilot: Autopilot,
) -> None:
    # --ekf-delay sitl at speed 50: no LOCAL_POSITION_NED for the first 42 s (ArduCopter) or
    # 30 s (PX4) of vehicle time; the provider keeps waiting, then connects
    delay = SITL_EKF_DELAY_S[autopilot]
    with (
        mavsim(autopilot, speed=50.0, ekf_delay_s=delay) as sim,
        provider(speed=50.0, connect_timeout_s=10.0 * margin()) as p,
    ):
        [v] = p.attach_all(requests(sim))
        assert sim.simulator.time_s >= delay
        assert v.backend.estimator_ready()  # type: ignore[attr-defined]
        np.testing.assert_allclose(v.backend.telemetry().position, (5.0, 5.0, 0.0), atol=0.05)
