"""A mission spread over processes (docs/distributed.md): the coordinator and agent processes
over Zenoh, their vehicles in one mavsim, their logs merged; and the fault drills of issue #17,
each with real processes on 127.0.0.1."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import time
from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from btmission.links.bus import Assignment, InMemoryBus
from btmission.missions import load_mission
from btmission.runtime.distribution import (
    CLOCK_FOLLOW_WALL_S,
    ClockFollower,
    MergeError,
    merge_logs,
    remote_bid_window,
    with_backends,
)
from btmission.runtime.events import Event
from btmission.vehicles.clock import ScaledWallClock
from tests.fleet_helpers import ME, CuttableProxy, Fleet, free_port, read_log, wait_for

ROOT = Path(__file__).resolve().parents[2]
SMALL = ROOT / "docs" / "examples" / "processes_small.yaml"


def ev(t: float, kind: str, **data: Any) -> Event:
    return Event(t, kind, data)


# ------------------------------------------------------------------------------------- pure
def test_merged_log_is_the_coordinators_with_the_agents_events_in_time_order() -> None:
    coord = [
        ev(0.0, "header", mission="m", part="coordinator"),
        ev(0.0, "built", map={}),
        ev(1.0, "round", round=1),
        ev(5.0, "task", task="T1", state="done"),
        ev(9.0, "end", reason="completed"),
    ]
    r1 = [
        ev(0.0, "header", mission="m", part="agents R1"),
        ev(0.0, "built", map={}),
        ev(0.5, "pose", agent="R1"),
        ev(4.9, "progress", agent="R1", task="T1", event="done"),
        ev(9.5, "tree", agent="R1"),  # after the mission's end: left out
        ev(9.6, "end", reason="completed"),
    ]
    r2 = [ev(0.0, "header", mission="m", part="agents R2"), ev(1.0, "pose", agent="R2")]
    merged = merge_logs(coord, [r1, r2])
    assert [(e.t, e.kind) for e in merged] == [
        (0.0, "header"), (0.0, "built"), (0.5, "pose"), (1.0, "round"), (1.0, "pose"),
        (4.9, "progress"), (5.0, "task"), (9.0, "end"),
    ]  # fmt: skip
    assert merged[0] is coord[0] and merged[-1] is coord[-1]
    with pytest.raises(MergeError, match="agent log 1 is of mission 'other'"):
        merge_logs(coord, [[ev(0.0, "header", mission="other")]])
    with pytest.raises(MergeError, match="an agent process's"):
        merge_logs(r1, [coord])
    # a coordinator killed before its end: every event, in time order
    cut = merge_logs(coord[:4], [r1])
    assert [e.kind for e in cut][-2:] == ["task", "tree"] and cut[-1].t == 9.5


def test_an_agent_clock_follows_the_coordinators_assignments() -> None:
    bus = InMemoryBus()
    clock = ScaledWallClock(10.0)
    seen: list[tuple[float, float]] = []
    link = ClockFollower(bus.agent_link("R1"), clock, lambda was, now: seen.append((was, now)))
    got: list[Assignment] = []
    link.connect(lambda a: None, got.append, lambda a: None)
    slack = CLOCK_FOLLOW_WALL_S * 10.0
    assert not link.synced
    bus.assign(Assignment(0.0, 1, {"R1": None}, _ann(), sent_s=120.0))
    assert link.synced and abs(clock.now() - 120.0) < 0.5 and len(got) == 1
    assert len(seen) == 1 and seen[0][1] == 120.0
    # ahead by less than the slack: left alone (no jumps from message latency)
    bus.assign(Assignment(0.0, 2, {"R1": None}, _ann(), sent_s=clock.now() + slack / 2))
    assert len(seen) == 1
    # an assignment that waited in the mailbox (older than the clock): never set back
    bus.assign(Assignment(0.0, 3, {"R1": None}, _ann(), sent_s=clock.now() - 5.0))
    assert len(seen) == 1 and clock.now() > 120.0
    # behind by more than the slack: set forward
    bus.assign(Assignment(0.0, 4, {"R1": None}, _ann(), sent_s=clock.now() + 3 * slack))
    assert len(seen) == 2 and seen[1][1] - seen[1][0] > 2 * slack
    # a coordinator of another epoch (restarted on another clock): followed, back too
    bus.assign(Assignment(0.0, 1, {"R1": None}, _ann(epoch=7), sent_s=50.0))
    assert len(seen) == 3 and abs(clock.now() - 50.0) < 0.5
    assert link.agent == "R1" and link.up and len(got) == 5


def _ann(epoch: int = 0) -> Any:
    from btmission.allocation.auction import Announcement

    return Announcement(epoch=epoch)


def test_backends_and_time_scale_are_replaced_for_one_process() -> None:
    m = load_mission(SMALL)
    out = with_backends(m, {"R2": "mavlink+udp://127.0.0.1:15000"}, 3.0)
    assert [a.backend for a in out.agents] == [m.agents[0].backend, "mavlink+udp://127.0.0.1:15000"]
    assert out.spec.runtime.mavlink.time_scale == 3.0 and m.spec.runtime.mavlink.time_scale == 5
    assert not out.spec.runtime.mavlink.map_sensors  # MAVLink agents: as the mission says
    sim = load_mission(ROOT / "missions" / "mine_inspection.yaml")
    flown = with_backends(sim, {"R1": "mavlink+udp://127.0.0.1:15001"}, None)
    assert flown.spec.runtime.mavlink.map_sensors  # a simulator agent keeps its LiDAR
    assert flown.spec.runtime.mavlink.time_scale == sim.spec.runtime.mavlink.time_scale
    assert remote_bid_window(1.0, 5.0) == 0.5 and remote_bid_window(10.0, 4.0) == 1.0


# ------------------------------------------------------------------------------ bad input
def _cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*ME, *args], capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["agent", str(SMALL), "--id", "R9"], "--id R9: no such agent in"),
        (["agent", str(SMALL), "--id", "R1", "--id", "R2", "--backend", "mavlink+udp://127.0.0.1:1"],
         "give exactly one --id"),
        (["agent", str(ROOT / "missions" / "mine_inspection.yaml"), "--id", "R1"],
         "agent R1's backend is sim, a simulator that lives in one process"),
        (["coordinator", str(ROOT / "missions" / "mine_haulage.yaml")],
         "run-wide services that every agent calls in one process"),
        (["coordinator", str(SMALL), "--listen", "tcp/127.0.0.1"], "listen tcp/127.0.0.1): invalid socket address"),
        (["run", str(SMALL), "--listen", "tcp/127.0.0.1:7447"], "--listen is the coordinator's"),
        (["run", str(SMALL), "--processes", "--view"], "--processes runs on the wall clock"),
        (["mavsim", "--mission", str(SMALL), "--backend", "R7=mavlink+udp://127.0.0.1:1"],
         "expected AGENT=URL with AGENT one of R1, R2"),
        (["mavsim", "--mission", str(SMALL), "--backend", "R1=udp:1"], "--backend R1=udp:1"),
    ],
)  # fmt: skip
def test_distributed_commands_refuse_bad_input(args: list[str], message: str) -> None:
    out = _cli(*args)
    assert out.returncode == 2, out.stderr
    assert message in out.stderr and "Traceback" not in out.stderr
    assert len([ln for ln in out.stderr.splitlines() if "Error" in ln]) == 1


def test_an_existing_log_file_is_never_overwritten(tmp_path: Path) -> None:
    log = tmp_path / "c.jsonl"
    log.write_text("keep\n")
    out = _cli("coordinator", str(SMALL), "--log-file", str(log))
    assert out.returncode == 2 and "exists already" in out.stderr
    assert log.read_text() == "keep\n"


def test_resume_refuses_a_log_it_cannot_continue(tmp_path: Path) -> None:
    example = ROOT / "docs" / "examples" / "pick_and_deliver.jsonl"
    out = _cli("coordinator", str(SMALL), "--resume", str(example))
    assert out.returncode == 2, out.stderr
    assert "not a log of processes_small's coordinator (mission 'pick_and_deliver'" in out.stderr
    lines = [json.loads(line) for line in example.read_text().splitlines()]
    lines[0].update(mission="processes_small", part="coordinator")
    ended = tmp_path / "ended.jsonl"
    ended.write_text("".join(json.dumps(e) + "\n" for e in lines))
    before = ended.read_bytes()
    out = _cli("coordinator", str(SMALL), "--resume", str(ended))
    assert out.returncode == 2, out.stderr
    assert "that run has ended (completed)" in out.stderr and "Traceback" not in out.stderr
    assert ended.read_bytes() == before  # nothing written


def test_an_agent_without_its_coordinator_says_so(tmp_path: Path) -> None:
    port = free_port(socket.SOCK_STREAM)
    out = _cli("agent", str(SMALL), "--id", "R1", "--connect", f"tcp/127.0.0.1:{port}",
               "--log", str(tmp_path))  # fmt: skip
    assert out.returncode == 1, out.stderr
    assert "cannot reach the coordinator" in out.stderr and f"127.0.0.1:{port}" in out.stderr
    assert list(tmp_path.iterdir()) == []  # nothing ran: no log


# ---------------------------------------------------------------------------- end to end
def _small(tmp: Path) -> str:
    """processes_small on free UDP ports (tests may run side by side)."""
    text = SMALL.read_text()
    for old in ("14660", "14661"):
        text = text.replace(old, str(free_port(socket.SOCK_DGRAM)))
    path = tmp / "processes_small.yaml"
    path.write_text(text)
    return str(path)


def _done_once(events: list[dict[str, Any]], tasks: set[str]) -> None:
    done = Counter(e["task"] for e in events if e["ev"] == "task" and e.get("state") == "done")
    assert set(done) == tasks and all(n == 1 for n in done.values()), done


@pytest.mark.slow
def test_run_processes_completes_with_every_task_done_once(tmp_path: Path) -> None:
    mission = _small(tmp_path)
    out = _cli("run", mission, "--processes", "--log", str(tmp_path), "--no-png", timeout=240)
    assert out.returncode == 0, out.stderr
    assert "Tasks done              3 of 3" in out.stdout
    [merged] = tmp_path.glob("processes_small-*-seed0.jsonl")
    [parts] = [p for p in tmp_path.iterdir() if p.is_dir()]
    assert {p.name for p in parts.glob("*.jsonl")} == {"coordinator.jsonl", "R1.jsonl", "R2.jsonl"}
    events = read_log(merged)
    assert events[0]["ev"] == "header" and events[0]["part"] == "coordinator"
    assert events[-1]["ev"] == "end" and events[-1]["reason"] == "completed"
    _done_once(events, {"T1", "T2", "T3"})
    assert {e["agent"] for e in events if e["ev"] == "pose"} == {"R1", "R2"}
    times = [e["t"] for e in events]
    assert times == sorted(times)
    # every agent process ended because the coordinator said so, its log closed
    for agent in ("R1", "R2"):
        log = read_log(parts / f"{agent}.jsonl")
        assert log[-1]["ev"] == "end" and log[-1]["reason"] == "completed"
    # report --merge gives the same report from the parts
    again = _cli("report", "--merge", str(parts / "coordinator.jsonl"), str(parts / "R1.jsonl"),
                 str(parts / "R2.jsonl"))  # fmt: skip
    assert again.returncode == 0 and "Tasks done              3 of 3" in again.stdout


@pytest.fixture
def fleet(tmp_path: Path) -> Any:
    f = Fleet(tmp_path, _small(tmp_path), speed=2.0)
    try:
        yield f
    finally:
        f.close()


def _assigned(log: list[dict[str, Any]], agent: str) -> str | None:
    """The task the coordinator's last round assigned to ``agent`` (None: none yet)."""
    for e in reversed(log):
        if e["ev"] == "round" and "assignments" in e:
            return e["assignments"].get(agent)  # type: ignore[no-any-return]
    return None


@pytest.mark.slow
def test_sigterm_ends_an_agent_alone_or_the_coordinator_and_then_its_agents(
    fleet: Fleet,
) -> None:
    fleet.start_all()
    wait_for("a first assignment", lambda: _assigned(fleet.log("coordinator"), "R1"), 90)
    # an agent process alone: it ends its own log; the mission goes on without it
    fleet.signal("R2", signal.SIGTERM)
    assert fleet.wait_exit("R2", 30) == 143
    r2 = fleet.log("R2")
    assert r2[-1]["ev"] == "end" and r2[-1]["reason"] == "terminated"
    assert any(e["ev"] == "command" and e.get("by") == "SIGTERM" for e in r2)
    assert fleet.procs["coordinator"].poll() is None and fleet.procs["R1"].poll() is None
    # the coordinator: it ends its log and the mission, and R1 ends with it
    fleet.signal("coordinator", signal.SIGTERM)
    assert fleet.wait_exit("coordinator", 30) == 143
    code = fleet.wait_exit("R1", 60)  # told by the coordinator's end, not by a signal
    r1 = fleet.log("R1")
    assert r1[-1]["ev"] == "end" and r1[-1]["reason"] == "terminated", r1[-1]
    assert not any(e["ev"] == "command" and e.get("by") == "SIGTERM" for e in r1)
    assert code == 143  # an agent process exits with its mission's status
    coord = fleet.log("coordinator")
    assert coord[-1]["ev"] == "end" and coord[-1]["reason"] == "terminated"
    assert any(e["ev"] == "command" and e.get("by") == "SIGTERM" for e in coord)


@pytest.mark.slow
def test_a_killed_agent_loses_its_task_and_a_restarted_one_registers_again(fleet: Fleet) -> None:
    fleet.start_all()
    wait_for("R1 to hold a task", lambda: _assigned(fleet.log("coordinator"), "R1"), 90)
    fleet.signal("R1", signal.SIGKILL)
    fleet.wait_exit("R1", 10)

    def released() -> str | None:
        """The task R1 held when it died, once the coordinator has put it back in the pool (not
        necessarily its first: a later round may have swapped R1's task for another)."""
        for e in fleet.log("coordinator"):
            if (
                e["ev"] == "task"
                and e.get("state") == "open"
                and ("lease of R1 ran out" in (e.get("reason") or ""))
            ):
                return str(e["task"])
        return None

    held = wait_for(
        "R1's task to return to the pool (its lease: 30 s of mission time)", released, 60
    )
    coord = fleet.log("coordinator")
    assert any(
        e["ev"] == "task" and e["task"] == held and e.get("agent") == "R1"
        and e.get("state") == "assigned"
        for e in coord
    ), f"{held} went back to the pool for R1, which never held it"  # fmt: skip
    fleet.start_agent("R1", name="R1-again")

    def back() -> bool:
        log = fleet.log("coordinator")
        kill = next(i for i, e in enumerate(log) if e["ev"] == "task" and e.get("state") == "open"
                    and "lease of R1 ran out" in (e.get("reason") or ""))  # fmt: skip
        return any(e["ev"] == "round" and e.get("agents") == 2 for e in log[kill:])

    wait_for("the restarted R1 in the auction again", back, 90)
    assert fleet.wait_exit("coordinator", 180) == 0
    coord = fleet.log("coordinator")
    assert coord[-1]["reason"] == "completed"
    _done_once(coord, {"T1", "T2", "T3"})
    never_two = _holders_never_two(coord)
    assert never_two, "a task was assigned to two agents in one round"


def _holders_never_two(log: list[dict[str, Any]]) -> bool:
    for e in log:
        if e["ev"] == "round" and "assignments" in e:
            held = [t for t in e["assignments"].values() if t is not None]
            if len(held) != len(set(held)):
                return False
    return True


@pytest.mark.slow
def test_an_agent_cut_off_for_20_s_keeps_its_task_and_reports_when_back(fleet: Fleet) -> None:
    """The partition drill of issue #37 over Zenoh: R1 cut off for 20 s of mission time (10 s
    of wall time at --speed 2), within its lease (30 s): it goes on with its task, says it lost
    and regained its coordinator, and nobody else is given its task meanwhile."""
    fleet.start_mavsim()
    fleet.start_coordinator()
    proxy = CuttableProxy(fleet.port)
    try:
        fleet.start_agent("R1", endpoint=f"tcp/127.0.0.1:{proxy.port}")
        fleet.start_agent("R2")
        task = wait_for("R1 to hold a task", lambda: _assigned(fleet.log("coordinator"), "R1"), 90)
        proxy.cut()
        cut_at = time.monotonic()
        time.sleep(20.0 / fleet.speed)
        during = fleet.log("R1")
        proxy.restore()
        # R1 went on with its task while cut off: it finished it (or was still at it)
        stages = [e for e in during if e["ev"] in ("stage", "progress") and e.get("task") == task]
        assert stages, "R1 did nothing with its task while its link was down"
        assert fleet.wait_exit("coordinator", 180) == 0
    finally:
        proxy.close()
    assert time.monotonic() - cut_at >= 20.0 / fleet.speed
    coord = fleet.log("coordinator")
    assert coord[-1]["reason"] == "completed"
    _done_once(coord, {"T1", "T2", "T3"})
    assert _holders_never_two(coord)
    # within its lease: R1's task was never re-offered, nobody was withdrawn from it
    assert not [e for e in coord if "lease of" in (e.get("reason") or "")]
    assert not [e for e in coord if e["ev"] == "withdrawn"]
    r1 = fleet.log("R1")
    links = [(e["t"], e["up"]) for e in r1 if e["ev"] == "coordinator_link"]
    assert [up for _, up in links[:2]] == [False, True], links
    (lost, _), (back, _) = links[:2]
    r2_on_it = [
        e for e in fleet.log("R2")
        if e["ev"] == "agent_task" and e.get("task") == task and lost <= e["t"] <= back
    ]  # fmt: skip
    assert not r2_on_it, "R2 was given R1's task while R1 was cut off"
    mine = [e for e in r1 if e["ev"] == "progress" and e["event"] == "done"]
    assert mine, "R1 completed nothing"
    # what R1 did while cut off reached the coordinator after the link came back
    took = {e["task"]: e for e in coord if e["ev"] == "task" and e.get("state") == "done"}
    for p in mine:
        assert p["task"] in took


@pytest.mark.slow
def test_a_coordinator_killed_and_restarted_from_its_log_completes_the_mission(
    fleet: Fleet,
) -> None:
    fleet.start_all()

    def one_done() -> bool:
        return any(e["ev"] == "task" and e.get("state") == "done" for e in fleet.log("coordinator"))

    wait_for("a first task done", one_done, 120)
    fleet.signal("coordinator", signal.SIGKILL)
    fleet.wait_exit("coordinator", 10)
    before = fleet.log("coordinator")
    assert before[-1]["ev"] != "end"
    time.sleep(2.0)  # the agents go on meanwhile, their reports queued
    log = fleet.dir / "coordinator.jsonl"
    fleet._start("coordinator-again", [*ME, "coordinator", fleet.mission, "--listen",
                                       fleet.endpoint, "--resume", str(log), "--speed",
                                       str(fleet.speed), "--quiet"])  # fmt: skip
    assert fleet.wait_exit("coordinator-again", 180) == 0, fleet.output("coordinator-again")
    after = fleet.log("coordinator")
    assert after[: len(before)] == before  # appended to, nothing rewritten
    assert [e["ev"] for e in after].count("header") == 1
    (resumed,) = [e for e in after if e["ev"] == "resumed"]
    assert resumed["last_s"] == before[-1]["t"] and resumed["t"] >= before[-1]["t"]
    assert after[-1]["ev"] == "end" and after[-1]["reason"] == "completed"
    _done_once(after, {"T1", "T2", "T3"})
    assert _holders_never_two(after[len(before) :])
    rounds = [e["round"] for e in after if e["ev"] == "round"]
    assert rounds == sorted(rounds) and len(set(rounds)) == len(rounds)  # counted on
    for agent in ("R1", "R2"):  # they were told the end by the restarted coordinator
        assert fleet.wait_exit(agent, 60) == 0


@pytest.mark.slow
def test_several_agents_in_one_process(fleet: Fleet) -> None:
    fleet.start_mavsim()
    fleet.start_coordinator()
    fleet._start("agents", [*ME, "agent", fleet.mission, "--id", "R1", "--id", "R2",
                            "--connect", fleet.endpoint, "--log-file",
                            str(fleet.dir / "agents.jsonl"), "--speed", str(fleet.speed),
                            "--quiet"])  # fmt: skip
    assert fleet.wait_exit("coordinator", 180) == 0
    assert fleet.wait_exit("agents", 60) == 0
    coord, agents = fleet.log("coordinator"), fleet.log("agents")
    _done_once(coord, {"T1", "T2", "T3"})
    assert agents[0]["part"] == "agents R1, R2"
    assert {e["agent"] for e in agents if e["ev"] == "pose"} == {"R1", "R2"}
    assert agents[-1]["ev"] == "end" and agents[-1]["reason"] == "completed"
