"""Build a py_trees tree from an abstract tree.

Composites become ``Selector``/``Sequence`` with ``memory=False``: back-chained PPA trees must re-check
every condition on every tick (that is what makes them reactive, seed 000 §IV-A). Leaves come from a
*leaf factory* — the symbolic dry run supplies symbolic leaves, the runtime supplies leaves bound to
a backend — so this module knows nothing about what leaves do.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import TypeVar

import py_trees

from btmission.recursion import call_deep, recursion_for_depth
from btmission.synthesis.tree import Kind, Node, walk

LeafFactory = Callable[[Node], py_trees.behaviour.Behaviour]
T = TypeVar("T")


_RUNNING = py_trees.common.Status.RUNNING
_SUCCESS = py_trees.common.Status.SUCCESS
_FAILURE = py_trees.common.Status.FAILURE
_INVALID = py_trees.common.Status.INVALID
"""(the statuses as module globals, here and in the runtime's leaves, which import them: read on
every tick, and on Python 3.11 an Enum member read through its class costs five times a global)"""


def _stop_composite(
    composite: py_trees.composites.Composite, new_status: py_trees.common.Status
) -> None:
    """py_trees' ``Composite.stop`` — on INVALID forget the current child and stop every child
    that is not INVALID; terminate; take the status — without its debug message and without
    making a fresh tick generator that nothing reads (:class:`LeanTick`)."""
    if new_status is _INVALID:
        composite.current_child = None
        for child in composite.children:
            if child.status is not _INVALID:
                child.stop(new_status)
    composite.terminate(new_status)
    composite.status = new_status


class LeanTick:
    """The base of the quiet composites and the runtime's leaves: ``tick()`` is :meth:`tick_now`
    (a plain call that ticks to the end) and then yields the behaviour itself, once; and
    ``iterator``, the fresh tick generator py_trees keeps (made at every ``stop``; py_trees itself
    never reads it), is made when read."""

    def tick_now(self) -> None:  # pragma: no cover - every subclass defines it
        raise NotImplementedError

    def tick(self) -> Iterator[py_trees.behaviour.Behaviour]:
        self.tick_now()
        yield self  # type: ignore[misc]

    @property
    def iterator(self) -> Iterator[py_trees.behaviour.Behaviour]:
        return self.tick()

    @iterator.setter
    def iterator(self, _value: object) -> None:
        pass


def tick_behaviour(behaviour: py_trees.behaviour.Behaviour) -> None:
    """Tick ``behaviour`` once, to the end (its ``status`` is then the outcome): its
    ``tick_now()`` when it has one (quiet composites, the runtime's guarded leaves), otherwise
    by running py_trees' ``tick()`` generator out."""
    lean = getattr(behaviour, "tick_now", None)
    if lean is not None:
        lean()
        return
    for _ in behaviour.tick():
        pass


class QuietSelector(LeanTick, py_trees.composites.Selector):
    """A py_trees ``Selector`` whose ``tick()`` yields only itself, once, at the end.

    A composite's ``tick()`` yields every behaviour ticked below it, and each of those yields
    passes through every ancestor's generator: a tick of a tree ``d`` levels deep costs O(d) per
    node, which makes a 1,000-action chain take seconds a tick. A parent composite only acts on
    the yield of the child itself, which is always the last one, so ticking the subtree to the end
    and yielding ``self`` once changes nothing but that cost. Use only where nobody visits the
    yielded behaviours: the dry run, and the agents' trees, whose status visitor
    (:class:`~btmission.runtime.treestatus.StatusChanges`) compares every node after the tick.

    Without ``memory`` (every synthesised tree) the tick is :meth:`tick_now`: py_trees'
    ``Selector.tick`` step for step — initialise unless RUNNING; tick the children in order
    until one is RUNNING or SUCCESS; if that is not the child that ran before, stop (INVALID)
    every child after it; take its status (stopping on SUCCESS), or FAILURE when all failed —
    as plain calls instead of nested generators (a fleet's trees tick thousands of composites a
    second)."""

    def tick_now(self) -> None:
        """One tick to the end (class docstring)."""
        if self.memory:
            for _ in py_trees.composites.Selector.tick(self):
                pass
            return
        children = self.children
        if self.status is not _RUNNING:
            self.current_child = children[0] if children else None
            self.initialise()
        if not children:
            self.current_child = None
            self.stop(_FAILURE)
            return
        previous = self.current_child
        for child in children:
            lean = getattr(child, "tick_now", None)  # (tick_behaviour, inlined: every child)
            if lean is not None:
                lean()
            else:
                tick_behaviour(child)
            status = child.status
            if status is _RUNNING or status is _SUCCESS:
                self.current_child = child
                if previous is not child:  # interrupted: invalidate the lower priorities
                    passed = False
                    for other in children:
                        if passed and other.status is not _INVALID:
                            other.stop(_INVALID)
                        passed = passed or other is child
                if status is _SUCCESS:
                    self.stop(status)
                else:
                    self.status = status
                return
        self.stop(_FAILURE)
        self.current_child = children[-1]

    def stop(self, new_status: py_trees.common.Status = _INVALID) -> None:
        """py_trees' ``Selector.stop`` (it only logs, then does ``Composite.stop``):
        :func:`_stop_composite`."""
        _stop_composite(self, new_status)


class QuietSequence(LeanTick, py_trees.composites.Sequence):
    """The ``Sequence`` counterpart of :class:`QuietSelector`; without ``memory`` its
    :meth:`tick_now` is py_trees' ``Sequence.tick`` step for step: unless RUNNING, stop every
    child that is not INVALID and initialise; tick the children in order while they succeed;
    at the first that does not, stop (INVALID) the children after it and take its status
    (stopping unless RUNNING); SUCCESS when all succeeded."""

    def tick_now(self) -> None:
        """One tick to the end (class docstring)."""
        if self.memory:
            for _ in py_trees.composites.Sequence.tick(self):
                pass
            return
        children = self.children
        self.current_child = children[0] if children else None
        if self.status is not _RUNNING:
            for child in children:
                if child.status is not _INVALID:
                    child.stop(_INVALID)
            self.initialise()
        if not children:
            self.current_child = None
            self.stop(_SUCCESS)
            return
        last = len(children) - 1
        for index, child in enumerate(children):
            lean = getattr(child, "tick_now", None)  # (tick_behaviour, inlined: every child)
            if lean is not None:
                lean()
            else:
                tick_behaviour(child)
            status = child.status
            if status is not _SUCCESS:
                for other in children[index + 1 :]:  # kill dangling runners
                    if other.status is not _INVALID:
                        other.stop(_INVALID)
                if status is not _RUNNING:
                    self.stop(status)
                else:
                    self.status = status
                return
            if index < last:
                self.current_child = children[index + 1]
        self.stop(_SUCCESS)

    def stop(self, new_status: py_trees.common.Status = _INVALID) -> None:
        """py_trees' ``Sequence.stop`` (as :class:`QuietSelector`): :func:`_stop_composite`."""
        _stop_composite(self, new_status)


def build_behaviour_tree(
    root: Node, leaf: LeafFactory, *, quiet: bool = False
) -> py_trees.behaviour.Behaviour:
    """The py_trees behaviour for ``root``; shared abstract subtrees get distinct behaviours.

    ``quiet``: build :class:`QuietSelector`/:class:`QuietSequence` composites (a tick costs
    O(nodes) instead of O(nodes × depth); ticking yields only the root).
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
