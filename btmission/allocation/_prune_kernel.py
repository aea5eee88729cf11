# mypy: allow-untyped-defs
"""numba kernels of the pruned assignment solver (:mod:`btmission.allocation.pruned`).

Imported lazily (numba takes ~1 s to import); ``cache=True`` stores the machine code next to this
file and ``nogil=True`` lets two threads scan disjoint rows of the cost matrix at once. Kept free
of Python objects so numba compiles them in nopython mode.
"""

from __future__ import annotations

import numpy as np
from numba import njit

INF = np.inf


@njit(cache=True, nogil=True)
def scan_rows(costs, bonus, incumbent, rows, top_col, top_x, stats):  # pragma: no cover
    """One pass over the cost matrix rows ``rows``: each row's best bids and what the profit
    transform and the range check need.

    For row ``rows[p]`` (``x = cost − bonus`` on its bids, the finite costs — ``bonus`` may be
    None: ``x = cost`` —; NaN and ±inf are no bid): ``top_col[p, :m]``/``top_x[p, :m]`` its
    ``m = min(w, bids)`` smallest ``x`` in increasing order (ties: lower column first),
    ``w = top_col.shape[1]``, its incumbent left out (the caller keeps it anyway); the caller
    fills ``top_x`` with +inf beforehand, so ``top_x[p, 0]`` is the row's smallest ``x``
    (incumbent aside) and ``top_x[p, w − 1]`` the smallest ``x`` not among the first ``w − 1``.
    ``stats[p]`` = (max ``x``, min cost — NaN ignored, ±inf included —, max finite cost).

    The loop has one branch, rarely taken (a new entry among the best); the rest is min/max
    (branch-free), so the pattern of bids and no-bids costs no branch mispredictions (a branch
    per cell made this pass 4× slower at 30 % bids). Without a bonus, ``x`` is the cost and one
    reduction less is needed (numba compiles the two cases apart).
    """
    nt = costs.shape[1]
    w = top_col.shape[1]
    for p in range(rows.size):
        i = rows[p]
        inc = incumbent[i]
        m = 0
        worst = INF  # top_x[p, w - 1] once the list is full
        xhi = -INF
        clo = INF
        chi = -INF
        for j in range(nt):
            c = costs[i, j]
            bid = abs(c) < INF  # False for NaN and ±inf
            if bonus is None:
                x = c
            else:
                x = c - bonus[j]
                chi = max(chi, c if bid else -INF)
            xl = x if bid else INF
            xhi = max(xhi, x if bid else -INF)
            clo = min(clo, c if c == c else INF)  # −inf included: rejected
            if xl < worst and j != inc:
                if m == w:  # full: the worst one leaves the list
                    m -= 1
                q = m
                while q > 0 and top_x[p, q - 1] > xl:
                    top_x[p, q] = top_x[p, q - 1]
                    top_col[p, q] = top_col[p, q - 1]
                    q -= 1
                top_x[p, q] = xl
                top_col[p, q] = j
                m += 1
                if m == w:
                    worst = top_x[p, w - 1]
        stats[p, 0] = xhi
        stats[p, 1] = clo
        stats[p, 2] = xhi if bonus is None else chi


@njit(cache=True, nogil=True)
def _push(hd, hj, size, d, j):  # pragma: no cover
    q = size
    hd[q] = d
    hj[q] = j
    while q > 0:
        parent = (q - 1) // 2
        if hd[parent] < hd[q] or (hd[parent] == hd[q] and hj[parent] <= hj[q]):
            break
        hd[q], hd[parent] = hd[parent], hd[q]
        hj[q], hj[parent] = hj[parent], hj[q]
        q = parent
    return size + 1


@njit(cache=True, nogil=True)
def _pop(hd, hj, size):  # pragma: no cover
    """Remove the top of the heap (the smallest (d, j)); returns the new size."""
    size -= 1
    hd[0] = hd[size]
    hj[0] = hj[size]
    q = 0
    while True:
        a = 2 * q + 1
        if a >= size:
            break
        b = a + 1
        if b < size and (hd[b] < hd[a] or (hd[b] == hd[a] and hj[b] < hj[a])):
            a = b
        if hd[q] < hd[a] or (hd[q] == hd[a] and hj[q] <= hj[a]):
            break
        hd[q], hd[a] = hd[a], hd[q]
        hj[q], hj[a] = hj[a], hj[q]
        q = a
    return size


@njit(cache=True, nogil=True)
def shortest_augmenting_paths(cols, cost, n_cols, big):  # pragma: no cover
    """Minimum-cost assignment of every row on a sparse graph, with its dual solution.

    Row ``i`` may take column ``cols[i, t]`` (``-1``: no edge) at ``cost[i, t]``, or its own
    dummy column ``n_cols + i`` at ``big``, so a full assignment always exists. Successive
    shortest augmenting paths (Dijkstra on reduced costs, a binary heap over the columns reached:
    the sparse form of the rectangular Jonker-Volgenant of Crouse 2016, which scipy's
    ``linear_sum_assignment`` implements densely). Returns ``(col4row, u, v)``: each row's column
    and the duals, with ``u[i] + v[j] ≤ cost`` on every edge (``=`` on the assigned ones),
    ``v ≤ 0``, and ``v = 0`` on every column left unassigned — the certificate the caller
    extends to the edges it left out.
    """
    na, width = cols.shape
    nc = n_cols + na
    u = np.zeros(na)
    v = np.zeros(nc)
    row4col = np.full(nc, -1, np.int64)
    col4row = np.full(na, -1, np.int64)
    spc = np.full(nc, INF)
    path = np.full(nc, -1, np.int64)
    scanned = np.zeros(nc, np.bool_)
    touched = np.empty(nc, np.int64)
    done = np.empty(nc, np.int64)
    tree = np.empty(na, np.int64)
    cap = na * (width + 1) + 1
    hd = np.empty(cap)
    hj = np.empty(cap, np.int64)
    for cur in range(na):
        n_touched = 0
        n_done = 0
        n_tree = 0
        size = 0
        min_val = 0.0
        i = cur
        sink = -1
        while sink == -1:
            tree[n_tree] = i
            n_tree += 1
            base = min_val - u[i]
            for t in range(width + 1):
                if t < width:
                    j = cols[i, t]
                    if j < 0:
                        continue
                    c = cost[i, t]
                else:
                    j = n_cols + i
                    c = big
                if scanned[j]:
                    continue
                r = base + c - v[j]
                if r < spc[j]:
                    if spc[j] == INF:
                        touched[n_touched] = j
                        n_touched += 1
                    spc[j] = r
                    path[j] = i
                    size = _push(hd, hj, size, r, j)
            while True:  # the nearest column not scanned yet (stale heap entries skipped)
                d = hd[0]
                j = hj[0]
                size = _pop(hd, hj, size)
                if not scanned[j] and d == spc[j]:
                    break
            min_val = d
            scanned[j] = True
            done[n_done] = j
            n_done += 1
            if row4col[j] == -1:
                sink = j
            else:
                i = row4col[j]
        u[cur] += min_val
        for t in range(1, n_tree):
            i = tree[t]
            u[i] += min_val - spc[col4row[i]]
        for t in range(n_done):
            j = done[t]
            v[j] -= min_val - spc[j]
        j = sink
        while True:
            i = path[j]
            row4col[j] = i
            prev = col4row[i]
            col4row[i] = j
            j = prev
            if i == cur:
                break
        for t in range(n_touched):
            j = touched[t]
            spc[j] = INF
            path[j] = -1
            scanned[j] = False
    return col4row, u, v
