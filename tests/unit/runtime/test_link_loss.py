"""Link loss without lost work (issue #13 §5) and leases (issue #37): progress and completions made
while an agent's link is down are queued on the agent and delivered when it returns; within its
lease the cut-off agent keeps its task (nobody else flies it); past it the task is re-offered,
the agent having stopped it first; the first completion wins, the other holder is withdrawn in
the same round; a dead agent never delivers, its task waits for its lease."""

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


def coordinator_link(rec: Recorder, agent: str) -> list[tuple[float, bool]]:
    return [(e.t, e.get("up")) for e in rec.of("coordinator_link") if e.get("agent") == agent]


def test_outage_during_a_task_the_agent_keeps_it_within_its_lease(tmp_path: Path) -> None:
    run, rec = outage(robots(tmp_path), "G1", 3.0, 8.0, until=28)
    # silent for agent_timeout_s (1 s), then 5 s in all: far within its lease (30 s), so A stays
    # G1's; G2 is never offered it
    assert [(s, a) for _, s, a in task_states(rec, "A")] == [("assigned", "G1"), ("done", "G1")]
    assert executing(rec, "G2") == []
    assert [e.get("agent") for e in rec.of("progress") if e.get("event") == "done"] == ["G1"]
    # G1 said it lost its coordinator (1 s after the last word) and when it had it back
    (lost, _), (back, _) = coordinator_link(rec, "G1")
    assert [up for _, up in coordinator_link(rec, "G1")] == [False, True]
    assert 3.0 + 1.0 <= lost <= 3.0 + 1.2 and back == pytest.approx(8.0)
    assert rec.of("warning") == [] and rec.of("withdrawn") == []
    assert run.agents["G1"].unacknowledged == []


def test_a_partition_within_the_lease_the_task_is_flown_once(tmp_path: Path) -> None:
    """The drill of issue #37: cut off 3-30 s, G1 finishes A at 27.6 s during the cut; the
    coordinator kept A with it (lease 30 s), so nobody flies A again and the completion,
    delivered on return, is the only one."""
    run, rec = outage(robots(tmp_path), "G1", 3.0, 30.0, until=31)
    g1_done = next(e for e in rec.of("progress") if e.get("agent") == "G1")
    assert g1_done.get("event") == "done" and 27 < g1_done.t < 30
    (done,) = done_events(rec, "A")
    assert done.get("agent") == "G1" and done.t == pytest.approx(30.0)  # delivered on return
    assert [(s, a) for _, s, a in task_states(rec, "A")] == [("assigned", "G1"), ("done", "G1")]
    assert executing(rec, "G2") == [] and rec.of("withdrawn") == []
    assert not [e for e in rec.of("progress") if e.get("agent") == "G2"]
    assert rec.of("warning") == []
    assert run.agents["G1"].unacknowledged == [] and run.coordinator.open_tasks() == []


def test_a_partition_past_the_lease_the_first_completion_wins(tmp_path: Path) -> None:
    # G1 stays silent until 50 s: it finishes A at 27.6 s, within its lease; the coordinator
    # re-offers A when the lease ends (30 s after G1's last bid) and G2 starts on it; G1's
    # completion arrives at 50 s and wins (counted once), G2 is withdrawn
    run, rec = outage(robots(tmp_path), "G1", 3.0, 50.0, until=52)
    released = next(e for e in rec.of("task") if e.get("state") == "open")
    assert 3.0 + 30.0 <= released.t <= 3.0 + 30.2
    assert released.get("reason").startswith("lease of G1 ran out (no word for 30.")
    (done,) = done_events(rec, "A")
    assert done.get("agent") == "G1" and done.t == pytest.approx(50.0)
    assert "reported late by G1" in done.get("reason") and "G2 withdrawn" in done.get("reason")
    (w,) = rec.of("withdrawn")
    assert (w.t, w.get("agent"), w.get("task"), w.get("by")) == (done.t, "G2", "A", "G1")
    assert executing(rec, "G2") == [(released.t, "A"), (pytest.approx(50.0), None)]
    assert not [e for e in rec.of("progress") if e.get("agent") == "G2"]
    assert run.agents["G1"].unacknowledged == []  # delivered and acknowledged at 50 s


def test_cut_off_past_its_lease_the_agent_stops_before_the_task_is_re_offered(
    tmp_path: Path,
) -> None:
    """Lease 10 s, G1 cut off 3-40 s (it would reach A at 27.6 s): it stops A
    agent_timeout_s before its lease ends, says so, and only then does the coordinator offer
    A to G2: never two agents on A at once; A is done once, by G2."""
    m = mission_text(
        ROBOTS.replace("agent_timeout_s: 1.0}", "agent_timeout_s: 1.0, lease_s: 10}"), tmp_path
    )
    run, rec = outage(m, "G1", 3.0, 40.0, until=50)
    g1, g2 = executing(rec, "G1"), executing(rec, "G2")
    assert g1[0] == (0.0, "A") and g1[1][1] is None
    stopped = g1[1][0]
    assert 3.0 + 9.0 <= stopped <= 3.0 + 9.2  # lease − guard (agent_timeout_s) after its last word
    (warning,) = rec.of("warning")
    assert warning.t == stopped and warning.get("message").startswith(
        "G1: its lease on A ran out (coordinator not heard for 9."
    )
    released = next(e for e in rec.of("task") if e.get("state") == "open")
    assert released.get("reason").startswith("lease of G1 ran out (no word for 10.")
    assert stopped < released.t and g2[0] == (released.t, "A")
    (done,) = done_events(rec, "A")
    assert done.get("agent") == "G2"
    assert [e.get("event") for e in rec.of("progress") if e.get("agent") == "G1"] == ["gave_up"]
    assert run.agents["G1"].unacknowledged == []  # its give-up delivered when the link returned


def test_a_dead_agent_never_delivers_its_task_is_redone_when_its_lease_ends(
    tmp_path: Path,
) -> None:
    rec = Recorder()
    run = MissionRun(robots(tmp_path), observers=[rec])
    run.at(8.0, lambda r: r.kill_agent("G1"))
    result = run.run(until=80)
    assert result.done == ["A"]
    released = next(e for e in rec.of("task") if e.get("state") == "open")
    assert 8.0 + 30.0 <= released.t <= 8.0 + 30.2  # its lease, not agent_timeout_s (1 s)
    assert released.get("reason").startswith("lease of G1 ran out")
    assert executing(rec, "G2")[0] == (released.t, "A")
    assert [e.get("agent") for e in done_events(rec, "A")] == ["G2"]
    assert not [e for e in rec.of("progress") if e.get("agent") == "G1"]
    assert rec.of("withdrawn") == [] and rec.of("warning") == []


def test_pick_and_deliver_delivery_during_an_outage_ends_done(tmp_path: Path) -> None:
    """The only robot is cut off 30-55 s: committed to P1 at ~25 s, it delivers at ~49 s; the
    delivery reaches the coordinator when the link returns (before: P1 stayed open forever).
    The cut is within its lease: P1 stays with it throughout."""
    m = load_mission(MISSIONS / "pick_and_deliver.yaml")
    run, rec = outage(m, "G1", 30.0, 55.0, until=56, controller="track")
    p1 = task_states(rec, "P1")
    assert [(s, a) for t, s, a in p1 if t >= 25.0] == [("committed", "G1"), ("done", "G1")]
    (done,) = done_events(rec, "P1")
    assert done.get("agent") == "G1" and done.t == pytest.approx(55.0)
    assert 30 < done.get("reported_s") < 55
    assert run.result("until").done == ["P1", "I1"]
    assert rec.of("warning") == []


def test_pick_and_deliver_commit_point_passed_during_an_outage(tmp_path: Path) -> None:
    """Cut off 20-35 s, the robot passes P1's commit point (picks the item) at ~25 s: its
    report arrives on its return (P1 stayed with it: the cut is within its lease), and it
    delivers."""
    m = load_mission(MISSIONS / "pick_and_deliver.yaml")
    _, rec = outage(m, "G1", 20.0, 35.0, until=50, controller="track")
    p1 = [(s, a) for t, s, a in task_states(rec, "P1") if t >= 20.0]
    assert p1 == [("committed", "G1"), ("done", "G1")]
    committed = [
        e for e in rec.of("task") if e.get("task") == "P1" and e.get("state") == "committed"
    ]
    assert committed[-1].t == pytest.approx(35.0) and 20 < committed[-1].get("reported_s") < 35
    assert rec.of("warning") == []


@pytest.mark.slow
def test_mine_inspection_a_20_s_partition_t3_is_flown_once() -> None:
    """The drill of issue #37 on the shipped mission (tracking controller): R2's link is down
    20 s (67.7-87.7 s) while it flies T3 and finishes it (85.6 s). Before leases, the
    coordinator released T3 after agent_timeout_s of silence and R1 flew it again; now T3
    stays R2's (lease 30 s), nobody else flies it, and R2's completion, delivered on return,
    is the only one."""
    m = load_mission(MISSIONS / "mine_inspection.yaml")
    _, rec = outage(m, "R2", 67.7, 87.7, until=90, controller="track")
    assert [(s, a) for _, s, a in task_states(rec, "T3")] == [("assigned", "R2"), ("done", "R2")]
    (done,) = done_events(rec, "T3")
    assert done.t == pytest.approx(87.7) and 67.7 < done.get("reported_s") < 87.7
    assert not [e for e in rec.of("agent_task") if e.get("task") == "T3" and e.get("agent") != "R2"]
    assert [e.get("agent") for e in rec.of("progress") if e.get("task") == "T3"] == ["R2"]
    assert [e.get("up") for e in rec.of("coordinator_link")] == [False, True]
    assert rec.of("withdrawn") == [] and rec.of("warning") == []


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
    s = AuctionState(AuctionConfig(agent_timeout_s=3.0, lease_s=4.0), TaskPool().add_all(tasks))
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


def test_a_lease_no_longer_than_the_agent_timeout_is_refused(tmp_path: Path) -> None:
    """The agent stops its task agent_timeout_s before its lease ends: validate says a lease
    that leaves no time for that is wrong, at the line."""
    from btmission.diagnostics import SpecError

    body = ROBOTS.replace("agent_timeout_s: 1.0}", "agent_timeout_s: 1.0, lease_s: 1.0}")
    assert body != ROBOTS
    with pytest.raises(SpecError) as err:
        mission_text(body, tmp_path)
    (diag,) = err.value.diagnostics
    assert diag.item == "coordination.lease_s" and diag.where.line == 13
    assert "must be longer than agent_timeout_s (1 s)" in diag.message
    assert mission_text(ROBOTS, tmp_path).spec.coordination.lease_s == 30.0  # the default
