"""mavsim rules taken from real SITL (issue #36 item 8: every difference between real SITL and
mavsim becomes a mavsim rule with a test), stepped by hand where they can be (no thread, no
wall clock): the link-loss failsafes are off unless asked for, as the firmwares ship them."""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from btmission.backends._pymavlink import mavlink
from btmission.backends.mavlink_modes import Autopilot, mode_request
from btmission.backends.mavlink_url import MavlinkAddress
from btmission.backends.sim import SimConfig
from btmission.cli.main import cli
from btmission.mavsim import (
    SITL_EKF_DELAY_S,
    MavSim,
    MavSimConfig,
    VehicleSpec,
    _SimulatedAutopilot,
    mission_vehicles,
    vehicles_in_a_row,
)
from btmission.missions import load_mission
from btmission.vehicles.base import LandedState, Mode, VehicleKind
from btmission.world.minegen import empty_world
from tests.mavlink_helpers import free_port
from tests.wallclock import WallClock

ROOT = Path(__file__).resolve().parents[3]
PX4, APM = Autopilot.PX4, Autopilot.ARDUPILOT
MULTI = VehicleKind.MULTIROTOR


def _address(autopilot: Autopilot) -> MavlinkAddress:
    if autopilot is PX4:  # (nobody listens there: what it sends is dropped)
        return MavlinkAddress("udp", "127.0.0.1", free_port())
    return MavlinkAddress("tcp", "127.0.0.1", 0)


@contextmanager
def stepped(autopilot: Autopilot, **config: Any) -> Iterator[MavSim]:
    """One drone R1 at (5, 5, 0), not started: the test steps it with :func:`run`."""
    spec = VehicleSpec("R1", MULTI, (5.0, 5.0, 0.0), _address(autopilot), 1)
    sim = MavSim(MavSimConfig((spec,), empty_world((30, 30, 12), 0.5), autopilot=autopilot,
                              **config))  # fmt: skip
    try:
        yield sim
    finally:
        sim.close()


def run(sim: MavSim, seconds: float, gcs: bool = False) -> None:
    """``seconds`` of simulated time, each step as ``MavSim.run_forever`` does it (``gcs``: a
    ground station's heartbeat heard on every step)."""
    end = sim.simulator.time_s + seconds
    while sim.simulator.time_s < end - 1e-9:
        for ap in sim.autopilots.values():
            ap.receive()
            if gcs:
                ap.gcs_heartbeat_at = ap.now()
        for ap in sim.autopilots.values():
            ap.step()
        sim.simulator.step()
        for ap in sim.autopilots.values():
            ap.send_due()


def airborne(sim: MavSim, altitude: float = 3.0) -> _SimulatedAutopilot:
    """R1 armed and hovering at ``altitude`` m (GUIDED on ArduPilot, HOLD after a take-off on
    PX4), its ground station's last heartbeat heard just now."""
    ap = sim.autopilots["R1"]
    if ap.autopilot is APM:
        assert ap._set_mode(mode_request(APM, MULTI, Mode.OFFBOARD).custom_mode) == 0
        assert ap._arm_disarm(True, False) == 0
        assert ap._takeoff(altitude) == 0
    else:
        assert ap._arm_disarm(True, False) == 0
        assert ap._takeoff(ap.cfg.home_amsl_m + altitude) == 0
    run(sim, 8.0, gcs=True)
    assert ap.backend.telemetry().position[2] == pytest.approx(altitude, abs=0.2)
    return ap


def _command_long(command: int, *params: float) -> Any:
    p = [*params, *[0.0] * (7 - len(params))]
    return mavlink.MAVLink_command_long_message(1, 1, command, 0, *p)


# ---------------------------------------------------------------- 1. link-loss failsafes off
@pytest.mark.parametrize("autopilot", [PX4, APM])
def test_link_loss_failsafes_are_off_by_default_as_the_firmwares_ship_them(
    autopilot: Autopilot,
) -> None:
    """PX4's NAV_DLL_ACT and ArduCopter's FS_GCS_ENABLE default to 0: a drone whose ground
    station fell silent flies on (on ArduCopter SITL it braked in GUIDED and resumed)."""
    with stepped(autopilot) as sim:
        ap = airborne(sim)
        mode = ap.backend.telemetry().mode
        run(sim, 30.0)  # 3 × COM_DL_LOSS_T, 6 × FS_GCS_TIMEOUT without a heartbeat
        state = sim.vehicle_state("R1")
        assert state["armed"] and not state["landed"]
        assert ap.backend.telemetry().mode is mode and not ap.failsafe_note


@pytest.mark.parametrize(
    ("autopilot", "option", "seconds", "note"),
    [
        (PX4, "datalink_loss_s", 10.0, "data link lost: landing"),
        (APM, "gcs_failsafe_s", 5.0, "GCS failsafe: landing"),
    ],
)
def test_a_link_loss_failsafe_asked_for_lands_after_its_timeout(
    autopilot: Autopilot, option: str, seconds: float, note: str
) -> None:
    with stepped(autopilot, **{option: seconds}) as sim:
        ap = airborne(sim)
        run(sim, seconds - 0.5)
        assert ap.backend.telemetry().mode is not Mode.LAND
        run(sim, 1.0)
        assert ap.backend.telemetry().mode is Mode.LAND and ap.failsafe_note == note


def test_failsafe_timeouts_must_be_positive() -> None:
    spec = VehicleSpec("R1", MULTI, (5.0, 5.0, 0.0), _address(APM), 1)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="gcs_failsafe_s must be positive or None"):
            MavSimConfig((spec,), empty_world((10, 10, 5), 0.5), gcs_failsafe_s=bad)


def _config_of(monkeypatch: pytest.MonkeyPatch, *args: str, count: bool = True) -> MavSimConfig:
    """The configuration ``btmission mavsim ARGS`` would serve (nothing is served)."""
    import btmission.mavsim

    seen: list[MavSimConfig] = []

    def capture(config: MavSimConfig) -> None:
        seen.append(config)
        raise OSError("captured")

    monkeypatch.setattr(btmission.mavsim, "MavSim", capture)
    r = CliRunner().invoke(cli, ["mavsim", *(["--count", "1"] if count else []), *args])
    assert r.exit_code == 2 and "captured" in r.output, r.output
    return seen[0]


def test_the_cli_turns_a_link_loss_failsafe_on_only_when_asked(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    config = _config_of(monkeypatch)
    assert config.datalink_loss_s is None and config.gcs_failsafe_s is None
    config = _config_of(monkeypatch, "--datalink-loss", "10", "--gcs-failsafe", "5")
    assert (config.datalink_loss_s, config.gcs_failsafe_s) == (10.0, 5.0)
    help_text = CliRunner().invoke(cli, ["mavsim", "--help"]).output
    assert "NAV_DLL_ACT" in help_text and "FS_GCS_ENABLE" in help_text


# ---------------------------------------------------------------- 3. landing and disarming
def _land_timing(sim: MavSim) -> tuple[float, float, float]:
    """From 2 m up, a LAND: the fastest descent speed, the vehicle seconds until the firmware
    says ON_GROUND, then until disarmed."""
    ap = airborne(sim, 2.0)
    assert ap._command(_command_long(mavlink.MAV_CMD_NAV_LAND)) == mavlink.MAV_RESULT_ACCEPTED
    t0 = ap.now()
    on_ground = disarmed = math.nan
    sink = 0.0
    while math.isnan(disarmed) and ap.now() < t0 + 20.0:
        run(sim, sim.config.step_s, gcs=True)
        tel = ap.backend.telemetry()
        sink = max(sink, -float(tel.velocity[2]))
        if math.isnan(on_ground) and ap.landed_state() is LandedState.ON_GROUND:
            on_ground = ap.now()
        if not math.isnan(on_ground) and not ap.armed():
            disarmed = ap.now()
    return sink, on_ground - t0, disarmed - on_ground


@pytest.mark.parametrize(
    ("autopilot", "speed", "down_s", "disarm_s"),
    [(APM, 0.5, (4.0, 5.0), 0.5), (PX4, 0.7, (7.2, 12.3), 2.0)],
)
def test_a_land_from_2_m_descends_and_disarms_as_the_firmware_does(
    autopilot: Autopilot, speed: float, down_s: tuple[float, float], disarm_s: float
) -> None:
    """ArduCopter SITL descends at 0.5 m/s (LAND_SPEED) and disarms ~0.5 s after touchdown.
    PX4 v1.16 SIH descends at MPC_LAND_SPEED (0.7 m/s), below 1 m (MPC_LAND_ALT3, its distance
    sensor giving the height) at MPC_LAND_CRWL (0.3 m/s): 7.2-12.3 s from about 2 m to "Landing
    detected" (ON_GROUND), then "Disarmed by landing" 2.0 s later (COM_DISARM_LAND)."""
    with stepped(autopilot) as sim:
        sink, down, off = _land_timing(sim)
        assert sink == pytest.approx(speed, abs=0.05)
        assert down_s[0] <= down <= down_s[1], down  # (ArduPilot: ~4 s; 4.7 s here)
        assert off == pytest.approx(disarm_s, abs=2.5 * sim.config.step_s)


def test_px4_crawls_the_last_metre_of_a_landing() -> None:
    """Below MPC_LAND_ALT3 (1 m) PX4 descends at MPC_LAND_CRWL (0.3 m/s), above it at
    MPC_LAND_SPEED (0.7 m/s); the embedded simulator's own landing has no crawl."""
    with stepped(PX4) as sim:
        ap = airborne(sim, 2.0)
        assert ap._command(_command_long(mavlink.MAV_CMD_NAV_LAND)) == mavlink.MAV_RESULT_ACCEPTED
        sinks: dict[bool, float] = {True: 0.0, False: 0.0}  # below 1 m: the slowest sink
        below = math.inf
        while not ap.backend.telemetry().landed and ap.now() < 30.0:
            run(sim, sim.config.step_s)
            tel = ap.backend.telemetry()
            low = tel.height_above_ground < 1.0
            below = min(below, ap.now()) if low else below
            sinks[low] = max(sinks[low], -float(tel.velocity[2]))
            if 0.1 < tel.height_above_ground < 0.3:  # (slowed down from 0.7 m/s by then)
                assert -float(tel.velocity[2]) == pytest.approx(0.3, abs=0.06)
        assert sinks[False] == pytest.approx(0.7, abs=0.06)
        assert 1.0 / 0.7 + 0.5 < ap.now() - below < 1.0 / 0.3  # 1 m at 0.7 m/s: 1.4 s
    assert SimConfig().land_crawl_m_s is None


# ---------------------------------------------------------------- 6. LAND on the ground
def test_a_disarmed_arducopter_accepts_land_and_then_refuses_to_arm_in_it() -> None:
    """ArduCopter's ModeLand allows entry on the ground: DO_SET_MODE LAND and NAV_LAND are
    accepted while disarmed; the copter shows LAND (heartbeat) and, as in any LAND, refuses to
    arm until it is put in another mode."""
    land = mode_request(APM, MULTI, Mode.LAND).custom_mode
    guided = mode_request(APM, MULTI, Mode.OFFBOARD).custom_mode
    with stepped(APM) as sim:
        ap = sim.autopilots["R1"]
        assert ap._set_mode(land) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 1.0)
        assert ap.custom_mode() == land and sim.vehicle_state("R1")["mode"] is Mode.LAND
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_FAILED  # Mode not armable
        assert ap._set_mode(guided) == mavlink.MAV_RESULT_ACCEPTED
        nav_land = _command_long(mavlink.MAV_CMD_NAV_LAND)
        assert ap._command(nav_land) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 1.0)
        state = sim.vehicle_state("R1")
        assert state["mode"] is Mode.LAND and state["landed"] and not state["armed"]
        assert ap._set_mode(guided) == mavlink.MAV_RESULT_ACCEPTED
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_ACCEPTED


# ---------------------------------------------------------------- 5. system ids as the SITLs'
def test_every_ardupilot_tcp_vehicle_is_sysid_1_and_px4_instance_i_is_i_plus_1(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Every ArduCopter SITL instance is sysid 1, each on its own TCP port; PX4 SITL instance i
    is MAV_SYS_ID i + 1. Vehicles sharing a UDP port still need distinct ones; a URL's
    ``?sysid=`` wins."""
    assert [s.sysid for s in vehicles_in_a_row(3, APM)] == [1, 1, 1]
    assert [s.sysid for s in vehicles_in_a_row(3, PX4)] == [1, 2, 3]
    assert [s.sysid for s in vehicles_in_a_row(3, APM, transport="udp")] == [1, 2, 3]
    assert [s.sysid for s in vehicles_in_a_row(3, PX4, transport="tcp")] == [1, 2, 3]
    shipped = ROOT / "missions" / "mine_inspection_ardupilot.yaml"
    mission = load_mission(shipped)
    assert [s.sysid for s in mission_vehicles(mission, APM)] == [1, 1, 1]
    assert [s.sysid for s in mission_vehicles(mission, PX4)] == [1, 2, 3]
    config = _config_of(monkeypatch, "--mission", str(shipped), count=False)
    assert config.autopilot is APM and [s.sysid for s in config.vehicles] == [1, 1, 1]
    text = shipped.read_text().replace("127.0.0.1:5770'", "127.0.0.1:5770?sysid=7'")
    (tmp_path / "m.yaml").write_text(text)
    config = _config_of(monkeypatch, "--mission", str(tmp_path / "m.yaml"), count=False)
    assert [s.sysid for s in config.vehicles] == [1, 7, 1]


# ---------------------------------------------------------------- 7. estimator start-up
@pytest.mark.parametrize("autopilot", [PX4, APM])
def test_no_local_position_before_the_estimator_is_ready(autopilot: Autopilot) -> None:
    """ArduCopter sends no LOCAL_POSITION_NED before EKF3 has an origin (SITL: ~42 s), PX4
    none before its local position is valid (SIH: ready ~30 s after start): asked for at once,
    the stream starts when the estimator is ready (``--ekf-delay sitl``)."""
    delay = SITL_EKF_DELAY_S[autopilot]
    with stepped(autopilot, ekf_delay_s=delay) as sim:
        ap = sim.autopilots["R1"]
        sent: list[float] = []
        real = ap._send_message

        def send(msg_id: int) -> bool:
            done = real(msg_id)
            if done and msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
                sent.append(ap.now())
            return done

        ap._send_message = send  # type: ignore[method-assign]
        interval = _command_long(
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 1e5
        )
        assert ap._command(interval) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, delay - 1.0)
        assert sent == []
        assert ap._arm_disarm(True, False) != mavlink.MAV_RESULT_ACCEPTED
        run(sim, 2.0)
        assert sent and delay <= sent[0] < delay + 0.1
        assert len(sent) == pytest.approx(10, abs=2)  # then at the 10 Hz asked


@pytest.mark.parametrize(("autopilot", "seconds"), [("ardupilot", 42.0), ("px4", 4.0)])
def test_the_cli_asks_for_the_sitls_estimator_start_up_by_name(
    monkeypatch: pytest.MonkeyPatch, autopilot: str, seconds: float
) -> None:
    config = _config_of(monkeypatch, "--autopilot", autopilot, "--ekf-delay", "sitl")
    assert config.ekf_delay_s == seconds == SITL_EKF_DELAY_S[Autopilot(autopilot)]
    assert _config_of(monkeypatch, "--autopilot", autopilot).ekf_delay_s == 0.0  # (tests: fast)
    assert _config_of(monkeypatch, "--ekf-delay", "2.5").ekf_delay_s == 2.5
    r = CliRunner().invoke(cli, ["mavsim", "--count", "1", "--ekf-delay", "soon"])
    assert r.exit_code == 2 and "--ekf-delay" in r.output


# ---------------------------------------------------------------- 2. a frozen simulator
def test_a_frozen_simulator_resumes_its_clock_where_it_stopped(wall: WallClock) -> None:
    """A lockstep SITL frozen with kill -STOP resumes its clock where it stopped (ArduCopter
    SITL frozen 8 s flew on, no failsafe). mavsim's loop, frozen 8 s of wall time, drops them
    instead of running 400 late steps in a burst; frozen 0.5 s (a busy machine), it catches up.
    The loop runs on a hand-moved wall clock: its waits move it, as do the freezes."""
    with stepped(APM) as sim:
        assert sim.paused_s == 0.0 and sim.pauses == 0  # (counted)
        freezes = {2.0: 8.0, 4.0: 0.5}  # at this simulated time, frozen this many wall s
        t0 = wall.t

        def wait(delay: float) -> bool:
            wall.t += delay
            for at in [at for at in freezes if sim.simulator.time_s >= at]:
                wall.t += freezes.pop(at)
            if sim.simulator.time_s >= 6.0:
                sim._stop.set()
            return sim._stop.is_set()

        sim._wait = wait
        sim.run_forever()
        assert sim.pauses == 1 and sim.paused_s == pytest.approx(8.0, abs=0.05)
        assert sim.late_steps == pytest.approx(0.5 / sim.config.step_s, abs=2)  # caught up
        # the wall time passed is the simulated time plus the freeze it dropped
        assert wall.t - t0 == pytest.approx(sim.simulator.time_s + sim.paused_s, abs=0.05)


def test_the_cli_says_how_long_the_simulator_was_frozen(monkeypatch: pytest.MonkeyPatch) -> None:
    import btmission.mavsim

    class Frozen:
        """What a MavSim that was frozen once for 8.2 s reports when it stops."""

        error = None
        steps, late_steps, paused_s, pauses = 300, 3, 8.2, 1

        def __init__(self, config: MavSimConfig) -> None:
            self.endpoints: list[Any] = []
            self.simulator = type("S", (), {"time_s": 6.0})()

        def start(self) -> None: ...

        def stop(self) -> None: ...

        def counters(self) -> dict[str, Any]:
            return {}

    monkeypatch.setattr(btmission.mavsim, "MavSim", Frozen)
    r = CliRunner().invoke(cli, ["mavsim", "--count", "1", "--duration", "0.01"])
    assert r.exit_code == 0, r.output
    assert r.output.splitlines()[-1] == (
        "stopped after 6.0 simulated s (300 steps, 3 late step(s), paused 8.2 s wall in "
        "1 freeze(s))"
    )


# ------------------------------------------------------- PX4's offboard loss: Position mode
def _offboard_then_silent(sim: MavSim) -> _SimulatedAutopilot:
    """R1 flying OFFBOARD at 3 m on its setpoints, which then stop."""
    ap = airborne(sim)
    here = ap.backend.telemetry().position.copy()
    for _ in range(60):  # 1.2 s of setpoints, then OFFBOARD
        ap.backend.set_position_setpoint(here, None, 0.0)
        ap.last_setpoint_t = ap.now()
        run(sim, sim.config.step_s, gcs=True)
    ap.backend.set_mode(Mode.OFFBOARD)
    run(sim, 0.2, gcs=True)
    assert ap.backend.telemetry().mode is Mode.OFFBOARD
    return ap


@pytest.mark.parametrize("action", ["position", "hold"])
def test_px4s_offboard_loss_flies_position_mode_by_default_which_sinks_without_rc(
    action: str,
) -> None:
    """PX4 v1.16 SITL with default parameters (COM_OBL_RC_ACT 0): 1.1 s after its setpoints
    stopped, "Failsafe activated", Position mode (custom mode 196608) with system status
    CRITICAL, sinking without RC (5.2 m to 0.1 m seen); back to OFFBOARD by itself once they
    stream again. ``--offboard-loss hold`` holds instead (COM_OBL_RC_ACT 5)."""
    with stepped(PX4, offboard_loss_action=action) as sim:
        ap = _offboard_then_silent(sim)
        run(sim, 1.5, gcs=True)  # the setpoints stopped 1.7 s ago
        assert ap.backend.telemetry().mode is Mode.HOLD  # (the simulator's failsafe)
        assert ap.position_fallback() is (action == "position")
        custom = ap.custom_mode()
        z0 = ap.backend.telemetry().position[2]
        run(sim, 3.0, gcs=True)
        sunk = z0 - ap.backend.telemetry().position[2]
        if action == "position":
            assert custom == 196608
            assert sunk == pytest.approx(3 * 0.8, abs=0.4)  # without RC, Position mode sinks
        else:
            assert custom == mode_request(PX4, MULTI, Mode.HOLD).custom_mode
            assert abs(sunk) < 0.1
        here = ap.backend.telemetry().position.copy()
        for _ in range(75):  # the setpoints stream again: OFFBOARD by itself
            ap.backend.set_position_setpoint(here, None, 0.0)
            ap.last_setpoint_t = ap.now()
            run(sim, sim.config.step_s, gcs=True)
        assert ap.backend.telemetry().mode is Mode.OFFBOARD and not ap.position_fallback()


def test_the_cli_takes_the_offboard_loss_action(monkeypatch: pytest.MonkeyPatch) -> None:
    assert _config_of(monkeypatch).offboard_loss_action == "position"
    config = _config_of(monkeypatch, "--offboard-loss", "hold")
    assert config.offboard_loss_action == "hold"
    r = CliRunner().invoke(cli, ["mavsim", "--count", "1", "--offboard-loss", "rtl"])
    assert r.exit_code == 2 and "--offboard-loss" in r.output


# ---------------------------------------------------------------- PX4 SITL rules (issue #36)
def _stream_here(sim: MavSim, seconds: float) -> None:
    """``seconds`` of position setpoints at R1's place, at 10 Hz (as a ground station streams)."""
    ap = sim.autopilots["R1"]
    here = ap.frame.to_local(ap.backend.telemetry().position)
    for _ in range(round(seconds / 0.1)):
        ap._position_target(
            mavlink.MAVLink_set_position_target_local_ned_message(
                0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0b110111111000, *map(float, here),
                0, 0, 0, 0, 0, 0, 0, 0,
            )
        )  # fmt: skip
        run(sim, 0.1)


def test_px4_takes_offboard_disarmed_without_setpoints_then_refuses_to_arm_until_they_stream() -> (
    None
):
    """PX4 v1.16 SITL, OFFBOARD asked while disarmed with no setpoints: ACCEPTED (twice), then
    arming TEMPORARILY_REJECTED, "Arming denied: Resolve system health failures first", until
    setpoints stream; armed on the ground with no setpoints, OFFBOARD is TEMPORARILY_REJECTED
    ("Switching to Offboard is currently not available"), not DENIED."""
    offboard = mode_request(PX4, MULTI, Mode.OFFBOARD).custom_mode
    with stepped(PX4) as sim:
        ap = sim.autopilots["R1"]
        texts: list[str] = []
        ap.text = lambda severity, message: texts.append(message)  # type: ignore[method-assign]
        assert ap._set_mode(offboard) == mavlink.MAV_RESULT_ACCEPTED
        assert ap._set_mode(offboard) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 1.0)
        assert sim.vehicle_state("R1")["mode"] is Mode.OFFBOARD and not ap.armed()
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        assert texts[-1] == "Arming denied: Resolve system health failures first"
        _stream_here(sim, 1.5)
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 0.1)
        assert ap.backend.telemetry().mode is Mode.OFFBOARD  # the simulator's own, now
    with stepped(PX4) as sim:
        ap = sim.autopilots["R1"]
        ap.text = lambda severity, message: texts.append(message)  # type: ignore[method-assign]
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_ACCEPTED  # (no OFFBOARD asked)
        assert ap._set_mode(offboard) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        assert texts[-1] == "Switching to Offboard is currently not available"
        assert sim.vehicle_state("R1")["mode"] is not Mode.OFFBOARD


def test_a_refused_offboard_leaves_px4s_offboard_loss_hold_to_end_when_setpoints_resume() -> None:
    """A refused request changes nothing on PX4: in the offboard-loss HOLD, an OFFBOARD asked
    before the setpoints stream again is TEMPORARILY_REJECTED, and the failsafe still ends by
    itself (back to OFFBOARD) once they have streamed a second."""
    offboard = mode_request(PX4, MULTI, Mode.OFFBOARD).custom_mode
    with stepped(PX4) as sim:
        ap = airborne(sim)
        _stream_here(sim, 1.5)
        assert ap._set_mode(offboard) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 2.0)  # no setpoints: COM_OF_LOSS_T
        assert ap.backend.telemetry().mode is Mode.HOLD
        assert ap._set_mode(offboard) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        _stream_here(sim, 1.5)
        assert ap.backend.telemetry().mode is Mode.OFFBOARD


def _land_and_disarm(sim: MavSim) -> None:
    ap = sim.autopilots["R1"]
    assert ap._command(_command_long(mavlink.MAV_CMD_NAV_LAND)) == mavlink.MAV_RESULT_ACCEPTED
    assert sim.vehicle_state("R1")["mode"] is Mode.LAND
    end = ap.now() + 20.0
    while ap.armed() and ap.now() < end:
        run(sim, 0.1)
    assert not ap.armed() and sim.vehicle_state("R1")["landed"]
    run(sim, 1.0)


def test_px4_disarmed_by_landing_shows_the_mode_it_was_in_before_land() -> None:
    """PX4 v1.16 SITL, after "Disarmed by landing", shows the last mode asked that allows arming:
    OFFBOARD when LAND was asked from OFFBOARD (and, disarmed in OFFBOARD without setpoints,
    refuses to arm until they stream), Hold after a HOLD then LAND — not MANUAL."""
    offboard = mode_request(PX4, MULTI, Mode.OFFBOARD).custom_mode
    hold = mode_request(PX4, MULTI, Mode.HOLD).custom_mode
    with stepped(PX4) as sim:
        ap = airborne(sim, 2.0)
        _stream_here(sim, 1.5)
        assert ap._set_mode(offboard) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 0.2)
        _land_and_disarm(sim)
        assert sim.vehicle_state("R1")["mode"] is Mode.OFFBOARD
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        _stream_here(sim, 1.5)  # the next task's setpoints: it arms, in OFFBOARD
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 0.1)
        assert ap.backend.telemetry().mode is Mode.OFFBOARD
    with stepped(PX4) as sim:
        ap = airborne(sim, 2.0)
        _stream_here(sim, 1.5)
        assert ap._set_mode(offboard) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 0.2)
        assert ap._set_mode(hold) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 0.2)
        _land_and_disarm(sim)
        assert sim.vehicle_state("R1")["mode"] is Mode.HOLD
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_ACCEPTED


def test_px4_accepts_nav_takeoff_while_disarmed_and_leaves_the_ground_only_once_armed() -> None:
    """PX4 v1.16 SITL ACCEPTED NAV_TAKEOFF while disarmed (mavsim said DENIED): the drone shows
    Takeoff and stays on the ground until it is armed, then climbs to the altitude asked."""
    with stepped(PX4, home_amsl_m=100.0) as sim:
        ap = sim.autopilots["R1"]
        takeoff = _command_long(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, 103.0)
        assert ap._command(takeoff) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 3.0)
        state = sim.vehicle_state("R1")
        assert state["mode"] is Mode.TAKEOFF and state["landed"] and not state["armed"]
        assert state["position"][2] == pytest.approx(0.0, abs=0.05)  # nothing moved
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 6.0)
        assert ap.backend.telemetry().position[2] == pytest.approx(3.0, abs=0.2)


def test_px4_sends_current_mode_at_2_hz_whatever_was_asked_and_on_each_change() -> None:
    """PX4 v1.16 SITL ACCEPTED a 50 Hz CURRENT_MODE stream but sent it at about 2 Hz, and
    whenever its vehicle status changed: a new mode is told in the step it happens."""
    from btmission.backends._pymavlink import CURRENT_MODE_ID

    hold = mode_request(PX4, MULTI, Mode.HOLD).custom_mode
    with stepped(PX4) as sim:
        ap = sim.autopilots["R1"]
        sent: list[tuple[float, int]] = []
        real = ap._send_message

        def send(msg_id: int) -> bool:
            if msg_id == CURRENT_MODE_ID:
                sent.append((ap.now(), ap.custom_mode()))
            return real(msg_id)

        ap._send_message = send  # type: ignore[method-assign]
        interval = _command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, CURRENT_MODE_ID, 2e4)
        assert ap._command(interval) == mavlink.MAV_RESULT_ACCEPTED
        run(sim, 5.0)
        assert len(sent) == pytest.approx(10, abs=1)  # 2 Hz, not the 50 Hz asked
        assert ap._arm_disarm(True, False) == mavlink.MAV_RESULT_ACCEPTED
        assert ap._set_mode(hold) == mavlink.MAV_RESULT_ACCEPTED
        t, n = ap.now(), len(sent)
        run(sim, sim.config.step_s)
        assert sent[n:] == [(pytest.approx(t + sim.config.step_s), hold)]  # at once
