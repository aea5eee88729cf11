"""Build a py_trees tree from an abstract tree.

Composites become ``Selector``/``Sequence`` with ``memory=False``: back-chained PPA trees must re-check
every condition on every tick (that is what makes them reactive, seed 000 §IV-A). Leaves come from a
*leaf factory* — the symbolic dry run supplies symbolic leaves, the runtime supplies leaves bound to
a backend — so this module knows nothing about what leaves do.

``quiet=True`` builds btmission's own memoryless composites instead, :class:`QuietSelector` and
:class:`QuietSequence` (ticked to the end by plain calls; py_trees' statuses tick for tick): they
live with the other performance shortcuts in :mod:`btmission.fastpaths` and are re-exported here,
as are :class:`LeanTick` and :func:`tick_behaviour`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import py_trees

from btmission.fastpaths.ticks import LeanTick, QuietSelector, QuietSequence, tick_behaviour
from btmission.recursion import call_deep, recursion_for_depth
from btmission.synthesis.tree import Kind, Node, walk

LeafFactory = Callable[[Node], py_trees.behaviour.Behaviour]
T = TypeVar("T")

__all__ = [
    "LeafFactory",
    "LeanTick",
    "QuietSelector",
    "QuietSequence",
    "behaviour_depth",
    "build_behaviour_tree",
    "call_on_deep_tree",
    "tick_behaviour",
]


def build_behaviour_tree(
    root: Node, leaf: LeafFactory, *, quiet: bool = False
) -> py_trees.behaviour.Behaviour:
    """The py_trees behaviour for ``root``; shared abstract subtrees get distinct behaviours.

    ``quiet``: build :class:`QuietSelector`/:class:`QuietSequence` composites (a tick costs
    O(nodes) instead of O(nodes × depth); ticking yields only the root; they are not py_trees'
    ``Selector``/``Sequence`` classes but tick as those do with ``memory=False``).
    """
    selector, sequence = (
        (QuietSelector, QuietSequence)
        if quiet
        else (py_trees.composites.Selector, py_trees.composites.Sequence)
    )
    built: list[py_trees.behaviour.Behaviour] = []
    stack: list[tuple[Node, bool]] = [(root, False)]
    while stack:  # iterative post-order: children are built before their composite
        node, children_done = stack.pop()
        if node.is_leaf:
            built.append(leaf(node))
            continue
        if not children_done:
            stack.append((node, True))
            stack.extend((c, False) for c in reversed(node.children))
            continue
        kids = built[len(built) - len(node.children) :]
        del built[len(built) - len(node.children) :]
        cls = selector if node.kind is Kind.FALLBACK else sequence
        built.append(cls(name=node.name, memory=False, children=kids))
    assert len(built) == 1
    return built[0]


def behaviour_depth(root: py_trees.behaviour.Behaviour) -> int:
    """Levels of a py_trees tree (1 for a single leaf); iterative."""
    deepest = 0
    stack = [(1, root)]
    while stack:
        depth, node = stack.pop()
        deepest = max(deepest, depth)
        stack.extend((depth + 1, c) for c in node.children)
    return deepest


def call_on_deep_tree(root: Node | py_trees.behaviour.Behaviour, fn: Callable[[], T]) -> T:
    """``fn()``, which makes py_trees calls that recurse once per level (``tick``, ``stop``,
    ``iterate``) on a tree as deep as ``root``: the recursion limit is raised for the call only,
    by an amount computed from the depth and capped, in a thread with a big enough stack when
    the tree is deep (:func:`btmission.recursion.call_deep`), instead of patching py_trees."""
    if isinstance(root, Node):
        depth = 1 + max(d for d, _ in walk(root))
    else:
        depth = behaviour_depth(root)
    # tick: one generator frame a level (two for quiet composites), plus stop() calls inside it
    return call_deep(fn, recursion_for_depth(depth, frames_per_level=4))
