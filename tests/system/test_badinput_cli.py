"""Bad input at the CLI's edges (issue #12 §3): no traceback ever, no surprising side effects.

* an unexpected exception is one line + exit 70 + a traceback file (``--debug`` shows it);
* ``python -m btmission`` works; a closed pipe or a full disk is not a traceback;
* a 1,000-action chain library synthesises, dry-runs, exports and checks (no RecursionError);
* output options refuse symlinks, FIFOs, devices, directories and unwritable places;
* checking a library or mission never imports the implementation module its YAML names.
"""

from __future__ import annotations

import errno
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

import btmission.cli.common as common
import btmission.cli.synth_cmds as synth_cmds
from btmission.cli.common import BadInput, check_output_target, internal_error_sink
from btmission.cli.main import cli

REPO = Path(__file__).resolve().parents[2]
CHAIN = 1000


def invoke(*args: str, env: dict[str, str] | None = None) -> Result:
    return CliRunner().invoke(cli, list(args), env=env)


def _boom(*args: object, **kwargs: object) -> None:
    raise RuntimeError("boom\nsecond line")


# ---------------------------------------------------------------- last-resort handler
@pytest.fixture
def state_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    state = tmp_path / "state"
    monkeypatch.setenv("XDG_STATE_HOME", str(state))
    monkeypatch.delenv("BTMISSION_DEBUG", raising=False)
    return state


def test_internal_error_is_one_line_exit_70_and_a_traceback_file(
    state_home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(synth_cmds, "dry_run_fn", _boom)
    r = invoke("synth", "aerial", "--goal", "at_goal(goal)", "--dry-run")
    assert r.exit_code == 70, r.output
    lines = r.stderr.splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("internal error: RuntimeError: boom second line; details in ")
    assert "Traceback" not in r.output
    (crash,) = (state_home / "btmission").iterdir()
    assert lines[0].endswith(str(crash))
    text = crash.read_text()
    assert "Traceback (most recent call last)" in text and "RuntimeError: boom" in text
    assert "_boom" in text  # the frame that raised
    assert "command: " in text and "btmission 0." in text


@pytest.mark.parametrize("how", ["option", "env"])
def test_debug_shows_the_traceback(
    how: str, state_home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(synth_cmds, "dry_run_fn", _boom)
    args = ["synth", "aerial", "--goal", "at_goal(goal)", "--dry-run"]
    if how == "option":
        r = invoke("--debug", *args)
    else:
        r = invoke(*args, env={"BTMISSION_DEBUG": "1"})
    assert r.exit_code == 70
    assert "Traceback (most recent call last)" in r.stderr
    assert r.stderr.rstrip().endswith("RuntimeError: boom\nsecond line")
    assert "internal error:" not in r.stderr
    assert not (state_home / "btmission").exists()  # shown, not filed


def test_internal_error_sink_gets_the_traceback_and_is_named(
    state_home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The hook `run` uses to put the traceback in its open event log."""
    got: list[str] = []

    def sink(exc: BaseException, trace: str) -> str:
        got.append(trace)
        return "runs/x.jsonl"

    def boom_with_sink(*args: object, **kwargs: object) -> None:
        with internal_error_sink(sink):
            _boom()

    monkeypatch.setattr(synth_cmds, "dry_run_fn", boom_with_sink)
    r = invoke("synth", "aerial", "--goal", "at_goal(goal)", "--dry-run")
    assert r.exit_code == 70
    assert r.stderr.rstrip().endswith(" and runs/x.jsonl")
    assert len(got) == 1 and "RuntimeError: boom" in got[0]


def test_keyboard_interrupt_is_exit_130_without_traceback(
    state_home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(synth_cmds, "dry_run_fn", interrupted)
    r = invoke("synth", "aerial", "--goal", "at_goal(goal)", "--dry-run")
    assert r.exit_code == 130
    assert r.stderr.strip() == "interrupted"
    assert not (state_home / "btmission").exists()


@pytest.mark.parametrize(
    ("err", "message"),
    [
        (OSError(errno.ENOSPC, "No space left on device"), "Error: No space left on device"),
        (
            PermissionError(errno.EACCES, "Permission denied", "/srv/maps/x.npz"),
            "Error: /srv/maps/x.npz: Permission denied",
        ),
    ],
)
def test_environment_oserror_is_exit_2_with_the_reason(
    err: OSError, message: str, state_home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def fail(*args: object, **kwargs: object) -> None:
        raise err

    monkeypatch.setattr(synth_cmds, "dry_run_fn", fail)
    r = invoke("synth", "aerial", "--goal", "at_goal(goal)", "--dry-run")
    assert r.exit_code == 2
    assert r.stderr.strip() == message
    assert not (state_home / "btmission").exists()


# ---------------------------------------------------------------- real processes
def _env(tmp_path: Path, **extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("BTMISSION_DEBUG", None)
    env["XDG_STATE_HOME"] = str(tmp_path / "state")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tmp_path), env.get("PYTHONPATH")]))
    env.update(extra)
    return env


def test_python_m_btmission_version(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "btmission", "--version"],
        capture_output=True,
        text=True,
        timeout=120,
        env=_env(tmp_path),
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("btmission, version ")


BUGGY_PLUGIN = """
from btmission.plugins import Implementations


class Buggy(Implementations):
    def check(self, library):
        raise ZeroDivisionError("plugin bug")


IMPLEMENTATIONS = Buggy("buggy")
"""

BUGGY_LIBRARY = """\
library: buggy
version: 1
module: buggy_impl
conditions: {done: Done}
actions: {work: {post: [done]}}
"""


def test_internal_error_in_a_real_process(tmp_path: Path) -> None:
    """Through `python -m btmission`: a plugin bug ends in one line, exit 70 and a file."""
    (tmp_path / "buggy_impl.py").write_text(BUGGY_PLUGIN)
    lib = tmp_path / "buggy.yaml"
    lib.write_text(BUGGY_LIBRARY)
    cmd = [sys.executable, "-m", "btmission", "library", "check", str(lib)]
    proc = subprocess.run(
        [*cmd, "--with-implementations"],
        capture_output=True,
        text=True,
        timeout=120,
        env=_env(tmp_path),
    )
    assert proc.returncode == 70, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("internal error: ZeroDivisionError: plugin bug; details in ")
    crash = Path(proc.stderr.strip().rsplit(" ", 1)[1])
    assert crash.parent == tmp_path / "state" / "btmission"
    assert "ZeroDivisionError: plugin bug" in crash.read_text()
    # without --with-implementations the plugin's code is not run at all
    ok = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=_env(tmp_path))
    assert ok.returncode == 0, ok.stderr
    assert "buggy: 1 actions, 1 conditions" in ok.stdout


def test_closed_pipe_and_full_disk_on_stdout(tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "btmission", "schema", "mission"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(tmp_path))
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader is gone before anything is written (like `| head -0`)
    err = proc.stderr.read().decode()
    proc.stderr.close()
    assert proc.wait(timeout=120) == 141
    assert err == ""
    if Path("/dev/full").exists():
        with open("/dev/full", "w") as full:
            done = subprocess.run(
                cmd, stdout=full, stderr=subprocess.PIPE, text=True, timeout=120, env=_env(tmp_path)
            )
        assert done.returncode == 2
        assert (
            done.stderr.strip() == "Error: cannot write to standard output: No space left on device"
        )


# ---------------------------------------------------------------- a 1,000-action chain
CHAIN_MISSION = """\
mission: chain
version: 1
world:
  map: {generate: empty, size: [10, 10, 4]}
agents:
  - {id: R1, library: chain.yaml, start: [1, 1, 1]}
tasks:
  - {id: T1, type: deep, location: [5, 5, 1]}
task_types:
  deep: {goal: c%d, cost: distance(location)}
"""


@pytest.fixture(scope="module")
def chain(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """a1 pre c0 post c1, a2 pre c1 post c2, ... a1000 pre c999 post c1000."""
    d = tmp_path_factory.mktemp("chain")
    lines = ["library: chain", "version: 1", "conditions:"]
    lines += [f"  c{i}: condition {i}" for i in range(CHAIN + 1)]
    lines.append("actions:")
    lines += [f"  a{i}: {{pre: [c{i - 1}], post: [c{i}]}}" for i in range(1, CHAIN + 1)]
    (d / "chain.yaml").write_text("\n".join(lines) + "\n")
    (d / "mission.yaml").write_text(CHAIN_MISSION % CHAIN)
    return d


GOAL = f"c{CHAIN}"


def test_chain_synth_ascii(chain: Path) -> None:
    r = invoke("synth", str(chain / "chain.yaml"), "--goal", GOAL)
    assert r.exit_code == 0, r.output
    assert r.stdout.count("\n") == 4 * CHAIN + 1
    assert f"a{CHAIN}" in r.stdout and "a1\n" in r.stdout
    assert f"{4 * CHAIN + 1} nodes" in r.stderr


@pytest.mark.parametrize("suffix", ["json", "dot"])
def test_chain_exports(chain: Path, tmp_path: Path, suffix: str) -> None:
    out = tmp_path / f"t.{suffix}"
    r = invoke("synth", str(chain / "chain.yaml"), "--goal", GOAL, "-o", str(out))
    assert r.exit_code == 0, r.output
    text = out.read_text()
    assert f'"a{CHAIN}"' in text and '"c0"' in text


def test_chain_json_reads_back(chain: Path, tmp_path: Path) -> None:
    from btmission.export.jsonfmt import parse_json
    from btmission.synthesis.tree import walk

    out = tmp_path / "t.json"
    assert invoke("synth", str(chain / "chain.yaml"), "--goal", GOAL, "-o", str(out)).exit_code == 0
    tree = parse_json(out.read_text())
    assert max(d for d, _ in walk(tree)) == 2 * CHAIN


def test_chain_dry_run_ticks_the_whole_depth(chain: Path) -> None:
    before = sys.getrecursionlimit()
    r = invoke(
        "synth", str(chain / "chain.yaml"), "--goal", GOAL, "--dry-run", "--true", "c0",
        "--max-ticks", "3",
    )  # fmt: skip
    assert r.exit_code == 1, r.output  # 3 ticks are not enough for 1,000 actions
    lines = r.stdout.splitlines()
    assert lines[0].endswith("✓ c0  ▶ a1 [1/2]")  # tick 1 went all the way down
    assert lines[1].endswith("● a1 [2/2]  ▶ a2 [1/2]")
    assert (
        lines[-1] == "goal NOT reached (root RUNNING) after 3 tick(s); 0 precondition violation(s)"
    )
    assert sys.getrecursionlimit() == before  # raised for the ticks only


def test_chain_dry_run_failing_at_the_bottom(chain: Path) -> None:
    r = invoke("synth", str(chain / "chain.yaml"), "--goal", GOAL, "--dry-run", "--max-ticks", "2")
    assert r.exit_code == 1, r.output
    assert r.stdout.splitlines()[0].endswith("✗ c1  ✗ c0")
    assert "goal NOT reached (root FAILURE) after 2 tick(s)" in r.stdout


def test_too_deep_for_the_capped_limit_is_a_clear_message(
    chain: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Past the cap the dry run stops with RecursionError (never a crash): exit 2, no traceback."""
    import btmission.recursion

    monkeypatch.setattr(btmission.recursion, "MAX_RECURSION_LIMIT", 1500)
    before = sys.getrecursionlimit()
    r = invoke("synth", str(chain / "chain.yaml"), "--goal", GOAL, "--dry-run", "--max-ticks", "1")
    assert r.exit_code == 2, r.output
    assert r.stderr.strip().endswith(
        f"Error: the tree is too deep to dry-run ({4 * CHAIN + 1} nodes); export it with -o instead"
    )
    assert sys.getrecursionlimit() == before


def test_chain_library_check_and_show(chain: Path) -> None:
    r = invoke("library", "check", str(chain / "chain.yaml"))
    assert r.exit_code == 0, r.output
    assert f"chain: {CHAIN} actions, {CHAIN + 1} conditions — 0 error(s), 1 warning(s)" in r.stdout
    r = invoke("library", "show", str(chain / "chain.yaml"))
    assert r.exit_code == 0 and f"a{CHAIN}" in r.stdout


def test_chain_mission_tree_and_validate(chain: Path, tmp_path: Path) -> None:
    mission = str(chain / "mission.yaml")
    r = invoke("mission", "tree", mission, "--agent", "R1", "-o", str(tmp_path / "r1.json"))
    assert r.exit_code == 0, r.output
    assert f'"a{CHAIN}"' in (tmp_path / "r1.json").read_text()
    r = invoke("validate", mission)
    assert r.exit_code == 0, r.output
    assert "mission 'chain' OK — 1 agent(s) (chain), 1 task(s), 1 task type(s)" in r.stdout


# ---------------------------------------------------------------- output targets
@pytest.fixture
def targets(tmp_path: Path) -> Iterator[Path]:
    (tmp_path / "real.txt").write_text("keep me")
    (tmp_path / "link.txt").symlink_to(tmp_path / "real.txt")
    os.mkfifo(tmp_path / "fifo.txt")
    (tmp_path / "dir.txt").mkdir()
    (tmp_path / "plain").write_text("a file")
    yield tmp_path


def synth_to(path: Path | str) -> Result:
    return invoke("synth", "aerial", "--goal", "at_goal(goal)", "-o", str(path))


def test_refuses_to_replace_a_symlink(targets: Path) -> None:
    r = synth_to(targets / "link.txt")
    assert r.exit_code == 2
    assert f"refusing to write {targets / 'link.txt'}: it is a symbolic link" in r.stderr
    assert (targets / "link.txt").is_symlink()
    assert (targets / "real.txt").read_text() == "keep me"


def test_refuses_a_fifo_without_blocking(targets: Path) -> None:
    r = synth_to(targets / "fifo.txt")  # opening it would block: it is never opened
    assert r.exit_code == 2
    assert f"refusing to write {targets / 'fifo.txt'}: it is a named pipe (FIFO)" in r.stderr


def test_refuses_a_directory(targets: Path) -> None:
    r = synth_to(targets / "dir.txt")
    assert r.exit_code == 2 and "dir.txt' is a directory" in r.stderr
    with pytest.raises(BadInput, match="it is a directory, not a regular file"):
        check_output_target(targets / "dir.txt")


def test_refuses_a_device() -> None:
    """Replacing /dev/null (as root, os.replace would) is never what the user meant."""
    r = synth_to("/dev/null")
    assert r.exit_code == 2
    assert "refusing to write /dev/null: it is a device, not a regular file" in r.stderr


def test_refuses_a_parent_that_is_a_file(targets: Path) -> None:
    r = synth_to(targets / "plain" / "t.txt")
    assert r.exit_code == 2
    assert (
        f"cannot write {targets / 'plain' / 't.txt'}: {targets / 'plain'} is not a directory"
        in r.stderr
    )


def test_refuses_an_unwritable_directory(targets: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ro = targets / "ro"
    ro.mkdir()
    if os.geteuid() != 0:  # root may write anywhere: there, pretend the directory is read-only
        ro.chmod(0o555)
    else:
        real_access = os.access
        monkeypatch.setattr(
            os, "access", lambda p, mode: False if Path(p) == ro else real_access(p, mode)
        )
    try:
        r = synth_to(ro / "t.txt")
    finally:
        ro.chmod(0o755)
    assert r.exit_code == 2
    assert f"cannot write {ro / 't.txt'}: permission denied in {ro}" in r.stderr
    assert list(ro.iterdir()) == []


def test_disk_full_while_writing_is_a_clear_message(
    targets: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The temporary file is on a full disk (/dev/full): ENOSPC, the old file is kept."""
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    real_mkstemp = tempfile.mkstemp

    def full_mkstemp(*args: object, **kwargs: object) -> tuple[int, str]:
        fd, name = real_mkstemp(*args, **kwargs)  # type: ignore[call-overload]
        os.dup2(os.open("/dev/full", os.O_WRONLY), fd)
        return fd, name

    monkeypatch.setattr(common.tempfile, "mkstemp", full_mkstemp)
    r = synth_to(targets / "real.txt")
    assert r.exit_code == 2
    assert f"cannot write {targets / 'real.txt'}: No space left on device" in r.stderr
    assert (targets / "real.txt").read_text() == "keep me"
    assert sorted(p.name for p in targets.iterdir()) == [
        "dir.txt",
        "fifo.txt",
        "link.txt",
        "plain",
        "real.txt",
    ]  # fmt: skip  (no temporary file left behind)


def test_directory_targets(targets: Path) -> None:
    """A directory option accepts a directory, a link to one and a new path; nothing else."""
    (targets / "runs").symlink_to(targets / "dir.txt")
    for ok in ("dir.txt", "runs", "new/deeper"):
        assert check_output_target(targets / ok, "dir") == targets / ok
    for bad, what in (("real.txt", "a file"), ("fifo.txt", "a named pipe (FIFO)")):
        with pytest.raises(BadInput, match=rf"is {re.escape(what)}, not a directory"):
            check_output_target(targets / bad, "dir")
    r = invoke("report", "x.jsonl", "--png", str(targets / "real.txt"))
    assert r.exit_code == 2
    assert f"Directory '{targets / 'real.txt'}' is a file." in r.stderr  # click's own check


def test_writes_a_regular_file_atomically(targets: Path) -> None:
    r = synth_to(targets / "real.txt")
    assert r.exit_code == 0 and f"wrote {targets / 'real.txt'}" in r.stderr
    assert (targets / "real.txt").read_text().startswith("? Fallback")


# Every output option of every command, given a FIFO: refused before anything runs.
OUTPUT_OPTIONS = [
    ["synth", "aerial", "--goal", "at_goal(goal)", "-o", "{t}"],
    ["mission", "tree", "missions/mine_inspection.yaml", "--agent", "R1", "-o", "{t}"],
    ["schema", "mission", "-o", "{t}"],
    ["control", "plot", "apf", "-o", "{t}"],
    ["dispatch", "map", "x.yaml", "-o", "{t}"],
    ["dispatch", "static", "x.yaml", "--gantt", "{t}"],
    ["dispatch", "dynamic", "x.yaml", "--gantt", "{t}"],
    ["dispatch", "plan", "x.yaml", "-o", "{t}"],
    ["map", "generate", "-o", "{t}"],
    ["map", "generate", "-o", "{ok}", "--survey", "{t}"],
    ["map", "show", "x.npz", "--png", "{t}"],
    ["plan", "x.npz", "--from", "0,0,0", "--to", "1,1,1", "--png", "{t}"],
    ["reloc", "build", "x.npz", "-o", "{t}"],
    ["reloc", "scan", "x.npz", "--at", "0,0,0", "-o", "{t}"],
    ["bench", "auction", "--png", "{t}"],
    ["bench", "synth", "--out", "{t}"],
    ["run", "missions/pick_and_deliver.yaml", "--log", "{t}"],
    ["report", "x.jsonl", "--png", "{t}"],
    ["library", "new", "thing", "-o", "{t}"],
]


@pytest.mark.parametrize("args", OUTPUT_OPTIONS, ids=lambda a: " ".join(a[:2]))
def test_every_output_option_refuses_a_fifo(
    args: list[str], targets: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(REPO)
    fifo = targets / "fifo.txt"
    argv = [a.format(t=fifo, ok=targets / "ok.npz") for a in args]
    r = invoke(*argv)
    assert r.exit_code == 2, r.output
    assert str(fifo) in r.stderr or "'fifo.txt'" in r.stderr, r.stderr
    assert "Traceback" not in r.output
    assert not (targets / "ok.npz").exists()


# ---------------------------------------------------------------- checking is not running
MARKED_LIBRARY = """\
library: marked
version: 1
module: marker_impl
conditions: {done: Done, ready: Ready}
actions:
  prepare: {post: [ready]}
  work: {pre: [ready], post: [done]}
"""

MARKER_MODULE = """\
import os
from pathlib import Path
Path(os.environ["BTMISSION_TEST_MARKER"]).write_text("imported")
"""

MARKED_MISSION = """\
mission: marked
version: 1
world:
  map: {generate: empty, size: [10, 10, 4]}
agents:
  - {id: R1, library: marked.yaml, start: [1, 1, 1]}
tasks:
  - {id: T1, type: job, location: [5, 5, 1]}
task_types:
  job: {goal: done, cost: distance(location)}
"""


@pytest.fixture
def marked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    (tmp_path / "marker_impl.py").write_text(MARKER_MODULE)
    (tmp_path / "marked.yaml").write_text(MARKED_LIBRARY)
    (tmp_path / "mission.yaml").write_text(MARKED_MISSION)
    monkeypatch.setenv("BTMISSION_TEST_MARKER", str(tmp_path / "MARKER"))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    sys.modules.pop("marker_impl", None)


CHECKING = [
    ["library", "check", "{d}/marked.yaml"],
    ["library", "show", "{d}/marked.yaml"],
    ["synth", "{d}/marked.yaml", "--goal", "done"],
    ["synth", "{d}/marked.yaml", "--goal", "done", "--dry-run"],
    ["validate", "{d}/mission.yaml"],
    ["mission", "tree", "{d}/mission.yaml", "--agent", "R1"],
]


@pytest.mark.parametrize("args", CHECKING, ids=lambda a: " ".join(a[:2]))
def test_checking_does_not_import_the_module(args: list[str], marked: Path) -> None:
    argv = [a.format(d=marked) for a in args]
    r = invoke(*argv)
    assert r.exit_code == 0, r.output
    assert not (marked / "MARKER").exists()
    assert "marker_impl" not in sys.modules
    r = invoke(*argv, "--with-implementations")
    if args[0] == "validate":  # validate then checks what run needs: a registry of implementations
        assert r.exit_code == 2, r.output
        assert "module 'marker_impl' has no IMPLEMENTATIONS registry" in r.output
    else:
        assert r.exit_code == 0, r.output
    assert (marked / "MARKER").read_text() == "imported"


def test_show_says_the_module_was_not_imported(marked: Path) -> None:
    r = invoke("library", "show", str(marked / "marked.yaml"))
    assert "  module: marker_impl  (not imported; --with-implementations imports it)" in r.stdout
    assert r.stdout.rstrip().endswith(
        "(implementations not loaded: give --with-implementations to mark them)"
    )


def test_with_implementations_reports_what_is_implemented(marked: Path) -> None:
    (marked / "marker_impl.py").write_text(
        MARKER_MODULE
        + "from btmission.plugins import Implementations\n"
        + "IMPLEMENTATIONS = Implementations('marked')\n"
        + "IMPLEMENTATIONS.condition('ready')(lambda ctx: True)\n"
        + "IMPLEMENTATIONS.condition('bogus')(lambda ctx: True)\n"
    )
    r = invoke("library", "check", str(marked / "marked.yaml"), "--with-implementations")
    assert r.exit_code == 1
    assert (
        "module marker_impl implements condition 'bogus', which the library does not declare"
        in r.stderr
    )
    r = invoke("library", "show", str(marked / "marked.yaml"), "--with-implementations")
    assert " *ready " in r.stdout and "(* = implemented)" in r.stdout


def test_python_api_still_imports_by_default(marked: Path) -> None:
    from btmission.plugins import implementation_imports, load_library

    with implementation_imports("installed"):
        assert load_library(str(marked / "marked.yaml")).module_not_imported
    assert not (marked / "MARKER").exists()
    loaded = load_library(str(marked / "marked.yaml"))
    assert not loaded.module_not_imported
    assert (marked / "MARKER").exists()


def test_quiet_composites_tick_exactly_like_py_trees(monkeypatch: pytest.MonkeyPatch) -> None:
    """The dry run's quiet composites give the same trace as plain py_trees ones."""
    import btmission.synthesis.dryrun as dryrun
    from btmission.plugins import load_library
    from btmission.synthesis.backchain import synthesize
    from btmission.synthesis.pytrees import LeafFactory, build_behaviour_tree
    from btmission.synthesis.tree import Node

    def traces() -> list[str]:
        out = []
        cases: list[tuple[str, str | None, list[dict[str, bool]]]] = [
            ("aerial", "at_goal(goal)", [{}, {"is_flying": True}, {"has_home": True}]),
            ("aerial", "landed_at_home", [{}, {"has_home": True}]),
            ("ground", "delivered(pickup, dropoff)", [{}, {"is_localized": True}]),
            ("compra", None, [{}]),
            (str(REPO / "docs/examples/design.yaml"), "at_goal(goal)", [{}, {"battery_ok": True}]),
        ]
        for name, goal, starts in cases:
            lib = load_library(name).library
            goals = [goal] if goal else [str(g) for g in lib.goals[:1]]
            tree = synthesize(lib, goals).tree
            for start in starts:
                for ticks in (1, 2, 3):
                    r = dryrun.dry_run(tree, lib, start, action_ticks=ticks, max_ticks=60)
                    out.append(r.format_trace())
        return out

    quiet = traces()

    def plain(tree: Node, leaf: LeafFactory, quiet: bool = False) -> object:
        return build_behaviour_tree(tree, leaf)

    monkeypatch.setattr(dryrun, "build_behaviour_tree", plain)
    assert traces() == quiet
    assert any("\ngoal reached" in t for t in quiet)
    assert any("goal NOT reached" in t for t in quiet)


def test_a_module_that_does_not_exist_is_found_missing_without_importing(
    marked: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """validate says what run would: the module is looked up, not executed."""
    lib = (marked / "marked.yaml").read_text()
    (marked / "marked.yaml").write_text(lib.replace("module: marker_impl", "module: no_such_mod"))
    r = invoke("validate", str(marked / "mission.yaml"))
    assert r.exit_code == 2, r.output
    assert (
        "library 'marked.yaml' cannot run: ModuleNotFoundError: No module named 'no_such_mod'"
        in r.output
    )
    # a module inside a package is found without running the package's __init__ either
    pkg = marked / "markpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(MARKER_MODULE)
    (pkg / "impl.py").write_text(MARKER_MODULE)
    (marked / "marked.yaml").write_text(lib.replace("module: marker_impl", "module: markpkg.impl"))
    r = invoke("validate", str(marked / "mission.yaml"))
    assert r.exit_code == 0, r.output
    assert not (marked / "MARKER").exists()
    assert "markpkg" not in sys.modules
    (marked / "marked.yaml").write_text(lib.replace("module: marker_impl", "module: markpkg.nope"))
    r = invoke("validate", str(marked / "mission.yaml"))
    assert r.exit_code == 2 and "No module named 'markpkg.nope'" in r.output, r.output
    assert not (marked / "MARKER").exists()


# ------------------------------------------------------------------------- start-up
def test_import_btmission_is_light() -> None:
    """The API is imported on first use, so the command's Ctrl-C handling starts in milliseconds."""
    code = "import sys, btmission; print(sorted({'numpy', 'pydantic', 'py_trees', 'click'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr
    import btmission

    assert btmission.synthesize.__module__ == "btmission.synthesis.backchain"
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        btmission.nope  # noqa: B018


def test_ctrl_c_while_the_commands_are_imported_is_exit_130_without_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import types

    from btmission.cli import launch

    class Interrupted(types.ModuleType):
        def __getattr__(self, name: str) -> object:
            raise KeyboardInterrupt

    monkeypatch.setitem(sys.modules, "btmission.cli.main", Interrupted("btmission.cli.main"))
    with pytest.raises(SystemExit) as stop:
        launch.main()
    assert stop.value.code == 130
    assert capsys.readouterr().err == "\ninterrupted\n"
