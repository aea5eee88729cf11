"""Every exported tree loads, verifies, instantiates and ticks in real BehaviorTree.CPP (optional).

Runs only where a BehaviorTree.CPP build with our loader is present (tests/btcpp/README.md):

* ``BTCPP_CHECK=/path/to/btcpp_check``: the loader built from tests/btcpp/btcpp_check.cpp, or
* ``BTCPP_PREFIX=/prefix``: an install prefix holding ``bin/btcpp_check``.

Otherwise every test here is skipped with the reason. For each tree the loader registers the
file's ``<TreeNodesModel>`` as dummy nodes with their ports, runs ``BT::VerifyXML`` and
``createTreeFromText``, reads every input port of every node, and ticks the tree to completion.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from btmission.cli.main import cli
from btmission.export import btcpp as btcpp_module
from btmission.plugins import installed_libraries, load_library

ROOT = Path(__file__).resolve().parents[2]
MISSIONS = sorted((ROOT / "missions").glob("*.yaml"))
CHAIN_LENGTH = 1000
CHECK_TIMEOUT_S = 120


def _checker() -> Path | None:
    explicit = os.environ.get("BTCPP_CHECK")
    if explicit:
        return Path(explicit)
    prefix = os.environ.get("BTCPP_PREFIX")
    if prefix:
        return Path(prefix) / "bin" / "btcpp_check"
    return None


@pytest.fixture(scope="module")
def checker() -> Path:
    path = _checker()
    if path is None:
        pytest.skip(
            "no BehaviorTree.CPP build: set BTCPP_CHECK to a built tests/btcpp/btcpp_check "
            "(or BTCPP_PREFIX to its install prefix); see tests/btcpp/README.md"
        )
    if not (path.is_file() and os.access(path, os.X_OK)):
        pytest.fail(f"BTCPP_CHECK/BTCPP_PREFIX give {path}, which is not an executable file")
    return path


def check(checker: Path, xml: Path) -> tuple[int, str]:
    done = subprocess.run(
        [str(checker), str(xml)],
        capture_output=True,
        text=True,
        timeout=CHECK_TIMEOUT_S,
        check=False,
    )
    return done.returncode, done.stdout + done.stderr


def export(args: list[str], out: Path) -> Path:
    result = CliRunner().invoke(cli, [*args, "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert out.is_file()
    return out


def assert_loads(checker: Path, xml: Path) -> str:
    code, output = check(checker, xml)
    assert code == 0 and output.startswith("OK: "), output
    assert "-> SUCCESS" in output or "-> FAILURE" in output, output
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


def test_fig8(checker: Path, tmp_path: Path) -> None:
    """Seed 000 Fig. 8: the aerial library's tree for at_goal(goal)."""
    xml = export(["synth", "aerial", "--goal", "at_goal(goal)"], tmp_path / "fig8.xml")
    out = assert_loads(checker, xml)
    assert "1 blackboard keys" in out  # {goal} is read through the ports


def test_fig9(checker: Path, tmp_path: Path) -> None:
    """Seed 000 Fig. 9: the default (idle) behaviour, return home and land."""
    assert_loads(
        checker, export(["synth", "aerial", "--goal", "landed_at_home"], tmp_path / "f.xml")
    )


@pytest.mark.parametrize(("library", "goal"), LIBRARY_GOALS)
def test_library_goal(checker: Path, tmp_path: Path, library: str, goal: str) -> None:
    assert_loads(checker, export(["synth", library, "--goal", goal], tmp_path / "tree.xml"))


@pytest.mark.parametrize(("mission", "agent"), MISSION_AGENTS)
def test_mission_tree(checker: Path, tmp_path: Path, mission: str, agent: str) -> None:
    path = ROOT / "missions" / mission
    xml = export(["mission", "tree", str(path), "--agent", agent], tmp_path / "mission.xml")
    assert_loads(checker, xml)


def test_plugin_tree(checker: Path, tmp_path: Path) -> None:
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


def test_chain_of_1000_actions(checker: Path, tmp_path: Path) -> None:
    """2,000 levels deep: written as SubTrees, each within BT.CPP's nesting limit; the port
    {spot} is read by every node through 15 levels of auto-remapped SubTrees."""
    lib = tmp_path / "chain.yaml"
    lib.write_text(chain_yaml(CHAIN_LENGTH), encoding="utf-8")
    xml = export(["synth", str(lib), "--goal", f"c{CHAIN_LENGTH}(spot)"], tmp_path / "chain.xml")
    out = assert_loads(checker, xml)
    trees = int(re.search(r"(\d+) \(sub\)trees", out).group(1))  # type: ignore[union-attr]
    assert trees > 2 * CHAIN_LENGTH // 128
    assert f"{CHAIN_LENGTH + CHAIN_LENGTH + 1} node models" in out  # a1..an, c0..cn
    assert "1 blackboard keys" in out


# ------------------------------------------------------------------- the checker can fail
def test_checker_fails_on_an_unknown_node(checker: Path, tmp_path: Path) -> None:
    xml = export(["synth", "aerial", "--goal", "at_goal(goal)"], tmp_path / "fig8.xml")
    text = xml.read_text(encoding="utf-8")
    broken = re.sub(r'\s*<Action ID="takeoff">.*?</Action>', "", text, flags=re.S)
    assert broken != text
    xml.write_text(broken, encoding="utf-8")
    code, output = check(checker, xml)
    assert code == 1 and output.startswith("FAIL: ") and "takeoff" in output, output


def test_explicit_form_is_what_btcpp_rejected(checker: Path, tmp_path: Path) -> None:
    """The form written before: <Action ID=...> under a ReactiveSequence. BT.CPP 4.7-4.10
    reject it ("Unknown node type: Action"); other versions may accept it."""
    xml = export(["synth", "aerial", "--goal", "at_goal(goal)"], tmp_path / "fig8.xml")
    version = re.search(r"BehaviorTree\.CPP (\d+)\.(\d+)", assert_loads(checker, xml))
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
    code, output = check(checker, xml)
    if (int(version[1]), int(version[2])) in {(4, m) for m in range(7, 11)}:
        assert code == 1 and "Unknown node type: Action" in output, output


def test_without_subtrees_the_chain_is_refused(
    checker: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Why deep trees are split: written in one <BehaviorTree>, BT.CPP (and its tinyxml2)
    refuse the 2,000-level chain."""
    monkeypatch.setattr(btcpp_module, "SUBTREE_DEPTH", 10**6)
    lib = tmp_path / "chain.yaml"
    lib.write_text(chain_yaml(CHAIN_LENGTH), encoding="utf-8")
    xml = export(["synth", str(lib), "--goal", f"c{CHAIN_LENGTH}(spot)"], tmp_path / "chain.xml")
    assert "<SubTree" not in xml.read_text(encoding="utf-8")
    code, output = check(checker, xml)
    assert code == 1 and output.startswith("FAIL: "), output
    assert "deep" in output, output  # tinyxml2: "too deep"; BT.CPP: "too deeply nested"
