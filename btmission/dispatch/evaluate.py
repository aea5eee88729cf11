"""Fleet mission evaluation (seed 004 §4.2, eq. 1-2): collisions, duration, score.

Every vehicle's timeline is fixed by its mission: it is at ``nodes[0]`` from ``t0``, leaves node i
after its initial stop time ``waits[i]`` and reaches node i+1 after the segment's traversal time.
The paper evaluates a fleet mission by *event-driven stepping*: find each vehicle's time Δt_k to its
next node, advance time by the smallest, and check at the node p_min just reached

* **segment violations** — a segment pair (i→j and j→i) with vehicles on both members (a head-on
  meeting); several vehicles on *one* member are allowed;
* **grazing collisions** — another vehicle passed, stands at, or reaches p_min within the time
  window δ (vehicles are not points, and the map has no distances, so the margin is a time).

A vehicle stays at the end node of its mission (it blocks that node from then on).

Each conflicting pair is counted once, at the event where the stepping first sees it: a head-on
pair when the first of the two vehicles reaches the end of its segment, a node pair when the later
of the two visits begins. :func:`evaluate_reference` is that stepping, written for clarity; the
production path (:class:`Evaluator`) computes exactly the same set of pairs and detection times
from the timelines' intervals in a numba kernel (``cache=True``), bucketed by node and by segment
pair, which is what makes several thousand GA generations per run affordable. Tests compare the
two on random fleet missions.

Score (to maximise): with collisions ``s = −N_c + β t_c`` (eq. 1; t_c the time of the first
collision, β small enough that s stays < 0), otherwise ``s = (1/t_e)(ξ_min/ξ)`` (eq. 2; t_e the
time when the last vehicle completes its mission, ξ the number of mission items and ξ_min the
number when every vehicle follows Π0).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from btmission.dispatch.missions import FleetMission, fleet_items
from btmission.dispatch.topomap import TopoMap

DEFAULT_GRAZING_WINDOW_S = 2.0
"""δ: two vehicles at one node less than this apart (in time) is a grazing collision."""


@dataclass(frozen=True)
class Evaluation:
    """The outcome of evaluating one fleet mission."""

    score: float
    collisions: int
    """N_c: conflicting pairs (segment violations + grazing collisions)."""
    t_first: float
    """t_c: time of the first collision after the reference time (nan when feasible)."""
    duration: float
    """t_e: time (after the reference time) when the last vehicle completes its mission."""
    items: int
    """ξ: number of mission items."""

    @property
    def feasible(self) -> bool:
        return self.collisions == 0


@dataclass(frozen=True)
class Conflict:
    """One conflicting pair found by :func:`evaluate_reference` (for tests and explanations)."""

    kind: str  # "segment" | "node"
    time: float
    vehicles: tuple[int, int]
    where: tuple[int, ...]
    """The node (grazing) or the two nodes of the segment pair (head-on)."""


# ------------------------------------------------------------------------------- timelines
def timeline(
    tmap: TopoMap, nodes: Sequence[int], waits: Sequence[float], t0: float
) -> tuple[list[float], list[float]]:
    """Arrival and departure time at each node of a mission (departure from the end node = inf)."""
    arr: list[float] = []
    dep: list[float] = []
    t = t0
    for i in range(len(nodes)):
        arr.append(t)
        if i == len(nodes) - 1:
            dep.append(math.inf)
        else:
            d = t + float(waits[i])
            dep.append(d)
            t = d + float(tmap.ttime[nodes[i], nodes[i + 1]])
    return arr, dep


def evaluate_reference(
    tmap: TopoMap, fleet: FleetMission, delta: float = DEFAULT_GRAZING_WINDOW_S
) -> tuple[list[Conflict], float]:
    """Event-driven stepping of §4.2, in plain Python. Returns the conflicts and t_end (absolute).

    At each step the vehicle(s) with the smallest time to their next node advance to it (several
    at once in the rare tie, footnote 3); at that node the segment pairs and the grazing window are
    checked for the pairs involving each vehicle that just arrived.
    """
    tl = [timeline(tmap, [int(x) for x in m.nodes], list(m.waits), m.t0) for m in fleet]
    nodes = [[int(x) for x in m.nodes] for m in fleet]
    pos = [0] * len(fleet)  # index of the last node reached
    t = min((m.t0 for m in fleet), default=0.0)
    conflicts: list[Conflict] = []
    while True:
        # Δt_k for every vehicle still under way; step to the smallest
        dts = [tl[k][0][pos[k] + 1] - t for k in range(len(fleet)) if pos[k] + 1 < len(nodes[k])]
        if not dts:
            break
        t += min(dts)
        movers = [
            k for k in range(len(fleet)) if pos[k] + 1 < len(nodes[k]) and tl[k][0][pos[k] + 1] == t
        ]
        for v in movers:
            i = pos[v] + 1
            p, x = nodes[v][i], nodes[v][i - 1]
            for u in range(len(fleet)):
                if u == v:
                    continue
                arr_u, dep_u = tl[u]
                # segment pair {x, p}: is u on p→x right now?
                for j in range(len(nodes[u]) - 1):
                    if nodes[u][j] == p and nodes[u][j + 1] == x:
                        s_u, e_u = dep_u[j], arr_u[j + 1]
                        if s_u < t and (e_u > t or (e_u == t and u in movers and v < u)):
                            conflicts.append(Conflict("segment", t, (v, u), (x, p)))
                # grazing at p: a visit of u that began before this arrival (or at the same
                # instant, counted once) and that ends less than δ before it
                dep_v = tl[v][1][i]
                for j in range(len(nodes[u])):
                    if nodes[u][j] != p:
                        continue
                    a_u = arr_u[j]
                    begun = a_u < t or (a_u == t and (j == 0 or u < v))
                    if begun and dep_u[j] + delta > t and a_u < dep_v + delta:
                        conflicts.append(Conflict("node", t, (v, u), (p,)))
        for v in movers:
            pos[v] += 1
    t_end = max((tl[k][0][-1] for k in range(len(fleet))), default=0.0)
    return conflicts, t_end


# ------------------------------------------------------------------------------- numba kernel
_KERNEL: Any = None


def _kernel() -> Any:
    """The compiled kernel (numba imported lazily; compiled once, cached on disk)."""
    global _KERNEL
    if _KERNEL is None:
        from btmission.dispatch._kernel import evaluate_kernel

        _KERNEL = evaluate_kernel
    return _KERNEL


def flatten(
    fleet: FleetMission,
) -> tuple[NDArray[np.int32], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """The flat arrays the kernel reads: nodes, waits, per-vehicle offsets and start times."""
    nodes = np.concatenate([m.nodes for m in fleet])
    waits = np.concatenate([m.waits for m in fleet])
    offsets = np.zeros(len(fleet) + 1, dtype=np.int64)
    np.cumsum([len(m.nodes) for m in fleet], out=offsets[1:])
    t0 = np.array([m.t0 for m in fleet], dtype=np.float64)
    return nodes, waits, offsets, t0


def default_beta(tmap: TopoMap, fleet: FleetMission, wait_max: float) -> float:
    """β of eq. 1: below 1 / (longest possible duration) so that β t_c < 1 whenever t_c counts.

    The bound: every vehicle, one after the other, drives its longest possible route (Π0 plus a
    pause visit per transit node, each with the longest wait) — generous, as the paper asks.
    """
    longest = float(np.max(tmap.dist)) if tmap.n > 1 else 1.0
    bound = 0.0
    for m in fleet:
        bound += m.t0 if m.t0 > 0 else 0.0
        bound += (m.items + 1) * (longest + wait_max) + m.min_wait
    return 1.0 / max(bound, 1.0)


class Evaluator:
    """Scores fleet missions on one map (eq. 1-2). Call it with a fleet mission to get the score.

    Args:
        tmap: the map.
        xi_min: ξ_min of eq. 2 (the items of the fleet when every vehicle follows Π0).
        beta: β of eq. 1.
        delta: grazing window δ in s.
        t_ref: the time durations and collision times are measured from (the end of the
            optimisation in dynamic planning; 0 in static planning).
    """

    def __init__(
        self,
        tmap: TopoMap,
        xi_min: int,
        beta: float,
        delta: float = DEFAULT_GRAZING_WINDOW_S,
        t_ref: float = 0.0,
    ) -> None:
        if delta < 0:
            raise ValueError("the grazing window must be >= 0 s")
        self.tmap = tmap
        self.xi_min = max(int(xi_min), 1)
        self.beta = float(beta)
        self.delta = float(delta)
        self.t_ref = float(t_ref)
        self.calls = 0
        self._ttime = np.ascontiguousarray(tmap.ttime)
        self._edge = np.ascontiguousarray(tmap.edge)

    def raw(self, fleet: FleetMission) -> tuple[int, float, float]:
        """(N_c, t_first, t_end) in absolute time, from the kernel."""
        self.calls += 1
        nodes, waits, offsets, t0 = flatten(fleet)
        n_c, t_first, t_end = _kernel()(
            nodes, waits, offsets, t0, self._ttime, self._edge, self.tmap.n, self.delta
        )
        return int(n_c), float(t_first), float(t_end)

    def score_of(self, n_c: int, t_first: float, t_end: float, items: int) -> float:
        """Eq. 1 when ``n_c`` > 0, else eq. 2."""
        if n_c > 0:
            tc = max(t_first - self.t_ref, 0.0)
            return -n_c + min(self.beta * tc, 0.999)
        te = max(t_end - self.t_ref, 1e-9)
        return (1.0 / te) * (self.xi_min / max(items, 1))

    def __call__(self, fleet: FleetMission) -> float:
        n_c, t_first, t_end = self.raw(fleet)
        return self.score_of(n_c, t_first, t_end, fleet_items(fleet))

    def evaluate(self, fleet: FleetMission) -> Evaluation:
        """The full :class:`Evaluation` (score, N_c, t_c, t_e, ξ)."""
        n_c, t_first, t_end = self.raw(fleet)
        xi = fleet_items(fleet)
        return Evaluation(
            score=self.score_of(n_c, t_first, t_end, xi),
            collisions=n_c,
            t_first=(t_first - self.t_ref) if n_c else math.nan,
            duration=max(t_end - self.t_ref, 0.0),
            items=xi,
        )
