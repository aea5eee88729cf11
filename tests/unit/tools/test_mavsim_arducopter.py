"""mavsim's ArduCopter modes, stepped by hand (no thread, no wall clock): a copter keeps the mode
it disarms in (LAND after landing) and refuses to arm in it; BRAKE — the provider's HOLD — holds
its altitude, LOITER without RC sinks (issue #36 item 6)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from btmission.backends._pymavlink import mavlink
from btmission.backends.mavlink_modes import Autopilot, mode_request
from btmission.backends.mavlink_url import MavlinkAddress
from btmission.mavsim import MavSim, MavSimConfig, VehicleSpec, _SimulatedAutopilot
from btmission.vehicles.base import Mode, VehicleKind
from btmission.world.minegen import empty_world

MULTI = VehicleKind.MULTIROTOR
GUIDED = mode_request(Autopilot.ARDUPILOT, MULTI, Mode.OFFBOARD).custom_mode
HOLD = mode_request(Autopilot.ARDUPILOT, MULTI, Mode.HOLD).custom_mode
LAND = mode_request(Autopilot.ARDUPILOT, MULTI, Mode.LAND).custom_mode
LOITER = 5
ACCEPTED, FAILED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED


@pytest.fixture
def sim() -> Iterator[MavSim]:
    spec = VehicleSpec("R1", MULTI, (5.0, 5.0, 0.0), MavlinkAddress("tcp", "127.0.0.1", 0), 1)
    made = MavSim(
        MavSimConfig((spec,), empty_world((30, 30, 12), 0.5), autopilot=Autopilot.ARDUPILOT)
    )
    try:
        yield made
    finally:
        made.close()


def run(sim: MavSim, seconds: float) -> None:
    """``seconds`` of simulated time, each step as ``MavSim.run_forever`` does it."""
    end = sim.simulator.time_s + seconds
    while sim.simulator.time_s < end:
        for ap in sim.autopilots.values():
            ap.step()
        sim.simulator.step()
        for ap in sim.autopilots.values():
            ap.send_due()


def flying(sim: MavSim, altitude: float = 5.0) -> _SimulatedAutopilot:
    """R1 armed in GUIDED and up at ``altitude`` m."""
    ap = sim.autopilots["R1"]
    assert ap._set_mode(GUIDED) == ACCEPTED
    assert ap._arm_disarm(True, False) == ACCEPTED
    assert ap._takeoff(altitude) == ACCEPTED
    run(sim, 10.0)
    assert ap.backend.telemetry().position[2] == pytest.approx(altitude, abs=0.2)
    return ap


def test_a_copter_that_landed_stays_in_land_and_arms_only_from_another_mode(sim: MavSim) -> None:
    ap = flying(sim, 3.0)
    assert ap._set_mode(LAND) == ACCEPTED
    run(sim, 15.0)  # down, then disarmed 0.5 s after touching the ground
    state = sim.vehicle_state("R1")
    assert state["landed"] and not state["armed"]
    assert state["mode"] is Mode.LAND and ap.custom_mode() == LAND  # not STABILIZE
    assert ap._arm_disarm(True, False) == FAILED  # "Arm: Mode not armable"
    assert not ap.armed()
    assert ap._set_mode(GUIDED) == ACCEPTED
    run(sim, 3.0)  # GUIDED has no timeout on the ground: it stays, disarmed
    assert ap.custom_mode() == GUIDED
    assert ap._arm_disarm(True, False) == ACCEPTED
    assert ap._takeoff(2.0) == ACCEPTED
    run(sim, 8.0)
    assert ap.backend.telemetry().position[2] == pytest.approx(2.0, abs=0.2)


def test_brake_is_hold_and_holds_where_loiter_without_rc_sinks(sim: MavSim) -> None:
    assert HOLD == 17  # BRAKE
    ap = flying(sim)
    assert ap._set_mode(HOLD) == ACCEPTED
    assert sim.vehicle_state("R1")["mode"] is Mode.HOLD
    run(sim, 10.0)
    assert ap.custom_mode() == HOLD
    assert ap.backend.telemetry().position[2] == pytest.approx(5.0, abs=0.2)
    assert ap._set_mode(LOITER) == ACCEPTED
    assert sim.vehicle_state("R1")["mode"] == "LOITER"
    run(sim, 2.0)
    assert ap.backend.telemetry().position[2] < 3.5  # the throttle stick is at the bottom
    run(sim, 8.0)
    assert ap.backend.telemetry().landed
    assert ap.custom_mode() == LOITER  # (disarmed there, it stays there)


def test_brake_refuses_to_arm_and_loiter_does_not(sim: MavSim) -> None:
    ap = sim.autopilots["R1"]
    assert ap._set_mode(HOLD) == ACCEPTED
    assert ap._arm_disarm(True, False) == FAILED  # "Arm: Mode not armable"
    assert ap._set_mode(LOITER) == ACCEPTED
    assert ap._arm_disarm(True, False) == ACCEPTED
