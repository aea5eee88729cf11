"""Every exported tree loads, is checked, instantiates and ticks in real BehaviorTree.CPP.

Each case runs through two checkers, which print the same one-line report:

* ``behaviortreepy``, always: tests/btcpp_py.py, on the BehaviorTree.CPP that the PyPI package
  behaviortreepy bundles (4.8.2 in 0.1.4; a ``test`` extra of pyproject.toml). Its nodes cannot
  declare ports, so it checks the leaves' ports against ``<TreeNodesModel>`` in Python and hands
  each leaf to BehaviorTree.CPP as a SubTree call (tests/btcpp/README.md says how and what that
  leaves out).
* ``btcpp_check``, where a BehaviorTree.CPP build with our C++ loader is present
  (tests/btcpp/README.md): ``BTCPP_CHECK=/path/to/btcpp_check``, or ``BTCPP_PREFIX=/prefix``
  holding ``bin/btcpp_check``. Otherwise its half of each test is skipped with the reason. It
  registers the file's ``<TreeNodesModel>`` as dummy nodes with their ports, runs
  ``BT::VerifyXML`` and ``createTreeFromText``, reads every input port of every node, and ticks
  the tree to completion.
"""

from __future__ import annotations

import os
import re
import subprocess
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from btmission.cli.main import cli
from btmission.export import btcpp as btcpp_module
from btmission.plugins import installed_libraries, load_library
from tests.btcpp_py import CheckFailed, check_xml, main

ROOT = Path(__file__).resolve().parents[2]
MISSIONS = sorted((ROOT / "missions").glob("*.yaml"))
CHAIN_LENGTH = 1000
CHECK_TIMEOUT_S = 120

Check = Callable[[Path], tuple[int, str]]
"""A checker: exit status (0 OK, 1 FAIL) and its one-line report, ``OK: …`` or ``FAIL: …``."""


def _cpp_checker() -> Path | None:
    explicit = os.environ.get("BTCPP_CHECK")
    if explicit:
        return Path(explicit)
    prefix = os.environ.get("BTCPP_PREFIX")
    if prefix:
        return Path(prefix) / "bin" / "btcpp_check"
    return None


def behaviortreepy_check(xml: Path) -> tuple[int, str]:
    try:
        return 0, check_xml(xml).line()
    except CheckFailed as exc:
        return 1, f"FAIL: {xml}: {exc}"


def _cpp_check_or_skip() -> Check:
    path = _cpp_checker()
    if path is None:
        pytest.skip(
            "no BehaviorTree.CPP build: set BTCPP_CHECK to a built tests/btcpp/btcpp_check "
            "(or BTCPP_PREFIX to its install prefix); see tests/btcpp/README.md"
        )
    if not (path.is_file() and os.access(path, os.X_OK)):
        pytest.fail(f"BTCPP_CHECK/BTCPP_PREFIX give {path}, which is not an executable file")

    def cpp_check(xml: Path) -> tuple[int, str]:
        done = subprocess.run(
            [str(path), str(xml)],
            capture_output=True,
            text=True,
            timeout=CHECK_TIMEOUT_S,
            check=False,
        )
        return done.returncode, done.stdout + done.stderr

    return cpp_check


@pytest.fixture(scope="module", params=["behaviortreepy", "btcpp_check"])
def checker(request: pytest.FixtureRequest) -> Check:
    """Each checker in turn: behaviortreepy always, the C++ loader where it is built."""
    return behaviortreepy_check if request.param == "behaviortreepy" else _cpp_check_or_skip()


@pytest.fixture(scope="module")
def cpp_checker() -> Check:
    """The C++ loader alone, for what only it can show (nodes registered with their ports)."""
    return _cpp_check_or_skip()


def export(args: list[str], out: Path) -> Path:
    result = CliRunner().invoke(cli, [*args, "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert out.is_file()
    return out


def assert_loads(checker: Check, xml: Path) -> str:
    code, output = checker(xml)
    assert code == 0 and output.startswith("OK: "), output
    assert "-> SUCCESS" in output or "-> FAILURE" in output, output
    return output


def assert_fails(checker: Check, xml: Path, *expected: str) -> str:
    code, output = checker(xml)
    assert code == 1 and output.startswith("FAIL: "), output
    for text in expected:
        assert text in output, output
    return output


# ------------------------------------------------------------------------------------- cases
LIBRARY_GOALS = [
    (name, str(goal))
    for name in sorted(installed_libraries())
    if name in ("aerial", "aerial_mine", "compra", "ground", "haulage")
    for goal in load_library(name).library.goals
]
MISSION_AGENTS = [
    (mission.name, agent["id"])
    for mission in MISSIONS
    for agent in yaml.safe_load(mission.read_text(encoding="utf-8"))["agents"]
]


def fig8(tmp_path: Path) -> Path:
    return export(["synth", "aerial", "--goal", "at_goal(goal)"], tmp_path / "fig8.xml")


def test_fig8(checker: Check, tmp_path: Path) -> None:
    """Seed 000 Fig. 8: the aerial library's tree for at_goal(goal)."""
    out = assert_loads(checker, fig8(tmp_path))
    assert "1 blackboard keys" in out  # {goal} is read through the ports


GOAL_READERS = ("at_goal", "has_path", "update_path", "follow_path")


def test_fig8_in_behaviortreepy(tmp_path: Path) -> None:
    """What BehaviorTree.CPP did with Fig. 8's 12 leaves (one instance each).

    btcpp_check's leaves: on tick 1 at_goal, is_flying and has_home fail and set_home starts
    (RUNNING); on tick 2 at_goal succeeds, and the ReactiveFallback halts set_home. With
    conditions failing and actions succeeding, one tick walks every branch of the tree."""
    report = check_xml(fig8(tmp_path))
    assert (report.ticks, report.status, report.leaf_ticks, report.halts) == (2, "SUCCESS", 5, 1)
    assert report.ticked_types == {"at_goal", "is_flying", "has_home", "set_home"}
    assert report.leaves == report.branch_leaves == 12
    assert report.branch_status == "SUCCESS"
    # each leaf with a port read {goal} once, through BehaviorTree.CPP's blackboard
    assert report.reads == Counter({(leaf, "goal", "value of goal"): 1 for leaf in GOAL_READERS})


def test_fig8_as_subtrees(checker: Check, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Fig. 8 cut into SubTrees every 2 levels (as a 1,000-action chain is every 128): the
    leaves read {goal} through the chain of ``_autoremap`` SubTrees."""
    monkeypatch.setattr(btcpp_module, "SUBTREE_DEPTH", 2)
    xml = fig8(tmp_path)
    assert xml.read_text(encoding="utf-8").count("<BehaviorTree ") > 3
    out = assert_loads(checker, xml)
    assert "1 blackboard keys" in out and "6 (sub)trees" in out
    if checker is behaviortreepy_check:
        report = check_xml(xml)
        assert report.reads == Counter(
            {(leaf, "goal", "value of goal"): 1 for leaf in GOAL_READERS}
        )
        assert report.branch_leaves == 12


def test_fig9(checker: Check, tmp_path: Path) -> None:
    """Seed 000 Fig. 9: the default (idle) behaviour, return home and land."""
    assert_loads(
        checker, export(["synth", "aerial", "--goal", "landed_at_home"], tmp_path / "f.xml")
    )


@pytest.mark.parametrize(("library", "goal"), LIBRARY_GOALS)
def test_library_goal(checker: Check, tmp_path: Path, library: str, goal: str) -> None:
    assert_loads(checker, export(["synth", library, "--goal", goal], tmp_path / "tree.xml"))


@pytest.mark.parametrize(("mission", "agent"), MISSION_AGENTS)
def test_mission_tree(checker: Check, tmp_path: Path, mission: str, agent: str) -> None:
    path = ROOT / "missions" / mission
    xml = export(["mission", "tree", str(path), "--agent", agent], tmp_path / "mission.xml")
    assert_loads(checker, xml)


def test_mission_tree_literal_ports(tmp_path: Path) -> None:
    """A literal port (the mission tree's task types, the idle timeout) is read as written."""
    path = ROOT / "missions" / "mine_inspection.yaml"
    xml = export(["mission", "tree", str(path), "--agent", "R1"], tmp_path / "mission.xml")
    reads = check_xml(xml).reads
    assert reads[("task_assigned", "type", "inspect")] == 1
    assert reads[("idle_timeout", "seconds", "10")] == 1
    assert reads[("at_goal", "goal", "value of location")] == 1


def test_a_leaf_type_with_two_sets_of_ports(checker: Check, tmp_path: Path) -> None:
    """One at_goal given an optional port the other lacks: each instance reads what it has."""
    path = ROOT / "missions" / "mine_inspection.yaml"
    xml = export(["mission", "tree", str(path), "--agent", "R1"], tmp_path / "mission.xml")
    text = xml.read_text(encoding="utf-8")
    text = text.replace(
        '<Condition ID="at_goal">', '<Condition ID="at_goal">\n<input_port name="tolerance"/>'
    )
    text = text.replace('goal="{location}"/>', 'goal="{location}" tolerance="0.5"/>', 1)
    xml.write_text(text, encoding="utf-8")
    assert_loads(checker, xml)
    if checker is behaviortreepy_check:
        reads = check_xml(xml).reads
        assert reads[("at_goal", "tolerance", "0.5")] == 1
        assert reads[("at_goal", "goal", "value of location")] == 1
        assert reads[("at_goal", "goal", "value of home")] == 1


def test_plugin_tree(checker: Check, tmp_path: Path) -> None:
    """A third-party library as `library new` scaffolds it, synthesised for its goal."""
    result = CliRunner().invoke(cli, ["library", "new", "rover_demo", "-o", str(tmp_path / "p")])
    assert result.exit_code == 0, result.output
    spec = tmp_path / "p" / "btmission_rover_demo" / "rover_demo.yaml"
    (goal,) = yaml.safe_load(spec.read_text(encoding="utf-8"))["goals"]
    assert_loads(checker, export(["synth", str(spec), "--goal", goal], tmp_path / "plugin.xml"))


def chain_yaml(n: int) -> str:
    """``a{i}(x)`` needs ``c{i-1}(x)`` and gives ``c{i}(x)``; ``c0`` is assumed. Goal ``c{n}(x)``."""
    lines = [
        "library: chain",
        "version: 1",
        f"description: {n} actions in a chain",
        f"goals: [c{n}(x)]",
        "conditions:",
        *(f"  c{i}: {{doc: step {i} done, params: [x]}}" for i in range(n + 1)),
        "actions:",
        *(
            f"  a{i}: {{doc: step {i}, params: [x], pre: [c{i - 1}(x)], post: [c{i}(x)]}}"
            for i in range(1, n + 1)
        ),
    ]
    return "\n".join(lines) + "\n"


def chain(tmp_path: Path) -> Path:
    lib = tmp_path / "chain.yaml"
    lib.write_text(chain_yaml(CHAIN_LENGTH), encoding="utf-8")
    return export(["synth", str(lib), "--goal", f"c{CHAIN_LENGTH}(spot)"], tmp_path / "chain.xml")


def test_chain_of_1000_actions(checker: Check, tmp_path: Path) -> None:
    """2,000 levels deep: written as SubTrees, each within BT.CPP's nesting limit; the port
    {spot} is read by every node through 15 levels of auto-remapped SubTrees."""
    xml = chain(tmp_path)
    out = assert_loads(checker, xml)
    trees = int(re.search(r"(\d+) \(sub\)trees", out).group(1))  # type: ignore[union-attr]
    assert trees > 2 * CHAIN_LENGTH // 128
    assert f"{CHAIN_LENGTH + CHAIN_LENGTH + 1} node models" in out  # a1..an, c0..cn
    assert "1 blackboard keys" in out
    if checker is behaviortreepy_check:
        report = check_xml(xml)
        assert report.leaves == 2 * CHAIN_LENGTH + 1
        assert sum(report.reads.values()) == report.leaves  # every leaf has the port x
        assert set(report.reads) == {
            (f"{kind}{i}", "x", "value of spot")
            for kind, first in (("a", 1), ("c", 0))
            for i in range(first, CHAIN_LENGTH + 1)
        }


def test_both_checkers_count_the_same(cpp_checker: Check, tmp_path: Path) -> None:
    """Where the C++ loader is built: for every tree but the plugin's, both checkers report the
    same models, (sub)trees, nodes, keys, ticks, final status, leaf ticks and node types ticked
    (whatever their BehaviorTree.CPP versions: the leaves' rewrite changes none of them)."""
    cases = [["synth", "aerial", "--goal", goal] for goal in ("at_goal(goal)", "landed_at_home")]
    cases += [["synth", library, "--goal", goal] for library, goal in LIBRARY_GOALS]
    cases += [
        ["mission", "tree", str(ROOT / "missions" / mission), "--agent", agent]
        for mission, agent in MISSION_AGENTS
    ]
    lib = tmp_path / "chain.yaml"
    lib.write_text(chain_yaml(CHAIN_LENGTH), encoding="utf-8")
    cases.append(["synth", str(lib), "--goal", f"c{CHAIN_LENGTH}(spot)"])

    def counts(line: str) -> str:
        """From the node models to the node types ticked: what both reports hold."""
        return line[line.index(", ") : line.index(" node types ticked")]

    for n, args in enumerate(cases):
        xml = export(args, tmp_path / f"tree{n}.xml")
        python = counts(behaviortreepy_check(xml)[1])
        assert python == counts(assert_loads(cpp_checker, xml)), (args, python)


# ------------------------------------------------------------------- the checker can fail
def broken_fig8(tmp_path: Path, pattern: str, replacement: str) -> Path:
    """Fig. 8 with the first match of ``pattern`` replaced (it must match)."""
    xml = fig8(tmp_path)
    text = xml.read_text(encoding="utf-8")
    broken = re.sub(pattern, replacement, text, count=1, flags=re.S)
    assert broken != text
    xml.write_text(broken, encoding="utf-8")
    return xml


def test_checker_fails_on_an_unknown_node(checker: Check, tmp_path: Path) -> None:
    """A leaf with no model in <TreeNodesModel>: no node type of that name is registered."""
    xml = broken_fig8(tmp_path, r'\s*<Action ID="takeoff">.*?</Action>', "")
    assert_fails(checker, xml, "takeoff")


def test_checker_fails_on_an_undeclared_port(checker: Check, tmp_path: Path) -> None:
    """A leaf's attribute that its model does not declare as a port (BT.CPP: "a port with name
    [goal] is found in the XML ... but not in the providedPorts() of its registered node type")."""
    xml = broken_fig8(tmp_path, r'(<Condition ID="at_goal">)\s*<input_port name="goal"/>', r"\1")
    assert_fails(checker, xml, "a port with name [goal] is found in the XML (<at_goal>, line 5)")


def test_checker_fails_on_a_control_node_without_children(checker: Check, tmp_path: Path) -> None:
    xml = broken_fig8(
        tmp_path,
        r'<ReactiveFallback name="has_home">.*?</ReactiveFallback>',
        '<ReactiveFallback name="has_home"/>',
    )
    assert_fails(checker, xml, "The node 'ReactiveFallback' must have 1 or more children")


@pytest.fixture()
def fig8_subtrees(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setattr(btcpp_module, "SUBTREE_DEPTH", 2)
    return fig8(tmp_path).read_text(encoding="utf-8")


def test_checker_fails_on_a_malformed_remapping(
    checker: Check, tmp_path: Path, fig8_subtrees: str
) -> None:
    """``_autoremap`` must be a boolean: BT.CPP refuses the document."""
    xml = tmp_path / "maybe.xml"
    xml.write_text(fig8_subtrees.replace('_autoremap="true"', '_autoremap="maybe"'), "utf-8")
    assert_fails(checker, xml, "invalid bool conversion")


def test_checker_fails_on_a_remapping_that_loses_a_port(
    checker: Check, tmp_path: Path, fig8_subtrees: str
) -> None:
    """Without ``_autoremap`` a SubTree does not see its parent's {goal}: reading the port of a
    leaf inside fails."""
    xml = tmp_path / "private.xml"
    xml.write_text(fig8_subtrees.replace('_autoremap="true"', '_autoremap="false"'), "utf-8")
    assert_fails(checker, xml, "input port 'goal'")


def test_checker_refuses_a_subtree_that_contains_itself(tmp_path: Path, fig8_subtrees: str) -> None:
    """BehaviorTree.CPP (4.8.2) recurses without end on it, until the process dies (SIGSEGV);
    the Python checker refuses it before BehaviorTree.CPP sees it."""
    xml = tmp_path / "cycle.xml"
    xml.write_text(
        fig8_subtrees.replace('<SubTree ID="aerial_sub2"', '<SubTree ID="aerial"'), "utf-8"
    )
    assert_fails(behaviortreepy_check, xml, "<SubTree ID='aerial'> contains itself")


def test_checker_fails_on_xml_that_is_not_well_formed(checker: Check, tmp_path: Path) -> None:
    assert_fails(checker, broken_fig8(tmp_path, r"</root>", ""), "not well-formed XML")


def test_explicit_form_is_what_btcpp_rejected(cpp_checker: Check, tmp_path: Path) -> None:
    """The form written before: <Action ID=...> under a ReactiveSequence. BT.CPP 4.7-4.10
    reject it ("Unknown node type: Action"); other versions may accept it. The C++ loader
    alone: it registers the leaf under its ID, behaviortreepy's check does not."""
    xml = fig8(tmp_path)
    version = re.search(r"BehaviorTree\.CPP (\d+)\.(\d+)", assert_loads(cpp_checker, xml))
    assert version is not None
    text = xml.read_text(encoding="utf-8")
    head, models = text.split("<TreeNodesModel>")
    kind_of = {m[1]: m[0] for m in re.findall(r'<(Action|Condition) ID="(\w+)"', models)}
    explicit = re.sub(
        r"<(\w+) name=",
        lambda m: f'<{kind_of[m[1]]} ID="{m[1]}" name=' if m[1] in kind_of else m[0],
        head,
    )
    xml.write_text(explicit + "<TreeNodesModel>" + models, encoding="utf-8")
    code, output = cpp_checker(xml)
    if (int(version[1]), int(version[2])) in {(4, m) for m in range(7, 11)}:
        assert code == 1 and "Unknown node type: Action" in output, output


def test_without_subtrees_the_chain_is_refused(
    checker: Check, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Why deep trees are split: written in one <BehaviorTree>, BT.CPP (and its tinyxml2)
    refuse the 2,000-level chain."""
    monkeypatch.setattr(btcpp_module, "SUBTREE_DEPTH", 10**6)
    xml = chain(tmp_path)
    assert "<SubTree" not in xml.read_text(encoding="utf-8")
    assert_fails(checker, xml, "deep")  # tinyxml2: "too deep"; BT.CPP: "too deeply nested"


def test_the_python_checker_runs_from_the_command_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``python -m tests.btcpp_py FILE.xml``, like btcpp_check: its line, exit 0, 1 or 2."""
    xml = fig8(tmp_path)
    assert main([str(xml)]) == 0
    assert capsys.readouterr().out.startswith(f"OK: {xml}: BehaviorTree.CPP ")
    xml.write_text("<root/>", encoding="utf-8")
    assert main([str(xml)]) == 1
    assert capsys.readouterr().out == f"FAIL: {xml}: no <TreeNodesModel>\n"
    assert main([]) == 2
