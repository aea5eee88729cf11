"""Symbolic dry run: tick a synthesised tree against an abstract world, with no robot.

The world is a truth assignment over ground conditions (``at_goal(goal)``, ``is_armed``, …). A
condition leaf succeeds iff its condition is true. An action leaf runs for ``action_ticks`` ticks
(RUNNING) and then makes its postconditions true and succeeds — the paper's assumption that actions
achieve their postconditions and invalidate none of their own preconditions (seed 000 §IV-A).

Every time an action is ticked, its ground preconditions are checked against the world; a tick of
an action whose preconditions are false is a *violation*. A correct back-chained tree reaches its
goal from every initial assignment with no violation.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import py_trees
from py_trees.common import Status

from btmission.spec.library import Atom, Library
from btmission.synthesis.pytrees import build_behaviour_tree, call_on_deep_tree
from btmission.synthesis.tree import Kind, Node, walk


@dataclass
class LeafTick:
    """One leaf tick: the leaf's label, its kind and the status it returned."""

    label: str
    kind: Kind
    status: Status
    progress: str = ""


@dataclass
class SymbolicWorld:
    """Truth values of ground conditions, and what happened in each tick."""

    truth: dict[str, bool] = field(default_factory=dict)
    action_ticks: int = 2
    tick: int = 0
    trace: list[list[LeafTick]] = field(default_factory=list)
    violations: list[str] = field(default_factory=list)

    def holds(self, key: str) -> bool:
        return self.truth.get(key, False)

    def record(self, leaf: LeafTick) -> None:
        while len(self.trace) <= self.tick:
            self.trace.append([])
        self.trace[self.tick].append(leaf)


class SymbolicCondition(py_trees.behaviour.Behaviour):
    """SUCCESS iff the world says the condition holds."""

    def __init__(self, node: Node, world: SymbolicWorld) -> None:
        super().__init__(name=node.label)
        self.key = node.label
        self.world = world

    def update(self) -> Status:
        status = Status.SUCCESS if self.world.holds(self.key) else Status.FAILURE
        self.world.record(LeafTick(self.key, Kind.CONDITION, status))
        return status


class SymbolicAction(py_trees.behaviour.Behaviour):
    """RUNNING for ``action_ticks`` ticks, then makes its postconditions true and succeeds."""

    def __init__(
        self, node: Node, world: SymbolicWorld, pre: Iterable[str], post: Iterable[str]
    ) -> None:
        super().__init__(name=node.label)
        self.world = world
        self.pre = tuple(pre)
        self.post = tuple(post)
        self.count = 0

    def initialise(self) -> None:
        self.count = 0

    def update(self) -> Status:
        false_pre = [p for p in self.pre if not self.world.holds(p)]
        if false_pre:
            self.world.violations.append(
                f"tick {self.world.tick}: {self.name} ticked while {', '.join(false_pre)} false"
            )
        self.count += 1
        done = self.count >= self.world.action_ticks
        if done:
            for p in self.post:
                self.world.truth[p] = True
        status = Status.SUCCESS if done else Status.RUNNING
        self.world.record(
            LeafTick(self.name, Kind.ACTION, status, f"{self.count}/{self.world.action_ticks}")
        )
        return status


def ground_effects(library: Library, node: Node) -> tuple[list[str], list[str]]:
    """Ground pre- and postconditions of an action leaf, as condition labels."""
    act = library.actions.get(node.name)
    if act is None:  # built-in or unknown leaf: no declared effects
        return [], []
    binding = {a.param: a.value for a in node.args}
    return [str(p.substitute(binding)) for p in act.pre], [
        str(p.substitute(binding)) for p in act.post
    ]


@dataclass
class DryRunResult:
    success: bool
    ticks: int
    world: SymbolicWorld
    status: Status

    @property
    def violations(self) -> list[str]:
        return self.world.violations

    def format_trace(self, unicode: bool = True) -> str:
        """One line per tick: every leaf visited, ✓/✗ for conditions, ▶ for running actions."""
        ok, bad, run, done = ("✓", "✗", "▶", "●") if unicode else ("+", "-", ">", "*")
        lines = []
        for t, leaves in enumerate(self.world.trace, start=1):
            parts = []
            for lt in leaves:
                if lt.kind is Kind.CONDITION:
                    parts.append(f"{ok if lt.status is Status.SUCCESS else bad} {lt.label}")
                else:
                    mark = done if lt.status is Status.SUCCESS else run
                    parts.append(f"{mark} {lt.label} [{lt.progress}]")
            lines.append(f"tick {t:3d}: " + "  ".join(parts))
        verdict = "goal reached" if self.success else f"goal NOT reached (root {self.status.value})"
        lines.append(
            f"{verdict} after {self.ticks} tick(s); {len(self.violations)} precondition violation(s)"
        )
        lines.extend(f"  violation: {v}" for v in self.violations)
        return "\n".join(lines)


def conditions_in(tree: Node) -> list[str]:
    """Every distinct condition label of the tree, in pre-order of first appearance."""
    seen: dict[str, None] = {}
    for _, n in walk(tree):
        if n.kind is Kind.CONDITION:
            seen.setdefault(n.label, None)
    return list(seen)


def dry_run(
    tree: Node,
    library: Library,
    initial: Mapping[str, bool] | None = None,
    *,
    action_ticks: int = 2,
    max_ticks: int = 1000,
) -> DryRunResult:
    """Tick ``tree`` until its root succeeds (or ``max_ticks``) in a symbolic world."""
    world = SymbolicWorld(dict(initial or {}), action_ticks)

    def leaf(node: Node) -> py_trees.behaviour.Behaviour:
        if node.kind is Kind.CONDITION:
            return SymbolicCondition(node, world)
        pre, post = ground_effects(library, node)
        return SymbolicAction(node, world, pre, post)

    root = build_behaviour_tree(tree, leaf, quiet=True)  # nobody visits the yields

    def tick_until_done() -> tuple[int, Status]:
        status = Status.INVALID
        ticks = 0
        for _ in range(max_ticks):
            world.tick = ticks
            for _node in root.tick():
                pass
            ticks += 1
            status = root.status
            if status is Status.SUCCESS:
                break
        return ticks, status

    ticks, status = call_on_deep_tree(tree, tick_until_done)
    return DryRunResult(status is Status.SUCCESS, ticks, world, status)


def goal_holds(result: DryRunResult, goals: Iterable[Atom]) -> bool:
    return all(result.world.holds(str(g)) for g in goals)
