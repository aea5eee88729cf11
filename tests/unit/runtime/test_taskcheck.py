"""The one check of a task added to a running mission (btmission.runtime.taskcheck): every way
in takes it, ids are reserved atomically, a refused task leaves nothing behind, and the task the
pool gets is the one that was checked. (Parity with the mission file and the console, over HTTP
and the CLI: tests/unit/console/test_console.py.)"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from btmission.allocation.tasks import TaskInfo
from btmission.runtime.commands import AddTask, SetPriority
from btmission.runtime.events import Recorder
from btmission.runtime.runner import MissionRun
from btmission.runtime.taskcheck import TOO_MANY, TaskError
from tests.system.test_runtime import ROBOTS, mission_text

BAD = {"id": "X", "type": "inspect", "location": [3, 3, 0], "colour": "red"}
"""A task the mission file refuses (a key its type does not use)."""
BAD_MESSAGE = (
    "colour: unknown key 'colour' for a task of type 'inspect' (expected: id, type, at, "
    "priority, location)"
)


def _run(tmp_path: Path) -> tuple[MissionRun, Recorder]:
    rec = Recorder()
    return MissionRun(mission_text(ROBOTS, tmp_path), observers=[rec]), rec


def test_every_way_in_gives_the_mission_files_message(tmp_path: Path) -> None:
    """add_task, submit and at (the console's and the CLI's way is submit's: test_console)."""
    run, rec = _run(tmp_path)
    for way in (
        run.add_task,
        lambda t: run.submit(AddTask(t)),
        lambda t: run.port.add_task(t, "x"),
    ):
        with pytest.raises(TaskError) as refused:
            way(BAD)
        assert (str(refused.value), refused.value.field) == (BAD_MESSAGE, "colour")
    run.at(0.5, AddTask(BAD, by="script"))
    run.run(until=1.0)
    commands = [e for e in rec.events if e.kind == "command"]
    assert [(c.get("ok"), c.get("error"), c.get("task")) for c in commands] == [
        (False, BAD_MESSAGE, "X")
    ]


def test_a_refused_task_leaves_nothing_behind(tmp_path: Path) -> None:
    """Refused: not in the pool, its id not reserved, nothing queued, nothing logged but the
    refusal of a scripted add."""
    run, rec = _run(tmp_path)
    for bad in (
        BAD,
        {"id": "X", "type": "inspect", "location": [30, 3, 0]},  # outside the map
        {"id": "X", "type": "inspect", "location": [3, 3, 0], "priority": 1e300},
        {"id": "X", "type": "inspect", "location": [3, 3, 0], "at": float("inf")},
    ):
        with pytest.raises(TaskError):
            run.add_task(bad)
        assert not run.knows_task("X") and run.commands.empty()
        assert not run.port.tasks.waiting
    run.run(until=1.0)
    assert "X" not in run.coordinator.state.pool
    assert not [e for e in rec.events if e.kind == "command"]
    assert [e.get("task") for e in rec.events if e.kind == "task_added"] == ["A"]  # the file's
    # the same id, now good: taken
    info = run.add_task({"id": "X", "type": "inspect", "location": [3, 3, 0]})
    assert run.knows_task("X") and run.port.tasks.waiting and "X" not in run.coordinator.state.pool
    run.run(until=1.5)
    assert run.coordinator.state.pool["X"].info == info and not run.port.tasks.waiting
    added = [e for e in rec.events if e.kind == "task_added" and e.get("task") == "X"]
    assert len(added) == 1 and added[0].get("by") == "api"


def test_the_pool_gets_the_task_as_checked(tmp_path: Path) -> None:
    """What was checked is what enters: a TaskInfo is checked as a mapping is, numpy values and
    tuples are plain data, a priority by name is the type's times its level, the arrival is not
    before the time it was added."""
    run, _ = _run(tmp_path)
    run.run(until=1.0)
    got = run.add_task(
        {"id": "N", "type": "inspect", "location": np.array([3.0, 3.0, 0.0]), "priority": "urgent"}
    )
    assert got == TaskInfo("N", "inspect", {"location": [3.0, 3.0, 0.0]}, 4.0, 1.0)
    later = run.add_task(TaskInfo("L", "inspect", {"location": (4, 4, 0)}, 2.0, 30.0))
    assert later == TaskInfo("L", "inspect", {"location": [4, 4, 0]}, 2.0, 30.0)
    with pytest.raises(TaskError, match=r"^where: unknown key 'where'"):
        run.add_task(TaskInfo("W", "inspect", {"location": [4, 4, 0], "where": 1}))
    with pytest.raises(TaskError, match=r"^a task holds numbers, strings, lists and mappings"):
        run.add_task({"id": "S", "type": "inspect", "location": {1, 2, 3}})
    run.run(until=1.5)
    pool = run.coordinator.state.pool
    assert pool["N"].info == got and pool["L"].info == later


def test_two_threads_adding_without_ids_get_two_ids(tmp_path: Path) -> None:
    run, _ = _run(tmp_path)
    barrier = threading.Barrier(8)
    ids: list[str] = []

    def add() -> None:
        barrier.wait()
        ids.append(run.add_task({"type": "inspect", "location": [5, 5, 0]}).id)

    threads = [threading.Thread(target=add) for _ in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=10)
    assert sorted(ids) == [f"T{i}" for i in range(1, 9)]
    assert run.port.tasks.next_id("inspect") == "T9"


def test_the_coordinator_takes_no_task_twice(tmp_path: Path) -> None:
    """A checked task whose id the pool has (a caller that went around the check) is refused
    when applied, and logged so; the pool keeps the first."""
    run, rec = _run(tmp_path)
    run.commands.put(AddTask(TaskInfo("A", "inspect", {"location": [1, 1, 0]})))
    run.run(until=0.5)
    (command,) = [e for e in rec.events if e.kind == "command"]
    assert command.get("ok") is False and command.get("error") == "id: duplicate task id 'A'"
    assert run.coordinator.state.pool["A"].info.fields == {"location": [12, 2, 0]}


def test_a_task_queued_keeps_the_run_going(tmp_path: Path) -> None:
    """Every task done and every agent at rest, but a task added and not yet in the pool: the
    run is not over (it ends once that one is done too)."""
    run, _ = _run(tmp_path)
    first = run.run()
    assert first.reason == "completed"
    run.add_task({"id": "Z", "type": "inspect", "location": [6, 4, 0]})
    assert run.finished() is None
    second = run.run()
    assert second.reason == "completed" and "Z" in second.done


def test_a_new_priority_has_the_bounds_of_an_added_tasks(tmp_path: Path) -> None:
    """SetPriority (the console's PATCH) and an added task share the bounds and messages."""
    run, _ = _run(tmp_path)
    for value in (0, -1, 1e300, True, "huge"):
        with pytest.raises(TaskError) as added:
            run.add_task({"id": "P", "type": "inspect", "location": [3, 3, 0], "priority": value})
        with pytest.raises(TaskError) as changed:
            run.submit(SetPriority("A", value))
        with pytest.raises(TaskError) as scheduled:
            run.at(3.0, SetPriority("A", value))  # refused when scheduled, not at 3 s
        assert changed.value.field == added.value.field == "priority"
        assert str(changed.value) == str(added.value).replace("task 'P'", "task 'A'")
        assert str(scheduled.value) == str(changed.value)
    assert run.commands.empty()
    run.submit(SetPriority("A", "high"))  # a name: twice the type's (1)
    run.run(until=0.5)
    assert run.coordinator.state.pool["A"].info.priority == 2.0


def test_the_pool_bound_counts_the_tasks_queued(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run, _ = _run(tmp_path)
    monkeypatch.setenv("BTMISSION_MAX_TASKS", "2")
    run.add_task({"id": "B", "type": "inspect", "location": [3, 3, 0]})  # A and B: 2
    with pytest.raises(TaskError) as full:
        run.add_task({"id": "C", "type": "inspect", "location": [3, 3, 0]})
    assert full.value.code == TOO_MANY
    assert str(full.value) == "the mission has 2 tasks already (BTMISSION_MAX_TASKS)"
