"""Build a py_trees tree from an abstract tree.

Composites become ``Selector``/``Sequence`` with ``memory=False``: back-chained PPA trees must re-check
every condition on every tick (that is what makes them reactive, seed 000 §IV-A). Leaves come from a
*leaf factory* — the symbolic dry run supplies symbolic leaves, the runtime supplies leaves bound to
a backend — so this module knows nothing about what leaves do.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import py_trees

from btmission.recursion import recursion_for_depth, recursion_limit
from btmission.synthesis.tree import Kind, Node, walk

LeafFactory = Callable[[Node], py_trees.behaviour.Behaviour]


def build_behaviour_tree(root: Node, leaf: LeafFactory) -> py_trees.behaviour.Behaviour:
    """The py_trees behaviour for ``root``; shared abstract subtrees get distinct behaviours."""
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
        cls = (
            py_trees.composites.Selector
            if node.kind is Kind.FALLBACK
            else py_trees.composites.Sequence
        )
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


@contextmanager
def deep_tree_calls(root: Node | py_trees.behaviour.Behaviour) -> Iterator[None]:
    """Run py_trees calls that recurse once per level (``tick``, ``stop``, ``iterate``) on a tree
    as deep as ``root``: the recursion limit is raised for the block only, by an amount computed
    from the depth and capped (:mod:`btmission.recursion`), instead of patching py_trees."""
    if isinstance(root, Node):
        depth = 1 + max(d for d, _ in walk(root))
    else:
        depth = behaviour_depth(root)
    # tick: a generator frame per level, plus stop()/tip() calls nested inside it
    with recursion_limit(recursion_for_depth(depth, frames_per_level=4)):
        yield
