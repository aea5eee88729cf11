"""Backend conformance: the PX4-offboard rules every vehicle provider must keep.

Leaves are written against :class:`~btmission.vehicles.base.Backend`, so a behaviour that works in
the simulator must work on a real autopilot. These tests go through the provider API only
(:mod:`btmission.vehicles.provider`: the registry, ``attach``, ``step``, ``clock``), never through
a provider's internals, so that any provider can be held to them: add its backend URL to
:data:`PROVIDERS` (the simulator and the fake provider are there; issue #14 adds the MAVLink
provider against PX4 SITL). Time is driven with :func:`advance`, which steps the provider and
lets the provider's clock pass (the simulator's ``sleep_until`` returns at once, the wall clock
really waits).

What each test holds a provider to is PX4's behaviour (DESIGN.md §8): OFFBOARD only after
setpoints have streamed (> 2 Hz for 1 s), HOLD when they stop in OFFBOARD (COM_OF_LOSS_T 1 s),
no change of the arming state in the air, take-off only when armed, LAND descends and disarms,
an armed vehicle that never takes off disarms (COM_DISARM_PRFLT 10 s), and a ground robot stops
when its cmd_vel stops (0.5 s).
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from btmission.missions import load_mission_text
from btmission.spec.vehicleref import VehicleRef
from btmission.vehicles.base import Ack, Backend, Mode, Sensors, VehicleKind
from btmission.vehicles.provider import (
    Vehicle,
    VehicleEvent,
    VehicleProvider,
    provider_factory,
)
from btmission.world.build import world_from_spec

PROVIDERS = [
    pytest.param("sim", id="sim"),
    pytest.param("fake", id="fake"),
    pytest.param("mavlink-px4", id="mavlink-px4", marks=pytest.mark.slow),
    pytest.param("mavlink-ardupilot", id="mavlink-ardupilot", marks=pytest.mark.slow),
]
"""The providers under test; each gets the same mission (below). ``mavlink-*``: the MAVLink
provider against mavsim (in this process, on loopback) with PX4 or ArduPilot behaviour (in the
slow selection, which CI runs too; tests/unit/backends/test_mavlink_provider.py is the fast one)."""

LATENCY_S = 0.6
"""What a real link adds before a vehicle's reaction shows in its telemetry (the provider keeps
a setpoint streaming 0.3 s after the mission's last one; modes arrive with heartbeats)."""

MISSION = """
mission: conformance
version: 1
world:
  map: {{generate: empty, size: [30, 30, 8]}}
  resolution: 0.5
agents:
  - {{id: R1, library: aerial, start: [5, 5, 0], backend: '{url}'}}
tasks: []
task_types: {{}}
runtime: {{mavlink: {{time_scale: {speed}, connect_timeout_s: 5, telemetry_hz: 20}}}}
"""

STEP_S = 0.05
"""The step :func:`advance` drives the provider with (the mission's ``runtime.sim.step_s``)."""


@pytest.fixture(params=PROVIDERS)
def urls(request: pytest.FixtureRequest) -> Iterator[dict[VehicleKind, str]]:
    """The backend URL of each vehicle (a drone R1 at (5, 5, 0), a ground robot G1 at (5, 10, 0))
    of the provider under test; for MAVLink, mavsim serves both."""
    name = str(request.param)
    if not name.startswith("mavlink-"):
        yield {VehicleKind.MULTIROTOR: name, VehicleKind.GROUND: name}
        return
    from btmission.backends.mavlink_modes import Autopilot
    from tests.mavlink_helpers import mavsim, spec

    ap = Autopilot(name.split("-", 1)[1])
    drone = spec(ap, "R1", (5.0, 5.0, 0.0))
    robot = spec(ap, "G1", (5.0, 10.0, 0.0), VehicleKind.GROUND, sysid=2)
    # (PX4's offboard-loss action set to Hold, as docs/mavlink.md advises: its default,
    # Position mode, sinks without RC; test_mavsim_firmware.py covers it)
    with mavsim(ap, drone, robot, offboard_loss_action="hold") as sim:
        by_agent = {e.agent_id: e.url for e in sim.endpoints}
        yield {VehicleKind.MULTIROTOR: by_agent["R1"], VehicleKind.GROUND: by_agent["G1"]}


@pytest.fixture
def url(urls: dict[VehicleKind, str]) -> str:
    """The backend URL of the drone (the mission's agent: it picks the provider)."""
    return urls[VehicleKind.MULTIROTOR]


@pytest.fixture
def provider(url: str, tmp_path: Path) -> Iterator[VehicleProvider]:
    """The provider of ``url``'s scheme, from the registry, for a small open world."""
    from tests.mavlink_helpers import SPEED

    text = textwrap.dedent(MISSION.format(url=url, speed=SPEED)).lstrip()
    mission = load_mission_text(text, str(tmp_path / "m.yaml"))
    world = world_from_spec(mission.spec.world, mission.base_dir)
    made = provider_factory(VehicleRef.parse(url).scheme)(mission, world, 0)
    yield made
    made.close()


@pytest.fixture
def attach(provider: VehicleProvider, urls: dict[VehicleKind, str]) -> Callable[..., Vehicle]:
    """Attach a multirotor (R1) or a ground robot (G1) to the provider under test."""

    def attach_one(kind: VehicleKind = VehicleKind.MULTIROTOR) -> Vehicle:
        if kind is VehicleKind.MULTIROTOR:
            return provider.attach("R1", kind, (5.0, 5.0, 0.0), VehicleRef.parse(urls[kind]))
        return provider.attach("G1", kind, (5.0, 10.0, 0.0), VehicleRef.parse(urls[kind]))

    return attach_one


def advance(
    provider: VehicleProvider, seconds: float, every_step: Callable[[], object] | None = None
) -> list[VehicleEvent]:
    """Let ``seconds`` of the provider's time pass, calling ``every_step`` before each step."""
    events: list[VehicleEvent] = []
    clock = provider.clock
    end = clock.now() + seconds
    while clock.now() < end - 1e-9:
        if every_step is not None:
            every_step()
        clock.sleep_until(clock.now() + STEP_S)  # a real provider: wall time passes
        events.extend(provider.step(STEP_S))
    return events


def answered(
    provider: VehicleProvider,
    call: Callable[[], Ack],
    shown: Callable[[], bool] | None = None,
    every_step: Callable[[], object] | None = None,
    seconds: float = 30.0,
) -> Ack:
    """A command's answer. A provider whose commands travel (MAVLink) answers on a later call
    (the first returns a pending Ack): the provider's time is let pass until the answer is in
    and, when accepted, until ``shown()`` (the telemetry shows its effect), up to ``seconds``."""
    end = provider.clock.now() + seconds
    ack = call()
    while ack.pending or (ack.accepted and shown is not None and not shown()):
        if provider.clock.now() >= end:
            break
        advance(provider, STEP_S, every_step)
        ack = call()
    return ack


def in_mode(backend: Backend, mode: Mode) -> Callable[[], bool]:
    return lambda: backend.telemetry().mode is mode


def streaming(backend: Backend, hz: float = 20.0) -> Callable[[], None]:
    """Hold-position setpoints at ``hz`` (called every step)."""
    every = max(1, round(1.0 / (hz * STEP_S)))
    count = [0]
    target = backend.telemetry().position.copy()

    def send() -> None:
        if count[0] % every == 0:
            backend.set_position_setpoint(target)
        count[0] += 1

    return send


def airborne(provider: VehicleProvider, backend: Backend, altitude_m: float = 2.0) -> None:
    """Stream, arm, switch to OFFBOARD and climb to ``altitude_m`` with position setpoints."""
    stream = streaming(backend)
    advance(provider, 1.3, stream)
    assert answered(provider, backend.arm, None, stream), "arm refused on the ground"
    ack = answered(
        provider, lambda: backend.set_mode(Mode.OFFBOARD), in_mode(backend, Mode.OFFBOARD), stream
    )
    assert ack, ack.reason
    p = backend.telemetry().position
    goal = (float(p[0]), float(p[1]), float(p[2]) + altitude_m)
    advance(provider, 6.0, lambda: backend.set_position_setpoint(goal))
    for _ in range(6):  # a real link's round trips (an ArduCopter's take-off spools up after
        tel = backend.telemetry()  # its ack) may leave it short of the goal: climb on a while
        if abs(tel.height_above_ground - altitude_m) <= 0.3:
            break
        advance(provider, 1.0, lambda: backend.set_position_setpoint(goal))
    tel = backend.telemetry()
    assert not tel.landed and tel.height_above_ground == pytest.approx(altitude_m, abs=0.3)


# ------------------------------------------------------------------------------ the provider
def test_the_provider_hands_out_vehicles_and_owns_the_clock(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    assert isinstance(provider, VehicleProvider)
    vehicle = attach()
    assert vehicle.id == "R1" and vehicle.kind is VehicleKind.MULTIROTOR
    assert isinstance(vehicle.backend, Backend) and vehicle.backend.kind is VehicleKind.MULTIROTOR
    assert vehicle.sensors is None or isinstance(vehicle.sensors, Sensors)
    t0 = provider.clock.now()
    events = advance(provider, 1.0)
    assert provider.clock.now() - t0 == pytest.approx(1.0, abs=2 * STEP_S)
    assert events == []  # a vehicle standing in an open world hits nothing
    provider.close()
    provider.close()  # idempotent


def test_ground_truth_hooks_are_absent_or_callable(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    vehicle = attach()
    if provider.realtime:  # a real robot has no ground truth
        assert vehicle.odometer_m is None and vehicle.clearance_m is None
        return
    assert vehicle.odometer_m is not None and vehicle.odometer_m() == 0.0
    advance(provider, 0.2)
    assert vehicle.clearance_m is not None
    clearance = vehicle.clearance_m()
    assert clearance is None or clearance >= 0.0


def test_telemetry_is_sane_at_power_on(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach().backend
    advance(provider, 0.2)
    tel = backend.telemetry()
    assert tel.position.shape == (3,) and tel.velocity.shape == (3,)
    assert np.all(np.isfinite(tel.position)) and np.all(np.isfinite(tel.velocity))
    assert tel.landed and not tel.armed and tel.mode is Mode.MANUAL
    assert tel.height_above_ground == pytest.approx(0.0, abs=0.1)
    assert 0.0 < tel.battery <= 1.0
    assert all(math.isfinite(x) for x in (tel.yaw, tel.roll, tel.pitch, tel.yaw_rate))
    assert tel.time_s == pytest.approx(provider.clock.now(), abs=2 * STEP_S)
    advance(provider, 0.5)
    assert backend.telemetry().time_s > tel.time_s


# ------------------------------------------------------------------------------ offboard
def test_offboard_is_refused_before_setpoints_stream(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach().backend
    # armed on the ground (a disarmed PX4 takes OFFBOARD without setpoints, as PX4 v1.16 SITL
    # did, and then refuses to arm until they stream)
    assert answered(provider, backend.arm)
    offboard = in_mode(backend, Mode.OFFBOARD)
    ack = answered(provider, lambda: backend.set_mode(Mode.OFFBOARD), offboard)
    assert not ack and ack.reason
    assert ack.transient  # once the setpoints stream, it is accepted: worth asking again
    stream = streaming(backend)
    advance(provider, 0.5, stream)  # streaming, but not for a second yet
    # (asked once: a transient refusal is asked again with a back-off, which PX4's
    # TEMPORARILY_REJECTED invites, and would be accepted once a second has streamed)
    backend.set_mode(Mode.OFFBOARD)
    advance(provider, 0.2, stream)
    assert backend.telemetry().mode is not Mode.OFFBOARD


def test_offboard_is_refused_below_2_hz(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach().backend
    assert answered(provider, backend.arm)  # (armed: see the test above)
    stream = streaming(backend, hz=1.0)
    advance(provider, 2.0, stream)
    assert not answered(
        provider, lambda: backend.set_mode(Mode.OFFBOARD), in_mode(backend, Mode.OFFBOARD), stream
    )


def test_offboard_is_accepted_after_a_second_of_setpoints(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach().backend
    stream = streaming(backend, hz=5.0)
    advance(provider, 1.2, stream)
    ack = answered(
        provider, lambda: backend.set_mode(Mode.OFFBOARD), in_mode(backend, Mode.OFFBOARD), stream
    )
    assert ack, ack.reason
    assert backend.telemetry().mode is Mode.OFFBOARD


def test_setpoint_loss_in_offboard_falls_back_to_hold(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach().backend
    airborne(provider, backend)
    advance(provider, 0.5)  # a short gap is tolerated
    assert backend.telemetry().mode is Mode.OFFBOARD
    advance(provider, 0.8 + (LATENCY_S if provider.realtime else 0.0))  # > 1 s without setpoints
    tel = backend.telemetry()
    assert tel.mode is Mode.HOLD and tel.armed and not tel.landed
    z = tel.position[2]
    advance(provider, 2.0)  # and it holds where it was
    assert backend.telemetry().position[2] == pytest.approx(z, abs=0.3)


# ------------------------------------------------------------------------------ arming, take-off, land
def test_the_arming_state_cannot_change_in_the_air(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach().backend
    airborne(provider, backend)
    assert backend.arm()  # already armed: nothing changes
    ack = backend.disarm()
    assert not ack and "air" in ack.reason
    assert backend.telemetry().armed


def test_takeoff_is_refused_unless_armed(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach().backend
    ack = backend.takeoff(2.0)
    assert not ack and "armed" in ack.reason and ack.transient
    assert backend.telemetry().mode is not Mode.TAKEOFF
    assert answered(provider, backend.arm)
    assert answered(provider, lambda: backend.takeoff(2.0))
    advance(provider, 8.0)
    tel = backend.telemetry()
    assert tel.mode is Mode.HOLD and not tel.landed
    assert tel.height_above_ground == pytest.approx(2.0, abs=0.2)


def test_land_descends_and_disarms(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach().backend
    airborne(provider, backend)
    assert answered(provider, backend.land)
    advance(provider, 1.0)
    tel = backend.telemetry()
    assert tel.mode is Mode.LAND and tel.velocity[2] < -0.2  # descending
    advance(provider, 10.0)  # (PX4 crawls its last metre and disarms 2 s after touchdown)
    tel = backend.telemetry()
    assert tel.landed and not tel.armed
    assert tel.height_above_ground == pytest.approx(0.0, abs=0.1)


def test_an_armed_vehicle_that_never_takes_off_disarms(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach().backend
    assert answered(provider, backend.arm)
    advance(provider, 5.0)
    assert backend.telemetry().armed
    advance(provider, 6.0)  # > 10 s armed on the ground
    assert not backend.telemetry().armed


# ------------------------------------------------------------------------------ ground robots
def test_a_ground_robot_stops_when_its_cmd_vel_stops(
    provider: VehicleProvider, attach: Callable[..., Vehicle]
) -> None:
    backend = attach(VehicleKind.GROUND).backend
    assert backend.kind is VehicleKind.GROUND
    assert not backend.takeoff(1.0)
    drive = lambda: backend.set_velocity_setpoint((0.3, 0.0, 0.0), 0.0)  # noqa: E731
    if provider.realtime:  # a real robot is armed and put in GUIDED/OFFBOARD first
        advance(provider, 2.5, drive)
    x0 = float(backend.telemetry().position[0])
    advance(provider, 1.0, drive)
    x1 = float(backend.telemetry().position[0])
    assert x1 - x0 == pytest.approx(0.3, abs=0.1)  # it drives its cmd_vel
    advance(provider, 1.5)  # no command: stopped within the 0.5 s timeout
    x2 = float(backend.telemetry().position[0])
    assert x2 - x1 < 0.3 * (0.5 + (LATENCY_S if provider.realtime else 0.0)) + 0.05
    advance(provider, 1.0)
    assert float(backend.telemetry().position[0]) == pytest.approx(x2, abs=0.01)
    assert np.linalg.norm(backend.telemetry().velocity[:2]) < 0.05
