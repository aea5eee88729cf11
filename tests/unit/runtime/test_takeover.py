"""An autopilot's failsafe is final until the operator says otherwise (issue #36 item 7): on
real PX4, after its own data-link-loss landing, the tree armed the drone and launched it again.
A drone taken over — switched by its autopilot (or its pilot) out of the modes the tree flies
it in, to one the tree did not ask for — makes its agent stand down: a ``taken_over`` event,
its task back to the pool for another agent, no bid, setpoint or command after it; the
operator's include brings it back.

The vehicles are the ``fake`` provider's, taken over with
:meth:`~btmission.backends.fake.FakeVehicle.take_over`."""

from __future__ import annotations

import textwrap
from pathlib import Path

from btmission.backends.fake import FakeVehicle
from btmission.missions import load_mission_text
from btmission.runtime.commands import IncludeAgent
from btmission.runtime.events import Recorder
from btmission.runtime.runner import MissionRun
from btmission.vehicles.base import Mode

MISSION = """
mission: takeover
version: 1
world:
  map: {generate: empty, size: [60, 30, 8]}
  resolution: 0.5
agents:
  - {id: R1, library: aerial, start: [5, 5, 0], backend: fake}
  - {id: R2, library: aerial, start: [5, 25, 0], backend: fake}
tasks:
  - {id: T1, type: inspect, location: [50, 5, 2]}
task_types:
  inspect: {goal: at_goal(location), cost: path_cost(location)}
coordination: {cooldown_s: 1000}
default_behavior: {goal: landed_at_home, idle_timeout_s: 2}
runtime: {controller: track, max_duration_s: 300}
"""


def fake(run: MissionRun, agent: str) -> FakeVehicle:
    vehicle = run.vehicles[agent].backend
    assert isinstance(vehicle, FakeVehicle)
    return vehicle


def take_over_in_flight(run: MissionRun, rec: Recorder, mode: Mode = Mode.LAND) -> list[float]:
    """Take R1 over (a failsafe landing) once it flies to T1, 10 m out; returns [when]."""
    when: list[float] = []

    def check(r: MissionRun) -> None:
        tel = fake(r, "R1").telemetry()
        if not when and tel.mode is Mode.OFFBOARD and not tel.landed and tel.position[0] > 15:
            fake(r, "R1").take_over(mode)
            when.append(r.now())
        elif not when:
            r.at(r.now() + 0.1, check)

    run.at(0.1, check)
    return when


def test_a_failsafe_landing_is_final_and_the_task_goes_to_another() -> None:
    rec = Recorder()
    run = MissionRun(load_mission_text(textwrap.dedent(MISSION), "m.yaml"), observers=[rec])
    when = take_over_in_flight(run, rec)
    result = run.run()
    assert when, "R1 never flew past x = 15"
    assert result.reason == "completed" and result.done == ["T1"]
    (ev,) = rec.of("taken_over")
    assert (ev.get("agent"), ev.get("mode"), ev.get("failsafe"), ev.get("task")) == (
        "R1", "LAND", True, "T1",
    )  # fmt: skip
    assert ev.get("final") is True  # (runtime.settings.takeover_is_final: the default)
    (gave_up,) = [e for e in rec.of("progress") if e.get("event") == "gave_up"]
    assert gave_up.get("agent") == "R1" and "failsafe" in str(gave_up.get("reason"))
    done = [(e.get("agent"), e.get("task")) for e in rec.of("progress") if e.get("event") == "done"]
    assert done == [("R2", "T1")]  # done once, by the other drone
    # R1: landed where its autopilot put it, never armed nor given a task again
    tel = fake(run, "R1").telemetry()
    assert tel.landed and not tel.armed and tel.position[0] > 15
    assert not [e for e in rec.of("stage") if e.get("agent") == "R1" and e.t > ev.t]
    assert not [e for e in rec.of("agent_task") if e.get("agent") == "R1" and e.t > ev.t]
    assert run.agents["R1"].stood_down == ("its autopilot's failsafe switched the vehicle to LAND")


def test_the_operators_include_brings_a_stood_down_agent_back() -> None:
    """With the other drone gone, the task waits for R1; the operator includes R1 again and
    it arms, takes off from where its autopilot landed it, and does the task."""
    rec = Recorder()
    text = textwrap.dedent(MISSION).replace("cooldown_s: 1000", "cooldown_s: 0")
    run = MissionRun(load_mission_text(text, "m.yaml"), observers=[rec])
    when = take_over_in_flight(run, rec)
    run.at(0.2, lambda r: r.kill_agent("R2", "test: gone"))

    def include_when_landed(r: MissionRun) -> None:
        tel = fake(r, "R1").telemetry()
        if when and tel.landed:  # (before it disarms: then the run would end, nobody left)
            r.submit(IncludeAgent("R1"))
        else:
            r.at(r.now() + 0.5, include_when_landed)

    run.at(1.0, include_when_landed)
    result = run.run()
    assert result.reason == "completed" and result.done == ["T1"]
    (ev,) = rec.of("taken_over")
    done = [(e.get("agent"), e.get("task")) for e in rec.of("progress") if e.get("event") == "done"]
    assert done == [("R1", "T1")]
    later = [e.get("action") for e in rec.of("stage") if e.get("agent") == "R1" and e.t > ev.t]
    assert "takeoff" in later  # flown again (still armed where it landed), on the operator's word
    assert run.agents["R1"].stood_down is None


def test_an_offboard_loss_hold_in_flight_is_taken_back_with_a_warning() -> None:
    """HOLD is the offboard-loss failsafe (setpoints late on a busy computer): the agent does
    not stand down but asks for OFFBOARD again, says so, and does its task (a drone left in
    HOLD hovered for the rest of the run beside eight CPU burners)."""
    rec = Recorder()
    run = MissionRun(load_mission_text(textwrap.dedent(MISSION), "m.yaml"), observers=[rec])
    when = take_over_in_flight(run, rec, Mode.HOLD)
    result = run.run()
    assert when and result.reason == "completed"
    assert rec.of("taken_over") == []
    (warning,) = [e for e in rec.of("warning") if "fell back to HOLD" in str(e.get("message"))]
    assert warning.get("agent") == "R1" and warning.t >= when[0]
    done = [(e.get("agent"), e.get("task")) for e in rec.of("progress") if e.get("event") == "done"]
    assert done == [("R1", "T1")]


def test_a_mission_may_say_its_tree_flies_on_after_a_takeover() -> None:
    """``runtime.settings.takeover_is_final: false``: the takeover is logged (``final`` false)
    and the agent does not stand down — its tree flies on from the vehicle's state, and the
    task is done (by whoever the auction gives it)."""
    rec = Recorder()
    text = textwrap.dedent(MISSION).replace(
        "runtime: {controller: track, max_duration_s: 300}",
        "runtime: {controller: track, max_duration_s: 300, settings: {takeover_is_final: false}}",
    )
    run = MissionRun(load_mission_text(text, "m.yaml"), observers=[rec])
    when = take_over_in_flight(run, rec)
    result = run.run()
    assert when and result.reason == "completed" and result.done == ["T1"]
    (ev,) = rec.of("taken_over")
    assert (ev.get("agent"), ev.get("final"), ev.get("task")) == ("R1", False, None)
    assert run.agents["R1"].stood_down is None
    assert not [e for e in rec.of("progress") if e.get("event") == "gave_up"]
    later = [e.get("action") for e in rec.of("stage") if e.get("agent") == "R1" and e.t > ev.t]
    assert later  # its tree went on


def test_takeover_is_final_takes_only_true_or_false(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from btmission.cli.main import cli

    path = tmp_path / "m.yaml"
    path.write_text(
        textwrap.dedent(MISSION).replace(
            "max_duration_s: 300}", "max_duration_s: 300, settings: {takeover_is_final: maybe}}"
        )
    )
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2, result.output
    assert (
        "runtime.settings.takeover_is_final: expected true or false (got 'maybe')" in result.output
    )
    assert "Traceback" not in result.output
