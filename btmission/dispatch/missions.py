"""Missions and fleet missions (seed 004 §3.2-3.3, §4.1).

A *mission* M(v) is a sequence of mission items, each a segment and an initial stop time t_w.
We store it as the node sequence ``nodes[0..q]`` (item i is the segment nodes[i]→nodes[i+1]) and
``waits[0..q]`` (``waits[i]`` is t_w of item i; ``waits[q]`` is unused and 0). A *fleet mission*
F is one mission per vehicle, a tuple of :class:`Mission`.

Rules enforced here (and kept by every mutation in :mod:`btmission.dispatch.ga`):

* t_w > 0 only for the first item and for items starting at a pause node (§3.3.2);
* a *prioritised* (inbound) mission M^P follows Π0 and may change only the first t_w (§3.3.1);
* for causality in dynamic planning, the first ``frozen`` items of a mission never change, and the
  t_w of item ``frozen`` is at least ``min_wait`` (§5).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from btmission.dispatch.topomap import TopoMap

FleetMission = tuple["Mission", ...]


@dataclass(frozen=True, eq=False)
class Mission:
    """One vehicle's mission: node sequence, initial stop times and the constraints on them."""

    nodes: NDArray[np.int32]
    waits: NDArray[np.float64]
    t0: float = 0.0
    """Time the vehicle is at ``nodes[0]`` (0 in static planning)."""
    prioritized: bool = False
    frozen: int = 0
    """Items ``[0, frozen)`` already started (or will have by the end of the optimisation)."""
    min_wait: float = 0.0
    """Lower bound of ``waits[frozen]`` (causality: the first free departure is after it)."""
    head: int = 0
    """Item where the current mission starts; earlier items belong to a mission the vehicle is
    finishing (dynamic planning appends a new mission to it). Its t_w is the mission's initial
    stop time."""
    slots: NDArray[np.int32] = field(default_factory=lambda: np.zeros(0, np.int32))
    """Items whose t_w may be mutated (set by :func:`make_mission`)."""

    @property
    def items(self) -> int:
        """Number of mission items q."""
        return len(self.nodes) - 1

    @property
    def lock(self) -> int:
        """Structural mutations only change items from here on (after the frozen part and the
        remainder of a mission being finished)."""
        return max(self.frozen, self.head)

    @property
    def start(self) -> int:
        return int(self.nodes[0])

    @property
    def end(self) -> int:
        return int(self.nodes[-1])

    def pause_visits(self, tmap: TopoMap) -> list[int]:
        """Positions i of detours nodes[i-1] → pause nodes[i] → nodes[i-1] (the set T2 of Alg. 3)."""
        nd = self.nodes.tolist()
        pause = tmap.is_pause
        return [
            i
            for i in range(max(1, self.lock + 1), len(nd) - 1)
            if pause[nd[i]] and nd[i - 1] == nd[i + 1]
        ]


def mutable_slots(
    tmap: TopoMap, nodes: NDArray[np.int32], prioritized: bool, frozen: int, head: int = 0
) -> NDArray[np.int32]:
    """Items whose initial stop time may be non-zero and may change (the κ parameters of Alg. 3).

    The mission's first item (``head``, if not frozen) and, for non-prioritised missions, every
    free item whose start node is a pause node.
    """
    q = len(nodes) - 1
    if q <= 0:
        return np.zeros(0, np.int32)
    out = [head] if frozen <= head < q else []
    if not prioritized:
        nd = nodes.tolist()
        pause = tmap.is_pause
        out.extend(i for i in range(max(1, frozen), q) if pause[nd[i]] and i != head)
    return np.asarray(out, dtype=np.int32)


def make_mission(
    tmap: TopoMap,
    nodes: Sequence[int] | NDArray[np.int32],
    waits: Sequence[float] | NDArray[np.float64] | None = None,
    *,
    t0: float = 0.0,
    prioritized: bool = False,
    frozen: int = 0,
    min_wait: float = 0.0,
    head: int = 0,
) -> Mission:
    """A checked mission: consecutive nodes joined by segments, waits only where §3.3 allows.

    Raises ``ValueError`` naming the first problem.
    """
    nd = np.asarray(nodes, dtype=np.int32)
    if nd.ndim != 1 or len(nd) < 1:
        raise ValueError("a mission needs at least its start node")
    w = np.zeros(len(nd)) if waits is None else np.asarray(waits, dtype=np.float64).copy()
    if w.shape != nd.shape:
        raise ValueError(f"{len(nd)} nodes need {len(nd)} waits, got {len(w)}")
    for i in range(len(nd) - 1):
        if tmap.edge[nd[i], nd[i + 1]] < 0:
            raise ValueError(
                f"item {i}: {tmap.nodes[nd[i]].name} and {tmap.nodes[nd[i + 1]].name} "
                "are not joined by a segment"
            )
    if len(nd) > 1 and np.any(w[:-1] < 0):
        raise ValueError("initial stop times must be >= 0")
    w[-1] = 0.0
    if not 0 <= head <= max(len(nd) - 1, 0) or not 0 <= frozen <= max(len(nd) - 1, 0):
        raise ValueError("head and frozen must be item indices of the mission")
    slots = mutable_slots(tmap, nd, prioritized, frozen, head)
    allowed = {0, head, *slots.tolist(), *range(frozen)}
    bad = [i for i in range(len(nd) - 1) if w[i] > 0 and i not in allowed]
    if bad:
        i = bad[0]
        kind = tmap.nodes[nd[i]].kind.name.lower()
        raise ValueError(
            f"item {i} starts at {tmap.nodes[nd[i]].name} ({kind}): initial stop times are only "
            "allowed at the start"
            + (" of a prioritized mission" if prioritized else " and at pause nodes")
        )
    fixed = max(frozen, head)
    if prioritized and tmap.path(int(nd[fixed]), int(nd[-1])) != [int(x) for x in nd[fixed:]]:
        raise ValueError("a prioritized mission must follow the direct path Π0")
    return Mission(nd, w, float(t0), prioritized, int(frozen), float(min_wait), int(head), slots)


def direct_mission(
    tmap: TopoMap,
    start: int,
    end: int,
    *,
    wait: float = 0.0,
    t0: float = 0.0,
    prioritized: bool | None = None,
    min_wait: float = 0.0,
) -> Mission:
    """M^0(v): Π0(start, end) with t_w = ``wait`` for the first item and 0 elsewhere (§4.1).

    ``prioritized`` defaults to whether ``end`` is a prioritised terminal (an inbound mission).
    """
    nodes = tmap.path(start, end)
    waits = np.zeros(len(nodes))
    if len(nodes) > 1:
        waits[0] = wait
    prio = bool(tmap.prioritized[end]) if prioritized is None else prioritized
    return make_mission(tmap, nodes, waits, t0=t0, prioritized=prio, min_wait=min_wait)


def initial_fleet(tmap: TopoMap, pairs: Sequence[tuple[int, int]]) -> FleetMission:
    """F^0 for (start, end) node pairs: every vehicle on Π0 with no stops (§4.1)."""
    return tuple(direct_mission(tmap, s, e) for s, e in pairs)


def fleet_items(fleet: FleetMission) -> int:
    """ξ: the number of mission items of the fleet mission."""
    return sum(m.items for m in fleet)


def with_waits(m: Mission, waits: NDArray[np.float64]) -> Mission:
    """``m`` with other initial stop times (same structure, so the same slots)."""
    return replace(m, waits=waits)


def insert_pause_visit(tmap: TopoMap, m: Mission, i: int, pause: int, wait: float) -> Mission:
    """Insert the detour nodes[i] → pause → nodes[i] after arriving at nodes[i] (Fig. 4, middle)."""
    nd = m.nodes
    new_nodes = np.concatenate([nd[: i + 1], np.array([pause, nd[i]], np.int32), nd[i + 1 :]])
    new_waits = np.concatenate([m.waits[: i + 1], np.array([wait, 0.0]), m.waits[i + 1 :]])
    slots = mutable_slots(tmap, new_nodes, m.prioritized, m.frozen, m.head)
    return replace(m, nodes=new_nodes, waits=new_waits, slots=slots)


def remove_pause_visit(tmap: TopoMap, m: Mission, i: int) -> Mission:
    """Remove the detour nodes[i-1] → pause nodes[i] → nodes[i-1] (Fig. 4, bottom)."""
    nd = m.nodes
    new_nodes = np.concatenate([nd[:i], nd[i + 2 :]])
    new_waits = np.concatenate([m.waits[:i], m.waits[i + 2 :]])
    new_waits[-1] = 0.0
    slots = mutable_slots(tmap, new_nodes, m.prioritized, m.frozen, m.head)
    return replace(m, nodes=new_nodes, waits=new_waits, slots=slots)


def describe(tmap: TopoMap, m: Mission) -> str:
    """``A -(5s)-> X -> P -(12s)-> X -> B``: the path with the non-zero initial stop times."""
    parts = []
    for i, x in enumerate(m.nodes):
        name = tmap.nodes[x].name
        if i < m.items and m.waits[i] > 0:
            name += f" [wait {m.waits[i]:.1f}s]"
        parts.append(name)
    return " → ".join(parts)
