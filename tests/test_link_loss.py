"""Link loss without lost work (issue #13 §5): progress and completions made while an agent's link
is down are queued on the agent and delivered when it returns; the first completion wins, the
other holder is withdrawn in the same round; a dead agent never delivers."""

from __future__ import annotations

from pathlib import Path

import pytest

from btmission.runtime.events import Event, Recorder
from btmission.runtime.runner import MissionRun
from btmission.spec.mission import Mission, load_mission
from tests.test_runtime import ROBOTS, mission_text

ROOT = Path(__file__).resolve().parents[1]
MISSIONS = ROOT / "missions"

# G1 (closer) wins A at t=0 and, with its link up, reaches it at t=27.6 s; G2 would at ~34 s.


def robots(tmp_path: Path) -> Mission:
    """Two ground robots, one task A (tests/test_runtime.py)."""
    return mission_text(ROBOTS, tmp_path)


def outage(
    m: Mission, agent: str, down: float, up: float | None, until: float, **kw: object
) -> tuple[MissionRun, Recorder]:
    rec = Recorder()
    run = MissionRun(m, observers=[rec], **kw)  # type: ignore[arg-type]
    run.at(down, lambda r: r.set_link(agent, False))
    if up is not None:
        run.at(up, lambda r: r.set_link(agent, True))
    run.run(until=until)
    return run, rec


def task_states(rec: Recorder, task: str) -> list[tuple[float, str, str | None]]:
    return [(e.t, e.get("state"), e.get("agent")) for e in rec.of("task") if e.get("task") == task]


def done_events(rec: Recorder, task: str) -> list[Event]:
    return [e for e in rec.of("task") if e.get("task") == task and e.get("state") == "done"]


def executing(rec: Recorder, agent: str) -> list[tuple[float, str | None]]:
    """When ``agent`` started (task) or stopped (None) executing."""
    return [(e.t, e.get("task")) for e in rec.of("agent_task") if e.get("agent") == agent]


def test_outage_during_a_task_the_agent_gets_it_back(tmp_path: Path) -> None:
    run, rec = outage(robots(tmp_path), "G1", 3.0, 8.0, until=28)
    states = task_states(rec, "A")
    # silent for agent_timeout_s: A goes to G2; back at 8 s, G1 (closer) wins it again
    assert [(s, a) for _, s, a in states] == [
        ("assigned", "G1"), ("open", None), ("assigned", "G2"), ("assigned", "G1"), ("done", "G1"),
    ]  # fmt: skip
    assert executing(rec, "G2") == [(pytest.approx(4.0), "A"), (pytest.approx(8.0), None)]
    assert [e.get("agent") for e in rec.of("progress") if e.get("event") == "done"] == ["G1"]
    assert rec.of("warning") == [] and rec.of("withdrawn") == []
    assert run.agents["G1"].unacknowledged == []


def test_outage_across_a_completion_the_first_completion_wins(tmp_path: Path) -> None:
    run, rec = outage(robots(tmp_path), "G1", 3.0, 30.0, until=31)
    # G1 finished A at 27.6 s while cut off (G2, which got A at 4 s, still on its way)
    g1_done = next(e for e in rec.of("progress") if e.get("agent") == "G1")
    assert g1_done.get("event") == "done" and 27 < g1_done.t < 30
    (done,) = done_events(rec, "A")
    assert done.get("agent") == "G1" and done.t == pytest.approx(30.0)  # delivered on return
    assert done.get("reported_s") == g1_done.t
    assert "reported late by G1" in done.get("reason") and "G2 withdrawn" in done.get("reason")
    (w,) = rec.of("withdrawn")
    assert (w.t, w.get("agent"), w.get("task"), w.get("by")) == (done.t, "G2", "A", "G1")
    assert w.get("reason") == "G1 completed 'A' first (reported after its link returned)"
    # G2 stopped executing A in that same round, and never reported it done
    assert executing(rec, "G2") == [(pytest.approx(4.0), "A"), (pytest.approx(30.0), None)]
    assert not [e for e in rec.of("progress") if e.get("agent") == "G2"]
    assert rec.of("warning") == []
    assert run.agents["G1"].unacknowledged == [] and run.coordinator.open_tasks() == []


def test_long_silence_the_completion_arrives_late_and_is_counted_once(tmp_path: Path) -> None:
    # G1 stays silent until 50 s: G2 finishes A at ~34 s and gets the credit; G1's completion
    # (27.6 s) arrives at 50 s and is counted once, for G2, with a warning that says so
    run, rec = outage(robots(tmp_path), "G1", 3.0, 50.0, until=52)
    (done,) = done_events(rec, "A")
    assert done.get("agent") == "G2" and 30 < done.t < 40
    assert run.agents["G1"].unacknowledged == []  # delivered and acknowledged at 50 s
    (warning,) = rec.of("warning")
    assert warning.t == pytest.approx(50.0)
    assert warning.get("message").startswith("G1 reports 'A' done (t=27.6s), but G2 completed")
    assert warning.get("message").endswith("counted once, for G2")


def test_a_dead_agent_never_delivers_its_task_is_redone(tmp_path: Path) -> None:
    rec = Recorder()
    run = MissionRun(robots(tmp_path), observers=[rec])
    run.at(8.0, lambda r: r.kill_agent("G1"))
    result = run.run(until=40)
    assert result.done == ["A"]
    assert [e.get("agent") for e in done_events(rec, "A")] == ["G2"]
    assert not [e for e in rec.of("progress") if e.get("agent") == "G1"]
    assert rec.of("withdrawn") == [] and rec.of("warning") == []


def test_pick_and_deliver_delivery_during_an_outage_ends_done(tmp_path: Path) -> None:
    """The only robot is cut off 30-55 s: committed to P1 at ~25 s, it delivers at ~49 s; the
    delivery reaches the coordinator when the link returns (before: P1 stayed open forever)."""
    m = load_mission(MISSIONS / "pick_and_deliver.yaml")
    run, rec = outage(m, "G1", 30.0, 55.0, until=56, controller="track")
    p1 = task_states(rec, "P1")
    assert ("open", None) in [(s, a) for _, s, a in p1]  # released when G1 went silent
    (done,) = done_events(rec, "P1")
    assert done.get("agent") == "G1" and done.t == pytest.approx(55.0)
    assert 30 < done.get("reported_s") < 55
    assert run.result("until").done == ["P1", "I1"]
    assert rec.of("warning") == []


def test_pick_and_deliver_commit_point_passed_during_an_outage(tmp_path: Path) -> None:
    """Cut off 20-35 s, the robot passes P1's commit point (picks the item) at ~25 s: on its
    return the task is committed to it again, and it delivers."""
    m = load_mission(MISSIONS / "pick_and_deliver.yaml")
    _, rec = outage(m, "G1", 20.0, 35.0, until=50, controller="track")
    p1 = [(s, a) for _, s, a in task_states(rec, "P1")]
    assert p1[-3:] == [("open", None), ("committed", "G1"), ("done", "G1")]
    committed = [
        e for e in rec.of("task") if e.get("task") == "P1" and e.get("state") == "committed"
    ]
    assert committed[-1].t == pytest.approx(35.0) and 20 < committed[-1].get("reported_s") < 35
    assert "reported late by G1" in committed[-1].get("reason")
    assert rec.of("warning") == []


@pytest.mark.slow
def test_mine_inspection_r2_finishes_t3_while_cut_off() -> None:
    """Issue #13 §5, with the tracking controller: R2's link is down from 40 s; R2 finishes T3 at
    83.4 s, R1 (which got T3 at 43 s) would at 83.7 s. R2's completion arrives when its link
    returns at 83.5 s: T3 is done once, for R2, and R1 stops flying T3 in the same round."""
    m = load_mission(MISSIONS / "mine_inspection.yaml")
    _, rec = outage(m, "R2", 40.0, 83.5, until=86, controller="track")
    (done,) = done_events(rec, "T3")
    assert done.get("agent") == "R2" and done.t == pytest.approx(83.5)
    assert done.get("reported_s") == pytest.approx(83.4)
    holders = {a for _, s, a in task_states(rec, "T3") if s == "assigned"}
    assert holders == {"R2", "R1"}
    (w,) = rec.of("withdrawn")
    assert (w.get("agent"), w.get("task"), w.get("by")) == ("R1", "T3", "R2")
    r1 = executing(rec, "R1")
    t3_start = next(t for t, task in r1 if task == "T3")
    after = [(t, task) for t, task in r1 if t > t3_start]
    assert after and after[0][0] == pytest.approx(83.5) and after[0][1] != "T3"
    assert not [e for e in rec.of("progress") if e.get("task") == "T3" and e.get("agent") == "R1"]
