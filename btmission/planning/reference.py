"""Reference implementations the compiled planner is tested (and benchmarked) against.

* :func:`dijkstra_reference` — plain Python Dijkstra with ``heapq`` over the unpadded voxel grid,
  written straight from eq. 3-4 (step length + the cost of the voxel entered, rock never
  entered). Slow; for small maps in tests.
* :func:`grid_graph` — the same graph as a ``scipy.sparse`` matrix for
  ``scipy.sparse.csgraph.dijkstra`` (the peer in ``btmission bench planner``).
"""

from __future__ import annotations

import heapq
import itertools
import math
from typing import Any

import numpy as np
import numpy.typing as npt

from btmission.planning.risk import CostMap

NEIGHBOURS: tuple[tuple[int, int, int], ...] = tuple(
    (a, b, c) for a, b, c in itertools.product((-1, 0, 1), repeat=3) if (a, b, c) != (0, 0, 0)
)


def dijkstra_reference(cost_map: CostMap, start: tuple[int, int, int]) -> npt.NDArray[np.float64]:
    """Optimal cost from voxel ``start`` to every voxel (inf where unreachable), pure Python."""
    vc = cost_map.voxel_cost
    res = cost_map.resolution
    shape = vc.shape
    dist = np.full(shape, np.inf)
    if not math.isfinite(vc[start]):
        return dist
    dist[start] = 0.0
    heap: list[tuple[float, tuple[int, int, int]]] = [(0.0, start)]
    done: set[tuple[int, int, int]] = set()
    while heap:
        d, u = heapq.heappop(heap)
        if u in done:
            continue
        done.add(u)
        for dx, dy, dz in NEIGHBOURS:
            v = (u[0] + dx, u[1] + dy, u[2] + dz)
            if not (0 <= v[0] < shape[0] and 0 <= v[1] < shape[1] and 0 <= v[2] < shape[2]):
                continue
            c = float(vc[v])
            if not math.isfinite(c):  # occupied: never entered
                continue
            nd = d + (res * math.sqrt(dx * dx + dy * dy + dz * dz) + c)
            if nd < dist[v]:
                dist[v] = nd
                heapq.heappush(heap, (nd, v))
    return dist


def grid_graph(cost_map: CostMap) -> tuple[Any, npt.NDArray[np.int64]]:
    """The planner's graph as a CSR matrix over the enterable voxels, and their flat map numbers.

    Edge ``u → v`` weighs ``step + c(v)``; rock and the border are not nodes.
    """
    from scipy.sparse import csr_matrix

    from btmission.planning.dstar import neighbour_table

    cost = cost_map.flat_padded()
    off, step = neighbour_table(cost_map.padded.shape, cost_map.resolution)
    nodes = np.flatnonzero(np.isfinite(cost))
    ids = np.full(cost.size, -1, dtype=np.int64)
    ids[nodes] = np.arange(len(nodes))
    rows, cols, weights = [], [], []
    for o, s in zip(off, step):
        v = nodes + o
        ok = np.isfinite(cost[v])
        rows.append(ids[nodes[ok]])
        cols.append(ids[v[ok]])
        weights.append(s + cost[v[ok]])
    n = len(nodes)
    graph = csr_matrix(
        (np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
    flat_map = cost_map.map.flat(cost_map.unpad_index(nodes))
    return graph, flat_map
