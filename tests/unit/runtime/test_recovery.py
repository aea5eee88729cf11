"""Coordinator restart (issue #17): the coordinator's state rebuilt from its event log
(btmission.runtime.recovery) matches the live coordinator's wherever the log is cut, and a
coordinator restored from it finishes the mission with every task done once."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from btmission.allocation.loop import Progress
from btmission.allocation.tasks import TaskPool, TaskState
from btmission.links.bus import InMemoryBus, ProgressAck
from btmission.missions import load_mission
from btmission.runtime.commands import (
    AddTask,
    CancelTask,
    ExcludeAgent,
    IncludeAgent,
    RecallAgent,
    SetAllocation,
    SetPriority,
)
from btmission.runtime.coordinator import Coordinator
from btmission.runtime.events import Event, read_events
from btmission.runtime.recovery import Recovered, logged_key, recover
from btmission.runtime.runner import MissionRun
from btmission.runtime.session import RunSession

ROOT = Path(__file__).resolve().parents[3]
PICK = ROOT / "missions" / "pick_and_deliver.yaml"
MINE = ROOT / "missions" / "mine_inspection.yaml"

View = dict[str, tuple[Any, ...]]


def view(pool: TaskPool) -> View:
    """Each task's state, holder, priority, arrival, fields and history (times as logged)."""
    return {
        t.id: (
            t.state,
            t.agent,
            t.info.priority,
            t.info.arrival_s,
            t.info.multi_stage,
            dict(t.info.fields),
            [(round(e.time_s, 4), e.state, e.agent, e.reason) for e in t.history],
        )
        for t in pool
    }


def assert_recovers(run: MissionRun, log: Path) -> Recovered:
    """recover() from the log as it stands gives the live coordinator's state."""
    rec = recover(run.mission, read_events(log).events)
    live = run.coordinator
    assert rec.problems == ()
    assert view(rec.pool) == view(live.state.pool)
    assert list(rec.pool.tasks) == list(live.state.pool.tasks)  # same order
    assert rec.round == live.state.round
    assert dict(rec.assignments) == live._last_assignments
    assert rec.holders() == live.state.holders()
    assert (rec.recalled, rec.excluded, rec.paused) == (
        live.recalled,
        live.state.excluded,
        live.paused,
    )
    assert rec.added == live._added
    assert dict(rec.seen) == {a: keys for a, keys in live._seen.items() if keys}
    for tid, n in rec.logged.items():  # what the live coordinator logged of each history
        assert live._history_len.get(tid, 1) == n or len(live.state.pool[tid].history) > n
    assert rec.time_s == pytest.approx(read_events(log).events[-1].t)
    return rec


def test_recovery_matches_the_live_coordinator_at_every_cut(tmp_path: Path) -> None:
    """pick_and_deliver with an operator's task, a cancel and priority changes, cut at several
    times (before and after the switch, the commit point and a completion)."""
    log = tmp_path / "run.jsonl"
    with RunSession(PICK, controller="track", log_path=log) as s:
        run = s.start()
        assert run is not None
        run.run(until=2.0)
        assert_recovers(run, log)
        run.submit(AddTask({"id": "X1", "type": "inspect", "location": [6, 2, 0]}))
        run.run(until=3.05)  # X1 added at 2 s; I1 arrived at 3 s and took G1 off P1
        rec = assert_recovers(run, log)
        assert rec.pool["X1"].info.arrival_s == 2.0 and rec.pool["X1"].state is TaskState.OPEN
        assert rec.pool["I1"].agent == "G1" and rec.pool["P1"].state is TaskState.OPEN
        # 5.1 s is a step without a round (9 Hz): the commands are applied, not logged by a
        # round yet — the cancel is in the history but the log has only its command
        run.run(until=5.1)
        rounds = run.coordinator.state.round
        run.submit(CancelTask("X1", "not needed"))
        run.submit(SetPriority("I2", 2.5))
        run.run(until=5.15)
        assert run.coordinator.state.round == rounds
        rec = assert_recovers(run, log)
        assert rec.pool["X1"].state is TaskState.CANCELLED and rec.pool["I2"].info.priority == 2.5
        assert rec.logged["X1"] == len(rec.pool["X1"].history) - 1  # the next round logs it
        for t in (9.65, 25.05, 41.0, 49.3):
            run.run(until=t)
            rec = assert_recovers(run, log)
        assert rec.pool["P1"].state is TaskState.DONE and rec.pool["I2"].agent == "G1"
        commit = next(e for e in rec.pool["P1"].history if e.state is TaskState.COMMITTED)
        assert commit.reason == "commit point"  # reported by the robot: a progress report
        assert ("P1", "committed", commit.time_s) in rec.seen["G1"]
        result = s.run()
        assert result is not None and result.reason == "completed"
        rec = assert_recovers(run, log)
    assert rec.pool["X1"].state is TaskState.CANCELLED
    assert rec.pool["X1"].history[-1].reason == "not needed"


def test_an_operators_task_to_arrive_later_is_recovered_with_its_arrival(tmp_path: Path) -> None:
    log = tmp_path / "run.jsonl"
    with RunSession(PICK, controller="track", log_path=log) as s:
        run = s.start()
        assert run is not None
        run.run(until=2.0)
        run.submit(AddTask({"id": "X2", "type": "inspect", "location": [6, 2, 0], "at": 30.0}))
        run.run(until=3.0)
        rec = assert_recovers(run, log)  # the live pool's arrival, 30 s, not 2 s
    assert rec.pool["X2"].info.arrival_s == 30.0


def test_recovery_follows_recall_pause_and_exclusion(tmp_path: Path) -> None:
    """mine_inspection, three drones: the operator recalls one (between two rounds), pauses
    and resumes allocation, excludes and includes another."""
    log = tmp_path / "mine.jsonl"
    with RunSession(MINE, controller="track", log_path=log) as s:
        run = s.start()
        assert run is not None
        run.at(20.0, AddTask({"id": "X1", "type": "inspect", "location": [100, 9.6, 2.5]}))
        run.at(60.05, RecallAgent("R2"))  # a step between two rounds (10 Hz)
        run.at(90.0, SetAllocation(True))
        run.at(100.0, SetAllocation(False))
        run.at(100.0, ExcludeAgent("R3"))
        run.at(115.0, IncludeAgent("R3"))
        seen: list[Recovered] = []
        for t in (30.0, 60.1, 60.2, 95.0, 110.0, 120.0):
            run.run(until=t)
            seen.append(assert_recovers(run, log))
    _, recalled, after, paused, excluded, included = seen
    held = recalled.pool["T3"]  # R2 held T3: back to the pool, not logged by a round yet
    assert (held.state, held.history[-1].reason) == (
        TaskState.OPEN,
        "agent R2 recalled by the operator",
    )
    assert recalled.logged["T3"] == len(held.history) - 1
    assert recalled.recalled == {"R2"} and "R2" not in recalled.holders()
    assert after.logged["T3"] == len(after.pool["T3"].history)  # logged now, once
    assert paused.paused and not excluded.paused and excluded.excluded == {"R3"}
    assert included.excluded == frozenset() and included.recalled == {"R2"}


def test_a_log_cut_in_the_middle_of_a_line_is_recovered_up_to_it(tmp_path: Path) -> None:
    """The coordinator died writing a round's line: the task events before it count, the
    round does not (its number is the next one)."""
    log = tmp_path / "run.jsonl"
    with RunSession(PICK, controller="track", log_path=log) as s:
        run = s.start()
        assert run is not None
        run.run(until=3.05)  # the round at 3 s moved G1 from P1 to I1
        live = assert_recovers(run, log)
    lines = log.read_bytes().splitlines(keepends=True)
    last = max(i for i, line in enumerate(lines) if b'"ev":"round"' in line)
    assert b'"assignments":{"G1":"I1"}' in lines[last]
    cut = tmp_path / "cut.jsonl"
    cut.write_bytes(b"".join(lines[:last]) + lines[last][: len(lines[last]) // 2])
    contents = read_events(cut)
    assert contents.truncated and contents.events[-1].kind == "task"
    rec = recover(run.mission, contents.events)
    assert rec.problems == ()
    assert rec.round == live.round - 1 and rec.assignments == {"G1": "P1"}
    assert view(rec.pool) == view(live.pool)  # the round's task events were written
    assert rec.holders() == {"G1": "I1"}


def test_events_the_pool_refuses_are_reported_not_forced() -> None:
    m = load_mission(PICK)

    def ev(t: float, kind: str, **data: Any) -> Event:
        return Event(t, kind, data)

    rec = recover(
        m,
        [
            ev(0.0, "task_added", task="P1", type="pick_and_deliver", fields={}, priority=1.0),
            ev(0.0, "task", task="P1", state="assigned", agent="G1", reason="won"),
            ev(0.0, "task", task="I1", state="assigned", agent="G1", reason="won"),
            ev(0.0, "round", round=1, announced=1, agents=1, method="dense", bids=1, step_ms=1.0,
               assignments={"G1": "P1"}),
            ev(1.0, "task", task="P1", state="done", agent="G1", reason="completed"),
            ev(2.0, "task", task="P1", state="assigned", agent="G2", reason="won"),
            ev(2.0, "task", task="Z9", state="open", agent=None, reason="?"),
            ev(2.0, "command", command="cancel_task", by="api", task="P1", ok=True),
            ev(2.0, "command", command="cancel_task", by="api", task="I1", ok=False),
        ],
    )  # fmt: skip
    assert rec.problems == (
        "t=0s round: agent G1 holds P1, I1",
        "t=2s task: cannot assign task 'P1': it is already done",
        "t=2s task: unknown task 'Z9'",
        "t=2s command: cannot cancel task 'P1': it is already done",
    )
    assert rec.pool["P1"].state is TaskState.DONE and rec.pool["P1"].agent == "G1"
    assert rec.pool["I1"].state is TaskState.ASSIGNED  # the refused cancel was not applied
    assert rec.seen == {"G1": frozenset({("P1", "done", 1.0)})}


# ------------------------------------------------------------------------ restarting
class _Down:
    """The coordinator's process is dead: no rounds, nothing taken from the bus."""

    def step(self, now: float) -> None:
        pass


def restart(run: MissionRun, events: list[Event]) -> Coordinator:
    """A new coordinator on the run's bus, restored from ``events``, in place of the old one."""
    new = Coordinator(
        run.mission, run.bus, run.now, run.emit_event, check_location=run.paths.problem,
        places=run.places,
    )  # fmt: skip
    rec = recover(run.mission, events)
    assert rec.problems == ()
    new.restore(rec)
    run.coordinator = new
    run.coordinator_side.coordinator = new
    return new


def record_progress(run: MissionRun) -> list[Progress]:
    """Every progress report the agents send (as sent: exact times)."""
    sent: list[Progress] = []
    send = run.bus.send_progress

    def recording(p: Progress) -> None:
        sent.append(p)
        send(p)

    run.bus.send_progress = recording  # type: ignore[method-assign,assignment]
    return sent


def assert_settled_once(events: list[Event], m: Any) -> Recovered:
    """The log of a run whose coordinator was restarted reads as one run: every task added
    once and done at most once, rounds numbered 1, 2, ... and after each round no agent holds
    two tasks and nothing done changed again (recover() checks both)."""
    rec = recover(m, events)
    assert rec.problems == ()
    added = Counter(e.get("task") for e in events if e.kind == "task_added")
    assert set(added.values()) == {1}
    done = Counter(e.get("task") for e in events if e.kind == "task" and e.get("state") == "done")
    assert set(done.values()) == {1}
    rounds = [e.get("round") for e in events if e.kind == "round"]
    assert rounds == list(range(1, len(rounds) + 1))
    assert not [e for e in events if e.kind == "warning"]
    return rec


def test_a_restarted_coordinator_finishes_pick_and_deliver(tmp_path: Path) -> None:
    """Killed at 48 s while its log's last round line was half written, down for 2.5 s (the
    robot delivers P1 meanwhile), restarted from that log: the delivery is taken once, I2 (added
    before the kill) is not added again, every report the robot had sent and is resent is
    recognised as a copy, and the mission completes."""
    log = tmp_path / "run.jsonl"
    with RunSession(PICK, controller="track", log_path=log) as s:
        run = s.start()
        assert run is not None
        sent = record_progress(run)
        run.run(until=48.0)
        assert run.coordinator.state.pool["P1"].state is TaskState.COMMITTED
        lines = log.read_bytes().splitlines(keepends=True)
        last = max(i for i, line in enumerate(lines) if b'"ev":"round"' in line)
        cut = tmp_path / "cut.jsonl"
        cut.write_bytes(b"".join(lines[:last]) + lines[last][:40])
        kept = read_events(cut).events
        old_round = run.coordinator.state.round
        run.coordinator_side.coordinator = _Down()  # type: ignore[assignment]
        run.run(until=50.5)
        assert [(p.task, p.event) for p in sent][-1] == ("P1", "done")  # made while down
        later = len(read_events(log).events)
        new = restart(run, kept)
        for p in list(sent):  # the robot resends what it sent (as if no ack had reached it)
            run.bus.send_progress(p)
        result = s.run()
    assert result is not None and result.reason == "completed"
    assert result.done == ["P1", "I1", "I2"]
    events = read_events(log).events
    after = events[later:]
    rounds = [e for e in after if e.kind == "round"]
    assert rounds[0].get("round") == old_round  # the half-written round, run again
    assert rounds[0].get("assignments") == {"G1": "I2"}  # P1 done, I2 won in that round
    rec = assert_settled_once(kept + after, run.mission)
    assert view(rec.pool) == view(new.state.pool)
    assert [e.get("task") for e in after if e.kind == "task_added"] == []
    done = [e for e in after if e.kind == "task" and e.get("state") == "done"]
    assert [e.get("task") for e in done] == ["P1", "I2"]
    assert done[0].t == pytest.approx(50.5) and done[0].get("reported_s") == pytest.approx(49.2)


def test_a_restarted_coordinator_keeps_the_operators_decisions(tmp_path: Path) -> None:
    """mine_inspection: an added task, a cancel, a priority, a recall and an exclusion before
    the restart; after it the recalled drone wins nothing, the excluded one nothing new until
    it is included again, and every task left is done once."""
    log = tmp_path / "mine.jsonl"
    with RunSession(MINE, controller="track", log_path=log) as s:
        run = s.start()
        assert run is not None
        run.at(20.0, AddTask({"id": "X1", "type": "inspect", "location": [100, 9.6, 2.5]}))
        run.at(30.0, CancelTask("T6"))
        run.at(30.0, SetPriority("T4", 3.0))
        run.at(60.05, RecallAgent("R2"))
        run.at(100.0, ExcludeAgent("R3"))
        run.run(until=105.0)
        before = read_events(log).events
        r3 = run.coordinator.state.holders().get("R3")
        new = restart(run, before)
        assert (new.recalled, new.state.excluded) == ({"R2"}, {"R3"})
        assert new.state.pool["T4"].info.priority == 3.0
        run.run(until=112.0)
        assert new.state.holders().get("R3") == r3  # kept what it held, won nothing else
        run.submit(IncludeAgent("R3"))

        def settled(r: MissionRun) -> None:
            if r.coordinator.settled(r.now()):
                r.stop("settled")

        result = s.run(progress=settled)
    assert result is not None and result.reason == "settled"
    events = read_events(log).events
    rec = assert_settled_once(events, run.mission)
    assert view(rec.pool) == view(new.state.pool)
    assert rec.pool["T6"].state is TaskState.CANCELLED and rec.pool["T4"].info.priority == 3.0
    assert {t.id for t in rec.pool if t.state is TaskState.DONE} == {
        "T1", "T2", "T3", "T4", "T5", "T7", "X1",
    }  # fmt: skip
    won = [
        (e.t, e.get("agent"))
        for e in events
        if e.kind == "task" and e.get("state") == "assigned" and e.t >= 105.0
    ]
    assert won and "R2" not in {a for _, a in won}
    assert not [t for t, a in won if a == "R3" and t < 112.0]
    assert [a for t, a in won if t >= 112.0].count("R3") >= 1  # included again: it wins


def test_a_resent_report_is_a_copy_whatever_the_digits_the_log_dropped() -> None:
    """The log keeps 4 decimals of a report's time; a copy resent with its exact time after a
    restart is still recognised (acknowledged with its own key, not applied again)."""
    m = load_mission(PICK)
    exact = 1.987654321
    written: list[tuple[float, str, dict[str, Any]]] = [
        (0.0, "task_added", {"task": "P1", "type": "pick_and_deliver", "fields": {}}),
        (0.0, "task", {"task": "P1", "state": "assigned", "agent": "G1", "reason": "won"}),
        (0.0, "round", {"round": 1, "assignments": {"G1": "P1"}}),
        (2.0, "task", {"task": "P1", "state": "done", "agent": "G1", "reason": "completed",
                       "reported_s": exact}),
        (2.0, "round", {"round": 2, "assignments": {}}),
    ]  # fmt: skip
    # as read back from a log (times rounded when written)
    logged = [Event.from_json(Event(t, kind, data).to_json()) for t, kind, data in written]
    rec = recover(m, logged)
    assert rec.problems == () and rec.seen == {"G1": {logged_key(("P1", "done", exact))}}
    assert logged_key(("P1", "done", exact)) == ("P1", "done", 1.9877)
    bus = InMemoryBus()
    acks: list[ProgressAck] = []
    bus.connect("G1", lambda ann: None, lambda a: None, acks.append)
    emitted: list[tuple[str, dict[str, Any]]] = []
    coord = Coordinator(m, bus, lambda: 2.1, lambda ev: emitted.append((ev.kind, ev.to_data())))
    coord.restore(rec)
    ann = coord.state.announcement  # its own epoch, serials after the predecessor's
    assert (ann.epoch, ann.serial) == (coord.epoch, 2)
    history = coord.state.pool["P1"].history
    bus.send_progress(Progress("G1", "P1", "done", exact))  # resent: no ack had reached G1
    coord.step(2.1)
    assert [k for k, _ in emitted] == ["round"] and emitted[0][1]["round"] == 3
    assert coord.state.pool["P1"].history == history
    assert acks == [ProgressAck("G1", (("P1", "done", exact),))]


def test_a_restarted_coordinator_leaves_a_silent_holder_its_task_for_its_lease(
    tmp_path: Path,
) -> None:
    """Issue #37: the coordinator is restarted at 10 s while G1, holding a task, is cut off:
    the new coordinator does not take the task from it at its first round (G1 has not bid
    yet) but when its lease ends, 30 s after the last round the old one logged."""
    log = tmp_path / "run.jsonl"
    with RunSession(PICK, controller="track", log_path=log) as s:
        run = s.start()
        assert run is not None
        run.run(until=10.0)
        (held,) = run.coordinator.state.holders().values()
        last_round = run.coordinator.state.board["G1"].time_s
        run.set_link("G1", False)
        later = len(read_events(log).events)
        restart(run, read_events(log).events)
        run.run(until=30.0)
        assert run.coordinator.state.holders() == {"G1": held}
        run.run(until=45.0)
    after = read_events(log).events[later:]
    released = [e for e in after if e.kind == "task" and e.get("state") == "open"]
    assert released[0].get("task") == held
    assert released[0].get("reason").startswith("lease of G1 ran out")
    assert last_round + 30.0 < released[0].t <= last_round + 30.0 + 0.2
    assert not [e for e in after if "is not bidding" in (e.get("reason") or "")]
