"""What real PX4 v1.16 SITL did that broke runs (issue #36 item 7), each as a mavsim rule and the
provider's answer to it: a range finder's out-of-range reading is no reading; a landing is told
by the autopilot's landed state (EXTENDED_SYS_STATE), PX4 landing at ~0.8 m/s; a run that stops
disarms the drones armed on the ground."""

from __future__ import annotations

import time

import numpy as np
import pytest

from btmission.backends.mavlink_link import range_reading
from btmission.backends.mavlink_modes import Autopilot
from btmission.mavsim import PX4_RANGE_ON_GROUND_CM
from btmission.runtime.navconfig import NavConfig, NavState
from btmission.runtime.navigation import Navigator
from btmission.spec.vehicleref import VehicleRef
from btmission.vehicles.base import LandedState, Mode, VehicleKind
from tests.mavlink_helpers import SPEED, answer, mavsim, provider

PX4 = Autopilot.PX4
START = (5.0, 5.0, 0.0)


# ------------------------------------------------------------------------------ range finder
def test_a_range_reading_counts_only_within_the_sensors_declared_range() -> None:
    assert range_reading(250, 10, 10000) == (2.5, False)
    assert range_reading(10, 10, 10000) == (0.1, False)  # the bounds are in range
    assert range_reading(10000, 10, 10000) == (100.0, False)
    assert range_reading(65533, 10, 10000) == (None, False)  # PX4 SIH on the ground
    assert range_reading(65535, 0, 0) == (None, False)  # UINT16_MAX: unknown
    assert range_reading(700, 0, 0) == (7.0, False)  # no maximum declared
    assert range_reading(0, 1, 4000) == (None, True)  # closer than it measures


@pytest.mark.serial  # paced by mavsim's clock
def test_a_px4_drone_whose_range_finder_reads_out_of_range_on_the_ground_takes_off() -> None:
    """mavsim's PX4 sends 65533 cm on the ground (above the declared 10000 cm), as SIH does: the
    ground stays under the drone (not 655 m below it) and the navigator's take-off climbs to
    its altitude above that ground."""
    with mavsim(PX4) as sim, provider() as p:
        ep = sim.endpoints[0]
        b = p.attach("R1", VehicleKind.MULTIROTOR, START, VehicleRef.parse(ep.url)).backend
        st = b.state  # type: ignore[attr-defined]
        end = time.monotonic() + 5.0
        while st.range_at == -np.inf and time.monotonic() < end:
            time.sleep(0.01)
        assert st.range_at > -np.inf, "no DISTANCE_SENSOR came"
        assert st.range_m is None and not st.range_below_min  # 65533 cm: no reading
        assert b.telemetry().ground_z == pytest.approx(0.0, abs=0.05)
        assert PX4_RANGE_ON_GROUND_CM > 10000
        nav = Navigator("R1", b, None, "track", NavConfig(altitude_m=2.0))
        t0 = time.monotonic()

        def step_for(seconds: float, until: object = None) -> None:
            end = time.monotonic() + seconds / SPEED
            while time.monotonic() < end:
                nav.step(time.monotonic() - t0)
                if until is not None and until():  # type: ignore[operator]
                    return
                time.sleep(0.05 / SPEED)

        nav.hold()
        step_for(1.5)  # the stream has run a second: OFFBOARD is accepted
        keep = lambda: nav.step(time.monotonic() - t0)  # noqa: E731
        assert answer(b.arm, every=keep)
        assert answer(lambda: b.set_mode(Mode.OFFBOARD), every=keep)
        nav.takeoff()
        step_for(10.0, lambda: nav.status.state is not NavState.RUNNING)
        assert nav.status.command == "takeoff" and nav.status.state is NavState.ARRIVED
        tel = b.telemetry()
        assert tel.position[2] == pytest.approx(2.0, abs=0.25)
        assert tel.ground_z == pytest.approx(0.0, abs=0.1)  # the range finder's, in the air
        assert st.range_m == pytest.approx(tel.position[2], abs=0.1)


@pytest.mark.serial  # paced by mavsim's clock
def test_a_px4_landing_is_told_by_its_landed_state_and_lands_at_px4s_speed() -> None:
    """mavsim's PX4 descends at 0.7 m/s in LAND (0.3 m/s the last metre) and says so in EXTENDED_SYS_STATE (LANDING,
    then ON_GROUND): the provider's telemetry carries it, and the navigator's arrival over home
    holds through the whole descent."""
    with mavsim(PX4) as sim, provider(telemetry_hz=50.0) as p:
        ep = sim.endpoints[0]
        b = p.attach("R1", VehicleKind.MULTIROTOR, START, VehicleRef.parse(ep.url)).backend
        nav = Navigator("R1", b, None, "track", NavConfig(altitude_m=2.0))
        end = time.monotonic() + 1.5 / SPEED
        while time.monotonic() < end:
            b.set_position_setpoint(np.array([5.0, 5.0, 2.0]))
            time.sleep(0.05 / SPEED)
        keep = lambda: b.set_position_setpoint(np.array([5.0, 5.0, 2.0]))  # noqa: E731
        assert answer(b.arm, every=keep)
        assert answer(lambda: b.set_mode(Mode.OFFBOARD), every=keep)
        end = time.monotonic() + 8.0 / SPEED
        while abs(b.telemetry().position[2] - 2.0) > 0.1 and time.monotonic() < end:
            b.set_position_setpoint(np.array([5.0, 5.0, 2.0]))
            time.sleep(0.05 / SPEED)
        assert b.telemetry().landed_state is LandedState.IN_AIR
        assert answer(b.land)
        states, fastest, at_home = set(), 0.0, True
        end = time.monotonic() + 15.0 / SPEED  # (7.5 s, then disarmed 2 s later)
        while time.monotonic() < end:
            tel = b.telemetry()
            states.add(tel.landed_state)
            fastest = max(fastest, -float(tel.velocity[2]))
            at_home = at_home and nav.at(START, tel)
            if tel.landed and not tel.armed:
                break
            time.sleep(0.02 / SPEED)
        assert b.telemetry().landed and not b.telemetry().armed
        assert LandedState.LANDING in states and LandedState.ON_GROUND in states
        assert fastest == pytest.approx(0.7, abs=0.1)
        assert at_home


@pytest.mark.serial  # paced by mavsim's clock
def test_stopping_disarms_a_drone_armed_on_the_ground() -> None:
    """Armed, not yet taken off (PX4 would disarm it by itself only after 10 s): the provider's
    stop disarms it, and says so."""
    said: list[str] = []
    with mavsim(PX4) as sim, provider() as p:
        p._progress = said.append
        ep = sim.endpoints[0]
        b = p.attach("R1", VehicleKind.MULTIROTOR, START, VehicleRef.parse(ep.url)).backend
        assert answer(b.arm) and sim.vehicle_state("R1")["armed"]
        acks = p.stop_vehicles()
        assert [bool(a) for a in acks["R1"]] == [True]
        assert not sim.vehicle_state("R1")["armed"]
        assert said[-1] == "R1: the run stopped: armed on the ground, DISARM accepted"
