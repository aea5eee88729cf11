"""The run session, the command queue and the run's snapshots (issue #13 §2)."""

from __future__ import annotations

import dataclasses
import textwrap
import threading
from pathlib import Path
from typing import Any

import pytest

from btmission.diagnostics import SpecError
from btmission.missions import load_mission_text
from btmission.runtime.commands import (
    COMMANDS,
    AddTask,
    CancelTask,
    CommandError,
    KillAgent,
    RecallAgent,
    SetLink,
    SetPriority,
    Stop,
    command_from_data,
)
from btmission.runtime.events import Event, Recorder, read_events
from btmission.runtime.loops import AgentRuntime
from btmission.runtime.runner import MissionRun
from btmission.runtime.session import RunSession
from btmission.runtime.taskcheck import TaskError
from tests.system.test_runtime import ROBOTS as ROBOTS_OF_TEST_RUNTIME

ROBOTS = ROBOTS_OF_TEST_RUNTIME.replace(  # two ground robots, one task more, arriving at 30 s
    "  - {id: A, type: inspect, location: [12, 2, 0]}\n",
    "  - {id: A, type: inspect, location: [12, 2, 0]}\n"
    "  - {id: B, type: inspect, location: [12, 6, 0], at: 30}\n",
).replace("runtime: {controller: track}", "runtime: {controller: track, max_duration_s: 120}")


def robots(tmp_path: Path) -> Path:
    path = tmp_path / "robots.yaml"
    path.write_text(textwrap.dedent(ROBOTS).lstrip("\n"))
    return path


def commands_in(events: list[Event]) -> list[dict[str, Any]]:
    return [dict(e.data, t=e.t) for e in events if e.kind == "command"]


def last_state(events: list[Event], task: str) -> tuple[str | None, str | None]:
    evs = [e for e in events if e.kind == "task" and e.get("task") == task]
    return (evs[-1].get("state"), evs[-1].get("agent")) if evs else (None, None)


# ------------------------------------------------------------------------ the session
def test_a_session_runs_logs_reports_and_closes(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    with RunSession(robots(tmp_path), log_dir=logs) as s:
        run = s.start()
        assert run is not None and s.log_path is not None and s.log_path.parent == logs
        result = s.run()
        rep = s.report()
    assert result is not None and result.reason == "completed" and s.exit_code == 0
    assert rep.summary.tasks_done == 2 and rep.summary.end == "completed"
    events = read_events(s.log_path).events
    assert events[0].kind == "header" and events[-1].kind == "end"
    assert s.log is not None and s.log._fh is None  # closed by the with block


def test_a_mission_the_run_refuses_leaves_no_log(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(textwrap.dedent(ROBOTS).replace("library: ground", "library: nowhere"))
    logs = tmp_path / "logs"
    with RunSession(bad, log_dir=logs) as s, pytest.raises(SpecError) as err:
        s.start()
    assert "nowhere" in str(err.value)
    assert not logs.exists() or list(logs.iterdir()) == []


def test_the_session_closes_the_runs_services(tmp_path: Path) -> None:
    closed: list[str] = []

    class Service:
        def close(self) -> None:
            closed.append("closed")

    with RunSession(robots(tmp_path), log_dir=None) as s:
        run = s.start()
        assert run is not None
        run.services["ground"] = {"svc": Service(), "again": run.services.get("x", Service())}
        s.run(until=1.0)
    assert closed == ["closed", "closed"]  # two instances, each closed once


# ------------------------------------------------------------------------ commands
def test_commands_round_trip_as_plain_data() -> None:
    for name, cls in COMMANDS.items():
        fields = {f.name: f.type for f in dataclasses.fields(cls) if f.name != "by"}
        sample: dict[str, Any] = {}
        for f in fields:
            sample[f] = {"task": "T1", "agent": "R1", "priority": 2.0, "up": False}.get(f, "x")
        if name == "add_task":
            sample["task"] = {"id": "T9", "type": "inspect", "location": [1, 2, 0]}
        cmd = command_from_data(name, sample, by="console:ana")
        assert cmd.name == name and cmd.by == "console:ana" and cmd.to_data() == sample
    with pytest.raises(CommandError, match="unknown command 'fly'"):
        command_from_data("fly", {})
    with pytest.raises(CommandError, match="cancel_task"):
        command_from_data("cancel_task", {"tsk": "T1"})


def test_bad_commands_are_refused_when_submitted(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    run = MissionRun(m)
    with pytest.raises(CommandError, match=r"kill_agent: unknown agent 'R9' \(agents: G1, G2\)"):
        run.submit(KillAgent("R9"))
    with pytest.raises(CommandError, match="cancel_task: unknown task 'Z'"):
        run.submit(CancelTask("Z"))
    with pytest.raises(TaskError, match=r"^priority: Input should be greater than 0 \(got -1\)$"):
        run.submit(SetPriority("A", -1))
    with pytest.raises(TaskError, match=r"^id: duplicate task id 'A'$"):
        run.submit(AddTask({"id": "A", "type": "inspect", "location": [2, 2, 0]}))
    with pytest.raises(CommandError, match="unknown agent"):
        run.at(3.0, RecallAgent("nobody"))
    assert run.commands.empty()


def test_commands_are_applied_between_steps_and_logged(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    rec = Recorder()
    run = MissionRun(m, observers=[rec])
    run.at(2.0, CancelTask("B", by="console:ana"))  # before it arrives
    run.at(2.0, AddTask({"id": "C", "type": "inspect", "location": [6, 4, 0]}, by="console:ana"))
    run.at(3.0, SetPriority("C", 5.0, by="console:ana"))
    run.at(3.0, CancelTask("B"))  # already cancelled: refused when applied, and logged
    result = run.run()
    run.end(result)
    cmds = commands_in(rec.events)
    assert [(c["command"], c["ok"], c["t"]) for c in cmds] == [
        ("cancel_task", True, 2.0),
        ("add_task", True, 2.0),
        ("set_priority", True, 3.0),
        ("cancel_task", False, 3.0),
    ]
    assert cmds[0]["by"] == "console:ana" and cmds[1]["task"] == "C"
    assert cmds[3]["error"] == "cannot cancel task 'B': it is already cancelled"
    assert last_state(rec.events, "B")[0] == "cancelled"
    assert last_state(rec.events, "C")[0] == "done"
    assert result.reason == "completed" and result.cancelled == ["B"] and "B" not in result.open
    end = rec.of("end")[0]
    assert end.get("cancelled") == ["B"]
    pool = run.coordinator.state.pool
    assert pool["C"].info.priority == 5.0


def test_cancelling_a_held_task_stops_its_agent(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    rec = Recorder()
    run = MissionRun(m, observers=[rec])
    run.run(until=3.0)
    holder = run.coordinator.state.pool["A"].agent
    assert holder in ("G1", "G2") and run.agents[holder].task is not None
    run.cancel_task("A", "not needed any more")
    run.run(until=4.0)
    assert run.agents[holder].task is None
    state, agent = last_state(rec.events, "A")
    assert state == "cancelled" and agent is None
    switched = [e for e in rec.of("agent_task") if e.get("agent") == holder]
    assert switched[-1].get("task") is None and 3.0 <= switched[-1].t <= 3.2


def test_recall_sends_an_agent_home_at_once(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    rec = Recorder()
    run = MissionRun(m, observers=[rec])
    run.run(until=4.0)
    holder = run.coordinator.state.pool["A"].agent
    assert holder is not None
    far = run.snapshot.agent(holder).position
    run.recall_agent(holder)
    run.run(until=40.0)
    # its task went back to the pool and to the other robot; it took nothing more
    other = {"G1": "G2", "G2": "G1"}[holder]
    state, agent = last_state(rec.events, "A")
    assert (state, agent) == ("done", other)
    assert not [
        e
        for e in rec.of("task")
        if e.t > 4.0 and e.get("agent") == holder and e.get("state") == "assigned"
    ]
    # and went home (its start) straight away: no idle timeout
    start = m.agent(holder).start
    home = run.snapshot.agent(holder).position
    assert abs(home[0] - start[0]) < 0.5 and abs(home[1] - start[1]) < 0.5
    assert abs(far[0] - start[0]) > 1.0
    cmd = commands_in(rec.events)[0]
    assert cmd["command"] == "recall_agent" and cmd["agent"] == holder and cmd["ok"]


def test_link_and_kill_commands_keep_their_events(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    rec = Recorder()
    run = MissionRun(m, observers=[rec])
    run.at(1.0, SetLink("G2", False))
    run.at(2.0, SetLink("G2", True))
    run.at(3.0, KillAgent("G2", "battery"))
    run.run(until=5.0)
    assert [(e.t, e.get("up")) for e in rec.of("link")] == [(1.0, False), (2.0, True)]
    assert [(e.t, e.get("reason")) for e in rec.of("agent_lost")] == [(3.0, "battery")]
    assert not run.agents["G2"].alive and not run.snapshot.agent("G2").alive


# ------------------------------------------------------------------------ snapshots
def test_snapshots_are_immutable_and_follow_the_run(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    run = MissionRun(m)
    first = run.snapshot
    assert first.time_s == 0.0 and first.steps == 0 and first.ended is None
    run.run(until=5.0)
    snap = run.snapshot
    assert snap is not first and snap.time_s == pytest.approx(run.now())
    assert first.time_s == 0.0  # the old one did not change
    with pytest.raises(dataclasses.FrozenInstanceError):
        snap.time_s = 1.0  # type: ignore[misc]
    a = snap.task("A")
    held = run.coordinator.state.pool["A"]
    assert (a.state, a.agent) == (held.state.value, held.agent)
    with pytest.raises(KeyError):
        snap.task("B")  # not arrived yet
    g1 = snap.agent("G1")
    tel = run.agents["G1"].ctx.telemetry()
    assert g1.position == pytest.approx(tuple(tel.position)) and g1.link_up and g1.alive
    assert g1.mode == tel.mode.value
    assert dict(g1.tree) == dict(run.agents["G1"].tree_status) and g1.tree[0] == "RUNNING"
    assert len(g1.tree) == len(g1.tree_nodes) == len(run.agents["G1"].tree_nodes)
    assert g1.tree_nodes[0][1] == -1 and g1.tree_nodes[0][0] == "mission(G1)"
    result = run.run()
    run.end(result)
    assert run.snapshot.ended == "completed" and run.snapshot.counts() == {"done": 2}


def test_snapshots_are_published_at_most_every_period_and_fresh_on_the_stepping_thread(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fast run publishes a snapshot when SNAPSHOT_PERIOD_S of wall time has passed (other
    threads see that one); the thread that steps the run always reads the last step's."""
    import btmission.runtime.runner as runner_module

    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    run = MissionRun(m)
    monkeypatch.setattr(runner_module, "SNAPSHOT_PERIOD_S", 3600.0)  # none published by steps
    for _ in range(5):
        run.step()
    seen: list[Any] = []
    reader = threading.Thread(target=lambda: seen.append(run.snapshot))
    reader.start()
    reader.join()
    assert seen[0].steps == 0  # another thread: the one published at the start
    assert run.snapshot.steps == run.steps == 5  # the stepping thread: this step's
    monkeypatch.setattr(runner_module, "SNAPSHOT_PERIOD_S", 0.0)  # every step publishes
    run.step()
    reader = threading.Thread(target=lambda: seen.append(run.snapshot))
    reader.start()
    reader.join()
    assert seen[1].steps == run.steps == 6


def test_a_reader_thread_steers_the_run_through_snapshots_and_commands(tmp_path: Path) -> None:
    """Another thread reads snapshots while the loop runs and stops it with a command."""
    seen: list[float] = []
    asked: list[float] = []
    errors: list[BaseException] = []
    with RunSession(robots(tmp_path), log_dir=tmp_path / "logs") as s:
        run = s.start()
        assert run is not None

        def console() -> None:
            try:
                while True:
                    snap = s.snapshot
                    assert snap is not None
                    seen.append(snap.time_s)
                    if snap.time_s >= 8.0:
                        asked.append(snap.time_s)
                        s.submit(Stop("stopped by the operator", by="console:ana"))
                        return
                    if snap.ended:
                        return
                    threading.Event().wait(0.001)
            except BaseException as exc:
                errors.append(exc)

        reader = threading.Thread(target=console)
        reader.start()
        result = s.run()
        reader.join(timeout=30)
    assert not errors and not reader.is_alive()
    assert seen == sorted(seen) and len(seen) > 1
    assert result is not None and result.reason == "stopped by the operator"
    assert 8.0 <= asked[0] <= result.time_s  # how far the loop got meanwhile depends on load
    events = read_events(s.log_path).events  # type: ignore[arg-type]
    stop = commands_in(events)[-1]
    assert stop["command"] == "stop" and stop["by"] == "console:ana"
    step = run.dt
    assert result.time_s - step - 1e-9 <= stop["t"] <= result.time_s  # then it ended
    assert events[-1].kind == "end" and events[-1].get("reason") == "stopped by the operator"


# ------------------------------------------------------------------------ the two sides
def test_an_agent_side_steps_like_the_phases(tmp_path: Path) -> None:
    """AgentRuntime.step (what a process per agent runs) gives the same run, for one agent, as
    the in-process phases."""
    one = textwrap.dedent(ROBOTS).replace("  - {id: G2, library: ground, start: [1, 7, 0]}\n", "")

    def run_with(stepper: str) -> list[tuple[float, str, str]]:
        m = load_mission_text(one, str(tmp_path / "m.yaml"))
        rec = Recorder()
        run = MissionRun(m, observers=[rec])
        if stepper == "step":
            side: AgentRuntime = run.agent_sides[0]
            real = MissionRun.step

            def step(self: MissionRun) -> None:
                # run everything but the agents' phases, and the agent's side in one call
                phases = (side.tick, side.control, side.report)
                side.tick = side.control = lambda now: None  # type: ignore[method-assign]
                side.report = lambda now: False  # type: ignore[method-assign]
                try:
                    real(self)
                finally:
                    side.tick, side.control, side.report = phases  # type: ignore[method-assign]

            # the agent's side runs before the provider steps, like the phases
            provider_step = run.provider.step

            def sides_then(*a: Any) -> Any:
                side.step(run.now())
                return provider_step(*a)

            run.provider.step = sides_then  # type: ignore[method-assign]
            run.step = step.__get__(run)  # type: ignore[method-assign]
        run.run(until=20.0)
        return [
            (e.t, e.kind, str(e.get("task")))
            for e in rec.events
            if e.kind in ("task", "agent_task")
        ]

    assert run_with("phases") == run_with("step")


def test_leaves_see_a_narrow_view_of_their_agent(tmp_path: Path) -> None:
    """ctx.agent is an AgentView: the task and the reporting hooks, not the runtime's Agent."""
    from btmission.runtime.leaves import AgentView

    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    run = MissionRun(m)
    run.run(until=2.0)
    agent = run.agents["G1"]
    view = agent.ctx.agent
    assert isinstance(view, AgentView)
    assert view.id == "G1" and view.mission is m and view.task is agent.task
    for private in ("tick", "kill", "recall", "bus", "root", "bidder", "control_step"):
        assert not hasattr(view, private), private
    with pytest.raises(AttributeError):
        view.task = None  # type: ignore[misc]


def test_realtime_paces_one_step_per_step_of_wall_time(tmp_path: Path) -> None:
    """--realtime (and every real-vehicle provider) steps once per `runtime.sim.step_s` of wall
    time; a stop cuts the wait short."""
    import time

    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    run = MissionRun(m, realtime=True)
    t0 = time.perf_counter()
    result = run.run(until=0.5)
    wall = time.perf_counter() - t0
    assert result.reason == "until" and result.steps == 10
    assert wall >= 0.45  # ten steps of 0.05 s; never faster than the wall clock
    threading.Timer(0.2, run.stop, args=("stopped",)).start()
    t0 = time.perf_counter()
    result = run.run(until=60.0)
    assert result.reason == "stopped" and time.perf_counter() - t0 < 30.0
    assert 0.1 <= result.time_s - 0.5 < 30.0  # cut short of 60 s (how soon depends on load)


def test_a_task_added_can_be_steered_in_the_same_step(tmp_path: Path) -> None:
    """AddTask then SetPriority / CancelTask of it at the same time: both apply, in order."""
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    rec = Recorder()
    run = MissionRun(m, observers=[rec])
    run.at(1.0, AddTask({"id": "C", "type": "inspect", "location": [6, 4, 0]}))
    run.at(1.0, SetPriority("C", 4.0))
    run.at(1.0, AddTask({"id": "D", "type": "inspect", "location": [7, 4, 0]}))
    run.at(1.0, CancelTask("D"))
    run.run(until=2.0)
    cmds = commands_in(rec.events)
    assert [(c["command"], c["task"], c["ok"]) for c in cmds] == [
        ("add_task", "C", True),
        ("set_priority", "C", True),
        ("add_task", "D", True),
        ("cancel_task", "D", True),
    ]
    assert run.coordinator.state.pool["C"].info.priority == 4.0
    assert run.coordinator.state.pool["D"].state.value == "cancelled"
    run.submit(SetPriority("C", 2.0))  # known to the coordinator, not yet stepped: accepted


def test_commands_after_the_end_are_refused_and_leftovers_are_logged(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    rec = Recorder()
    run = MissionRun(m, observers=[rec])
    run.run(until=1.0)
    run.kill_agent("G2")  # queued; the run ends before its step
    run.stop("enough")
    run.end(run.result("enough"))
    cmds = commands_in(rec.events)
    assert [(c["command"], c["ok"], c.get("error")) for c in cmds] == [
        ("kill_agent", False, "not applied: the run had ended"),
        ("stop", True, None),
    ]
    assert run.agents["G2"].alive
    with pytest.raises(CommandError, match=r"kill_agent: the run has ended \(enough\)"):
        run.kill_agent("G2")
    with pytest.raises(CommandError, match="add_task: the run has ended"):
        run.add_task({"id": "Z", "type": "inspect", "location": [6, 4, 0]})


def test_a_run_whose_agents_are_all_recalled_ends_once_they_are_home(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    run = MissionRun(m)
    run.at(3.0, RecallAgent("G1"))
    run.at(3.0, RecallAgent("G2"))
    result = run.run()
    assert result.reason == "no agents left" and result.time_s < 60.0
    assert set(result.open) == {"A"} and result.pending == ["B"]
    for aid in ("G1", "G2"):
        start = m.agent(aid).start
        p = run.snapshot.agent(aid).position
        assert abs(p[0] - start[0]) < 0.5 and abs(p[1] - start[1]) < 0.5


def test_two_threads_adding_one_id_one_is_refused(tmp_path: Path) -> None:
    m = load_mission_text(textwrap.dedent(ROBOTS), str(tmp_path / "m.yaml"))
    run = MissionRun(m)
    for k in range(30):
        barrier = threading.Barrier(2)
        outcomes: list[str] = []

        def add(
            k: int = k, barrier: threading.Barrier = barrier, outcomes: list[str] = outcomes
        ) -> None:
            barrier.wait()
            try:
                run.add_task({"id": f"X{k}", "type": "inspect", "location": [6, 4, 0]})
                outcomes.append("ok")
            except TaskError as exc:
                outcomes.append(str(exc))

        threads = [threading.Thread(target=add) for _ in range(2)]
        for th in threads:
            th.start()
        for th in threads:
            th.join(timeout=10)
        assert sorted(outcomes) == [f"id: duplicate task id 'X{k}'", "ok"]


def test_the_report_shows_operator_commands(tmp_path: Path) -> None:
    from btmission.runtime.report import format_report, report_json

    with RunSession(robots(tmp_path), log_dir=tmp_path / "logs") as s:
        run = s.start()
        assert run is not None
        run.at(2.0, CancelTask("B", "not needed", by="console:ana"))
        run.at(3.0, CancelTask("B", by="console:bo"))  # refused: already cancelled
        s.run()
        rep = s.report()
    text = format_report(rep)
    table = text[text.index("Operator commands (2)") :].splitlines()
    assert table[1].split() == ["Time", "[s]", "By", "Command", "Arguments", "Result"]
    assert table[3].split() == ["2.0", "console:ana", "cancel_task", "task=B,", "reason=not",
                                "needed", "ok"]  # fmt: skip
    assert table[4].startswith("3.0") and table[4].endswith(
        "refused: cannot cancel task 'B': it is already cancelled"
    )
    assert [c["result"][:7] for c in report_json(rep)["commands"]] == ["ok", "refused"]
    assert "B" in text and "cancelled: not needed" in text  # the task's row says why
