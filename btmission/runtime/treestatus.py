"""Behaviour-tree status for observers: which nodes changed status, throttled (``tree`` events).

BehaviorTree.CPP's ``StatusChangeLogger`` is the model: a logger attached to a tree sees every
node whose status changed and reports ``(node, previous, new)``. In py_trees the idiom is a
:class:`py_trees.trees.BehaviourTree` around the root (here :class:`LeanBehaviourTree`, the same
tick for less, one of :mod:`btmission.fastpaths`' shortcuts, imported from there) with a
*visitor*: :class:`StatusChanges` keeps each node's last seen status and collects the changes of
the tick (the nodes ticked, and the active ones a parent stopped without ticking them).
:class:`TreeStatusLogger` adds it to the tree with a post-tick handler that accumulates the
changes and publishes them:

* at most one ``tree`` event every ``period_s`` of mission time (the ``tree_event_s`` setting),
  carrying the *net* change of each node since the previous event (a node that went RUNNING →
  SUCCESS → RUNNING in between is not in it), so a tree ticked at 10 Hz does not flood the log;
* the first event carries the tree itself (``nodes``: name, parent, kind in pre-order), so the
  changes can name nodes by their pre-order index (``uid``, as BehaviorTree.CPP's UIDs);
* :attr:`TreeStatusLogger.status` is the current status of every node, for snapshots.

The agent adds to each ``tree`` event its blackboard keys that changed since its previous one
(``blackboard``: key → :func:`blackboard_value`; ``unset``: keys removed), so a viewer shows a
tree's blackboard next to its statuses from the log alone (Groot2's blackboard panel).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import py_trees
from py_trees.common import Status

from btmission.fastpaths.ticks import LeanBehaviourTree as LeanBehaviourTree
from btmission.fastpaths.ticks import QuietSelector, QuietSequence

TREE_EVENT_S = 0.5
"""Default of the ``tree_event_s`` setting: at most one ``tree`` event per agent per this many
seconds of mission time (0: one per tick with changes)."""


@dataclass(frozen=True)
class TreeEventSettings:
    """The runtime's own setting (every run has it, as it has the navigator's)."""

    tree_event_s: float = TREE_EVENT_S
    """At most one ``tree`` event per agent per this many seconds of mission time (s; 0: one
    per tick with changes)."""


Change = tuple[int, str, str]
"""(uid, old status, new status)."""

BLACKBOARD_TEXT = 80
"""A blackboard value that is not plain JSON data is shown as its ``repr``, cut to this many
characters; so is a sequence longer than :data:`BLACKBOARD_ITEMS`."""
BLACKBOARD_ITEMS = 16


def blackboard_value(value: Any) -> Any:
    """How a blackboard value is shown in a ``tree`` event: numbers (finite floats rounded to
    4 decimals; NaN and infinities as text), strings, booleans and None as they are, short
    sequences (a location) as lists of those, anything else as a shortened ``repr``."""
    if value is None or isinstance(value, (bool, int, str)):
        return (
            value
            if not isinstance(value, str) or len(value) <= BLACKBOARD_TEXT
            else (value[: BLACKBOARD_TEXT - 1] + "…")
        )
    if isinstance(value, float):
        return round(value, 4) if math.isfinite(value) else str(value)
    if (
        hasattr(value, "tolist")
        and getattr(value, "size", BLACKBOARD_ITEMS + 1) <= BLACKBOARD_ITEMS
    ):
        value = value.tolist()  # a small numpy array or scalar
    if isinstance(value, (list, tuple)) and len(value) <= BLACKBOARD_ITEMS:
        items = [blackboard_value(v) for v in value]
        if all(not isinstance(v, (list, dict)) for v in items):
            return items
    if isinstance(value, (int, float, bool, str)) or value is None:  # a numpy scalar's tolist()
        return blackboard_value(value)
    text = _set_repr(value) if isinstance(value, (set, frozenset)) else repr(value)
    return text if len(text) <= BLACKBOARD_TEXT else text[: BLACKBOARD_TEXT - 1] + "…"


def _set_repr(value: set[Any] | frozenset[Any]) -> str:
    """A set's ``repr`` with its items in sorted order: a set iterates in the order of its
    items' hashes, which for strings change with every process (``PYTHONHASHSEED``), and the
    same seed must give the same log."""
    if not value:
        return repr(value)
    inner = "{" + ", ".join(sorted(repr(v) for v in value)) + "}"
    return inner if type(value) is set else f"{type(value).__name__}({inner})"


_FALLBACKS = (py_trees.composites.Selector, QuietSelector)
_SEQUENCES = (py_trees.composites.Sequence, QuietSequence)


def node_kind(behaviour: py_trees.behaviour.Behaviour) -> str:
    """fallback, sequence, condition or action (the abstract tree's kinds), else the class:
    py_trees' ``Selector``/``Sequence`` and btmission's own (the quiet composites an agent's tree
    is built of, :mod:`btmission.fastpaths.ticks`) are fallbacks and sequences."""
    if isinstance(behaviour, _FALLBACKS):
        return "fallback"
    if isinstance(behaviour, _SEQUENCES):
        return "sequence"
    node = getattr(behaviour, "node", None)  # a runtime leaf knows its abstract node
    kind = getattr(node, "kind", None)
    return str(getattr(kind, "value", kind)) if kind is not None else type(behaviour).__name__


def preorder(root: py_trees.behaviour.Behaviour) -> list[py_trees.behaviour.Behaviour]:
    """The nodes of the tree in pre-order (iteratively: trees may be thousands of levels deep;
    py_trees' ``iterate()`` is post-order)."""
    out: list[py_trees.behaviour.Behaviour] = []
    stack = [root]
    while stack:
        b = stack.pop()
        out.append(b)
        stack.extend(reversed(b.children))
    return out


_STATUS_OF = operator.attrgetter("status")


class StatusChanges(py_trees.visitors.VisitorBase):
    """A visitor collecting the behaviours whose status differs from the one it saw last
    (module docstring): when a tick is over (:meth:`finalise`) it compares every behaviour of
    the tree, ticked or not (a parent may have stopped a child without ticking it), in one pass
    over the flat pre-order list. It needs none of the behaviours the tick yields, so the tree
    it watches may be built of quiet composites (:func:`~btmission.synthesis.pytrees.
    build_behaviour_tree` with ``quiet=True``), whose tick costs O(nodes) instead of
    O(nodes × depth). Node ``uid`` = pre-order index (the root is 0, then its first child's
    subtree...)."""

    def __init__(self, root: py_trees.behaviour.Behaviour) -> None:
        super().__init__(full=False)
        self.behaviours = preorder(root)
        self.last: list[Status] = [Status.INVALID] * len(self.behaviours)
        self.changes: list[Change] = []
        """The changes seen since :meth:`initialise` (the last tick's, after a tick)."""
        self.version = 0
        """Counts the changes ever seen: :attr:`last` is the same while it is."""

    def initialise(self) -> None:
        self.changes = []

    def run(self, behaviour: py_trees.behaviour.Behaviour) -> None:
        """Nothing per ticked behaviour: :meth:`finalise` compares them all."""

    def finalise(self) -> None:
        now = list(map(_STATUS_OF, self.behaviours))
        if now == self.last:  # (a C loop; the usual tick changes nothing or a few nodes)
            return
        last = self.last
        for uid, status in enumerate(now):
            if status is not last[uid]:
                self._changed(uid, status)

    def _changed(self, uid: int, status: Status) -> None:
        old = self.last[uid]
        self.last[uid] = status
        self.version += 1
        self.changes.append((uid, old.value, status.value))

    def visit_all(self) -> list[Change]:
        """Compare every behaviour now (outside a tick: after a ``stop``); the changes."""
        self.changes = []
        self.finalise()
        return self.changes


_STATUS_NAMES: dict[Status, str] = {s: s.value for s in Status}
"""Each status's name (an enum's ``.value`` is a slow descriptor; snapshots take ~70 a tick)."""


class TreeStatusLogger:
    """Publishes an agent's tree status changes as throttled ``tree`` events (module
    docstring). ``publish(changes, nodes)`` receives the net changes (and, the first time, the
    tree's nodes); ``clock()`` is mission time."""

    def __init__(
        self,
        tree: py_trees.trees.BehaviourTree,
        publish: Callable[[list[list[Any]], list[list[Any]] | None], None],
        clock: Callable[[], float],
        period_s: float = TREE_EVENT_S,
        dirty: Callable[[], bool] | None = None,
    ) -> None:
        """``dirty()`` True: something else the event carries changed (the blackboard), so an
        event goes out at its time even if no status changed."""
        self.visitor = StatusChanges(tree.root)
        self._status: tuple[int, Mapping[int, str]] | None = None
        self._dirty = dirty
        self.period_s = period_s
        self._publish = publish
        self._clock = clock
        self._pending: dict[int, list[str]] = {}  # uid → [status at the last event, now]
        self._next_t = -float("inf")
        self._sent_nodes = False
        tree.add_visitor(self.visitor)
        tree.add_post_tick_handler(self._post_tick)

    @property
    def nodes(self) -> list[list[Any]]:
        """``[name, parent uid, kind]`` per node, by uid (the root's parent is -1)."""
        uid = {id(b): i for i, b in enumerate(self.visitor.behaviours)}
        return [
            [b.name, uid.get(id(b.parent), -1) if i else -1, node_kind(b)]
            for i, b in enumerate(self.visitor.behaviours)
        ]

    @property
    def status(self) -> Mapping[int, str]:
        """uid → status (py_trees' ``INVALID``/``RUNNING``/``SUCCESS``/``FAILURE``) as of the
        last tick: a read-only copy (the same one while no status changed)."""
        visitor = self.visitor
        cached = self._status
        if cached is None or cached[0] != visitor.version:
            names = _STATUS_NAMES
            status = MappingProxyType({i: names[s] for i, s in enumerate(visitor.last)})
            cached = self._status = (visitor.version, status)
        return cached[1]

    def _post_tick(self, tree: py_trees.trees.BehaviourTree) -> None:
        changes = self.visitor.changes
        if changes:
            self._note(changes)
        elif not self._pending and not (
            self._sent_nodes and self._dirty is not None and self._dirty()
        ):
            return  # (most ticks: nothing a flush would publish, whatever the time)
        now = self._clock()
        if now + 1e-9 >= self._next_t:
            self.flush(now)

    def collect(self) -> None:
        """Take the changes made outside a tick (the tree was stopped); published with the next
        tick's."""
        self._note(self.visitor.visit_all())

    def _note(self, changes: list[Change]) -> None:
        pending = self._pending
        for uid, old, new in changes:
            seen = pending.get(uid)
            if seen is None:
                pending[uid] = [old, new]
            else:
                seen[1] = new

    def flush(self, now: float | None = None) -> None:
        """Publish the pending net changes now (if any), whatever the period."""
        net = [[uid, old, new] for uid, (old, new) in sorted(self._pending.items()) if old != new]
        self._pending.clear()
        if not net and not (self._sent_nodes and self._dirty is not None and self._dirty()):
            return
        self._next_t = (self._clock() if now is None else now) + self.period_s
        nodes = None
        if not self._sent_nodes:
            self._sent_nodes = True
            nodes = self.nodes
        self._publish(net, nodes)
