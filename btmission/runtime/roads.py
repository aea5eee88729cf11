"""Named places and road distances from a mission's topological map (seed 004 §3.1).

A mission with ``world.topomap`` names its task locations by map node (``pickup: L1n``). The
runtime then needs two things the voxel world cannot give:

* **places** — where a named node is: its ``xy`` from the map, on the ground of the voxel world;
* **road costs** for the auction's ``path_cost`` — trucks drive the roads, so the cost of going
  from a point to a node is the length of the road between them, not of a free-space D*+ path.

:class:`RoadCosts` answers ``path_cost(start, goal)`` (metres, the unit of the D*+ costs) by
projecting both points onto the nearest road segment and adding the segment remainders to the
length of the unique road path Π0 between the segment ends (the map is a tree, §3.1). A point
farther than ``snap_m`` from every road is not on the network: it falls back to the D*+ provider.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from btmission.allocation.bidder import CostProvider
from btmission.dispatch.topomap import TopoMap
from btmission.errors import BtmissionError

Point = tuple[float, float, float]


class RoadMapError(BtmissionError, ValueError):
    """The topological map cannot be driven (a node without a position)."""


@dataclass(frozen=True)
class _Snap:
    seg: int
    u: float
    """Fraction along segment ``seg`` (from its first to its second node)."""
    off: float
    """Distance from the point to the road (m)."""


class RoadCosts:
    """Road distances on ``tmap`` (module docstring); ``ground_z(x, y)`` puts places on the
    ground. Implements :class:`~btmission.allocation.bidder.CostProvider`."""

    def __init__(
        self,
        tmap: TopoMap,
        ground_z: Callable[[float, float], float],
        fallback: CostProvider | None = None,
        *,
        snap_m: float = 25.0,
    ) -> None:
        missing = [n.name for n in tmap.nodes if n.xy is None]
        if missing:
            raise RoadMapError(
                f"topological map '{tmap.name}': nodes {', '.join(missing)} have no xy position; "
                "running a mission on it needs the position of every node (metres, world frame)"
            )
        self.tmap = tmap
        self.fallback = fallback
        self.snap_m = snap_m
        xy = np.array([n.xy for n in tmap.nodes], dtype=np.float64)
        self.xy = xy
        self.places: dict[str, Point] = {
            n.name: (float(x), float(y), float(ground_z(float(x), float(y))))
            for n, (x, y) in zip(tmap.nodes, xy, strict=True)
        }
        ends = [(tmap.index[s.a], tmap.index[s.b]) for s in tmap.segments]
        self.ends = np.array(ends, dtype=np.int64).reshape(-1, 2)
        self.length = np.linalg.norm(xy[self.ends[:, 1]] - xy[self.ends[:, 0]], axis=1)
        self.road = road_lengths(tmap, xy)

    def place(self, name: str) -> Point:
        """Position of node ``name`` (KeyError if there is none)."""
        return self.places[name]

    def _snap(self, p: Point) -> _Snap | None:
        a = self.xy[self.ends[:, 0]]
        d = self.xy[self.ends[:, 1]] - a
        q = np.array(p[:2], dtype=np.float64)
        den = np.maximum((d * d).sum(axis=1), 1e-12)
        u = np.clip(((q - a) * d).sum(axis=1) / den, 0.0, 1.0)
        off = np.linalg.norm(a + u[:, None] * d - q, axis=1)
        k = int(np.argmin(off))
        if off[k] > self.snap_m:
            return None
        return _Snap(k, float(u[k]), float(off[k]))

    def path_cost(self, start: Point, goal: Point) -> float:
        """Road length from ``start`` to ``goal`` in metres (module docstring)."""
        s, g = self._snap(start), self._snap(goal)
        if s is None or g is None:
            if self.fallback is None:
                return math.inf
            return float(self.fallback.path_cost(start, goal))
        if s.seg == g.seg:
            along = abs(s.u - g.u) * float(self.length[s.seg])
            return s.off + along + g.off
        best = math.inf
        for i, di in self._ends_of(s):
            for j, dj in self._ends_of(g):
                best = min(best, di + float(self.road[i, j]) + dj)
        return s.off + best + g.off

    def _ends_of(self, s: _Snap) -> tuple[tuple[int, float], tuple[int, float]]:
        a, b = (int(x) for x in self.ends[s.seg])
        n = float(self.length[s.seg])
        return (a, s.u * n), (b, (1.0 - s.u) * n)


def road_lengths(tmap: TopoMap, xy: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """``L[i, j]``: length (m) of Π0(i, j), the unique road path, from node positions."""
    n = tmap.n
    out = np.zeros((n, n))
    for i in range(n):  # one tree walk per root: O(n²) in all
        stack = [i]
        seen = {i}
        while stack:
            x = stack.pop()
            for y in tmap.neighbors[x]:
                if y not in seen:
                    seen.add(y)
                    out[i, y] = out[i, x] + float(np.hypot(*(xy[y] - xy[x])))
                    stack.append(y)
    return out
