"""Transient refusals are retried, tasks are not lost (issue #36 item 4): a vehicle that refuses
to arm a few times still does its task (the retries are in the log); one that keeps refusing
gives its task back and another agent does it, the first cooled down for it; a task fails for
good only after its type's ``max_attempts``, with every attempt's reason; an agent that gives
up everything is taken out of the auction; a restarted coordinator keeps the attempt counts.

The vehicles are the ``fake`` provider's (kinematic, simulated time), made to refuse arming with
:meth:`~btmission.backends.fake.FakeVehicle.refuse_arming`."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import pytest
from py_trees.common import Status

from btmission.allocation.tasks import TaskState
from btmission.backends.fake import FakeVehicle
from btmission.missions import load_mission_text
from btmission.runtime.actions import COMMAND_TIMEOUT_S
from btmission.runtime.commands import IncludeAgent
from btmission.runtime.coordinator import Coordinator
from btmission.runtime.events import Event, JsonlEventLog, Recorder, read_events
from btmission.runtime.recovery import recover
from btmission.runtime.report import build_report, format_report, report_json
from btmission.runtime.runner import MissionRun
from btmission.runtime.substitution import TestLeaf
from btmission.spec.mission import Mission

MISSION = """
mission: refusals
version: 1
world:
  map: {{generate: empty, size: [40, 30, 8]}}
  resolution: 0.5
agents:
  - {{id: R1, library: aerial, start: [5, 5, 0], backend: fake}}
{more_agents}tasks:
{tasks}task_types:
  inspect: {{goal: at_goal(location), cost: path_cost(location), max_attempts: {attempts}}}
coordination: {{cooldown_s: {cooldown}, exclude_after: {exclude}}}
default_behavior: {{goal: landed_at_home, idle_timeout_s: 2}}
runtime: {{controller: track, max_duration_s: 400}}
"""
R2 = "  - {id: R2, library: aerial, start: [5, 25, 0], backend: fake}\n"
T1 = "  - {id: T1, type: inspect, location: [9, 7, 2]}\n"


def mission(
    tmp_path: Path,
    *,
    two: bool = False,
    tasks: str = T1,
    attempts: int = 3,
    cooldown: float = 30.0,
    exclude: int = 3,
) -> Mission:
    text = MISSION.format(
        more_agents=R2 if two else "", tasks=tasks, attempts=attempts, cooldown=cooldown,
        exclude=exclude,
    )  # fmt: skip
    return load_mission_text(textwrap.dedent(text).lstrip(), str(tmp_path / "m.yaml"))


def fake(run: MissionRun, agent: str) -> FakeVehicle:
    vehicle = run.vehicles[agent].backend
    assert isinstance(vehicle, FakeVehicle)
    return vehicle


def of(rec: Recorder, kind: str, **match: Any) -> list[Event]:
    return [e for e in rec.of(kind) if all(e.get(k) == v for k, v in match.items())]


def test_a_vehicle_that_refuses_to_arm_twice_still_does_its_task(tmp_path: Path) -> None:
    rec = Recorder()
    run = MissionRun(mission(tmp_path), observers=[rec])
    fake(run, "R1").refuse_arming(2, "PreArm: estimator not ready")
    result = run.run()
    assert result.reason == "completed" and result.done == ["T1"]
    retries = of(rec, "retry", agent="R1")
    assert [(e.get("task"), e.get("action"), e.get("retry"), e.get("retries")) for e in retries] == [
        ("T1", "arm", 1, 3), ("T1", "arm", 2, 3),
    ]  # fmt: skip
    assert {e.get("reason") for e in retries} == {"PreArm: estimator not ready"}
    assert [e.get("wait_s") for e in retries] == [2.0, 4.0]  # the back-off doubles
    # each try lasts COMMAND_TIMEOUT_S, then the back-off: the leaf kept running meanwhile
    assert retries[0].t == pytest.approx(COMMAND_TIMEOUT_S, abs=0.2)
    assert retries[1].t - retries[0].t == pytest.approx(2.0 + COMMAND_TIMEOUT_S, abs=0.2)
    progress = [(e.get("agent"), e.get("event")) for e in rec.of("progress")]
    assert progress == [("R1", "done")]  # never failed nor given up
    assert rec.of("attempt") == []
    assert [e.get("state") for e in of(rec, "task", task="T1")] == ["assigned", "done"]


def test_a_vehicle_that_always_refuses_loses_its_task_to_another(tmp_path: Path) -> None:
    rec = Recorder()
    run = MissionRun(mission(tmp_path, two=True), observers=[rec])
    fake(run, "R1").refuse_arming(None, "PreArm: Compass not calibrated")
    result = run.run()
    assert result.reason == "completed" and result.done == ["T1"]
    assert len(of(rec, "retry", agent="R1")) == 3  # refusal_retries, then it gave up
    (gave_up,) = of(rec, "progress", event="gave_up")
    assert gave_up.get("agent") == "R1"
    assert gave_up.get("reason") == ("arm: PreArm: Compass not calibrated (gave up after 4 tries)")
    (attempt,) = rec.of("attempt")
    assert (attempt.get("task"), attempt.get("agent"), attempt.get("attempt")) == ("T1", "R1", 1)
    assert attempt.get("max_attempts") == 3 and attempt.get("gave_up") is True
    assert attempt.get("state") == "open"
    assert attempt.get("cooldown_until") == pytest.approx(gave_up.t + 30.0)
    states = [(e.get("state"), e.get("agent")) for e in of(rec, "task", task="T1")]
    assert states == [("assigned", "R1"), ("open", None), ("assigned", "R2"), ("done", "R2")]
    reopened = of(rec, "task", task="T1", state="open")[0]
    assert reopened.get("reason") == f"R1 gave up (attempt 1 of 3): {gave_up.get('reason')}"
    done = of(rec, "progress", event="done")
    assert [(e.get("agent"), e.get("task")) for e in done] == [("R2", "T1")]  # done once
    # R1 was cooled down: it bid all along but won nothing, and its vehicle never armed
    assert not [e for e in rec.of("agent_task") if e.get("agent") == "R1" and e.t > gave_up.t]
    assert not fake(run, "R1").telemetry().armed
    # the report shows the attempt, its retries and its reason
    rep = build_report(rec.events)
    (row,) = rep.rows
    (a,) = row.attempts
    assert (a.attempt, a.agent, a.retries, a.outcome) == (1, "R1", 3, "offered to the others")
    text = format_report(rep)
    assert "Attempts that did not succeed (1)" in text
    assert "arm: PreArm: Compass not calibrated (gave up after 4 tries)" in text
    assert report_json(rep)["tasks"][0]["attempts"][0]["agent"] == "R1"


def test_the_cooled_down_agent_is_offered_the_task_again_when_no_one_else_takes_it(
    tmp_path: Path,
) -> None:
    """One agent only: it gives up, waits out the cool-down (the task open, saying why), tries
    again and, once its vehicle arms, does it."""
    rec = Recorder()
    run = MissionRun(mission(tmp_path, cooldown=10.0), observers=[rec])
    fake(run, "R1").refuse_arming(4 + 1)  # its first try and 3 retries, then one more
    result = run.run()
    assert result.done == ["T1"]
    gave_up = of(rec, "progress", event="gave_up")
    assert len(gave_up) == 1
    assert (
        run.coordinator.state.pool["T1"]
        .history[-3]
        .reason.startswith("R1 gave up (attempt 1 of 3)")
    )
    won_again = of(rec, "task", task="T1", state="assigned")[1]
    assert won_again.get("agent") == "R1"
    assert won_again.t == pytest.approx(gave_up[0].t + 10.0, abs=0.25)
    assert len(run.coordinator.state.pool["T1"].attempts) == 1


def test_a_task_fails_for_good_after_max_attempts_with_every_reason(tmp_path: Path) -> None:
    rec = Recorder()
    run = MissionRun(mission(tmp_path, attempts=2, cooldown=1.0), observers=[rec])
    fake(run, "R1").refuse_arming(None, "PreArm: Battery unhealthy")
    result = run.run()
    assert result.reason == "finished with open tasks" and result.done == []
    attempts = rec.of("attempt")
    assert [(e.get("attempt"), e.get("state")) for e in attempts] == [(1, "open"), (2, "failed")]
    assert attempts[1].get("cooldown_until") is None
    t1 = run.coordinator.state.pool["T1"]
    assert t1.state is TaskState.FAILED and len(t1.attempts) == 2
    why = "arm: PreArm: Battery unhealthy (gave up after 4 tries)"
    assert t1.history[-1].reason == f"failed after 2 attempt(s): R1: {why}; R1: {why}"
    (failed,) = of(rec, "task", task="T1", state="failed")
    assert failed.get("reason") == t1.history[-1].reason
    text = format_report(build_report(rec.events))
    assert "Attempts that did not succeed (2)" in text and "2 of 2" in text


def test_a_final_refusal_is_not_retried_and_the_task_goes_to_another(tmp_path: Path) -> None:
    rec = Recorder()
    run = MissionRun(mission(tmp_path, two=True), observers=[rec])
    fake(run, "R1").refuse_arming(None, "battery too low (5%)", transient=False)
    result = run.run()
    assert result.done == ["T1"] and rec.of("retry") == []
    (gave_up,) = of(rec, "progress", event="gave_up")
    assert gave_up.t < 0.5 and gave_up.get("reason") == "arm: battery too low (5%)"
    assert [e.get("agent") for e in of(rec, "progress", event="done")] == ["R2"]


def test_an_agent_that_gives_up_everything_is_taken_out_of_the_auction(tmp_path: Path) -> None:
    tasks = "".join(
        f"  - {{id: T{i}, type: inspect, location: [{6 + 2 * i}, 7, 2]}}\n" for i in (1, 2, 3)
    )
    rec = Recorder()
    run = MissionRun(mission(tmp_path, two=True, tasks=tasks, exclude=2), observers=[rec])
    fake(run, "R1").refuse_arming(None, "PreArm: Compass not calibrated", transient=False)
    run.run(until=40.0)
    (out,) = rec.of("agent_excluded")
    gave_up = [e.get("task") for e in of(rec, "progress", event="gave_up")]
    assert out.get("agent") == "R1" and out.get("tasks") == gave_up and len(gave_up) == 2
    assert out.get("reason").startswith(
        f"gave up 2 different tasks in a row ({', '.join(gave_up)})"
    )
    assert "R1" in run.coordinator.state.excluded
    assert not [e for e in rec.of("agent_task") if e.get("agent") == "R1" and e.t > out.t]
    assert "R1" in run.snapshot.excluded  # the page shows it as the operator's exclusion
    result = run.run()
    assert sorted(result.done) == ["T1", "T2", "T3"]
    assert {e.get("agent") for e in of(rec, "progress", event="done")} == {"R2"}
    # the operator's include brings it back, with a clean slate
    run.submit(IncludeAgent("R1"))
    run.run(until=run.now() + 0.5)
    assert "R1" not in run.coordinator.state.excluded
    assert "R1" not in run.coordinator.state.streaks


def test_the_last_agent_bidding_is_never_taken_out(tmp_path: Path) -> None:
    tasks = "".join(
        f"  - {{id: T{i}, type: inspect, location: [{6 + 2 * i}, 7, 2]}}\n" for i in (1, 2)
    )
    rec = Recorder()
    run = MissionRun(
        mission(tmp_path, tasks=tasks, attempts=1, exclude=1), observers=[rec]
    )  # fmt: skip
    fake(run, "R1").refuse_arming(None, "no", transient=False)
    result = run.run()
    assert rec.of("agent_excluded") == []
    assert result.reason == "finished with open tasks" and result.done == []  # all failed
    assert [e.get("state") for e in rec.of("attempt")] == ["failed", "failed"]


def test_a_real_failure_still_fails_the_task_at_once(tmp_path: Path) -> None:
    """A leaf's failure that is no refusal (the path is blocked): the task fails for good, not
    offered again."""
    rec = Recorder()
    subs = {"R1/follow_path(location)": TestLeaf(Status.FAILURE, reason="blocked")}
    run = MissionRun(mission(tmp_path, two=True), observers=[rec], substitutions=subs)
    run.run(until=30.0)
    (failed,) = of(rec, "progress", event="failed")
    assert failed.get("reason") == "follow_path(location): blocked"
    (attempt,) = rec.of("attempt")
    assert (attempt.get("gave_up"), attempt.get("state")) == (False, "failed")
    assert run.coordinator.state.pool["T1"].state is TaskState.FAILED
    assert rec.of("retry") == [] and of(rec, "progress", event="gave_up") == []
    assert not [e for e in rec.of("agent_task") if e.get("agent") == "R2" and e.get("task")]


def test_a_restarted_coordinator_keeps_the_attempt_counts(tmp_path: Path) -> None:
    """R1, alone, always refuses and gives T1 up; the log is cut after that and a new
    coordinator restored from it: same attempts, cool-down and streak; R1 tries again after
    the cool-down and the count goes on from the first, to max_attempts."""
    log = tmp_path / "run.jsonl"
    m = mission(tmp_path, cooldown=5.0)
    with JsonlEventLog(log) as sink:
        run = MissionRun(m, observers=[sink])
        fake(run, "R1").refuse_arming(None, "PreArm: Compass not calibrated")
        run.run(until=36.0)
        live = run.coordinator
        assert len(live.state.pool["T1"].attempts) == 1
        rec = recover(m, read_events(log).events)
        assert rec.problems == ()
        assert rec.pool["T1"].attempts == live.state.pool["T1"].attempts
        assert [(e.state, e.agent, e.reason) for e in rec.pool["T1"].history] == [
            (e.state, e.agent, e.reason) for e in live.state.pool["T1"].history
        ]
        assert dict(rec.streaks) == dict(live.state.streaks) == {"R1": ("T1",)}
        assert rec.attempts_logged == {"T1": 1}
        assert any(k[:2] == ("T1", "gave_up") for k in rec.seen["R1"])
        new = Coordinator(m, run.bus, run.now, run.emit_event, check_location=run.paths.problem)
        new.restore(rec)
        assert dict(new.state.cooldown) == pytest.approx(dict(live.state.cooldown))
        run.coordinator = new
        run.coordinator_side.coordinator = new
        run.run(until=130.0)
    events = read_events(log).events
    attempts = [(e.get("task"), e.get("attempt"), e.get("state")) for e in events
                if e.kind == "attempt"]  # fmt: skip
    assert attempts == [("T1", 1, "open"), ("T1", 2, "open"), ("T1", 3, "failed")]
    assert new.state.pool["T1"].state is TaskState.FAILED
    again = recover(m, events)
    assert again.problems == ()
    assert again.pool["T1"].attempts == new.state.pool["T1"].attempts


def test_a_task_added_while_the_mission_runs_has_its_types_max_attempts(tmp_path: Path) -> None:
    """The command port's check (TaskCheck) gives an added task its type's max_attempts, and
    a coordinator restored from the log gives it the same."""
    log = tmp_path / "run.jsonl"
    m = mission(tmp_path, attempts=2)
    with JsonlEventLog(log) as sink:
        run = MissionRun(m, observers=[sink])
        info = run.add_task({"id": "X", "type": "inspect", "location": [12, 7, 2]})
        run.run(until=1.0)
    assert info.max_attempts == 2 and run.coordinator.state.pool["X"].info.max_attempts == 2
    assert recover(m, read_events(log).events).pool["X"].info.max_attempts == 2
