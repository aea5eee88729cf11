"""The ``aerial_mine`` library: Table I plus ``relocalize``, and the relocalization BT leaf."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import py_trees
import pytest

from btmission.localization.database import random_poses, save_database
from btmission.localization.relocalize import pose_error
from btmission.localization.scan import pose_matrix, simulate_scan
from btmission.plugins import load_library
from btmission.synthesis.backchain import synthesize
from btmission.synthesis.checks import check_library
from btmission.synthesis.pytrees import build_behaviour_tree
from btmission.synthesis.tree import Node
from btmission_library.aerial_mine import (
    IMPLEMENTATIONS,
    IS_LOCALIZED,
    SCAN,
    WORLD_FROM_ROBOT,
    Relocalize,
    is_localized,
)
from tests.reloc_helpers import OTHER_SEED, small_database, small_mine, small_relocalizer

Status = py_trees.common.Status


@pytest.fixture(autouse=True)
def clean_blackboard():  # type: ignore[no-untyped-def]
    py_trees.blackboard.Blackboard.clear()
    yield
    py_trees.blackboard.Blackboard.clear()


def agent_board(namespace: str = "/agents/R1") -> py_trees.blackboard.Client:
    board = py_trees.blackboard.Client(name="sim", namespace=namespace)
    board.register_key(SCAN, access=py_trees.common.Access.WRITE)
    for key in (IS_LOCALIZED, WORLD_FROM_ROBOT):
        board.register_key(key, access=py_trees.common.Access.READ)
    return board


def tick(behaviour: py_trees.behaviour.Behaviour, until_done: bool = True) -> Status:
    for _ in range(2000):
        behaviour.tick_once()
        if behaviour.status != Status.RUNNING or not until_done:
            return behaviour.status
        time.sleep(0.005)
    raise AssertionError("the leaf kept running")


# ------------------------------------------------------------------------------------ library
def test_library_checks_clean_in_strict_mode() -> None:
    loaded = load_library("aerial_mine")
    report = check_library(loaded.library, loaded.diagnostics, strict=True)
    assert report.ok and not [d for d in report.diagnostics if d.severity.value != "info"]
    assert loaded.implementations is IMPLEMENTATIONS
    assert set(IMPLEMENTATIONS.actions) == {"relocalize"}


def _strip(node: Node) -> str:
    from btmission.export import export_tree

    return str(export_tree(node, "ascii"))


def test_aerial_stays_table_one_and_aerial_mine_adds_relocalize_before_takeoff() -> None:
    aerial = load_library("aerial").library
    mine = load_library("aerial_mine").library
    assert "relocalize" not in aerial.actions and "is_localized" not in aerial.conditions
    assert set(mine.actions) == set(aerial.actions) | {"relocalize"}
    takeoff = mine.actions["takeoff"]
    assert [str(p) for p in takeoff.pre] == ["is_localized", "has_home", "is_armed", "in_offboard"]
    plain = _strip(synthesize(aerial, ["at_goal(goal)"]).tree)
    reloc = _strip(synthesize(mine, ["at_goal(goal)"]).tree)
    assert "relocalize" not in plain and "[relocalize]" in reloc
    # the Fig. 8 tree with one more fallback: is_localized first under takeoff
    assert reloc.index("is_localized") < reloc.index("has_home") < reloc.index("[takeoff]")
    assert len(reloc.splitlines()) == len(plain.splitlines()) + 3


# ------------------------------------------------------------------------------------ the leaf
def test_the_leaf_sets_is_localized_and_the_pose_transform() -> None:
    vm = small_mine().map
    truth = random_poses(vm, 1, rng=21)[0]
    board = agent_board()
    leaf = Relocalize(relocalizer=small_relocalizer(), namespace="/agents/R1", blocking=True)
    leaf.setup()
    assert tick(leaf, until_done=False) == Status.RUNNING  # no scan yet
    assert leaf.feedback_message == "waiting for a scan"
    board.set(SCAN, simulate_scan(vm, truth, rng=3))
    assert tick(leaf) == Status.SUCCESS
    assert board.get(IS_LOCALIZED) is True
    dt, dyaw = pose_error(board.get(WORLD_FROM_ROBOT), truth)
    assert dt < 0.3 and dyaw < 3.0
    store = py_trees.blackboard.Blackboard.storage
    assert store["/agents/R1/reloc_confidence"] >= 0.2
    assert store["/agents/R1/reloc_result"].localized


def test_the_leaf_runs_on_a_worker_thread() -> None:
    vm = small_mine().map
    truth = random_poses(vm, 1, rng=22)[0]
    board = agent_board()
    board.set(SCAN, simulate_scan(vm, truth, rng=4))
    leaf = Relocalize(relocalizer=small_relocalizer(), namespace="/agents/R1")
    leaf.setup()
    try:
        assert tick(leaf, until_done=False) == Status.RUNNING  # localising in the background
        assert tick(leaf) == Status.SUCCESS
        assert pose_error(board.get(WORLD_FROM_ROBOT), truth)[0] < 0.3
    finally:
        leaf.shutdown()


def test_a_scan_from_another_map_fails_and_leaves_no_pose() -> None:
    other = small_mine(OTHER_SEED).map
    board = agent_board()
    board.set(SCAN, simulate_scan(other, random_poses(other, 1, rng=23)[0], rng=5))
    leaf = Relocalize(relocalizer=small_relocalizer(), namespace="/agents/R1", blocking=True)
    leaf.setup()
    assert tick(leaf) == Status.FAILURE
    assert board.get(IS_LOCALIZED) is False
    assert not board.exists(WORLD_FROM_ROBOT)
    assert leaf.feedback_message.startswith("not localised")


def test_the_lidar_mounting_is_taken_out_of_the_transform() -> None:
    """A LiDAR 0.3 m ahead of and 0.1 m above the robot's origin: the robot is there too."""
    vm = small_mine().map
    world_from_sensor = random_poses(vm, 1, rng=24)[0]
    robot_from_sensor = pose_matrix(0.3, 0.0, 0.1)
    board = agent_board()
    board.set(SCAN, simulate_scan(vm, world_from_sensor, rng=6))
    leaf = Relocalize(
        relocalizer=small_relocalizer(),
        namespace="/agents/R1",
        robot_from_sensor=robot_from_sensor,
        blocking=True,
    )
    leaf.setup()
    assert tick(leaf) == Status.SUCCESS
    truth = world_from_sensor @ np.linalg.inv(robot_from_sensor)
    assert pose_error(board.get(WORLD_FROM_ROBOT), truth)[0] < 0.3


def test_setup_loads_a_database_file_or_refuses(tmp_path: Path) -> None:
    path = save_database(small_database(), tmp_path / "db.npz")
    leaf = Relocalize(namespace="/agents/R2", blocking=True)
    leaf.setup(reloc_database=str(path))
    assert leaf.relocalizer is not None and len(leaf.relocalizer.db) == len(small_database())
    bare = Relocalize(namespace="/agents/R3")
    with pytest.raises(RuntimeError, match="no relocalizer"):
        bare.setup()
    assert tick(bare) == Status.FAILURE


def test_condition_reads_the_blackboard() -> None:
    board = py_trees.blackboard.Client(name="t", namespace="/agents/R9")
    board.register_key(IS_LOCALIZED, access=py_trees.common.Access.WRITE)
    assert is_localized(board) is False
    board.set(IS_LOCALIZED, True)
    assert is_localized(board) is True
    assert is_localized({IS_LOCALIZED: True}) and not is_localized({})


class _Condition(py_trees.behaviour.Behaviour):
    """A condition leaf over the library's condition implementation."""

    def __init__(self, name: str, namespace: str) -> None:
        super().__init__(name)
        self.board = self.attach_blackboard_client(name=name, namespace=namespace)
        self.board.register_key(IS_LOCALIZED, access=py_trees.common.Access.READ)

    def update(self) -> Status:
        return Status.SUCCESS if is_localized(self.board) else Status.FAILURE


def test_synthesised_subtree_relocalizes_once() -> None:
    """Back-chaining `is_localized` gives Fallback(is_localized, relocalize): the first tick runs
    the leaf, later ticks stop at the condition."""
    lib = load_library("aerial_mine").library
    tree = synthesize(lib, ["is_localized"]).tree
    calls: list[int] = []

    class Counting:
        def localize(self, points: np.ndarray) -> object:
            calls.append(len(points))
            return small_relocalizer().localize(points)

    def leaf(node: Node) -> py_trees.behaviour.Behaviour:
        if node.name == "relocalize":
            return Relocalize(relocalizer=Counting(), namespace="/agents/R1", blocking=True)
        return _Condition(node.name, "/agents/R1")

    root = build_behaviour_tree(tree, leaf)
    bt = py_trees.trees.BehaviourTree(root)
    bt.setup()
    vm = small_mine().map
    board = agent_board()
    board.set(SCAN, simulate_scan(vm, random_poses(vm, 1, rng=25)[0], rng=7))
    bt.tick()
    assert root.status == Status.SUCCESS and board.get(IS_LOCALIZED)
    assert len(calls) == 1
    bt.tick()
    bt.tick()
    assert root.status == Status.SUCCESS and len(calls) == 1  # the condition holds now
