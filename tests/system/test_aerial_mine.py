"""The ``aerial_mine`` library: Table I plus ``relocalize``, and its runtime leaf in the simulator
(scans from the simulated LiDAR at the agent's true pose)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from py_trees.common import Status

from btmission.backends.sim import Simulator
from btmission.cli.main import cli
from btmission.diagnostics import SpecError
from btmission.localization.database import random_poses, save_database
from btmission.localization.relocalize import pose_error
from btmission.localization.scan import pose_matrix
from btmission.plugins import load_library
from btmission.runtime.events import read_events
from btmission.runtime.leaves import AgentContext, Blackboard
from btmission.synthesis.backchain import synthesize
from btmission.synthesis.checks import check_library
from btmission.synthesis.tree import Kind, Node, action, condition, fallback, sequence
from btmission.world.voxel import VoxelMap
from btmission_library import aerial
from btmission_library.aerial_mine import (
    CONFIDENCE,
    IMPLEMENTATIONS,
    IS_LOCALIZED,
    RELOCALIZER,
    RESULT,
    WORLD_FROM_ROBOT,
    Relocalize,
    is_localized,
)
from tests.reloc_helpers import OTHER_SEED, small_database, small_mine
from tests.unit.synthesis.test_synthesis import fig8, shape, takeoff_subtree

ROOT = Path(__file__).resolve().parents[2]
MISSION = ROOT / "missions" / "mine_relocalize.yaml"
START = (7.0, 5.0, 0.0)
"""On the floor of the small mine's launch area (docs/examples/reloc_mine.yaml's start)."""


# ------------------------------------------------------------------------------------ library
def test_library_checks_clean_and_reuses_every_aerial_implementation() -> None:
    loaded = load_library("aerial_mine")
    report = check_library(loaded.library, loaded.diagnostics, strict=True)
    assert report.ok and not [d for d in report.diagnostics if d.severity.value != "info"]
    assert loaded.implementations is IMPLEMENTATIONS and loaded.runnable
    assert IMPLEMENTATIONS.missing(loaded.library) == []
    base = aerial.IMPLEMENTATIONS
    assert set(IMPLEMENTATIONS.actions) == set(base.actions) | {"relocalize"}
    assert set(IMPLEMENTATIONS.conditions) == set(base.conditions) | {"is_localized"}
    for name, impl in base.actions.items():
        assert IMPLEMENTATIONS.actions[name] is impl, name
    for name, fn in base.conditions.items():
        assert IMPLEMENTATIONS.conditions[name] is fn, name
    assert IMPLEMENTATIONS.vehicle == base.vehicle == "multirotor"
    assert IMPLEMENTATIONS.setup_hooks[: len(base.setup_hooks)] == base.setup_hooks
    # aerial itself gained nothing
    assert "relocalize" not in base.actions and "is_localized" not in base.conditions
    assert "reloc_database" not in base.settings


def with_relocalize_under_takeoff(node: Node) -> Node:
    """``node`` with Fallback(is_localized, relocalize) put first in every take-off sequence."""
    kids = tuple(with_relocalize_under_takeoff(c) for c in node.children)
    if node.kind is Kind.SEQUENCE and node.name == "takeoff":
        kids = (fallback("is_localized", condition("is_localized"), action("relocalize")), *kids)
    return replace(node, children=kids)


def test_aerial_mine_tree_is_fig8_with_relocalize_first_under_takeoff() -> None:
    """Seed 000 Fig. 8 with one more fallback: Fallback(is_localized, relocalize) is the first
    child of take-off's sequence. ``aerial``'s tree stays Fig. 8 exactly."""
    mine = synthesize(load_library("aerial_mine").library, ["at_goal(goal)"])
    assert mine.ok and shape(mine.tree) == shape(with_relocalize_under_takeoff(fig8()))
    follow = mine.tree.children[1]
    takeoff = follow.children[0].children[1]
    assert (follow.name, takeoff.kind, takeoff.name) == (
        "follow_path(goal)",
        Kind.SEQUENCE,
        "takeoff",
    )
    assert [shape(c) for c in takeoff.children] == [
        shape(fallback("is_localized", condition("is_localized"), action("relocalize"))),
        *[shape(c) for c in takeoff_subtree().children[1].children],
    ]
    plain = synthesize(load_library("aerial").library, ["at_goal(goal)"])
    assert shape(plain.tree) == shape(fig8())
    home = synthesize(load_library("aerial_mine").library, ["landed_at_home"]).tree
    assert shape(home) == shape(
        fallback(
            "landed_at_home",
            condition("landed_at_home"),
            sequence("land", with_relocalize_under_takeoff(fig8("home")), action("land")),
        )
    )


# ------------------------------------------------------------------------------------ the leaf
def _context(
    vm: VoxelMap,
    *,
    yaw: float = 0.0,
    start: tuple[float, float, float] = START,
    settings: dict[str, Any] | None = None,
    sensors: Any = "sim",
) -> tuple[AgentContext, list[tuple[str, dict[str, Any]]]]:
    """An agent context over a one-drone simulator in ``vm`` (no navigator or path service: the
    leaf uses neither), after the library's setup hooks ran; and the events it publishes."""
    sim = Simulator(vm, seed=5)
    veh = sim.add_multirotor("R1", start, yaw=yaw)
    events: list[tuple[str, dict[str, Any]]] = []
    ctx = AgentContext(
        agent_id="R1",
        blackboard=Blackboard("/agents/R1"),
        backend=veh,
        sensors=veh if sensors == "sim" else sensors,
        navigator=None,  # type: ignore[arg-type]
        paths=SimpleNamespace(map=vm),  # type: ignore[arg-type]
        clock=lambda: sim.time_s,
        settings={**IMPLEMENTATIONS.settings, **(settings or {})},
        start=start,
        events=lambda ev: events.append((ev.kind, ev.to_data())),
    )
    for hook in IMPLEMENTATIONS.setup_hooks:
        hook(ctx)
    ctx.state["sim"] = sim
    return ctx, events


@pytest.fixture(scope="module")
def db_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small mine's place database (built once per session by the helpers) as a file."""
    return save_database(small_database(), tmp_path_factory.mktemp("db") / "small_db.npz")


def test_relocalize_sets_is_localized_and_the_pose_from_the_simulated_lidar(db_file: Path) -> None:
    vm = small_mine().map
    yaw = 0.7
    ctx, events = _context(vm, yaw=yaw, settings={"reloc_database": str(db_file)})
    assert is_localized(ctx) is False  # before the leaf runs
    leaf = Relocalize(action("relocalize"), ctx)
    leaf.tick_once()  # localises inside the tick: one tick is enough
    assert leaf.status is Status.SUCCESS and leaf.reason == ""
    assert is_localized(ctx) is True and ctx.blackboard[IS_LOCALIZED] is True
    truth = pose_matrix(START[0], START[1], vm.ground_z((7.0, 5.0, 0.01)), yaw)
    err_m, err_deg = pose_error(ctx.blackboard[WORLD_FROM_ROBOT], truth)
    assert err_m < 0.3 and err_deg < 3.0
    assert ctx.blackboard[CONFIDENCE] >= 0.2 and ctx.blackboard[RESULT].localized
    kinds = [k for k, _ in events]
    assert kinds == ["stage", "relocalized"]
    ev = events[1][1]
    assert ev["localized"] and ev["error_m"] < 0.3 and ev["error_deg"] < 3.0
    assert ev["truth"]["yaw_deg"] == pytest.approx(math.degrees(yaw), abs=1e-3)
    assert ev["estimate"]["x"] == pytest.approx(START[0], abs=0.3)
    assert ev["points"] > 10_000 and ev["sensor"] == "os1-32"


def test_a_database_of_another_map_gives_failure_not_localised(db_file: Path) -> None:
    other = small_mine(OTHER_SEED).map
    x, y = random_poses(other, 1, rng=31)[0][:2, 3]
    start = (float(x), float(y), other.ground_z((x, y, 5.0)))
    ctx, events = _context(other, start=start, settings={"reloc_database": str(db_file)})
    leaf = Relocalize(action("relocalize"), ctx)
    leaf.tick_once()
    assert leaf.status is Status.FAILURE
    assert leaf.reason.startswith("not localised")
    assert is_localized(ctx) is False and WORLD_FROM_ROBOT not in ctx.blackboard
    ((_, ev),) = [e for e in events if e[0] == "relocalized"]
    assert not ev["localized"] and "estimate" not in ev and ev["reason"] == leaf.reason


class _NoScanYet:
    """A LiDAR driver that has not completed a turn."""

    def lidar_scan(self) -> None:
        return None


def test_relocalize_waits_for_a_scan_then_gives_up(db_file: Path) -> None:
    vm = small_mine().map
    ctx, events = _context(vm, settings={"reloc_database": str(db_file)}, sensors=_NoScanYet())
    sim: Simulator = ctx.state["sim"]
    leaf = Relocalize(action("relocalize"), ctx)
    leaf.tick_once()
    assert leaf.status is Status.RUNNING
    while sim.time_s < 4.9:
        sim.step()
    leaf.tick_once()
    assert leaf.status is Status.RUNNING
    sim.step()
    sim.step()
    leaf.tick_once()
    assert leaf.status is Status.FAILURE and leaf.reason == "no LiDAR scan within 5 s"
    assert not is_localized(ctx) and not [e for e in events if e[0] == "relocalized"]


def test_one_relocalizer_per_map_built_from_the_map_itself() -> None:
    vm = small_mine().map
    a, _ = _context(vm, settings={"reloc_spacing_m": 3.0})
    b, _ = _context(vm.copy(), settings={"reloc_spacing_m": 3.0})  # same content, same database
    c, _ = _context(vm, settings={"reloc_spacing_m": 4.0})
    assert a.state[RELOCALIZER] is b.state[RELOCALIZER]
    assert c.state[RELOCALIZER] is not a.state[RELOCALIZER]
    assert a.state[RELOCALIZER].db.meta["spacing_m"] == 3.0
    leaf = Relocalize(action("relocalize"), a)
    leaf.tick_once()
    assert leaf.status is Status.SUCCESS


def test_bad_relocalization_settings_are_mission_errors(tmp_path: Path) -> None:
    vm = small_mine().map
    not_db = tmp_path / "map.npz"
    np.savez(not_db, x=np.zeros(3))
    cases = [
        ({"reloc_database": str(tmp_path / "missing.npz")}, "reloc_database", "no such file"),
        ({"reloc_database": str(not_db)}, "reloc_database", "not a btmission place database"),
        ({"reloc_spacing_m": -1.0}, "reloc_spacing_m", "positive number of metres"),
        ({"reloc_spacing_m": "wide"}, "reloc_spacing_m", "positive number of metres"),
    ]
    for settings, item, message in cases:
        with pytest.raises(SpecError) as exc:
            _context(vm, settings=settings)
        (d,) = exc.value.diagnostics
        assert d.item == f"runtime.settings.{item}" and message in d.message, d.message


def test_a_bad_database_setting_stops_the_run_with_exit_2(tmp_path: Path) -> None:
    text = (ROOT / "docs" / "examples" / "reloc_mine.yaml").read_text()
    mission = tmp_path / "m.yaml"
    mission.write_text(text + "runtime: {settings: {reloc_database: no_such_db.npz}}\n")
    result = CliRunner().invoke(cli, ["run", str(mission), "--log", str(tmp_path), "--quiet"])
    assert result.exit_code == 2, result.output
    assert "runtime.settings.reloc_database" in result.output
    assert "no_such_db.npz: no such file" in result.output  # relative to the mission file
    assert str(tmp_path / "no_such_db.npz") in result.output
    assert not list(tmp_path.glob("*.jsonl"))


# ------------------------------------------------------------------------------------ mission
def test_mine_relocalize_mission_completes_with_each_agent_relocalised(tmp_path: Path) -> None:
    args = ["run", str(MISSION), "--log", str(tmp_path), "--quiet", "--no-png"]
    result = CliRunner().invoke(cli, [*args, "--controller", "track"])  # half the NMPC's time
    assert result.exit_code == 0, result.output
    (log,) = tmp_path.glob("mine_relocalize-*.jsonl")
    events = read_events(log).events
    header = events[0]
    starts = {a["id"]: a["start"] for a in header.get("agents")}
    assert len(starts) == 2 and {a["library"] for a in header.get("agents")} == {"aerial_mine"}
    tasks = {t["id"] for t in header.get("tasks")}
    done = {e.get("task") for e in events if e.kind == "progress" and e.get("event") == "done"}
    assert done == tasks and events[-1].get("reason") == "completed"
    relocs = [e for e in events if e.kind == "relocalized"]
    assert sorted(e.get("agent") for e in relocs) == sorted(starts)  # once each
    for e in relocs:
        assert e.get("localized") and e.get("error_m") < 0.3 and e.get("error_deg") < 3.0
        x, y, _ = starts[e.get("agent")]
        assert (e.get("truth")["x"], e.get("truth")["y"]) == (x, y)
        assert abs(e.get("estimate")["x"] - x) < 0.3 and abs(e.get("estimate")["y"] - y) < 0.3
    for agent in starts:  # each agent relocalised before it took off
        stages = [e.get("action") for e in events if e.kind == "stage" and e.get("agent") == agent]
        assert stages.index("relocalize") < stages.index("takeoff")
