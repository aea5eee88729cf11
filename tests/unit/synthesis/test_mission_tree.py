"""The per-agent mission tree (seed 000 Fig. 7) for every task type, and the multi-stage commit."""

from __future__ import annotations

from pathlib import Path

from btmission.missions import load_mission
from btmission.synthesis.backchain import synthesize
from btmission.synthesis.mission_tree import build_mission_tree
from btmission.synthesis.tree import Kind, Role

ROOT = Path(__file__).resolve().parents[3]


def test_fig7_structure_with_every_task_type_and_default() -> None:
    m = load_mission(ROOT / "missions" / "pick_and_deliver.yaml")
    mt = build_mission_tree(m, "G1")
    root = mt.tree
    assert (root.kind, root.name, root.role) == (Kind.FALLBACK, "mission(G1)", Role.MISSION)
    assert [c.name for c in root.children] == [
        "task(inspect)",
        "task(pick_and_deliver)",
        "default",
        "wait",
    ]
    inspect, pick, default, wait = root.children
    lib = m.library_of("G1").library
    # each task branch: task_assigned(type) guard, then exactly the back-chained subtree of the goal
    assert (
        inspect.children[0].label == 'task_assigned("inspect")'
        and inspect.children[0].role is Role.BUILTIN
    )
    assert inspect.children[1] == synthesize(lib, ["at_goal(location)"]).tree
    assert pick.children[1] == synthesize(lib, ["delivered(pickup, dropoff)"]).tree
    assert dict(pick.meta) == {"commit_after": "holding(pickup)", "task_type": "pick_and_deliver"}
    # default: idle timeout guard, then the default goal's tree (seed 003 Fig. 6a: go home)
    assert default.children[0].label == 'idle_timeout("5")'
    assert default.children[1] == synthesize(lib, ["at_goal(home)"]).tree
    assert (wait.kind, wait.role) == (Kind.ACTION, Role.BUILTIN)


def test_single_task_type_selection() -> None:
    m = load_mission(ROOT / "missions" / "mine_inspection.yaml")
    mt = build_mission_tree(m, "R2", ["inspect"])
    assert [c.name for c in mt.tree.children] == ["task(inspect)", "default", "wait"]
    assert set(mt.branches) == {"inspect", "default"}


def test_agent_without_the_capability_skips_the_type(tmp_path: Path) -> None:
    text = (
        (ROOT / "missions" / "pick_and_deliver.yaml")
        .read_text()
        .replace(
            "  - {id: G1, library: ground, start: [1, 1, 0]}",
            "  - {id: G1, library: ground, start: [1, 1, 0]}\n  - {id: D1, library: aerial, start: [2, 1, 0]}",
        )
        .replace("goal: at_goal(home)", "goal: [at_goal(home)]")
    )
    f = tmp_path / "m.yaml"
    f.write_text(text)
    m = load_mission(f)
    mt = build_mission_tree(m, "D1")
    assert (
        "pick_and_deliver" in mt.skipped
        and "no condition 'delivered'" in mt.skipped["pick_and_deliver"]
    )
    assert [c.name for c in mt.tree.children] == ["task(inspect)", "default", "wait"]
