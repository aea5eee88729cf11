# mypy: allow-untyped-defs
"""Compiled carrot chasing on a route polyline, for :class:`btmission.runtime.navigation.Polyline`.

Every vehicle projects itself onto its route and looks up its carrot twice per control period; a
route has tens of segments, so numpy's per-call overhead, not the arithmetic, was the cost. The
route is one (n, 9) table: per point its position (0:3), the segment to the next point (3:6, zero
on the last), that segment's squared length (6) and length (7), and the arc length at the point
(8).

numba in nopython mode (typed by numba, not annotated, like the planner's kernels); ``cache=True``
stores the machine code next to this file.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def project(table, px, py, pz, start, window):  # pragma: no cover - jit
    """(segment, arc length) of the route's point closest to (px, py, pz), searching ``window``
    segments from ``start``; the first of equally close segments wins."""
    n = table.shape[0] - 1
    if n <= 0:
        return 0, 0.0
    start = min(max(start, 0), n - 1)
    stop = min(n, start + window)
    best = start
    best_d = np.inf
    best_t = 0.0
    for i in range(start, stop):
        ax, ay, az = table[i, 0], table[i, 1], table[i, 2]
        bx, by, bz = table[i, 3], table[i, 4], table[i, 5]
        ll = table[i, 6]
        t = ((px - ax) * bx + (py - ay) * by + (pz - az) * bz) / (ll if ll > 0 else 1.0)
        t = min(max(t, 0.0), 1.0)
        dx = px - (ax + t * bx)
        dy = py - (ay + t * by)
        dz = pz - (az + t * bz)
        d = dx * dx + dy * dy + dz * dz
        if d < best_d or i == start:
            best, best_d, best_t = i, d, t
    return best, table[best, 8] + best_t * table[best, 7]


@njit(cache=True)
def _point_into(table, s, out, o):  # pragma: no cover - jit
    """Write the point at arc length ``s`` (clamped to the ends) to out[o:o + 3]."""
    n = table.shape[0] - 1
    if s <= 0 or n <= 0 or s >= table[n, 8]:
        k = 0 if s <= 0 else n
        out[o], out[o + 1], out[o + 2] = table[k, 0], table[k, 1], table[k, 2]
        return
    lo, hi = 0, n + 1  # the last point with arc ≤ s (searchsorted side="right", minus one)
    while lo < hi:
        mid = (lo + hi) // 2
        if table[mid, 8] <= s:
            lo = mid + 1
        else:
            hi = mid
    j = lo - 1
    seg_len = table[j, 7]
    frac = (s - table[j, 8]) / seg_len if seg_len > 0 else 0.0
    out[o] = table[j, 0] + frac * table[j, 3]
    out[o + 1] = table[j, 1] + frac * table[j, 4]
    out[o + 2] = table[j, 2] + frac * table[j, 5]


@njit(cache=True)
def point_at(table, s):  # pragma: no cover - jit
    """The point at arc length ``s``, clamped to the ends."""
    out = np.empty(3)
    _point_into(table, s, out, 0)
    return out


@njit(cache=True)
def carrots(table, px, py, pz, start, window, ahead1, ahead2):  # pragma: no cover - jit
    """:func:`project`, then the points ``ahead1`` and ``ahead2`` further along the route, in one
    call: [segment, arc length, point 1 (3), point 2 (3)]."""
    seg, arc = project(table, px, py, pz, start, window)
    out = np.empty(8)
    out[0], out[1] = seg, arc
    _point_into(table, arc + ahead1, out, 2)
    _point_into(table, arc + ahead2, out, 5)
    return out
