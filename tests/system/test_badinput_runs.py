"""Issue #12 §4: runs never lose work, whatever happens to them.

A plugin leaf that raises fails (``leaf_error`` event, the run goes on); SIGTERM and Ctrl-C at any
moment leave a log ``btmission report`` reads; events are in time order; the ``end`` event lists
only tasks that arrived; pick-and-deliver completion belongs to the task (warehouse P7); a library
variable nobody sets is warned about; ``report --latest DIR`` and several logs.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from btmission.cli.main import cli

# ---------------------------------------------------------------------------- a small plugin
LIBRARY = """\
library: {name}
version: 1
module: {module}
variables:
  home: "Where the robot starts (set by the on_setup hook, unless the module leaves it out)"
goals:
  - scanned(spot)
  - at_goal(home)
conditions:
  is_localized: Pose known
  has_path: {{doc: A path to the goal, params: [goal]}}
  at_goal: {{doc: At the goal, params: [goal]}}
  scanned: {{doc: The spot was scanned, params: [spot]}}
actions:
  localize: {{doc: Localise, post: [is_localized]}}
  update_path: {{doc: Plan, params: [goal], pre: [is_localized], post: [has_path(goal)]}}
  drive_path: {{doc: Drive, params: [goal], pre: [is_localized, has_path(goal)], post: [at_goal(goal)]}}
  scan: {{doc: Scan the spot, params: [spot], pre: [at_goal(spot)], post: [scanned(spot)]}}
"""

MODULE = """\
import os
import time
from py_trees.common import Status
from btmission.plugins import Implementations
from btmission.runtime import actions as A
from btmission.runtime.leaves import StatefulAction

IMPLEMENTATIONS = Implementations("{name}", vehicle="ground", settings={{"speed_m_s": 2.0}})

if {set_home}:
    @IMPLEMENTATIONS.on_setup
    def _home(ctx):
        ctx.blackboard.set("home", ctx.start)

if {setup_raises}:
    @IMPLEMENTATIONS.on_setup
    def broken_setup(ctx):
        raise RuntimeError("no calibration file")

if {service} == "raises":
    @IMPLEMENTATIONS.service("fleet")
    def fleet(run):
        raise OSError("dispatcher database not found")

if {service} == "step raises":
    class Fleet:
        def step(self, now):
            if now > 1.0:
                raise ZeroDivisionError("no trucks")

    IMPLEMENTATIONS.service("fleet")(lambda run: Fleet())

if {slow_service}:
    @IMPLEMENTATIONS.service("slow")
    def slow(run):
        time.sleep(60)  # a build that takes long: the test signals it meanwhile
        return object()

@IMPLEMENTATIONS.condition("is_localized")
def is_localized(ctx):
    return bool(ctx.blackboard.get("localized", False))

@IMPLEMENTATIONS.condition("scanned")
def scanned(ctx, spot):
    return ctx.blackboard.get("scanned") == ctx.blackboard.get("task")

@IMPLEMENTATIONS.action("localize")
class Localize(StatefulAction):
    def on_start(self):
        self.ctx.blackboard.set("localized", True)
        return Status.SUCCESS

@IMPLEMENTATIONS.action("scan")
class Scan(StatefulAction):
    def on_start(self):
        if self.ctx.blackboard.get("task") == "BAD":
            raise ValueError("sensor returned no data")
        self.ctx.blackboard.set("scanned", self.ctx.blackboard.get("task"))
        return Status.SUCCESS

IMPLEMENTATIONS.condition("has_path")(A.has_path)
IMPLEMENTATIONS.condition("at_goal")(A.at_goal)
IMPLEMENTATIONS.action("update_path")(A.UpdatePath)
IMPLEMENTATIONS.action("drive_path")(A.FollowPath)
"""

MISSION = """\
mission: {name}
version: 1
world:
  map: {{generate: empty, size: [8, 6, 1]}}
  resolution: 0.25
agents:
  - {{id: G1, library: ./{name}.yaml, start: [1, 1, 0]}}
tasks:
{tasks}
task_types:
  scan:
    goal: scanned(location)
    cost: path_cost(location)
coordination: {{auction_rate_hz: 5}}
default_behavior: {{goal: at_goal(home), idle_timeout_s: 0.5}}
runtime: {{controller: track}}
"""

_count = 0


def plugin_mission(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    tasks: str = "  - {id: BAD, type: scan, location: [2, 1, 0]}\n"
    "  - {id: OK, type: scan, location: [3, 2, 0]}",
    *,
    set_home: bool = True,
    setup_raises: bool = False,
    slow_service: bool = False,
    service: str = "",
) -> Path:
    """A library + implementation module + mission in ``tmp_path`` (module on sys.path and
    on PYTHONPATH for subprocesses, a fresh module name each time)."""
    global _count
    _count += 1
    name = f"runsplug{_count}"
    module = f"runsplug_impl_{os.getpid()}_{_count}"
    (tmp_path / f"{name}.yaml").write_text(LIBRARY.format(name=name, module=module))
    (tmp_path / f"{module}.py").write_text(
        MODULE.format(
            name=name,
            set_home=set_home,
            setup_raises=setup_raises,
            slow_service=slow_service,
            service=repr(service),
        )
    )
    mission = tmp_path / f"{name}_mission.yaml"
    mission.write_text(MISSION.format(name=name, tasks=tasks))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), *sys.path]))
    return mission


def events(log: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in log.read_text().splitlines() if line.strip()]


def only_log(directory: Path) -> Path:
    logs = list(directory.glob("*.jsonl"))
    assert len(logs) == 1, logs
    return logs[0]


def run_cli(args: list[str]) -> Any:
    return CliRunner().invoke(cli, args)


# ---------------------------------------------------------------------------- leaf exceptions
def test_a_leaf_that_raises_fails_its_task_and_the_run_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mission = plugin_mission(tmp_path, monkeypatch)
    r = run_cli(
        ["run", str(mission), "--until", "30", "--quiet", "--no-png", "--log", str(tmp_path)]
    )
    assert r.exit_code == 1, r.output  # a task failed: exit 1, not a crash
    assert "Traceback" not in r.output
    # one short line on stderr (CliRunner mixes it into output), the traceback only in the log
    assert r.output.count("scan(location) raised ValueError: sensor returned no data") == 1
    evs = events(only_log(tmp_path))
    errs = [e for e in evs if e["ev"] == "leaf_error"]
    assert len(errs) == 1
    err = errs[0]
    assert err["agent"] == "G1" and err["task"] == "BAD" and err["leaf"] == "scan(location)"
    assert err["error"] == "ValueError" and err["message"] == "sensor returned no data"
    assert err["phase"] == "update" and err["where"].startswith(str(tmp_path))
    assert 'raise ValueError("sensor returned no data")' in err["traceback"]
    # the task failed with the exception as its reason (normal failure rules) ...
    bad = [e for e in evs if e["ev"] == "task" and e["task"] == "BAD"]
    assert bad[-1]["state"] == "failed"
    assert "ValueError: sensor returned no data" in bad[-1]["reason"]
    # ... and the run went on: the other task was done after it
    ok = [e for e in evs if e["ev"] == "task" and e["task"] == "OK"]
    assert ok[-1]["state"] == "done" and ok[-1]["t"] > bad[-1]["t"]
    end = evs[-1]
    assert end["ev"] == "end" and end["done"] == ["OK"] and list(end["open"]) == ["BAD"]
    # `report` shows it again, on stderr
    rep = CliRunner().invoke(cli, ["report", str(only_log(tmp_path))])
    assert rep.exit_code == 0
    assert rep.stderr == (
        "warning: agent G1: scan(location) raised ValueError: sensor returned no data "
        "(traceback in the log)\n"
    )


def test_a_leaf_error_in_a_condition_is_logged_once(tmp_path: Path) -> None:
    from btmission.runtime.leaves import AgentContext, Blackboard, ConditionLeaf
    from btmission.synthesis.tree import Kind, Node

    seen: list[tuple[str, dict[str, Any]]] = []

    def broken(ctx: Any) -> bool:
        raise KeyError("no such frame")

    none: Any = None  # no backend, navigator or paths: the condition touches none of them
    ctx = AgentContext(
        "A", Blackboard("/a"), none, none, none, none, lambda: 0.0, {}, (0.0, 0.0, 0.0),
        events=lambda ev: seen.append((ev.kind, ev.to_data())),
    )  # fmt: skip
    leaf = ConditionLeaf(Node(Kind.CONDITION, "broken"), broken, ctx)
    for _ in range(5):  # ticked every tick: one event, not five
        leaf.tick_once()
        assert leaf.status.value == "FAILURE"
    assert [k for k, _ in seen] == ["leaf_error"]
    assert seen[0][1]["error"] == "KeyError" and "no such frame" in seen[0][1]["message"]


def test_a_setup_hook_that_raises_is_a_clear_error_before_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mission = plugin_mission(tmp_path, monkeypatch, setup_raises=True)
    r = run_cli(
        ["run", str(mission), "--until", "5", "--quiet", "--no-png", "--log", str(tmp_path)]
    )
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    assert f"{mission}: agents.G1: library " in r.output
    assert "setup hook broken_setup failed for agent G1: RuntimeError: no calibration file" in (
        r.output
    )
    assert not list(tmp_path.glob("*.jsonl"))  # nothing ran: no log


def test_a_service_that_fails_to_start_is_a_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mission = plugin_mission(tmp_path, monkeypatch, service="raises")
    r = run_cli(
        ["run", str(mission), "--until", "5", "--quiet", "--no-png", "--log", str(tmp_path)]
    )
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    assert "service 'fleet' failed to start: OSError: dispatcher database not found (at " in (
        r.output
    )
    assert not list(tmp_path.glob("*.jsonl"))


def test_a_service_step_that_raises_is_logged_and_the_run_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mission = plugin_mission(
        tmp_path,
        monkeypatch,
        "  - {id: OK, type: scan, location: [3, 2, 0]}",
        service="step raises",
    )
    r = run_cli(
        ["run", str(mission), "--until", "20", "--quiet", "--no-png", "--log", str(tmp_path)]
    )
    assert r.exit_code == 0, r.output  # the task was done all the same
    evs = events(only_log(tmp_path))
    errs = [e for e in evs if e["ev"] == "leaf_error"]
    assert len(errs) == 1  # raised on every step after 1 s: logged once
    assert errs[0]["leaf"].startswith("service runsplug") and errs[0]["leaf"].endswith(".fleet")
    assert errs[0]["phase"] == "step" and errs[0]["error"] == "ZeroDivisionError"
    assert evs[-1]["ev"] == "end" and evs[-1]["done"] == ["OK"]


def test_initialise_and_on_halted_that_raise_are_caught() -> None:
    from py_trees.common import Status

    from btmission.runtime.leaves import AgentContext, Blackboard, StatefulAction
    from btmission.synthesis.tree import Kind, Node

    class Halting(StatefulAction):
        def on_start(self) -> Status:
            return Status.RUNNING

        def on_halted(self) -> None:
            raise RuntimeError("cannot cancel")

    class BadInit(StatefulAction):
        def initialise(self) -> None:
            super().initialise()
            raise AttributeError("no driver")

    class Mixin:
        def update(self) -> Status:
            raise LookupError("from a mixin")

    class Mixed(Mixin, StatefulAction):
        pass

    class NoStatus(StatefulAction):
        def on_start(self) -> Status:
            return True  # type: ignore[return-value]  # a plugin's slip

    seen: list[dict[str, Any]] = []
    none: Any = None
    ctx = AgentContext(
        "A", Blackboard("/a"), none, none, none, none, lambda: 0.0, {}, (0.0, 0.0, 0.0),
        events=lambda ev: seen.append({"kind": ev.kind, **ev.to_data()}),
    )  # fmt: skip
    halting = Halting(Node(Kind.ACTION, "halting"), ctx)
    halting.tick_once()
    assert halting.status is Status.RUNNING
    halting.stop(Status.INVALID)  # a higher-priority branch took over: on_halted raises
    assert halting.status is Status.INVALID
    bad = BadInit(Node(Kind.ACTION, "bad_init"), ctx)
    bad.tick_once()
    assert bad.status is Status.FAILURE and bad.reason == "AttributeError: no driver"
    for cls, name in ((Mixed, "mixed"), (NoStatus, "no_status")):
        leaf = cls(Node(Kind.ACTION, name), ctx)
        leaf.tick_once()
        assert leaf.status is Status.FAILURE
    assert [(e["leaf"], e["phase"], e["error"]) for e in seen if e["kind"] == "leaf_error"] == [
        ("halting", "terminate", "RuntimeError"),
        ("bad_init", "initialise", "AttributeError"),
        ("mixed", "update", "LookupError"),
        ("no_status", "update", "TypeError"),
    ]
    assert seen[-1]["message"] == "returned True, not a py_trees Status"


# ---------------------------------------------------------------------------- library variables
def test_a_library_variable_nobody_sets_is_warned_about_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mission = plugin_mission(
        tmp_path, monkeypatch, "  - {id: OK, type: scan, location: [2, 1, 0]}", set_home=False
    )
    r = run_cli(
        ["run", str(mission), "--until", "8", "--quiet", "--no-png", "--log", str(tmp_path)]
    )
    assert r.exit_code == 0, r.output  # the task is done; the default behaviour cannot run
    line = "warning: 'home' is not on the blackboard, so update_path(home) cannot run"
    assert r.output.count(line) == 1, r.output
    assert "docs/plugins.md, 'Library variables'" in r.output
    warns = [e for e in events(only_log(tmp_path)) if e["ev"] == "warning"]
    assert len(warns) == 1 and warns[0]["agent"] == "G1" and warns[0]["variable"] == "home"


# ---------------------------------------------------------------------------- log order, end
def test_events_are_in_time_order_and_end_lists_only_arrived_tasks(tmp_path: Path) -> None:
    """A short run of a built-in mission: the log in time order, the ``end`` event without
    the task still to arrive, and no false alarm (the ground library sets its ``home``)."""
    r = run_cli(
        ["run", "missions/pick_and_deliver.yaml", "--until", "12", "--quiet", "--no-png",
         "--log", str(tmp_path)]
    )  # fmt: skip
    assert r.exit_code == 1, r.output  # --until: tasks left
    assert "warning" not in r.output
    evs = events(only_log(tmp_path))
    assert not [e for e in evs if e["ev"] in ("warning", "leaf_error")]
    times = [e["t"] for e in evs]
    assert times == sorted(times)
    late = [e for e in evs if "reported_s" in e]  # progress reported before the round took it
    assert late and all(e["reported_s"] <= e["t"] for e in late)
    end = evs[-1]
    assert end["ev"] == "end" and end["reason"] == "until"
    # I2 arrives at 40 s: neither done nor open at 12 s, but still to arrive
    assert "I2" not in end["open"] and "I2" not in end["done"] and end["pending"] == ["I2"]
    assert set(end["open"]) | set(end["done"]) == {"P1", "I1"}
    # the report's times are the reported ones: I1 finished when G1 said so
    done = next(e for e in evs if e["ev"] == "progress" and e["task"] == "I1")
    rep = run_cli(["report", str(only_log(tmp_path)), "--json"])
    row = next(t for t in json.loads(rep.output)["tasks"] if t["task"] == "I1")
    assert row["finished_s"] == done["t"]


def test_report_warnings_go_to_stderr(tmp_path: Path) -> None:
    log = tmp_path / "cut.jsonl"
    text = Path("docs/examples/pick_and_deliver.jsonl").read_text()
    log.write_text(text[: len(text) // 2].rsplit("\n", 1)[0] + '\n{"t": 1, "ev": "po')
    r = CliRunner().invoke(cli, ["report", str(log)])
    assert r.exit_code == 0
    assert "warning: the last line of the log was cut off" in r.stderr
    assert "warning" not in r.stdout and "Tasks (seed 000 Table III)" in r.stdout


# ---------------------------------------------------------------------------- P7
def test_same_pickup_and_dropoff_twice_is_two_deliveries(tmp_path: Path) -> None:
    mission = tmp_path / "twice.yaml"
    text = Path("missions/pick_and_deliver.yaml").read_text()
    tasks = (
        "tasks:\n"
        "  - {id: P1, type: pick_and_deliver, pickup: [3, 1, 0], dropoff: [5, 1, 0]}\n"
        "  - {id: P2, type: pick_and_deliver, pickup: [3, 1, 0], dropoff: [5, 1, 0], at: 1}\n"
        "task_types:"
    )
    head, rest = text.split("tasks:\n", 1)
    text = head + tasks + rest.split("task_types:", 1)[1]
    text = text.replace("resolution: 0.1", "resolution: 0.25")
    text += "runtime: {settings: {pick_time_s: 1.0, place_time_s: 1.0}}\n"
    mission.write_text(text)
    r = run_cli(["run", str(mission), "--controller", "track", "--until", "80", "--quiet",
                 "--no-png", "--log", str(tmp_path)])  # fmt: skip
    assert r.exit_code == 0, r.output
    evs = events(only_log(tmp_path))

    def first(kind: str, task: str, **match: Any) -> dict[str, Any]:
        return next(
            e for e in evs
            if e["ev"] == kind and e.get("task") == task
            and all(e.get(k) == v for k, v in match.items())
        )  # fmt: skip

    p1_done = first("progress", "P1", event="done")
    assigned = first("agent_task", "P2")
    picked = first("stage", "P2", action="pick(pickup)")
    placed = first("stage", "P2", action="place(pickup, dropoff)")
    done = first("progress", "P2", event="done")
    assert p1_done["t"] <= assigned["t"] < picked["t"] < placed["t"] < done["t"]
    # back to the pick-up (2 m), pick 1 s, to the drop-off (2 m), place 1 s: not 0.05 s
    assert done["t"] - assigned["t"] > 5.0


# ---------------------------------------------------------------------------- report --latest
def test_report_latest_and_several_logs(tmp_path: Path) -> None:
    example = Path("docs/examples/pick_and_deliver.jsonl").read_text()
    old, new = tmp_path / "a-old.jsonl", tmp_path / "b-new.jsonl"
    new.write_text(example)
    old.write_text(example.replace('"seed":0', '"seed":7', 1))
    os.utime(old, (time.time() - 100, time.time() - 100))
    r = CliRunner().invoke(cli, ["report", "--latest", str(tmp_path)])
    assert r.exit_code == 0, r.stderr
    assert "seed 0," in r.stdout and "seed 7," not in r.stdout
    r = CliRunner().invoke(cli, ["report", str(old), str(new)])
    assert r.exit_code == 0, r.stderr
    assert r.stdout.count("Tasks (seed 000 Table III)") == 2
    assert f"==> {old} <==" in r.stdout and f"==> {new} <==" in r.stdout
    r = CliRunner().invoke(cli, ["report", str(old), str(new), "--json"])
    assert [d["log"] for d in json.loads(r.stdout)] == [str(old), str(new)]
    empty = tmp_path / "empty"
    empty.mkdir()
    r = CliRunner().invoke(cli, ["report", "--latest", str(empty)])
    assert r.exit_code == 2 and f"{empty}: no event log (*.jsonl) in this directory" in r.stderr
    r = CliRunner().invoke(cli, ["report"])
    assert r.exit_code == 2 and "give a LOG file (or several), or --latest DIR" in r.stderr
    # a bad log among good ones: exit 2 naming it, before any report is printed
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"t": 0, "ev": "pose"}\n')
    r = CliRunner().invoke(cli, ["report", str(new), str(bad)])
    assert r.exit_code == 2 and f"{bad}: not a btmission event log" in r.stderr
    assert r.stdout == ""


# ---------------------------------------------------------------------------- signals
def _spawn(args: list[str], cwd: Path | None = None) -> subprocess.Popen[str]:
    code = "import sys; from btmission.cli.main import main; sys.argv[0] = 'btmission'; main()"
    return subprocess.Popen(
        [sys.executable, "-c", code, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
    )


def _wait_for(log_dir: Path, needle: str, proc: subprocess.Popen[str], timeout: float = 30) -> Path:
    """Wait until a log in ``log_dir`` contains ``needle``; return it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for log in log_dir.glob("*.jsonl"):
            if needle in log.read_text():
                return log
        if proc.poll() is not None:
            out, err = proc.communicate()
            raise AssertionError(f"the run ended early ({proc.returncode}): {out}\n{err}")
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"no '{needle}' in a log of {log_dir} after {timeout} s")


@pytest.fixture()
def procs() -> Iterator[list[subprocess.Popen[str]]]:
    started: list[subprocess.Popen[str]] = []
    yield started
    for p in started:  # never leave one behind
        if p.poll() is None:
            p.kill()
        p.communicate()


def _report(log: Path) -> Any:
    return CliRunner().invoke(cli, ["report", str(log)])


def test_sigterm_mid_run_ends_the_log_and_exits_143(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, procs: list[Any]
) -> None:
    mission = plugin_mission(tmp_path, monkeypatch)
    logs = tmp_path / "logs"
    proc = _spawn(["run", str(mission), "--realtime", "--quiet", "--no-png", "--log", str(logs)])
    procs.append(proc)
    log = _wait_for(logs, '"ev":"pose"', proc)
    time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "ended: terminated" in out  # the report was printed
    end = events(log)[-1]
    assert end["ev"] == "end" and end["reason"] == "terminated" and end["t"] > 0
    rep = _report(log)
    assert rep.exit_code == 0 and "ended: terminated" in rep.stdout


@pytest.mark.parametrize(
    ("sig", "code", "reason"),
    [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")],
)
def test_a_signal_while_the_run_is_built_ends_it_cleanly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, sig: int, code: int, reason: str
) -> None:
    """In this process (the signal comes from a thread once the header is written, while the
    slow service is being built): Ctrl-C or SIGTERM there ends the command cleanly."""
    mission = plugin_mission(tmp_path, monkeypatch, slow_service=True)
    logs = tmp_path / "logs"
    seen_build: list[bool] = []

    def signal_during_the_build() -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            for log in logs.glob("*.jsonl"):
                text = log.read_text()
                if '"ev":"header"' in text:
                    time.sleep(0.2)  # inside the service factory's sleep
                    seen_build.append('"ev":"built"' not in log.read_text())
                    os.kill(os.getpid(), sig)
                    return
            time.sleep(0.02)

    sender = threading.Thread(target=signal_during_the_build)
    sender.start()
    r = CliRunner().invoke(cli, ["run", str(mission), "--quiet", "--log", str(logs)])
    sender.join()
    assert seen_build == [True]
    assert r.exit_code == code, r.output
    assert not isinstance(r.exception, KeyboardInterrupt) and "Traceback" not in r.output
    assert f"{reason} while building the run" in r.stderr
    assert f"ended: {reason}" in r.stdout  # the report of what there is
    log = only_log(logs)
    evs = events(log)
    assert [e["ev"] for e in evs] == ["header", "end"] and evs[-1]["reason"] == reason
    assert evs[-1]["pending"] == ["BAD", "OK"] and not evs[-1]["open"]
    assert not list(logs.glob("*.png"))  # no figures of a run that never ran
    rep = _report(log)
    assert rep.exit_code == 0 and f"ended: {reason}" in rep.stdout


def test_a_kill_during_the_build_leaves_a_log_report_accepts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, procs: list[Any]
) -> None:
    mission = plugin_mission(tmp_path, monkeypatch, slow_service=True)
    proc = _spawn(["run", str(mission), "--quiet", "--no-png", "--log", str(tmp_path / "logs")])
    procs.append(proc)
    log = _wait_for(tmp_path / "logs", '"ev":"header"', proc)
    proc.kill()  # SIGKILL: no handler runs
    proc.communicate(timeout=30)
    rep = _report(log)
    assert rep.exit_code == 0, rep.stderr
    assert "ended: log ends" in rep.stdout and "Number of agents        1" in rep.stdout


def test_a_signal_before_the_log_exists_is_clean(tmp_path: Path) -> None:
    """The handlers are in place from the start: a stop while loading writes no log."""
    from btmission.runtime.session import RunSession, RunStopped

    session = RunSession("missions/pick_and_deliver.yaml", log_dir=tmp_path, handle_signals=True)
    with session, pytest.raises(RunStopped) as stopped:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1)  # the handler raises first
    assert stopped.value.code == 143 and stopped.value.reason == "terminated"
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # restored
    assert list(tmp_path.iterdir()) == []


def test_run_help_documents_sigterm() -> None:
    r = run_cli(["run", "--help"])
    assert "143 terminated (SIGTERM)" in r.output
    r = run_cli(["report", "--help"])
    assert "--latest" in r.output and "btmission report --latest runs" in r.output


# ------------------------------------------------------------------------ internal errors
def test_an_internal_error_mid_run_ends_the_log_with_its_traceback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A bug outside any leaf: exit 70, one line naming the log, and a log `report` accepts."""
    from btmission.runtime.runner import MissionRun

    mission = plugin_mission(tmp_path, monkeypatch)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    calls = {"n": 0}
    real_step = MissionRun.step

    def failing_step(self: MissionRun, *args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 20:
            raise ZeroDivisionError("a bug in the loop")
        return real_step(self, *args, **kwargs)

    monkeypatch.setattr(MissionRun, "step", failing_step)
    log_dir = tmp_path / "logs"
    r = run_cli(
        ["run", str(mission), "--until", "30", "--quiet", "--no-png", "--log", str(log_dir)]
    )
    assert r.exit_code == 70, r.output
    log = only_log(log_dir)
    assert "Traceback" not in r.output
    assert (
        r.stderr.strip()
        .splitlines()[-1]
        .startswith("internal error: ZeroDivisionError: a bug in the loop; details in ")
    )
    assert r.stderr.rstrip().endswith(f" and {log}")
    evs = events(log)
    crash = [e for e in evs if e["ev"] == "internal_error"]
    assert len(crash) == 1 and crash[0]["type"] == "ZeroDivisionError"
    assert 'raise ZeroDivisionError("a bug in the loop")' in crash[0]["traceback"]
    assert evs[-1]["ev"] == "end" and evs[-1]["reason"] == "internal error"
    rep = run_cli(["report", str(log)])
    assert rep.exit_code == 0, rep.output


def test_a_second_signal_stops_a_long_step_at_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The first Ctrl-C asks the loop to stop after the step; when that step is long (the first
    auction of a huge mission), the second one stops it mid-step, with the end event logged."""
    from btmission.runtime.runner import MissionRun

    mission = plugin_mission(tmp_path, monkeypatch)
    real_step = MissionRun.step
    in_long_step = threading.Event()

    def step(self: MissionRun) -> None:
        real_step(self)
        if self.now() > 1.0:  # a step that would take minutes
            in_long_step.set()
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                time.sleep(0.01)

    monkeypatch.setattr(MissionRun, "step", step)

    def press_ctrl_c_twice() -> None:
        assert in_long_step.wait(30)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.3)
        os.kill(os.getpid(), signal.SIGINT)

    sender = threading.Thread(target=press_ctrl_c_twice)
    sender.start()
    t0 = time.monotonic()
    logs = tmp_path / "logs"
    r = CliRunner().invoke(cli, ["run", str(mission), "--quiet", "--no-png", "--log", str(logs)])
    sender.join()
    assert time.monotonic() - t0 < 30  # not the 60 s the step would have taken
    assert r.exit_code == 130, r.output
    assert "interrupted: stopping after the current step (again to stop at once)" in r.stderr
    assert "Traceback" not in r.output
    evs = events(only_log(logs))
    assert evs[-1]["ev"] == "end" and evs[-1]["reason"] == "interrupted"
    assert _report(only_log(logs)).exit_code == 0


# ----------------------------------------------------------------------------- deep trees
CHAIN_MODULE = """\
from py_trees.common import Status
from btmission.plugins import Implementations
from btmission.runtime.leaves import StatefulAction
IMPLEMENTATIONS = Implementations("{name}", vehicle="ground")


def _condition(i):
    return lambda ctx: i == 0 or bool(ctx.blackboard.get(f"c{{i}}", False))


def _action(i):
    class Step(StatefulAction):
        def on_start(self):
            self.ctx.blackboard.set(f"c{{i}}", True)
            return Status.SUCCESS
    return Step


for i in range({n} + 1):
    IMPLEMENTATIONS.condition(f"c{{i}}")(_condition(i))
for i in range(1, {n} + 1):
    IMPLEMENTATIONS.action(f"a{{i}}")(_action(i))
"""


def chain_mission(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, n: int) -> Path:
    """A library whose goal c{n} back-chains through n actions (a tree ~2n levels deep)."""
    global _count
    _count += 1
    name, module = f"chain{_count}", f"chain_impl_{os.getpid()}_{_count}"
    conds = "\n".join(f"  c{i}: {{doc: step {i}}}" for i in range(n + 1))
    acts = "\n".join(f"  a{i}: {{pre: [c{i - 1}], post: [c{i}]}}" for i in range(1, n + 1))
    (tmp_path / f"{name}.yaml").write_text(
        f"library: {name}\nversion: 1\nmodule: {module}\nconditions:\n{conds}\nactions:\n{acts}\n"
    )
    (tmp_path / f"{module}.py").write_text(CHAIN_MODULE.format(name=name, n=n))
    monkeypatch.syspath_prepend(str(tmp_path))
    mission = tmp_path / "deep.yaml"
    mission.write_text(
        "mission: deep\nversion: 1\nworld:\n  map: {generate: empty, size: [10, 10, 4]}\n"
        f"agents:\n  - {{id: R1, library: {name}.yaml, start: [1, 1, 0]}}\n"
        "tasks:\n  - {id: T1, type: job}\n"
        f"task_types:\n  job: {{goal: c{n}, cost: 1}}\n"
    )
    return mission


def test_a_1000_action_chain_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """py_trees ticks recurse once per level: the agent raises the limit its tree needs."""
    mission = chain_mission(tmp_path, monkeypatch, 1000)
    r = run_cli(
        ["run", str(mission), "--until", "5", "--quiet", "--no-png", "--log", str(tmp_path)]
    )
    assert r.exit_code == 0, r.output
    assert "Tasks done              1 of 1" in r.stdout
    assert sys.getrecursionlimit() < 5000  # raised around the ticks only


def test_a_tree_too_deep_for_the_stack_is_refused_before_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Past what the main thread's C stack takes, the process would crash (SIGSEGV): exit 2."""
    import btmission.runtime.agent as agent_module

    mission = chain_mission(tmp_path, monkeypatch, 300)
    monkeypatch.setattr(agent_module, "main_thread_limit", lambda: 1500)
    r = run_cli(["run", str(mission), "--quiet", "--no-png", "--log", str(tmp_path / "logs")])
    assert r.exit_code == 2, r.output
    assert (
        f"{mission}:6:5: agents[0]: agent R1's mission tree is 603 levels deep; a run ticks "
        "trees up to about 125 levels with this stack (ulimit -s)"
    ) in r.stderr
    assert not list((tmp_path / "logs").glob("*.jsonl"))  # nothing ran, no log left
