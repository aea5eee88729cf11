# mypy: allow-untyped-defs
"""The planner's search as it was before issue 19 (commit 9e61e1a), kept to check the faster one
bit for bit: :class:`PreviousPlanner` is a :class:`~btmission.planning.dstar.Planner` whose
searches run this kernel, so every public result (one-to-all fields, single queries, costs_to,
incremental replanning) can be compared with the current planner's for the same inputs.

The kernel below is the previous ``_kernels.search`` unchanged: nine per-voxel work arrays, voxels
marked reached with run numbers, and a doubly linked list per bucket with decrease-key.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numba import njit

from btmission.planning._kernels import _clean_path, _heur
from btmission.planning.dstar import _NO_FIELD, _NO_TREE, Planner

INF = np.inf


@njit(cache=True, inline="always")
def _bucket_push(v, b, head, nxt, prv, bkt, mask):
    """Put voxel v at the front of bucket b (intrusive doubly linked list; the number of
    buckets is a power of two, ``mask`` = that number - 1)."""
    sl = b & mask
    bkt[v] = sl
    h0 = head[sl]
    nxt[v] = h0
    prv[v] = -1
    if h0 >= 0:
        prv[h0] = v
    head[sl] = v


@njit(cache=True)
def search(
    cost,
    off,
    step,
    sources,
    targets,
    heuristic,
    reverse,
    sx,
    sy,
    res,
    delta,
    n_buckets,
    w,
    run,
    hfield,
    hshift,
    tree,
):
    """Dijkstra (or A* with the octile heuristic when ``heuristic`` and one target) from every
    voxel in ``sources`` (cost 0) over the padded grid, with a bucket queue (Dial's algorithm).

    Keys are binned into buckets of width ``delta`` = the shortest step (the resolution). Every
    edge costs at least ``delta``, so in Dijkstra no voxel in the lowest bucket can improve another
    one in the same bucket: the whole bucket is final, in any order, and the result is exact.
    With A* the key ``g + h`` can stay level along a step, so a voxel improved after its
    expansion is re-queued and expanded again (label correcting); the search stops only once the
    goal's bucket is drained, which keeps it exact. ``n_buckets`` must exceed the largest key
    increase of one step divided by ``delta`` and be a power of two (a circular array of buckets; intrusive doubly
    linked lists, so a voxel sits in one bucket at a time).

    ``hfield`` (optional, empty to skip) is a lower bound on each voxel's cost to the goal known
    from an earlier search (a cost-to-goal field before the map changed); the heuristic is then
    ``max(octile, hfield - hshift)``. Costs that only rose since the field was computed keep it a
    lower bound; ``hshift`` = the sum of all cost decreases since restores that (see
    :class:`~btmission.planning.dstar.IncrementalPlanner`).

    ``tree`` = (next, changed, field_id, memo, stack) lets A* stop early when ``hfield`` is an
    exact cost-to-goal field from before the map changed and costs only rose since (``hshift`` =
    0): ``next[v]`` is v's next voxel toward the goal in that field's tree and ``changed[x] ==
    field_id`` marks the voxels changed since. A voxel whose old path to the goal enters no changed
    voxel still has that path at the same cost, and no cheaper one (costs only rose), so its
    cost-to-goal is exact: popping it gives a complete candidate ``g + hfield`` and it need not be
    expanded; the search stops once the best candidate's bucket is drained, which keeps it exact.
    The checks walk old paths once (``memo`` stamps the verdicts with ``run``). Empty ``next``
    disables this. The voxel whose candidate won is returned (-1 without a tree).

    With ``reverse`` the edges are walked backwards (the step ``v → u`` costs ``step + cost[u]``),
    so ``g`` is the cost *to* the sources: the backward tree D* Lite starts from.

    ``w`` is the tuple of work arrays kept by the caller between searches (so no page of them is
    allocated or cleared per search): g, parent, length, seen, done, nxt, prv, bkt, touched. A voxel
    counts as reached in this search only where ``seen == run`` (and settled where
    ``done == run``), so nothing needs resetting; ``touched[:n]`` lists the voxels reached.
    Stops when every target is settled (all voxels when ``targets`` is empty). Returns
    (expansions, n reached).
    """
    g, parent, length, seen, done, nxt, prv, bkt, touched = w
    gnext, chg, fid, memo, stack = tree
    use_tree = len(gnext) > 0
    best = INF
    best_node = -1
    n_targets = len(targets)
    use_h = heuristic and n_targets == 1
    goal = targets[0] if n_targets > 0 else -1
    remaining = 0
    for t in targets:  # targets are marked "done" with -run until settled
        if done[t] != -run:
            done[t] = -run
            remaining += 1
    head = np.full(n_buckets, -1, dtype=np.int32)
    mask = n_buckets - 1
    inv_delta = 1.0 / delta  # bucket = int(key * inv_delta); a rounding at a bucket edge only
    # re-opens a voxel (handled below), it never costs exactness
    queued = 0
    nt = 0
    cur = -1
    for s in sources:
        if seen[s] == run:
            continue
        seen[s] = run
        touched[nt] = s
        nt += 1
        g[s] = 0.0
        parent[s] = -1
        length[s] = 0.0
        hs = _heur(s, goal, sx, sy, res, hfield, hshift) if use_h else 0.0
        if hs == INF:  # cannot reach the goal at all
            continue
        b = int(hs * inv_delta)
        _bucket_push(s, b, head, nxt, prv, bkt, mask)
        queued += 1
        cur = b if cur < 0 else min(cur, b)
    stop_bucket = -1
    expanded = 0
    nnb = len(off)
    while queued > 0:
        if stop_bucket >= 0 and cur > stop_bucket:
            break
        sl = cur & mask
        u = head[sl]
        if u < 0:
            cur += 1
            continue
        q = nxt[u]
        head[sl] = q
        if q >= 0:
            prv[q] = -1
        queued -= 1
        if n_targets > 0 and done[u] == -run:
            remaining -= 1
        done[u] = run
        expanded += 1
        if n_targets > 0 and remaining == 0:
            if not use_h:
                break
            if stop_bucket < 0:
                stop_bucket = int(g[u] * inv_delta)
        if use_tree and _clean_path(u, goal, gnext, chg, fid, memo, run, stack):
            c = g[u] + hfield[u]
            if c < best:
                best = c
                best_node = u
                stop_bucket = int(best * inv_delta)
            continue
        gu = g[u]
        lu = length[u]
        cu = cost[u]
        for k in range(nnb):
            v = u + off[k]
            cv = cost[v]
            if cv == INF:
                continue
            nd = gu + (step[k] + (cu if reverse else cv))
            seen_v = seen[v] == run
            if seen_v and nd >= g[v]:
                continue
            hv = 0.0
            if use_h:
                hv = _heur(v, goal, sx, sy, res, hfield, hshift)
                if hv == INF:  # the field says v cannot reach the goal: prune it
                    continue
            if seen_v:
                if done[v] != run:  # queued: unlink from its bucket
                    p = prv[v]
                    q = nxt[v]
                    if p >= 0:
                        nxt[p] = q
                    else:
                        head[bkt[v]] = q
                    if q >= 0:
                        prv[q] = p
                    queued -= 1
                else:
                    done[v] = 0  # re-opened (A* only)
            else:
                seen[v] = run
                touched[nt] = v
                nt += 1
            g[v] = nd
            parent[v] = u
            length[v] = lu + step[k]
            if use_h:
                b = int((nd + hv) * inv_delta)
                # a key beyond the circular window would land in a wrong bucket: queue it early
                # instead (label correcting: an early expansion costs work, never exactness)
                b = min(b, cur + n_buckets - 1)
            else:
                b = int(nd * inv_delta)
            _bucket_push(v, max(b, cur), head, nxt, prv, bkt, mask)
            queued += 1
    return expanded, nt, best_node


class PreviousPlanner(Planner):
    """A Planner whose searches run the previous kernel; results are copied into the current
    work arrays (``g`` inf where unreached) so the rest of the planner reads them as usual."""

    _old: tuple[np.ndarray, ...] | None = None

    def _search(
        self,
        sources: Sequence[int],
        targets: Sequence[int],
        heuristic: bool,
        reverse: bool = False,
        hfield: np.ndarray | None = None,
        hshift: float = 0.0,
        tree: tuple[Any, ...] | None = None,
    ) -> tuple[int, int]:
        live = self._live() if self._live is not None else None
        if live is not None:
            live._detach()
        self._live = None
        w = self._work()
        n = self.cost_map.padded.size
        if self._old is None or len(self._old[0]) != n:
            i32 = np.int32
            self._old = (
                np.empty(n),
                np.empty(n, dtype=i32),
                np.empty(n),
                np.zeros(n, dtype=i32),
                np.zeros(n, dtype=i32),
                np.empty(n, dtype=i32),
                np.empty(n, dtype=i32),
                np.empty(n, dtype=i32),
                np.empty(n, dtype=i32),
            )
        self._run += 1
        expanded, reached, best = search(
            self.cost_map.flat_padded(),
            self._off,
            self._step,
            np.asarray(sources, dtype=np.int64),
            np.asarray(targets, dtype=np.int64),
            heuristic,
            reverse,
            self._sx,
            self._sy,
            self.cost_map.resolution,
            self._delta,
            self._n_buckets,
            self._old,
            self._run,
            _NO_FIELD if hfield is None else hfield,
            float(hshift),
            _NO_TREE if tree is None else tree,
        )
        g, parent, length = w[:3]
        g.fill(np.inf)
        ids = self._old[8][:reached]
        g[ids] = self._old[0][ids]
        parent[ids] = self._old[1][ids]
        length[ids] = self._old[2][ids]
        self._n_reached = int(reached)
        self._best_node = int(best)
        return int(expanded), int(reached)
