"""The tick fast path of btmission's behaviour trees (:mod:`btmission.fastpaths`, items 1-4).

* :data:`RUNNING`, :data:`SUCCESS`, :data:`FAILURE`, :data:`INVALID` — py_trees' statuses as
  module globals, for code that reads them on every tick (an Enum member read through its
  class costs about five times a global on Python 3.11);
* :class:`LeanTick` — the tick protocol of btmission's composites and of the runtime's leaves:
  ``tick_now()``, a plain call that ticks to the end, instead of a generator per behaviour;
  :func:`tick_behaviour` ticks any behaviour to the end, through it when it has one;
* :class:`QuietSelector` and :class:`QuietSequence` — btmission's own reactive (memoryless)
  composites, derived from py_trees' public base ``py_trees.composites.Composite``; their
  ticks are py_trees' ``Selector``/``Sequence`` with ``memory=False``, status for status;
* :class:`LeanBehaviourTree` — py_trees' ``BehaviourTree`` custodian with the same tick for
  less.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import py_trees
from py_trees.behaviour import Behaviour
from py_trees.common import Status
from py_trees.composites import Composite

__all__ = [
    "FAILURE",
    "INVALID",
    "RUNNING",
    "SUCCESS",
    "LeanBehaviourTree",
    "LeanTick",
    "QuietSelector",
    "QuietSequence",
    "tick_behaviour",
]

RUNNING = Status.RUNNING
SUCCESS = Status.SUCCESS
FAILURE = Status.FAILURE
INVALID = Status.INVALID
"""(the statuses as module globals, here and in the runtime's leaves, which import them: read on
every tick, and on Python 3.11 an Enum member read through its class costs five times a global)"""


class LeanTick:
    """The base of the quiet composites and the runtime's leaves: ``tick()`` is :meth:`tick_now`
    (a plain call that ticks to the end) and then yields the behaviour itself, once; and
    ``iterator``, the fresh tick generator py_trees' ``Behaviour.stop`` keeps (py_trees itself
    never reads it), is made when read instead of at every stop.

    Why: a py_trees tick is a generator per behaviour, and every behaviour ticked below a
    composite is yielded up through each ancestor's generator — a tree ``d`` levels deep costs
    O(d) per node a tick (a 1,000-action chain: seconds a tick). A parent acts only on its
    child's own, last, yield, so ticking to the end and yielding once changes nothing but that
    cost; the only difference a caller can see is that iterating ``tick()`` yields the
    behaviour alone, not every one ticked below it (a py_trees visitor that wants those sees
    only the root: btmission's own, :class:`~btmission.runtime.treestatus.StatusChanges`,
    compares every node after the tick)."""

    def tick_now(self) -> None:  # pragma: no cover - every subclass defines it
        raise NotImplementedError

    def tick(self) -> Iterator[Behaviour]:
        self.tick_now()
        yield self  # type: ignore[misc]

    @property
    def iterator(self) -> Iterator[Behaviour]:
        return self.tick()

    @iterator.setter
    def iterator(self, _value: object) -> None:
        pass


def tick_behaviour(behaviour: Behaviour) -> None:
    """Tick ``behaviour`` once, to the end (its ``status`` is then the outcome): its
    ``tick_now()`` when it has one (quiet composites, the runtime's guarded leaves), otherwise
    by running py_trees' ``tick()`` generator out (``Behaviour.tick_once``)."""
    lean = getattr(behaviour, "tick_now", None)
    if lean is not None:
        lean()
        return
    for _ in behaviour.tick():
        pass


class _Reactive(LeanTick, Composite):
    """A memoryless composite of btmission's own on py_trees' public base ``Composite``: py_trees
    documents ``Composite.tick`` as abstract, to be re-implemented by every composite, and
    ``stop`` as overridden by each (its own ``Selector``, ``Sequence`` and ``Parallel`` do).
    ``memory`` is kept for readers (always False: a back-chained tree re-checks every condition
    on every tick; py_trees' composites remain for a tree that needs memory)."""

    memory = False

    def __init__(
        self, name: str, memory: bool = False, children: Sequence[Behaviour] | None = None
    ) -> None:
        if memory:
            raise ValueError(
                f"{type(self).__name__} is memoryless (reactive); use "
                "py_trees.composites.Selector/Sequence(memory=True) for a composite with memory"
            )
        super().__init__(name, children)

    def stop(self, new_status: Status = INVALID) -> None:
        """py_trees' ``Composite.stop``: on INVALID forget the current child and stop every child
        that is not INVALID; terminate; take the status. (Without its fresh tick generator,
        which :class:`LeanTick` makes when read; py_trees' ``Selector``/``Sequence.stop`` only
        add a debug message to it.)"""
        if new_status is INVALID:
            self.current_child = None
            for child in self.children:
                if child.status is not INVALID:
                    child.stop(new_status)
        self.terminate(new_status)
        self.status = new_status


class QuietSelector(_Reactive):
    """btmission's fallback: py_trees' ``Selector(memory=False)`` tick for tick, as a
    :class:`LeanTick` (tick yields only itself, once, at the end).

    :meth:`tick_now` is ``Selector.tick`` (py_trees 2.x) step for step — initialise unless
    RUNNING; tick the children in order until one is RUNNING or SUCCESS; if that is not the
    child that ran before, stop (INVALID) every child after it; take its status (stopping on
    SUCCESS), or FAILURE when all failed — as plain calls, without the debug messages
    (``tests/unit/fastpaths/test_fastpaths.py`` and ``tests/unit/synthesis/test_synthesis.py`` tick it against py_trees' own
    ``Selector``)."""

    def tick_now(self) -> None:
        """One tick to the end (class docstring)."""
        children = self.children
        if self.status is not RUNNING:
            self.current_child = children[0] if children else None
            self.initialise()
        if not children:
            self.current_child = None
            self.stop(FAILURE)
            return
        previous = self.current_child
        for child in children:
            lean = getattr(child, "tick_now", None)  # (tick_behaviour, inlined: every child)
            if lean is not None:
                lean()
            else:
                tick_behaviour(child)
            status = child.status
            if status is RUNNING or status is SUCCESS:
                self.current_child = child
                if previous is not child:  # interrupted: invalidate the lower priorities
                    passed = False
                    for other in children:
                        if passed and other.status is not INVALID:
                            other.stop(INVALID)
                        passed = passed or other is child
                if status is SUCCESS:
                    self.stop(status)
                else:
                    self.status = status
                return
        self.stop(FAILURE)
        self.current_child = children[-1]


class QuietSequence(_Reactive):
    """btmission's sequence: py_trees' ``Sequence(memory=False)`` tick for tick, as
    :class:`QuietSelector` is its ``Selector``. :meth:`tick_now` is ``Sequence.tick`` step for
    step: unless RUNNING, stop every child that is not INVALID and initialise; tick the
    children in order while they succeed; at the first that does not, stop (INVALID) the
    children after it and take its status (stopping unless RUNNING); SUCCESS when all
    succeeded."""

    def tick_now(self) -> None:
        """One tick to the end (class docstring)."""
        children = self.children
        self.current_child = children[0] if children else None
        if self.status is not RUNNING:
            for child in children:
                if child.status is not INVALID:
                    child.stop(INVALID)
            self.initialise()
        if not children:
            self.current_child = None
            self.stop(SUCCESS)
            return
        last = len(children) - 1
        for index, child in enumerate(children):
            lean = getattr(child, "tick_now", None)  # (tick_behaviour, inlined: every child)
            if lean is not None:
                lean()
            else:
                tick_behaviour(child)
            status = child.status
            if status is not SUCCESS:
                for other in children[index + 1 :]:  # kill dangling runners
                    if other.status is not INVALID:
                        other.stop(INVALID)
                if status is not RUNNING:
                    self.stop(status)
                else:
                    self.status = status
                return
            if index < last:
                self.current_child = children[index + 1]
        self.stop(SUCCESS)


class LeanBehaviourTree(py_trees.trees.BehaviourTree):
    """py_trees' ``BehaviourTree`` with the same :meth:`tick` — pre-tick handlers, visitors
    (``initialise``, ``run`` on each ticked behaviour, then on every behaviour for ``full``
    ones, ``finalise``), post-tick handlers — minus its overhead: the visitor lists are made once
    per tick instead of once per ticked behaviour, and the second pass over the whole tree only
    runs for ``full`` visitors. A :class:`LeanTick` root is ticked with ``tick_now`` and only it
    is visited by the non-``full`` visitors (its tick yields only itself). On the mine mission's
    agent tree (50 nodes): a bare root tick 5.5 µs; this, with the agent's
    :class:`~btmission.runtime.treestatus.StatusChanges` visitor and its ``tree`` event
    logger, 7.8 µs; ``BehaviourTree.tick`` with the same, 28 µs."""

    def tick(
        self,
        pre_tick_handler: Callable[[py_trees.trees.BehaviourTree], None] | None = None,
        post_tick_handler: Callable[[py_trees.trees.BehaviourTree], None] | None = None,
    ) -> None:
        if pre_tick_handler is not None:
            pre_tick_handler(self)
        for handler in self.pre_tick_handlers:
            handler(self)
        for visitor in self.visitors:
            visitor.initialise()
        ticked = [v for v in self.visitors if not v.full]
        root = self.root
        lean = getattr(root, "tick_now", None)
        if ticked and lean is not None:  # a quiet root's tick yields only itself, at the end
            lean()
            for visitor in ticked:
                root.visit(visitor)
        elif ticked:
            for node in root.tick():
                for visitor in ticked:
                    node.visit(visitor)
        else:
            root.tick_once()
        full = [v for v in self.visitors if v.full]
        if full:
            for node in self.root.iterate():
                for visitor in full:
                    node.visit(visitor)
        for visitor in self.visitors:
            visitor.finalise()
        for handler in self.post_tick_handlers:
            handler(self)
        if post_tick_handler is not None:
            post_tick_handler(self)
        self.count += 1
