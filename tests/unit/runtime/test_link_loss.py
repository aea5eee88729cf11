"""Link loss without lost work (issue #13 §5): progress and completions made while an agent's link
is down are queued on the agent and delivered when it returns; the first completion wins, the
other holder is withdrawn in the same round; a dead agent never delivers."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import pytest

from btmission.allocation.auction import AuctionConfig, AuctionState, Bid, auction_round
from btmission.allocation.loop import Progress, Withdrawal, apply_progress
from btmission.allocation.tasks import TaskInfo, TaskPool, TaskState
from btmission.links.bus import ProgressAck
from btmission.missions import load_mission
from btmission.runtime.events import Event, Recorder
from btmission.runtime.runner import MissionRun
from btmission.spec.mission import Mission
from tests.system.test_runtime import ROBOTS, mission_text

ROOT = Path(__file__).resolve().parents[3]
MISSIONS = ROOT / "missions"

# G1 (closer) wins A at t=0 and, with its link up, reaches it at t=27.6 s; G2 would at ~34 s.


def robots(tmp_path: Path) -> Mission:
    """Two ground robots, one task A (tests/system/test_runtime.py)."""
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
    assert warning.get("message").startswith(
        "G1 reports 'A' done (finished at t=27.6s), but G2's completion (finished at t=34.4s) "
        "reached the coordinator first"
    )
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
    87.6 s, while R1 (which got T3 at 43 s) is still on its way (at 95 s too). R2's completion
    arrives when its link returns at 87.7 s: T3 is done once, for R2, and R1 stops flying T3 in
    the same round. (Since the separation rule of #36 item 9, R2 leaves its pad more slowly: it
    finished at 83.4 s before, and the link returned at 83.5 s.)"""
    m = load_mission(MISSIONS / "mine_inspection.yaml")
    _, rec = outage(m, "R2", 40.0, 87.7, until=90, controller="track")
    (done,) = done_events(rec, "T3")
    assert done.get("agent") == "R2" and done.t == pytest.approx(87.7)
    assert done.get("reported_s") == pytest.approx(87.6)
    holders = {a for _, s, a in task_states(rec, "T3") if s == "assigned"}
    assert holders == {"R2", "R1"}
    (w,) = rec.of("withdrawn")
    assert (w.get("agent"), w.get("task"), w.get("by")) == ("R1", "T3", "R2")
    r1 = executing(rec, "R1")
    t3_start = next(t for t, task in r1 if task == "T3")
    after = [(t, task) for t, task in r1 if t > t3_start]
    assert after and after[0][0] == pytest.approx(87.7) and after[0][1] != "T3"
    assert not [e for e in rec.of("progress") if e.get("task") == "T3" and e.get("agent") == "R1"]


def test_lost_acknowledgements_the_agent_resends_and_copies_are_ignored(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A lossy transport: every acknowledgement is lost until 30 s. G1 resends its completion
    (27.6 s) every second until one gets through; the coordinator takes it once."""
    rec = Recorder()
    run = MissionRun(robots(tmp_path), observers=[rec])
    bus = run.bus
    received: list[tuple[float, Progress]] = []
    send, acknowledge = bus.send_progress, bus.acknowledge

    def counted(p: Progress) -> None:
        received.append((run.now(), p))
        send(p)

    def lossy(ack: ProgressAck) -> None:
        if run.now() >= 30.0:
            acknowledge(ack)

    monkeypatch.setattr(bus, "send_progress", counted)
    monkeypatch.setattr(bus, "acknowledge", lossy)
    run.run(until=32)
    sent = [t for t, p in received if (p.agent, p.task, p.event) == ("G1", "A", "done")]
    # sent at 27.6 s, then every ~1 s (at the next tick) until the first ack after 30 s
    assert sent[0] == pytest.approx(27.6) and len(sent) == 4 and 30 < sent[-1] < 31
    assert all(1.0 <= b - a <= 1.1 + 1e-9 for a, b in pairwise(sent))
    assert len({(p.task, p.event, p.time_s) for _, p in received}) == 1
    assert [e.get("agent") for e in done_events(rec, "A")] == ["G1"]
    assert rec.of("warning") == [] and run.agents["G1"].unacknowledged == []


def two_holders() -> AuctionState:
    """G1 held A and G3 held P (multi-stage) until they went silent; now G2 holds A, G4 P."""
    tasks = [TaskInfo("A", "inspect", {}), TaskInfo("P", "pick", {}, multi_stage=True)]
    s = AuctionState(AuctionConfig(agent_timeout_s=3.0), TaskPool().add_all(tasks))
    _, s, _ = auction_round(s, [Bid.of("G1", 0, {"A": 1.0}), Bid.of("G3", 0, {"P": 1.0})], 0)
    assert s.holders() == {"G1": "A", "G3": "P"}
    _, s, r = auction_round(s, [Bid.of("G2", 5, {"A": 3.0}), Bid.of("G4", 5, {"P": 2.0})], 5)
    assert r.dropped == ("G1", "G3") and s.holders() == {"G2": "A", "G4": "P"}
    return s


def test_a_late_report_counts_only_from_a_former_holder() -> None:
    withdrawn: list[Withdrawal] = []
    late, problems = apply_progress(
        two_holders(),
        [
            Progress("G5", "A", "done", 5.5),  # never held A: refused
            Progress("G1", "A", "done", 4.5),  # G1 held A before G2: the first completion wins
            Progress("G2", "A", "done", 5.6),  # too late: counted once, for G1
            Progress("G3", "P", "failed", 4.6, "blocked"),  # a late failure is not taken
        ],
        withdrawn,
    )
    a = late.pool["A"]
    assert (a.state, a.agent, a.history[-1].time_s) == (TaskState.DONE, "G1", 4.5)
    assert a.note == "completed (reported late by G1, which had lost it while silent; G2 withdrawn)"
    assert withdrawn == [Withdrawal("G2", "A", "G1", "done")]
    assert problems == [
        "agent 'G5' cannot complete task 'A': it is held by G2",
        "G2 reports 'A' done (finished at t=5.6s), but G1's completion (finished at t=4.5s) "
        "reached the coordinator first: counted once, for G1",
        "agent 'G3' cannot fail task 'P': it is held by G4",
    ]
    assert late.pool["P"].state is TaskState.ASSIGNED and late.pool["P"].agent == "G4"


def test_a_late_commit_point_takes_the_task_back_unless_another_committed() -> None:
    withdrawn: list[Withdrawal] = []
    back, problems = apply_progress(
        two_holders(), [Progress("G3", "P", "committed", 4.5)], withdrawn
    )
    assert problems == [] and withdrawn == [Withdrawal("G4", "P", "G3", "committed")]
    assert (back.pool["P"].state, back.pool["P"].agent) == (TaskState.COMMITTED, "G3")
    assert withdrawn[0].reason == "G3 committed to 'P' first (reported after its link returned)"
    _, problems = apply_progress(
        two_holders(),
        [Progress("G4", "P", "committed", 5.5), Progress("G3", "P", "committed", 4.5)],
    )
    assert problems == ["agent 'G3' cannot commit to task 'P': it is held by G4"]
