"""The numba kernel of the fleet mission evaluation (imported lazily: numba takes ~1 s to import).

See :mod:`btmission.dispatch.evaluate` for what is computed; this is the same set of conflicting
pairs as the event-driven reference, found by bucketing node visits by node and segment traversals
by segment pair (counting sort), then checking the pairs inside each bucket.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _buckets(keys, n_keys):  # type: ignore[no-untyped-def]
    """Counting sort: items with key k are ``order[start[k]:start[k + 1]]`` (keys < 0 skipped)."""
    start = np.zeros(n_keys + 1, np.int64)
    for i in range(keys.size):
        if keys[i] >= 0:
            start[keys[i] + 1] += 1
    for k in range(n_keys):
        start[k + 1] += start[k]
    order = np.empty(start[n_keys], np.int64)
    fill = start[:-1].copy()
    for i in range(keys.size):
        k = keys[i]
        if k >= 0:
            order[fill[k]] = i
            fill[k] += 1
    return start, order


@njit(cache=True, nogil=True)
def evaluate_kernel(nodes, waits, offsets, t0, ttime, edge, n_nodes, delta):  # type: ignore[no-untyped-def]
    """(N_c, t_first, t_end) for a flattened fleet mission; t_first = inf when there is none."""
    nv = offsets.size - 1
    total = nodes.size
    arr = np.empty(total)
    dep = np.empty(total)
    veh = np.empty(total, np.int64)
    t_end = -np.inf
    for k in range(nv):
        t = t0[k]
        lo = offsets[k]
        hi = offsets[k + 1]
        for i in range(lo, hi):
            arr[i] = t
            veh[i] = k
            if i == hi - 1:
                dep[i] = np.inf
                if t > t_end:
                    t_end = t
            else:
                d = t + waits[i]
                dep[i] = d
                t = d + ttime[nodes[i], nodes[i + 1]]
    is_start = np.zeros(total, np.bool_)
    for k in range(nv):
        is_start[offsets[k]] = True

    n_c = 0
    t_first = np.inf
    # ---- node visits, bucketed by node
    start, order = _buckets(nodes, n_nodes)
    for x in range(n_nodes):
        for a in range(start[x], start[x + 1]):
            i = order[a]
            for b in range(a + 1, start[x + 1]):
                j = order[b]
                if veh[i] == veh[j] or (is_start[i] and is_start[j]):
                    continue
                if arr[j] < dep[i] + delta and arr[i] < dep[j] + delta:
                    n_c += 1
                    tc = arr[i] if arr[i] > arr[j] else arr[j]
                    if tc < t_first:
                        t_first = tc
    # ---- segment traversals (item i: nodes[i] -> nodes[i + 1]), bucketed by segment pair
    seg = np.full(total, -1, np.int64)
    n_edges = 0
    for i in range(total - 1):
        if veh[i + 1] == veh[i]:
            seg[i] = edge[nodes[i], nodes[i + 1]]
            if seg[i] + 1 > n_edges:
                n_edges = seg[i] + 1
    start, order = _buckets(seg, n_edges)
    for e in range(n_edges):
        for a in range(start[e], start[e + 1]):
            i = order[a]
            for b in range(a + 1, start[e + 1]):
                j = order[b]
                if veh[i] == veh[j] or nodes[i] == nodes[j]:
                    continue  # same vehicle, or the same direction
                if dep[i] < arr[j + 1] and dep[j] < arr[i + 1]:
                    n_c += 1
                    tc = arr[i + 1] if arr[i + 1] < arr[j + 1] else arr[j + 1]
                    if tc < t_first:
                        t_first = tc
    return n_c, t_first, t_end
