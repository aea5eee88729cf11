"""The click CLI through CliRunner: outputs, exit codes (0 ok, 1 checks failed, 2 bad input),
one clear message per problem and never a traceback."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission import __version__
from btmission.cli.main import cli
from btmission.export import graphviz_available

ROOT = Path(__file__).resolve().parents[2]
MINE = str(ROOT / "missions" / "mine_inspection.yaml")
PICK = str(ROOT / "missions" / "pick_and_deliver.yaml")


def run(runner: CliRunner, *args: str) -> tuple[int, str, str]:
    r = runner.invoke(cli, list(args))
    assert "Traceback" not in r.output + r.stderr, r.output + r.stderr
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        raise r.exception
    return r.exit_code, r.stdout, r.stderr


def test_version(runner: CliRunner) -> None:
    code, out, _ = run(runner, "--version")
    assert code == 0 and __version__ in out


@pytest.mark.parametrize(
    "args",
    [[], ["library"], ["synth"], ["mission", "tree"], ["validate"], ["schema"], ["bench", "synth"]],
)
def test_every_command_has_help(runner: CliRunner, args: list[str]) -> None:
    code, out, _ = run(runner, *args, "--help")
    assert code == 0 and "Usage:" in out and len(out.splitlines()) > 4


def test_library_list_and_json(runner: CliRunner) -> None:
    code, out, _ = run(runner, "library", "list")
    assert code == 0
    for name in ("aerial", "ground", "compra"):
        assert name in out
    code, out, _ = run(runner, "library", "list", "--json")
    rows = {r["name"]: r for r in json.loads(out)}
    assert rows["aerial"]["actions"] == 7 and rows["aerial"]["conditions"] == 7


def test_library_show(runner: CliRunner) -> None:
    code, out, _ = run(runner, "library", "show", "aerial")
    assert code == 0
    assert (
        "follow_path(goal)" in out
        and "pre: is_flying, has_path(goal)  →  post: at_goal(goal)" in out
    )


@pytest.mark.parametrize("name", ["aerial", "ground", "compra"])
def test_library_check_builtin_strict(runner: CliRunner, name: str) -> None:
    code, out, _ = run(runner, "library", "check", name, "--strict")
    assert code == 0 and "0 error(s), 0 warning(s)" in out


BAD_CYCLE = "library: c\nversion: 1\nconditions: {a: '', b: ''}\nactions:\n  A: {pre: [b], post: [a]}\n  B: {pre: [a], post: [b]}\n"
ASSUMED = (
    "library: s\nversion: 1\nconditions: {a: '', ok: ''}\nactions:\n  A: {pre: [ok], post: [a]}\n"
)


def test_library_check_exit_codes(runner: CliRunner, tmp_path: Path) -> None:
    cyc = tmp_path / "cyc.yaml"
    cyc.write_text(BAD_CYCLE)
    code, _, err = run(runner, "library", "check", str(cyc))
    assert (
        code == 1
        and "cycle between pre- and postconditions: a (by A) needs b (by B) needs a" in err
    )
    assumed = tmp_path / "assumed.yaml"
    assumed.write_text(ASSUMED)
    assert run(runner, "library", "check", str(assumed))[0] == 0
    code, _, err = run(runner, "library", "check", str(assumed), "--strict")
    assert code == 1 and "'ok' is assumed" in err
    broken = tmp_path / "broken.yaml"
    broken.write_text("library: x\nversion: 1\nconditions: [\n")
    code, _, err = run(runner, "library", "check", str(broken))
    assert code == 2 and f"{broken}:" in err and "YAML syntax error" in err
    code, _, err = run(runner, "library", "check", "nonexistent_lib")
    assert code == 2 and "unknown library 'nonexistent_lib'" in err


def test_library_check_json(runner: CliRunner, tmp_path: Path) -> None:
    cyc = tmp_path / "cyc.yaml"
    cyc.write_text(BAD_CYCLE)
    code, out, _ = run(runner, "library", "check", str(cyc), "--json")
    data = json.loads(out)
    assert code == 1 and data["ok"] is False
    assert [f["code"] for f in data["findings"] if f["severity"] == "error"] == ["cycle"]


def test_synth_ascii_is_fig8(runner: CliRunner) -> None:
    code, out, err = run(runner, "synth", "aerial", "--goal", "at_goal(goal)")
    assert code == 0
    lines = out.splitlines()
    assert lines[0] == "? Fallback: at_goal(goal)" and len(lines) == 20
    assert "20 nodes; inputs: goal" in err


@pytest.mark.parametrize("fmt", ["dot", "xml", "json"])
def test_synth_text_formats_contain_every_node(runner: CliRunner, fmt: str, tmp_path: Path) -> None:
    out_file = tmp_path / f"t.{fmt}"
    code, _, _ = run(runner, "synth", "aerial", "--goal", "at_goal(goal)", "-o", str(out_file))
    assert code == 0
    text = out_file.read_text()
    for name in (
        "at_goal",
        "is_flying",
        "set_home",
        "arm",
        "set_offboard",
        "takeoff",
        "update_path",
        "follow_path",
    ):
        assert name in text
    if fmt == "xml":
        root = ET.fromstring(text)
        assert root.get("BTCPP_format") == "4"
        assert len(list(root.find("BehaviorTree").iter())) == 1 + 20
    if fmt == "json":
        data = json.loads(text)
        assert (
            data["library"] == "aerial"
            and data["goals"] == ["at_goal(goal)"]
            and data["inputs"] == ["goal"]
        )


@pytest.mark.skipif(not graphviz_available(), reason="graphviz 'dot' is not installed")
def test_synth_png_and_svg(runner: CliRunner, tmp_path: Path) -> None:
    assert (
        run(runner, "synth", "aerial", "--goal", "landed_at_home", "-o", str(tmp_path / "t.png"))[0]
        == 0
    )
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (
        run(
            runner,
            "synth",
            "aerial",
            "--goal",
            "landed_at_home",
            "-f",
            "svg",
            "-o",
            str(tmp_path / "x"),
        )[0]
        == 0
    )
    ET.fromstring((tmp_path / "x").read_text())


def test_svg_without_graphviz_is_a_clear_error(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))
    target = tmp_path / "t.svg"
    target.write_text("previous content")
    code, _, err = run(runner, "synth", "aerial", "--goal", "landed_at_home", "-o", str(target))
    assert code == 2 and "graphviz 'dot' was not found" in err
    assert target.read_text() == "previous content"  # nothing already written is lost


def test_synth_dry_run(runner: CliRunner) -> None:
    code, out, _ = run(
        runner,
        "synth",
        "aerial",
        "--goal",
        "at_goal(goal)",
        "--dry-run",
        "--true",
        "has_home",
        "--ascii-only",
    )
    assert code == 0
    assert out.splitlines()[0].startswith(
        "tick   1: - at_goal(goal)  - is_flying  + has_home  - is_armed  > arm [1/2]"
    )
    assert "goal reached after 6 tick(s); 0 precondition violation(s)" in out


def test_synth_dry_run_that_cannot_finish_exits_1(runner: CliRunner, tmp_path: Path) -> None:
    lib = tmp_path / "s.yaml"
    lib.write_text(ASSUMED)
    code, out, err = run(runner, "synth", str(lib), "--goal", "a", "--dry-run", "--max-ticks", "5")
    assert code == 1 and "goal NOT reached" in out and "did not reach the goal" in err


def test_synth_bad_inputs_exit_2(runner: CliRunner, tmp_path: Path) -> None:
    code, _, err = run(runner, "synth", "aerial", "--goal", "at_gaol(goal)")
    assert code == 2 and "undefined condition 'at_gaol' (did you mean 'at_goal'?)" in err
    code, _, err = run(runner, "synth", "aerial")
    assert code == 2 and "give a goal with --goal" in err
    code, _, err = run(runner, "synth", "aerial", "--goal", "at_goal(a, b)")
    assert code == 2 and "takes 1" in err
    code, _, _ = run(runner, "synth", "aerial", "--goal", "is_armed", "-f", "gif")
    assert code == 2


def test_synth_cycle_exits_1(runner: CliRunner, tmp_path: Path) -> None:
    cyc = tmp_path / "cyc.yaml"
    cyc.write_text(BAD_CYCLE)
    code, out, err = run(runner, "synth", str(cyc), "--goal", "a")
    assert code == 1 and "[cycle!]" in out and "cycle between" in err


def test_validate(runner: CliRunner, tmp_path: Path) -> None:
    code, out, _ = run(runner, "validate", MINE)
    assert code == 0 and "3 agent(s) (aerial), 7 task(s), 1 task type(s)" in out
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        Path(MINE)
        .read_text()
        .replace("id: R2", "id: R1")
        .replace("type: inspect, location: [64.4", "type: inspct, location: [64.4")
    )
    code, out, err = run(runner, "validate", str(bad))
    assert code == 2 and out == ""
    lines = [line for line in err.splitlines() if line.startswith(str(bad))]
    assert len(lines) == 2
    assert "agents[1].id: duplicate agent id 'R1'" in lines[0]
    assert "tasks[0].type: unknown task type 'inspct' (did you mean 'inspect'?)" in lines[1]
    code, _, err = run(runner, "validate", str(tmp_path / "missing.yaml"))
    assert code == 2 and "file not found" in err


def test_mission_tree(runner: CliRunner) -> None:
    code, out, _ = run(runner, "mission", "tree", PICK, "--agent", "G1")
    assert code == 0
    lines = out.splitlines()
    assert lines[0] == "? Fallback: mission(G1)"
    assert (
        "→ Sequence: task(pick_and_deliver) {commit_after=holding(pickup), task_type=pick_and_deliver}"
        in out
    )
    assert '(idle_timeout("5")) [builtin]' in out and lines[-1].endswith("[wait] [builtin]")
    code, out, _ = run(
        runner, "mission", "tree", PICK, "--agent", "G1", "--task-type", "inspect", "-f", "json"
    )
    data = json.loads(out)
    assert code == 0 and data["branches"] == ["inspect", "default"]


def test_mission_tree_bad_agent_and_type(runner: CliRunner) -> None:
    code, _, err = run(runner, "mission", "tree", MINE, "--agent", "R9")
    assert code == 2 and "no agent 'R9' (agents: R1, R2, R3)" in err
    code, _, err = run(runner, "mission", "tree", MINE, "--agent", "R1", "--task-type", "haul")
    assert code == 2 and "no task type 'haul'" in err


@pytest.mark.parametrize("kind", ["library", "mission"])
def test_schema(runner: CliRunner, kind: str, tmp_path: Path) -> None:
    code, out, _ = run(runner, "schema", kind)
    schema = json.loads(out)
    assert code == 0 and schema["title"].startswith(f"btmission {kind} file")
    assert run(runner, "schema", kind, "-o", str(tmp_path / "s.json"))[0] == 0
    assert json.loads((tmp_path / "s.json").read_text()) == schema


def test_bench_synth_small(runner: CliRunner, tmp_path: Path) -> None:
    code, _, _ = run(
        runner, "bench", "synth", "--sizes", "5,10", "--repeat", "1", "--out", str(tmp_path)
    )
    assert code == 0 and (tmp_path / "synth.md").exists() and (tmp_path / "synth.csv").exists()
    code, _, err = run(runner, "bench", "synth", "--sizes", "x")
    assert code == 2 and "comma-separated integers" in err


def test_xml_export_of_unrepresentable_tree_is_a_clear_error(
    runner: CliRunner, tmp_path: Path
) -> None:
    lib = tmp_path / "arm.yaml"
    lib.write_text(
        "library: arm\nversion: 1\nconditions: {tagged: {params: [name]}, armed: ''}\n"
        "actions:\n  tag: {params: [name], post: [tagged(name)]}\n  arm: {post: [armed]}\n"
    )
    code, _, err = run(runner, "library", "check", str(lib))
    assert code == 0 and "btcpp-reserved" not in err and "reserved attribute names" in err
    code, _, err = run(runner, "synth", str(lib), "--goal", "tagged(x)", "-f", "xml")
    assert code == 2 and "cannot export as xml:" in err
    # the library is named like one of its actions: the tree ID is made distinct, export works
    code, out, _ = run(runner, "synth", str(lib), "--goal", "armed", "-f", "xml")
    assert code == 0 and 'main_tree_to_execute="arm_tree"' in out


def test_unknown_output_suffix_is_refused(runner: CliRunner, tmp_path: Path) -> None:
    code, _, err = run(
        runner, "synth", "aerial", "--goal", "is_armed", "-o", str(tmp_path / "t.jpg")
    )
    assert code == 2 and "cannot tell the format from 't.jpg'" in err
    assert not (tmp_path / "t.jpg").exists()
    assert (
        run(runner, "synth", "aerial", "--goal", "is_armed", "-o", str(tmp_path / "plain"))[0] == 0
    )
    assert (tmp_path / "plain").read_text().startswith("? Fallback: is_armed")


def test_output_files_get_normal_permissions(runner: CliRunner, tmp_path: Path) -> None:
    out = tmp_path / "t.json"
    assert run(runner, "synth", "aerial", "--goal", "is_armed", "-o", str(out))[0] == 0
    assert out.stat().st_mode & 0o044 == 0o044  # group/other readable (umask permitting)


def test_dry_run_true_option_is_named_in_errors(runner: CliRunner) -> None:
    code, _, err = run(
        runner, "synth", "aerial", "--goal", "is_armed", "--dry-run", "--true", "bogus"
    )
    assert code == 2 and "--true: undefined condition 'bogus'" in err
    code, _, err = run(
        runner, "synth", "aerial", "--goal", "is_armed", "--dry-run", "--true", "has_home"
    )
    assert code == 0 and "note: --true has_home: no such condition in this tree" in err


def test_library_path_not_found(runner: CliRunner) -> None:
    code, _, err = run(runner, "library", "check", "libs/none.yaml")
    assert code == 2 and "library file 'libs/none.yaml' not found" in err


def test_validate_strict_does_not_claim_ok(runner: CliRunner, tmp_path: Path) -> None:
    lib = tmp_path / "s.yaml"
    lib.write_text(
        "library: s\nversion: 1\nconditions: {at_goal: {params: [goal]}, ok: ''}\n"
        "actions:\n  go: {params: [goal], pre: [ok], post: [at_goal(goal)]}\n"
    )
    m = tmp_path / "m.yaml"
    m.write_text(
        "mission: m\nversion: 1\nworld: {map: {generate: empty, size: [10, 10, 3]}}\n"
        "agents: [{id: A, library: s.yaml, start: [0, 0, 0]}]\n"
        "task_types: {go: {goal: at_goal(location), cost: 1}}\n"
    )
    code, out, err = run(runner, "validate", str(m))
    assert code == 0 and "OK" in out and "'ok' is assumed" in err
    code, out, err = run(runner, "validate", str(m), "--strict")
    assert code == 1 and "OK" not in out and "warnings are errors under --strict" in err


def test_library_check_warns_of_a_leaf_named_like_a_btcpp_node_type(
    runner: CliRunner, tmp_path: Path
) -> None:
    """`-f xml` refuses such a leaf (exit 2); `library check` says so before anyone exports."""
    lib = tmp_path / "nap.yaml"
    lib.write_text(
        "library: nap\nversion: 1\nconditions: {rested: Rested}\n"
        "actions:\n  Sleep: {post: [rested]}\n"
    )
    code, _, err = run(runner, "library", "check", str(lib))
    assert code == 0
    assert (
        f"{lib}:5:3: warning: actions.Sleep: action 'Sleep' has the name of one of "
        "BehaviorTree.CPP's own node types or XML elements: the tree synthesises but cannot be "
        "exported with -f xml"
    ) in err
    code, _, err = run(runner, "synth", str(lib), "--goal", "rested", "-f", "xml")
    assert code == 2 and "'Sleep' is the name of one of BehaviorTree.CPP's own node types" in err


def test_top_level_help_lists_every_command_with_its_own_short_help() -> None:
    import click

    from btmission.cli.main import COMMANDS

    ctx = click.Context(cli)
    for name, (_, _, short) in COMMANDS.items():
        command = cli.commands[name]
        assert command.name == name
        assert command.get_short_help_str(1000) == short, name
    assert sorted(cli.list_commands(ctx)) == sorted(COMMANDS)


def modules_after(commands: list[list[str]], loaded_if: str) -> tuple[str, list[str]]:
    """Run ``btmission COMMAND`` for each of ``commands`` in one fresh interpreter: its output
    (with ``EXIT n`` after each command) and the imported modules ``m`` for which the expression
    ``loaded_if`` holds."""
    import ast
    import subprocess
    import sys

    probe = (
        "import sys\n"
        "from btmission.cli.main import cli\n"
        f"for args in {commands!r}:\n"
        "    try:\n"
        "        cli.main(args, prog_name='btmission')\n"
        "    except SystemExit as exc:\n"
        "        print('EXIT', exc.code)\n"
        f"print('LOADED', sorted(m for m in sys.modules if {loaded_if}))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    head, _, loaded = out.rpartition("LOADED ")
    return head, ast.literal_eval(loaded)


def test_help_and_version_import_no_command_module() -> None:
    heavy = ("numpy", "pydantic", "scipy", "py_trees", "yaml")
    out, loaded = modules_after([["--help"], ["--version"]], f"m in {heavy} or m.endswith('_cmds')")
    assert "Commands:" in out and "validate     Validate a mission file" in out
    assert loaded == []


def test_validate_imports_no_scipy_no_exporter_and_no_dry_run() -> None:
    """validate's path (issue 19): reachability labels runs with numpy (no scipy.ndimage, no numba
    kernels), and neither the exporters nor the dry run are imported to parse its options."""
    banned = ("scipy", "numba", "btmission.export.", "btmission.synthesis.dryrun")
    out, loaded = modules_after([["validate", MINE]], f"m.startswith({banned})")
    assert "mission 'mine_inspection' OK" in out and out.strip().endswith("EXIT 0")
    assert loaded == []
