"""The event log (JSON Lines, flushed per event, survives a crash) and the report computed from it."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from btmission.runtime.events import (
    LOG_FORMAT,
    LOG_VERSION,
    Event,
    EventStream,
    JsonlEventLog,
    LogError,
    Recorder,
    read_events,
)
from btmission.runtime.report import (
    build_report,
    format_report,
    format_warnings,
    report_from_log,
    report_json,
    timeline_png,
    topview_png,
)

ROOT = Path(__file__).resolve().parents[3]
HEADER = {
    "format": LOG_FORMAT,
    "version": LOG_VERSION,
    "mission": "demo",
    "seed": 0,
    "controller": "track",
    "world": {"map": {"generate": "empty", "size": [10, 10, 3]}, "resolution": 0.5},
    "agents": [{"id": "R1", "start": [0, 0, 0]}, {"id": "R2", "start": [1, 0, 0]}],
    "tasks": [],
}


def story() -> list[Event]:
    """A short mission: T1 and T2 at 0 s, T3 at 10 s (unreachable), R2 hands T2 over to R1."""
    s = EventStream()
    rec = Recorder()
    s.subscribe(rec)
    s.emit(0.0, "header", **HEADER)
    s.emit(0.0, "task_added", task="T1", type="inspect", fields={"location": [5, 0, 2]})
    s.emit(0.0, "task_added", task="T2", type="inspect", fields={"location": [0, 5, 2]})
    s.emit(0.0, "task", task="T1", state="assigned", agent="R1", reason="won")
    s.emit(0.0, "task", task="T2", state="assigned", agent="R2", reason="won")
    s.emit(0.0, "agent_task", agent="R1", task="T1")
    s.emit(0.0, "agent_task", agent="R2", task="T2")
    s.emit(1.0, "pose", agent="R1", p=[0, 0, 0], odometer_m=0.0, clearance_m=None)
    s.emit(1.0, "pose", agent="R2", p=[1, 0, 0], odometer_m=0.0, clearance_m=1.5)
    s.emit(4.0, "pose", agent="R2", p=[1, 3, 2], odometer_m=3.7, clearance_m=0.8)
    s.emit(6.0, "task", task="T1", state="done", agent="R1", reason="completed")
    s.emit(6.0, "agent_task", agent="R1", task=None)
    s.emit(7.0, "task", task="T2", state="assigned", agent="R1", reason="reassigned from R2")
    s.emit(7.0, "agent_task", agent="R2", task=None)
    s.emit(7.0, "agent_task", agent="R1", task="T2")
    s.emit(8.0, "collision", agent="R1", other="R2", p=[2, 2, 2])
    s.emit(8.0, "collision", agent="R2", other="R1", p=[2, 2, 2])
    s.emit(9.0, "collision", agent="R2", other="rock", p=[1, 3, 2])
    s.emit(10.0, "task_added", task="T3", type="inspect", fields={"location": [9, 9, 9]})
    s.emit(10.1, "task", task="T3", state="unreachable", agent=None, reason="unreachable: no path")
    s.emit(12.0, "pose", agent="R1", p=[3, 3, 2], odometer_m=9.25, clearance_m=1.1)
    s.emit(15.0, "task", task="T2", state="done", agent="R1", reason="completed")
    s.emit(15.0, "agent_task", agent="R1", task=None)
    s.emit(20.0, "end", reason="finished with open tasks", wall_s=0.5)
    return rec.events


def test_tables_ii_and_iii_from_events() -> None:
    rep = build_report(story())
    rows = {r.task: r for r in rep.rows}
    assert [r.task for r in rep.rows] == ["T1", "T2", "T3"]
    assert (rows["T1"].added_s, rows["T1"].finished_s, rows["T1"].execution_s) == (0.0, 6.0, 6.0)
    assert rows["T1"].agent == "R1"
    # T2 was R2's first; R1 got it at 7 s and finished it: execution counts from then
    assert (rows["T2"].finished_s, rows["T2"].execution_s, rows["T2"].agent) == (15.0, 8.0, "R1")
    assert rows["T3"].state == "unreachable" and rows["T3"].reason == "unreachable: no path"
    assert rows["T3"].added_s == 10.0 and rows["T3"].finished_s is None
    s = rep.summary
    assert s.duration_s == 20.0 and s.end == "finished with open tasks"
    assert s.distance_m == pytest.approx(9.25 + 3.7)
    assert rep.distance_by_agent == {"R1": 9.25, "R2": 3.7}
    assert (s.agents, s.tasks, s.tasks_done) == (2, 3, 2)
    assert s.min_clearance_m == 0.8
    assert s.collisions == 2  # R1-R2 counted once, plus R2 against rock
    assert rep.intervals["R1"] == [("T1", 0.0, 6.0, "done"), ("T2", 7.0, 15.0, "done")]
    assert rep.intervals["R2"] == [("T2", 0.0, 7.0, "left")]
    text = format_report(rep)
    assert "T3" in text and "unreachable: no path" in text and "12.9 m" in text


def test_log_is_one_json_object_per_line_flushed_as_written(tmp_path: Path) -> None:
    path = tmp_path / "x.jsonl"
    log = JsonlEventLog(path)
    events = story()
    for ev in events[:5]:
        log.on_event(ev)
        # flushed: another reader sees every event at once, the file open
        assert len(path.read_text().splitlines()) == log.count
    for ev in events[5:]:
        log.on_event(ev)
    log.close()
    lines = path.read_text().splitlines()
    assert len(lines) == len(events)
    objs = [json.loads(line) for line in lines]
    assert all(isinstance(o, dict) and {"t", "ev"} <= set(o) for o in objs)
    back = read_events(path).events
    assert [(e.t, e.kind, dict(e.data)) for e in back] == [
        (e.t, e.kind, json.loads(json.dumps(dict(e.data)))) for e in events
    ]
    assert report_json(report_from_log(path)) == report_json(build_report(events))


def test_non_finite_numbers_and_arrays_become_json(tmp_path: Path) -> None:
    import numpy as np

    ev = Event(1.23456, "pose", {"p": np.array([1.0, 2.0, 3.0]), "c": math.inf, "n": np.int64(3)})
    assert json.loads(ev.to_json()) == {
        "t": 1.2346,
        "ev": "pose",
        "p": [1.0, 2.0, 3.0],
        "c": None,
        "n": 3,
    }


def test_a_truncated_log_still_gives_a_report(tmp_path: Path) -> None:
    path = tmp_path / "cut.jsonl"
    text = "\n".join(e.to_json() for e in story()[:-1])  # no end event...
    path.write_text(text + '\n{"t": 20.5, "ev": "po')  # ...and a half-written last line
    contents = read_events(path)
    assert contents.truncated and contents.events[-1].kind == "agent_task"
    rep = report_from_log(path)
    assert rep.truncated and rep.summary.end == "log ends" and rep.summary.duration_s == 15.0
    assert "cut off" in "\n".join(format_warnings(rep)) and "cut off" not in format_report(rep)


def test_files_that_are_not_logs(tmp_path: Path) -> None:
    with pytest.raises(LogError, match="no such log file"):
        read_events(tmp_path / "none.jsonl")
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"t": 0, "ev": "pose"}\n')
    with pytest.raises(LogError, match="header"):
        read_events(bad)
    old = tmp_path / "old.jsonl"
    old.write_text(json.dumps({"t": 0, "ev": "header", "format": LOG_FORMAT, "version": 99}) + "\n")
    with pytest.raises(LogError, match="version 99"):
        read_events(old)


def test_report_pngs(tmp_path: Path) -> None:
    rep = build_report(story())
    for draw, name in ((timeline_png, "t.png"), (topview_png, "v.png")):
        out = draw(rep, tmp_path / name)
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _start_run(logs: Path, cwd: Path, *extra: str, **popen: object) -> subprocess.Popen[str]:
    """``btmission run missions/pick_and_deliver.yaml`` in a subprocess, paced to the wall clock."""
    return subprocess.Popen(  # type: ignore[call-overload, no-any-return]
        [
            sys.executable,
            "-m",
            "btmission.cli.main",
            "run",
            str(ROOT / "missions/pick_and_deliver.yaml"),
            "--log",
            str(logs),
            "--quiet",
            "--realtime",
            "--controller",
            "track",
            *extra,
        ],
        cwd=cwd,
        text=True,
        **popen,
    )


def _wait_for_poses(logs: Path, timeout_s: float = 60.0, after_s: float = -1.0) -> Path | None:
    """The run's log once it holds a pose event later than ``after_s`` of mission time."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = list(logs.glob("*.jsonl")) if logs.exists() else []
        lines = found[0].read_text().splitlines() if found else []
        poses = [line for line in lines if '"ev":"pose"' in line]
        try:
            if poses and json.loads(poses[-1])["t"] > after_s:
                return found[0]
        except ValueError:  # the line being written
            pass
        time.sleep(0.2)
    return None


def test_a_killed_run_leaves_a_log_the_report_reads(tmp_path: Path) -> None:
    """Kill ``btmission run`` mid-mission (SIGKILL: no cleanup at all); the report computes."""
    logs = tmp_path / "logs"
    proc = _start_run(logs, tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        log = _wait_for_poses(logs, after_s=1.5)  # let it run a few (real-time) seconds
        assert log is not None, "the run never started logging"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    rep = report_from_log(log)
    assert rep.summary.end == "log ends" and rep.summary.duration_s > 1.0
    assert {r.task for r in rep.rows} >= {"P1"}
    assert any(r.agent == "G1" for r in rep.rows)


def test_ctrl_c_ends_the_run_cleanly_with_the_report(tmp_path: Path) -> None:
    """SIGINT (Ctrl-C): exit 130, the log ends with an 'interrupted' end event, and the report of
    what happened so far is printed."""
    logs = tmp_path / "logs"
    proc = _start_run(logs, tmp_path, "--no-png", stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert _wait_for_poses(logs) is not None
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Tasks (seed 000 Table III)" in out and "ended: interrupted" in out
    log = next(logs.glob("*.jsonl"))
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    last = lines[-1]
    assert last["ev"] == "end" and last["reason"] == "interrupted"
    stops = [x for x in lines if x["ev"] == "command"]  # the operator's action is in the log
    assert [(x["command"], x["by"], x["reason"], x["ok"]) for x in stops] == [
        ("stop", "SIGINT", "interrupted", True)
    ]
