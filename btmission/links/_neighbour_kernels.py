# mypy: allow-untyped-defs
"""Compiled neighbour query of :class:`btmission.links.bus.InMemoryBus`: every agent asks every
control step which others are near, so numpy's per-call overhead on a fleet-sized array was the
cost.

numba in nopython mode (typed by numba, not annotated, like the planner's kernels); ``cache=True``
stores the machine code next to this file.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def near_rows(starts, n, x, y, within, own):  # pragma: no cover - jit
    """Rows ``r < n`` of ``starts`` other than ``own`` with √(dx² + dy²) ≤ ``within`` from
    (x, y), nearest first, equal distances in row order (a stable insertion sort: a few
    candidates). NaN rows (agents gone) never qualify."""
    rows = np.empty(n, dtype=np.int64)
    dist = np.empty(n)
    k = 0
    for r in range(n):
        if r == own:
            continue
        dx = starts[r, 0] - x
        dy = starts[r, 1] - y
        d = math.sqrt(dx * dx + dy * dy)
        if d <= within:
            j = k
            while j > 0 and dist[j - 1] > d:
                dist[j] = dist[j - 1]
                rows[j] = rows[j - 1]
                j -= 1
            dist[j] = d
            rows[j] = r
            k += 1
    return rows[:k]


@njit(cache=True)
def near_points(starts, n, x, y, within, own):  # pragma: no cover - jit
    """The points (k, 3) of :func:`near_rows`' rows, in its order."""
    rows = near_rows(starts, n, x, y, within, own)
    out = np.empty((len(rows), 3))
    for i in range(len(rows)):
        r = rows[i]
        out[i, 0] = starts[r, 0]
        out[i, 1] = starts[r, 1]
        out[i, 2] = starts[r, 2]
    return out


@njit(cache=True)
def near_states(starts, vel, n, x, y, within, own):  # pragma: no cover - jit
    """The points of :func:`near_rows`' rows beside their velocities ``vel``, (k, 6)."""
    rows = near_rows(starts, n, x, y, within, own)
    out = np.empty((len(rows), 6))
    for i in range(len(rows)):
        r = rows[i]
        for c in range(3):
            out[i, c] = starts[r, c]
            out[i, 3 + c] = vel[r, c]
    return out
