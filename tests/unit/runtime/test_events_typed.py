"""Typed events (one class per kind, stable JSON), log version 2 (v1 logs still read), and the new
``route`` and ``tree`` events and the header's ``world_ref`` (issue #13 §3)."""

from __future__ import annotations

import ast
import gzip
import itertools
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import py_trees
import pytest
from click.testing import CliRunner
from py_trees.common import Status

import btmission.runtime.events as events_module
from btmission.cli.main import cli
from btmission.missions import load_mission_text
from btmission.runtime.commands import (
    AddTask,
    CancelTask,
    KillAgent,
    Refused,
    SetLink,
    SetPriority,
    Signal,
)
from btmission.runtime.eventkinds import (
    CommandEvent,
    DispatchEvent,
    LeafErrorEvent,
    PoseEvent,
    RoundEvent,
    TaskStateEvent,
    WarningEvent,
)
from btmission.runtime.events import (
    EVENT_CLASSES,
    LOG_VERSION,
    READS_VERSIONS,
    Event,
    EventError,
    EventStream,
    GenericEvent,
    JsonlEventLog,
    LogError,
    Recorder,
    TypedEvent,
    event_class,
    event_of,
    read_events,
    register_event,
    world_reference,
)
from btmission.runtime.navconfig import ROUTE_EVENT_POINTS, route_points
from btmission.runtime.observers import QueuedObserver
from btmission.runtime.report import build_report, format_report, report_from_log, report_json
from btmission.runtime.runner import MissionRun
from btmission.runtime.treestatus import LeanBehaviourTree, StatusChanges, TreeStatusLogger

ROOT = Path(__file__).resolve().parents[3]
V1_LOG = ROOT / "docs" / "examples" / "pick_and_deliver.jsonl"
"""A version 1 log (written before typed events); its report must not change."""
GOLDEN = ROOT / "tests" / "data" / "logs"

SMALL = """
mission: small
version: 1
world:
  map: {generate: empty, size: [8, 4, 1]}
  resolution: 0.25
agents:
  - {id: G1, library: ground, start: [1, 1, 0]}
  - {id: G2, library: ground, start: [1, 3, 0]}
tasks:
  - {id: A, type: inspect, location: [6, 1, 0]}
task_types:
  inspect: {goal: at_goal(location), cost: path_cost(location)}
coordination: {auction_rate_hz: 2}
default_behavior: {goal: at_goal(home), idle_timeout_s: 1}
runtime: {controller: track, settings: {tree_event_s: 1.0}}
"""


@dataclass
class Ran:
    run: MissionRun
    events: list[Event]
    log: Path
    queued: list[Event]
    """What a Recorder behind a QueuedObserver got."""


@pytest.fixture(scope="module")
def ran(tmp_path_factory: pytest.TempPathFactory) -> Ran:
    """A short run of two ground robots (one task), logged: ~2 s."""
    tmp = tmp_path_factory.mktemp("typed")
    mission = load_mission_text(SMALL.lstrip("\n"), str(tmp / "small.yaml"))
    rec, behind = Recorder(), Recorder()
    with JsonlEventLog(tmp / "small.jsonl") as log, QueuedObserver(behind) as queued:
        run = MissionRun(mission, observers=[rec, log, queued])
        result = run.run(until=120)
        run.end(result)
    assert result.reason == "completed", result
    return Ran(run, rec.events, tmp / "small.jsonl", behind.events)


# ------------------------------------------------------------------------------ every kind
class Strict:
    """An observer that checks every event a run publishes is of its kind's typed class: a
    registered class (not :class:`GenericEvent`), every field declared (a ``command``'s
    arguments are its ``extra`` by design), and typed → JSON the same bytes as the event's."""

    def __init__(self, library_kinds: frozenset[str] = frozenset()) -> None:
        self.library_kinds = library_kinds
        self.kinds: set[str] = set()
        self.problems: list[str] = []

    def on_event(self, event: Event) -> None:
        self.kinds.add(event.kind)
        line = event.to_json()
        try:
            typed = event.typed()
        except EventError as exc:
            self.problems.append(f"{exc}: {line[:200]}")
            return
        if isinstance(typed, GenericEvent) and event.kind not in self.library_kinds:
            self.problems.append(f"no typed class: {line[:200]}")
        elif typed.extra and not isinstance(typed, CommandEvent):
            self.problems.append(f"undeclared fields {sorted(typed.extra)}: {line[:200]}")
        elif typed.to_json() != line:
            self.problems.append(f"not its JSON:\n  {line[:300]}\n  {typed.to_json()[:300]}")


@pytest.fixture(scope="module")
def busy(tmp_path_factory: pytest.TempPathFactory) -> Strict:
    """A short run with operator commands (added tasks, priority, cancel, a cut link, a signal, a
    refused command, a kill), every event checked by :class:`Strict`: ~2 s."""
    tmp = tmp_path_factory.mktemp("busy")
    mission = load_mission_text(SMALL.lstrip("\n"), str(tmp / "small.yaml"))
    strict = Strict()
    run = MissionRun(mission, observers=[strict])
    run.at(0.5, AddTask({"id": "B", "type": "inspect", "location": [6, 3, 0]}, by="console:ana"))
    run.at(0.5, AddTask({"id": "C", "type": "inspect", "location": [4, 3, 0], "at": 30.0}))
    run.at(1.0, SetLink("G2", False))
    run.at(1.5, SetPriority("B", 2.0))
    run.at(1.5, Signal("G1", "note", {"level": 2}))
    run.at(2.0, SetLink("G2", True))
    run.at(2.0, CancelTask("C"))
    run.at(2.5, Refused("kill_agent", {"agent": "G9"}, "unknown agent 'G9'", by="console:bo"))
    run.at(6.0, KillAgent("G2", "battery"))
    run.end(run.run(until=40))
    return strict


def test_a_run_publishes_only_typed_events_with_declared_fields(busy: Strict, ran: Ran) -> None:
    """What the producers publish (runtime, coordinator, agents, leaves, commands) is each
    kind's typed class, field for field: a new field or kind without its class fails here."""
    assert busy.problems == []
    assert {"header", "built", "task_added", "task", "round", "agent_task", "stage", "progress",
            "pose", "route", "tree", "command", "link", "signal", "agent_lost", "end"} <= busy.kinds  # fmt: skip
    strict = Strict()
    for e in ran.events:
        strict.on_event(e)
    assert strict.problems == [] and {"route", "tree"} <= strict.kinds


def test_the_golden_logs_hold_only_typed_events_with_declared_fields() -> None:
    """Every event of the shipped missions' golden logs (tests/golden: compra, haulage,
    relocalisation, ...) is of a registered class with all its fields declared (the golden
    logs are normalised: keys sorted, wall-clock fields left out)."""
    import btmission_library.haulage  # noqa: F401  (registers load / offload)

    kinds = set()
    for path in sorted((ROOT / "tests" / "golden").glob("*.events.jsonl.gz")):
        with gzip.open(path, "rt", encoding="utf-8") as f:
            for line in f:
                ev = Event.from_json(line)
                typed = ev.typed()
                assert not isinstance(typed, GenericEvent), f"{path.name}: {line[:200]}"
                if not isinstance(typed, CommandEvent):
                    assert not typed.extra, f"{path.name}: {line[:200]}"
                assert typed.to_data() == dict(ev.data), f"{path.name}: {line[:200]}"
                kinds.add(typed.kind)
    assert {"dispatch", "load", "objects", "junction", "relocalized", "pose"} <= kinds


EMITTERS = {"emit", "_emit", "emit_event", "events", "_events", "_leaf_event", "library_event"}

NAMED_KINDS = {("btmission/dispatch/service.py", "dispatch")}
"""Where a kind is still named: the fleet dispatcher is an algorithm (it knows no run, so no
event classes); ``haulage`` makes :class:`DispatchEvent`\\ s of what it publishes."""


def named_kinds() -> set[tuple[str, str]]:
    """(file, kind) of every call that publishes an event by naming its kind: a string as the
    first argument of ``emit(...)``, ``_emit``, ``emit_event``, ``events``, ``_events``,
    ``_leaf_event``, ``library_event`` or ``Event(t, "kind", ...)`` in btmission/, cli/ and
    library/."""
    found: set[tuple[str, str]] = set()
    for top in ("btmission", "cli", "library"):
        for path in (ROOT / top).rglob("*.py"):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            for node in ast.walk(tree):
                if not isinstance(node, ast.Call) or not node.args:
                    continue
                f = node.func
                name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
                if name == "Event" and len(node.args) >= 2:
                    arg = node.args[1]
                elif name in EMITTERS:
                    arg = node.args[0]
                else:
                    continue
                if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                    found.add((path.relative_to(ROOT).as_posix(), arg.value))
    return found


def test_producers_make_typed_events_instead_of_naming_kinds() -> None:
    """One vocabulary: the code publishes the typed classes (``emit_event(PoseEvent(...))``,
    ``ctx.events(ObjectsEvent(...))``), never a kind by name — which only a library's own kind
    without a class needs."""
    assert named_kinds() == NAMED_KINDS


def docstring_table() -> dict[str, str]:
    """The kinds table of :mod:`btmission.runtime.events`' docstring: kind → its row's text."""
    doc = events_module.__doc__ or ""
    _, table, _ = re.split(r"^=+  =+$", doc, maxsplit=2, flags=re.MULTILINE)
    rows: dict[str, str] = {}
    kind = ""
    for line in table.splitlines():
        m = re.match(r"``(\w+)``\s+(.*)", line)
        if m:
            kind = m.group(1)
            rows[kind] = m.group(2)
        elif kind:
            rows[kind] += " " + line.strip()
    return rows


def test_the_docstring_table_lists_every_kind_and_field() -> None:
    """The events module docstring's table of kinds is the registered classes (those of
    btmission's own kinds module: a library registers its own), and each row names every field
    of its class."""
    rows = docstring_table()
    own = {k: c for k, c in EVENT_CLASSES.items() if c.__module__ == "btmission.runtime.eventkinds"}
    assert len(own) >= 30
    assert sorted(rows) == sorted(own)
    for kind, cls in own.items():
        missing = [name for name, _, _ in cls._FIELDS if f"``{name}``" not in rows[kind]]
        assert missing == [], f"the row of '{kind}' does not name {missing}"


SAMPLES: dict[str, dict[str, Any]] = {
    "header": {"format": "btmission-log", "version": 2, "mission": "m", "description": "",
               "file": "m.yaml", "seed": 0, "controller": "track",
               "world": {"map": {"file": "x.npz"}, "resolution": 0.5, "topomap": None},
               "world_ref": {"base_dir": "/m", "map": "/m/x.npz", "topomap": None},
               "map": {"shape": [2, 2, 2], "resolution": 0.5, "origin": [0.0, 0.0, 0.0]},
               "step_s": 0.05, "part": "agents G1", "auction_rate_hz": 2.0,
               "agents": [{"id": "G1", "library": "ground", "vehicle": "ground",
                           "start": [1.0, 1.0, 0.0]}],
               "tasks": [{"id": "A", "type": "inspect", "at": 0.0, "fields": {}}],
               "artifacts": [{"label": "survivor", "p": [1.0, 2.0, 0.5], "size_m": 0.6}]},
    "built": {"map": {"shape": [2, 2, 2], "resolution": 0.5, "origin": [0.0, 0.0, 0.0]},
              "build_s": 0.25, "started_unix": 1700000000.5},
    "task_added": {"task": "A", "type": "inspect", "fields": {"location": [1, 2, 0]},
                   "priority": 1.0, "by": "api", "problems": ["location: inside rock"],
                   "at": 30.0},
    "task": {"task": "A", "state": "done", "agent": "G1", "reason": "completed",
             "reported_s": 12.5},
    "round": {"round": 3, "announced": 1, "agents": 2, "method": "dense", "bids": 2,
              "step_ms": 0.3, "assignments": {"G1": "A", "G2": None}, "dropped": ["G3"],
              "late_bids": 1, "stale_bids": 2},
    "agent_task": {"agent": "G1", "task": None},
    "stage": {"agent": "G1", "task": "A", "action": "drive_path(location)"},
    "junction": {"agent": "M1", "offsets": [-0.79, 0.15], "chosen": 1},
    "junction_switch": {"agent": "M1", "offsets": [-0.81, 0.11], "chosen": 0, "was": 0.145},
    "committed": {"agent": "G1", "task": "A"},
    "progress": {"agent": "G1", "task": "A", "event": "failed", "reason": "no path"},
    "pose": {"agent": "G1", "p": [1.0, 2.0, 0.0], "v": [0.0, 0.1, 0.0], "yaw": 0.5,
             "mode": "OFFBOARD", "armed": True, "flying": False, "odometer_m": 3.2,
             "clearance_m": None},
    "collision": {"agent": "G1", "other": "rock", "p": [1.0, 2.0, 0.0]},
    "agent_lost": {"agent": "G1", "reason": "killed"},
    "signal": {"agent": "D1", "name": "stop", "value": True},
    "link": {"agent": "G1", "up": False},
    "vehicle_link": {"agent": "R1", "up": True, "mode": "HOLD"},
    "coordinator_link": {"agent": "R1", "up": False, "silent_s": 3.1},
    "taken_over": {"agent": "R1", "mode": "LAND", "failsafe": True, "final": True, "task": "T1"},
    "objects": {"agent": "D1", "objects": [{"label": "survivor", "p": [1.0, 2.0, 0.5],
                                            "observations": 4}], "rejected": {"far": 2}},
    "relocalized": {"agent": "R1", "task": "L1", "localized": True, "confidence": 0.9,
                    "fitness": 0.05, "reason": "", "points": 1200, "sensor": "lidar",
                    "time_ms": 40.0, "truth": {"x": 1.0, "y": 2.0, "z": 3.0, "yaw_deg": 10.0},
                    "estimate": {"x": 1.0, "y": 2.1, "z": 3.0, "yaw_deg": 9.0},
                    "error_m": 0.1, "error_deg": 1.0},
    "dispatch": {"truck": "T1", "event": "adopted", "goal": "L1", "reason": "", "to": "D1", "items": 1,
                 "depart": None, "arrive": 30.5, "mission": {"nodes": ["L1", "D1"]}},
    "leaf_error": {"agent": "G1", "task": "A", "leaf": "scan(location)", "phase": "update",
                   "error": "ValueError", "message": "no data", "where": "x.py:3",
                   "traceback": "Traceback ..."},
    "warning": {"agent": "G1", "variable": "home", "leaf": "go(home)", "message": "not set"},
    "internal_error": {"type": "KeyError", "message": "'x'", "traceback": "Traceback ..."},
    "end": {"reason": "completed", "wall_s": 1.5, "steps": 30, "done": ["A"], "open": {},
            "pending": [], "cancelled": ["B"]},
    "command": {"command": "cancel_task", "by": "console:ana", "task": "B",
                "reason": "not needed", "ok": False,
                "error": "cannot cancel task 'B': it is already cancelled"},
    "withdrawn": {"agent": "R1", "task": "T3", "by": "R2", "reason": "R2 did it first"},
    "retry": {"agent": "R1", "task": "T1", "action": "arm", "retry": 1, "retries": 3,
              "reason": "PreArm: estimator not ready", "wait_s": 2.0},
    "attempt": {"task": "T1", "agent": "R1", "attempt": 1, "max_attempts": 3,
                "reason": "arm: PreArm: estimator not ready", "gave_up": True, "state": "open",
                "cooldown_until": 62.5, "reported_s": 32.45},
    "agent_excluded": {"agent": "R1", "tasks": ["T1", "T2", "T3"], "reason": "gave up"},
    "resumed": {"log": "runs/coordinator.jsonl", "last_s": 41.25},
    "clock": {"agent": "R1", "was_s": 0.5, "now_s": 120.0},
    "route": {"agent": "G1", "task": "A", "points": [[1.0, 1.0, 0.0], [6.0, 1.0, 0.0]],
              "length_m": 5.0},
    "tree": {"agent": "G1", "changes": [[0, "INVALID", "RUNNING"]],
             "nodes": [["mission(G1)", -1, "fallback"]], "blackboard": {"task": "A"},
             "unset": ["home"]},
    "load": {"agent": "T1", "until": 12.0},
    "offload": {"agent": "T1", "until": 20.0},
}  # fmt: skip
"""One event of every kind, with all its fields (the optional ones too)."""


@pytest.mark.parametrize("kind", sorted(SAMPLES))
def test_every_class_round_trips_json_typed_json(kind: str) -> None:
    import btmission_library.haulage  # noqa: F401

    line = Event(7.5, kind, SAMPLES[kind]).to_json()
    typed = Event.from_json(line).typed()
    assert type(typed) is EVENT_CLASSES[kind] and typed.kind == kind
    args = {"task", "reason"} if kind == "command" else set()  # a command's: its extra
    assert set(typed.extra) == args, "every other field of the sample is a declared one"
    declared = {name for name, _, _ in type(typed)._FIELDS}
    assert declared == set(SAMPLES[kind]) - args - {"reported_s"}, "the sample has them all"
    assert typed.to_json() == line
    # the same with every optional field left out, and the others as they are
    required = {
        name: value
        for name, value in SAMPLES[kind].items()
        if not any(n == name and opt for n, _, opt in type(typed)._FIELDS)
    }
    line = Event(7.5, kind, required).to_json()
    assert Event.from_json(line).typed().to_json() == line


def test_the_samples_cover_every_registered_class() -> None:
    import btmission_library.haulage  # noqa: F401

    assert sorted(EVENT_CLASSES) == sorted(SAMPLES)


@pytest.mark.parametrize("log", ["v1", "v2"])
def test_logs_round_trip_byte_for_byte(ran: Ran, log: str) -> None:
    """Every line of a real log (v1: the documentation's example; v2: a run now) → typed → the
    same line; every event of a built-in kind gets its class, all its fields declared."""
    path = V1_LOG if log == "v1" else ran.log
    lines = path.read_text(encoding="utf-8").splitlines()
    kinds = set()
    for line in lines:
        typed = Event.from_json(line).typed()
        assert typed.to_json() == line
        assert not isinstance(typed, GenericEvent) and not typed.extra, line[:200]
        kinds.add(typed.kind)
    if log == "v2":
        assert {"header", "route", "tree", "pose", "round", "task", "end"} <= kinds


def test_typed_events_of_a_run_are_its_events(ran: Ran) -> None:
    """``Event.typed()`` on the live events (numpy arrays, tuples) gives what the log has."""
    logged = ran.log.read_text(encoding="utf-8").splitlines()
    assert [e.typed().to_json() for e in ran.events] == logged
    pose = next(e for e in ran.events if e.kind == "pose").typed()
    assert isinstance(pose, PoseEvent) and pose.agent == "G1" and len(pose.p) == 3


def test_a_queued_observer_sees_the_run_as_the_others(ran: Ran) -> None:
    assert ran.queued == ran.events and ran.events[-1].kind == "end"


def test_typed_fields_and_constructing_events() -> None:
    ev = TaskStateEvent(t=3.0, task="A", state="assigned", agent=None, reason="won")
    assert ev.to_json() == (
        '{"t":3.0,"ev":"task","task":"A","state":"assigned","agent":null,"reason":"won"}'
    )
    r = RoundEvent(t=1.0, round=1, announced=0, agents=2, method="dense", bids=0, step_ms=0.1)
    assert "assignments" not in r.to_json() and "dropped" not in r.to_json()  # optional: left out
    assert r.to_event() == Event(
        1.0,
        "round",
        {"round": 1, "announced": 0, "agents": 2, "method": "dense", "bids": 0, "step_ms": 0.1},
    )
    with pytest.raises(AttributeError):
        r.round = 2  # type: ignore[misc]  # frozen


def test_what_a_producer_leaves_out_and_where_the_extra_fields_go() -> None:
    """Optional fields are left out when None — unless the field they go with is set (written
    as null then); a command's arguments go between ``by`` and ``ok``, as they always did."""
    tb = {"error": "KeyError", "message": "'x'", "where": "a.py:1", "traceback": "..."}
    mine = LeafErrorEvent(t=1.0, agent="G1", task=None, leaf="scan", phase="update", **tb)
    assert list(mine.to_data())[:3] == ["agent", "task", "leaf"] and mine.task is None
    service = LeafErrorEvent(t=1.0, leaf="service x.y", phase="step", **tb)
    assert list(service.to_data())[:2] == ["leaf", "phase"]
    parked = DispatchEvent(t=1.0, truck="T1", event="adopted", goal="P", to="P", items=0)
    assert list(parked.to_data()) == ["truck", "event", "goal", "to", "items"]
    moved = DispatchEvent(truck="T1", event="adopted", goal="P", to="P", items=0, arrive=3.0)
    assert moved.to_data()["depart"] is None and list(moved.to_data())[-2:] == ["depart", "arrive"]
    cmd = CommandEvent(t=2.0, command="cancel_task", by="api", ok=False, error="no",
                       extra={"task": "B", "reason": "r"})  # fmt: skip
    assert cmd.to_json() == (
        '{"t":2.0,"ev":"command","command":"cancel_task","by":"api","task":"B","reason":"r",'
        '"ok":false,"error":"no"}'
    )
    assert cmd.args == {"task": "B", "reason": "r"}
    assert Event.from_json(cmd.to_json()).typed() == cmd


def test_emit_event_stamps_the_time_and_keeps_the_log_in_order() -> None:
    """:meth:`MissionRun.emit_event`: an event made without a time is published now; one that
    happened before the last published goes out then, with its own time as ``reported_s``."""
    rec = Recorder()
    run: Any = SimpleNamespace(now=lambda: 5.0, last_t=0.0, events=EventStream([rec]))
    MissionRun.emit_event(run, WarningEvent(message="now"))
    MissionRun.emit_event(run, TaskStateEvent(t=4.0, task="A", state="done", agent="G1",
                                              reason="completed"))  # fmt: skip
    MissionRun.emit_event(run, WarningEvent(t=6.0, message="later"))
    assert [e.to_json() for e in rec.events] == [
        '{"t":5.0,"ev":"warning","message":"now"}',
        '{"t":5.0,"ev":"task","task":"A","state":"done","agent":"G1","reason":"completed",'
        '"reported_s":4.0}',
        '{"t":6.0,"ev":"warning","message":"later"}',
    ]
    assert math.isnan(WarningEvent(message="unpublished").t)


def test_a_library_publishes_typed_events_or_its_own_kinds_by_name() -> None:
    ev = WarningEvent(message="x")
    assert event_of(ev, {}) is ev
    with pytest.raises(TypeError, match="a typed event takes no other fields"):
        event_of(ev, {"agent": "G1"})
    own = event_of("sample_taken", {"agent": "G1", "grams": 3.5})
    assert isinstance(own, GenericEvent) and own.kind == "sample_taken"
    assert own.to_data() == {"agent": "G1", "grams": 3.5}


def test_consumers_skip_an_event_of_the_wrong_types_as_a_log_reader_does() -> None:
    bad = Event(1.0, "pose", {"agent": "G1", "p": "here"})
    assert bad.typed_or_none() is None
    with pytest.raises(EventError):
        bad.typed()
    good = Event(1.0, "warning", {"message": "m"})
    assert good.typed() is good.typed()  # made once


@pytest.mark.parametrize(
    ("kind", "data", "message"),
    [
        ("pose", {"agent": "G1", "p": [1, 2]}, "pose: field 'p' has the wrong type (got [1, 2])"),
        ("task", {"task": 5}, "task: field 'task' has the wrong type (got 5)"),
        ("round", {"round": True}, "round: field 'round' has the wrong type (got true)"),
        ("tree", {"changes": [[0, "INVALID"]]},
         "tree: field 'changes' has the wrong type (got [[0, \"INVALID\"]])"),
        ("mine", {"reported_s": "late"}, "mine: field 'reported_s' has the wrong type"),
    ],
)  # fmt: skip
def test_fields_of_the_wrong_type(kind: str, data: dict[str, Any], message: str) -> None:
    with pytest.raises(EventError) as exc:
        Event(1.0, kind, data).typed()
    assert str(exc.value) == message


def test_library_kinds_are_generic_until_registered() -> None:
    line = '{"t":2.0,"ev":"sample_taken","agent":"G1","grams":3.5,"reported_s":1.5}'
    typed = Event.from_json(line).typed()
    assert isinstance(typed, GenericEvent) and typed.kind == "sample_taken"
    assert typed.extra == {"agent": "G1", "grams": 3.5} and typed.reported_s == 1.5
    assert typed.to_json() == line
    assert event_class("sample_taken") is GenericEvent

    @register_event
    @dataclass(frozen=True, kw_only=True)
    class SampleTaken(TypedEvent):
        KIND = "sample_taken"
        agent: str
        grams: float

    try:
        typed = Event.from_json(line).typed()
        assert isinstance(typed, SampleTaken) and typed.grams == 3.5 and typed.to_json() == line

        @dataclass(frozen=True, kw_only=True)
        class Other(TypedEvent):
            KIND = "sample_taken"

        with pytest.raises(ValueError, match="event kind 'sample_taken' is already"):
            register_event(Other)
    finally:
        del EVENT_CLASSES["sample_taken"]


# ------------------------------------------------------------------------------ log versions
def test_this_btmission_writes_version_2_and_reads_1_and_2(ran: Ran) -> None:
    assert LOG_VERSION == 2 and READS_VERSIONS == (1, 2)
    assert read_events(ran.log).events[0].get("version") == 2
    assert read_events(V1_LOG).events[0].get("version") == 1


def test_the_report_of_a_version_1_log_is_unchanged(runner: CliRunner) -> None:
    """``btmission report`` of the documentation's v1 log prints what it printed before v2."""
    assert json.loads(V1_LOG.read_text(encoding="utf-8").split("\n", 1)[0])["version"] == 1, (
        "docs/examples/pick_and_deliver.jsonl is this test's version 1 log: keep a v1 copy"
    )
    r = runner.invoke(cli, ["report", str(V1_LOG.relative_to(ROOT))])
    assert r.exit_code == 0, r.output
    assert r.output == (GOLDEN / "pick_and_deliver_v1.report.txt").read_text(encoding="utf-8")
    rep = report_from_log(V1_LOG)
    want = json.loads((GOLDEN / "pick_and_deliver_v1.report.json").read_text(encoding="utf-8"))
    assert json.loads(json.dumps(report_json(rep), default=str)) == want


def test_the_new_events_do_not_change_the_report(ran: Ran) -> None:
    """A v2 log gives the report of the same events without tree/route/world_ref."""
    old = [e for e in ran.events if e.kind not in ("tree", "route")]
    old[0] = Event(0.0, "header", {k: v for k, v in old[0].data.items() if k != "world_ref"})
    assert format_report(build_report(ran.events)) == format_report(build_report(old))
    assert format_report(report_from_log(ran.log)) == format_report(build_report(ran.events))


@pytest.mark.parametrize("version", ["3", '"2"', "true", "null"])
def test_a_log_of_an_unknown_version_is_refused(
    runner: CliRunner, tmp_path: Path, version: str
) -> None:
    lines = V1_LOG.read_text(encoding="utf-8").splitlines()
    header = lines[0].replace('"version":1,', f'"version":{version},')
    header = header.replace('"agents":[', '"agents":7,"old":[')  # newer: other fields
    log = tmp_path / "new.jsonl"
    log.write_text("\n".join([header, *lines[1:]]) + "\n", encoding="utf-8")
    with pytest.raises(LogError) as exc:
        read_events(log)
    assert str(exc.value) == (
        f"{log}: log format version {json.loads(version)!r}; this btmission reads 1 and 2"
    )
    r = runner.invoke(cli, ["report", str(log)])
    assert r.exit_code == 2 and f"log format version {json.loads(version)!r}" in r.output


# ------------------------------------------------------------------------------ world_ref
def test_the_header_says_where_the_world_is(ran: Ran, tmp_path: Path) -> None:
    header = read_events(ran.log).events[0]
    ref = header.get("world_ref")
    assert ref == {"base_dir": str(ran.log.parent.resolve()), "map": None, "topomap": None}
    assert world_reference({"map": {"file": "maps/m.npz"}, "topomap": "roads.yaml"}, "rel") == {
        "base_dir": str(Path("rel").resolve()),
        "map": str(Path("rel").resolve() / "maps" / "m.npz"),
        "topomap": str(Path("rel").resolve() / "roads.yaml"),
    }
    assert world_reference({"map": {"generate": "mine"}, "topomap": "mine"}, tmp_path) == {
        "base_dir": str(tmp_path.resolve()),
        "map": None,
        "topomap": "mine",  # a built-in map: by name
    }


def test_the_report_finds_the_world_from_another_directory(
    ran: Ran, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The top view's map comes from ``world_ref``, not from where the run was started."""
    from btmission.runtime.report import world_from_header

    monkeypatch.chdir(tmp_path)
    header = dict(ran.events[0].data, file="small.yaml")  # relative: not from here
    vm = world_from_header(header)
    assert vm is not None and vm.shape == ran.run.map.shape


# ------------------------------------------------------------------------------ route events
def test_route_events_carry_each_new_path(ran: Ran) -> None:
    routes = [e for e in ran.events if e.kind == "route"]
    assert [(e.get("agent"), e.get("task")) for e in routes] == [("G1", "A"), ("G1", None)]
    to_a = routes[0]
    assert to_a.get("points")[-1] == [6.0, 1.0, 0.0] and 5.0 <= to_a.get("length_m") <= 5.5
    home = routes[1]  # back home (default behaviour), from where it stopped
    assert home.get("points")[-1] == [1.0, 1.0, 0.0]


def test_route_points_drop_straight_runs_and_keep_at_most_the_limit() -> None:
    straight = np.array([[x * 0.25, 0.0, 0.0] for x in range(41)])  # 10 m, voxel by voxel
    assert route_points(straight) == [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]
    bent = np.vstack([straight, [[10.0, y * 0.25, 0.0] for y in range(1, 9)]])
    assert route_points(bent) == [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 2.0, 0.0]]
    t = np.linspace(0, 6 * np.pi, 5000)
    spiral = np.stack([np.cos(t), np.sin(t), t], axis=1)
    pts = route_points(spiral)
    assert len(pts) == ROUTE_EVENT_POINTS
    assert pts[0] == [1.0, 0.0, 0.0] and pts[-1] == [round(float(v), 3) for v in spiral[-1]]


def test_following_the_same_path_again_is_not_a_new_route(ran: Ran) -> None:
    nav = ran.run.agents["G2"].navigator
    seen: list[float] = []
    nav.on_route = lambda points, length: seen.append(length)
    path = np.array([[1.0, 3.0, 0.0], [2.0, 3.0, 0.0]])
    nav.follow(path, [2.0, 3.0, 0.0], 0.0)
    nav.follow(path, [2.0, 3.0, 0.0], 1.0)
    nav.follow(path[::-1], [1.0, 3.0, 0.0], 2.0)
    assert seen == [1.0, 1.0]


# ------------------------------------------------------------------------------ tree events
class Flag(py_trees.behaviour.Behaviour):
    """A leaf returning what the test says."""

    def __init__(self, name: str, status: Status = Status.SUCCESS) -> None:
        super().__init__(name)
        self.result = status

    def update(self) -> Status:
        return self.result


def small_tree() -> tuple[py_trees.behaviour.Behaviour, dict[str, Flag]]:
    leaves = {n: Flag(n) for n in ("done", "step1", "step2", "fallback")}
    leaves["done"].result = Status.FAILURE
    seq = py_trees.composites.Sequence("work", memory=False,
                                       children=[leaves["step1"], leaves["step2"]])  # fmt: skip
    root = py_trees.composites.Selector(
        "root", memory=False, children=[leaves["done"], seq, leaves["fallback"]]
    )
    return root, leaves


def statuses(root: py_trees.behaviour.Behaviour) -> dict[str, str]:
    return {b.name: b.status.value for b in root.iterate()}


def test_the_visitor_sees_every_status_change_ticked_or_stopped() -> None:
    """After every tick the visitor's view is every node's status, though it only visited the
    ticked ones (a parent stops the others without ticking them)."""
    root, leaves = small_tree()
    tree = LeanBehaviourTree(root)
    visitor = StatusChanges(root)
    tree.add_visitor(visitor)
    names = [b.name for b in visitor.behaviours]
    assert names == ["root", "done", "work", "step1", "step2", "fallback"]  # pre-order uids
    script = [
        {"step2": Status.RUNNING},
        {"step2": Status.SUCCESS},
        {"done": Status.SUCCESS},  # the Selector stops "work" (and its children): not ticked
        {"done": Status.FAILURE, "step1": Status.FAILURE},
        {"step1": Status.RUNNING},
    ]
    for changes in script:
        before = {n: b.status.value for n, b in zip(names, visitor.behaviours)}
        for name, status in changes.items():
            leaves[name].result = status
        tree.tick()
        now = statuses(root)
        assert {names[u]: s for u, s in enumerate(s.value for s in visitor.last)} == now
        assert {(names[u], old, new) for u, old, new in visitor.changes} == {
            (n, before[n], now[n]) for n in names if before[n] != now[n]
        }
    # outside a tick (an agent's task switch stops its tree): compare them all
    before = statuses(root)
    root.stop(Status.INVALID)
    assert {(names[u], old, new) for u, old, new in visitor.visit_all()} == {
        (n, s, "INVALID") for n, s in before.items() if s != "INVALID"
    }


def test_tree_events_are_throttled_net_changes() -> None:
    root, leaves = small_tree()
    tree = LeanBehaviourTree(root)
    clock = [0.0]
    published: list[tuple[float, list[list[Any]], Any]] = []
    logger = TreeStatusLogger(
        tree, lambda ch, nodes: published.append((clock[0], ch, nodes)), lambda: clock[0], 1.0
    )
    script = {0.0: ("step2", Status.RUNNING), 0.2: ("step2", Status.SUCCESS),
              0.4: ("step2", Status.RUNNING), 1.5: ("step1", Status.FAILURE)}  # fmt: skip
    for k in range(25):  # 10 Hz for 2.4 s
        clock[0] = round(k * 0.1, 1)
        if clock[0] in script:
            name, status = script[clock[0]]
            leaves[name].result = status
        tree.tick()
    assert [t for t, _, _ in published] == [0.0, 1.5]
    first, second = published[0][1], published[1][1]
    assert published[0][2] == logger.nodes and published[1][2] is None
    assert logger.nodes[:3] == [
        ["root", -1, "fallback"],
        ["done", 0, "Flag"],
        ["work", 0, "sequence"],
    ]
    assert [0, "INVALID", "RUNNING"] in first  # root
    # step2 went SUCCESS at 0.2 and RUNNING again at 0.4: no net change to publish at 1.0
    assert {c[0]: (c[1], c[2]) for c in second} == {
        0: ("RUNNING", "SUCCESS"),
        2: ("RUNNING", "FAILURE"),
        3: ("SUCCESS", "FAILURE"),
        4: ("RUNNING", "INVALID"),
        5: ("INVALID", "SUCCESS"),
    }
    assert logger.status == {0: "SUCCESS", 1: "FAILURE", 2: "FAILURE", 3: "FAILURE",
                             4: "INVALID", 5: "SUCCESS"}  # fmt: skip


def test_an_agents_tree_events_replay_to_its_tree_status(ran: Ran) -> None:
    """Per agent: the first ``tree`` event names the nodes; they are at least ``tree_event_s``
    (1 s here) apart; replaying their changes gives :attr:`Agent.tree_status` at the end."""
    for aid, agent in ran.run.agents.items():
        evs = [e for e in ran.events if e.kind == "tree" and e.get("agent") == aid]
        assert evs, aid
        assert evs[0].get("nodes") == agent.tree_nodes
        assert all("nodes" not in e.data for e in evs[1:])
        assert agent.tree_nodes[0] == [f"mission({aid})", -1, "fallback"]
        gaps = [b.t - a.t for a, b in itertools.pairwise(evs[:-1])]  # the last: at the end
        assert all(g >= 1.0 - 1e-9 for g in gaps), gaps
        state = dict.fromkeys(range(len(agent.tree_nodes)), "INVALID")
        for e in evs:
            for uid, old, new in e.get("changes"):
                assert state[uid] == old != new
                state[uid] = new
        assert state == dict(agent.tree_status)
        assert agent.tree_status[0] == agent.root.status.value == "SUCCESS"
    with pytest.raises(TypeError):
        ran.run.agents["G1"].tree_status[0] = "FAILURE"  # type: ignore[index]  # read-only


@pytest.mark.parametrize(
    ("value", "problem"),
    [("-1", "runtime.settings.tree_event_s: expected a number ≥ 0 (got -1)"),
     ("soon", "runtime.settings.tree_event_s: expected a number (got 'soon')")],
)  # fmt: skip
def test_tree_event_s_is_a_setting_validate_checks(
    runner: CliRunner, tmp_path: Path, value: str, problem: str
) -> None:
    mission = tmp_path / "m.yaml"
    mission.write_text(SMALL.lstrip("\n").replace("tree_event_s: 1.0", f"tree_event_s: {value}"))
    r = runner.invoke(cli, ["validate", str(mission)])
    assert r.exit_code == 2 and f"{mission}:15:55: {problem}" in r.output, r.output
    mission.write_text(SMALL.lstrip("\n"))
    r = runner.invoke(cli, ["validate", str(mission)])
    assert r.exit_code == 0, r.output
