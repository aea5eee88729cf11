# mypy: allow-untyped-defs
"""numba kernels of the planner, on the flat padded cost array of :class:`~.risk.CostMap`.

Every voxel is a flat index ``p`` into an array of shape ``(NX, NY, NZ)`` (the map plus a one-voxel
border of ``inf``), so the 26 neighbours of ``p`` are ``p + off[k]`` with no bounds checks. The cost
of the step ``u → v`` is ``step[k] + cost[v]`` (eq. 4: step length c_d plus the risk and unknown
costs of the voxel entered); ``cost[v] = inf`` means v is never entered.

Kept free of Python objects so numba compiles them in nopython mode; ``cache=True`` stores the
machine code next to this file, so only the first run on a machine pays the compile time.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir as llir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

INF = np.inf


@njit(cache=True, inline="always")
def _octile(p, q, sx, sy, res):
    """Length of the shortest 26-connected move sequence between voxels p and q, in metres
    (a lower bound on any path's cost, since every step costs at least its length)."""
    px = p // sx
    py = (p - px * sx) // sy
    pz = p - px * sx - py * sy
    qx = q // sx
    qy = (q - qx * sx) // sy
    qz = q - qx * sx - qy * sy
    a = abs(px - qx)
    b = abs(py - qy)
    c = abs(pz - qz)
    # sort a >= b >= c
    if a < b:
        a, b = b, a
    if b < c:
        b, c = c, b
    if a < b:
        a, b = b, a
    return res * ((a - b) + (b - c) * 1.4142135623730951 + c * 1.7320508075688772)


# ------------------------------------------------------------------------------------ search
@intrinsic
def _prefetch(typingctx, arr, idx):
    """Hint the CPU to load ``arr[idx]`` into cache (LLVM's ``llvm.prefetch``; no bounds check,
    and a prefetch never faults)."""
    sig = types.void(arr, idx)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
        i8p = llir.IntType(8).as_pointer()
        i32 = llir.IntType(32)
        fnty = llir.FunctionType(llir.VoidType(), [i8p, i32, i32, i32])
        fn = builder.module.declare_intrinsic("llvm.prefetch", [i8p], fnty=fnty)
        # read, keep in all cache levels, data cache
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, inline="always")
def _heur(v, goal, sx, sy, res, hfield, hshift):
    h = _octile(v, goal, sx, sy, res)
    if len(hfield) > 0:
        hf = hfield[v] - hshift
        if hf > h:
            h = hf
    return h


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
    prev,
    pool,
):
    """Dijkstra (or A* with the octile heuristic when ``heuristic`` and one target) from every
    voxel in ``sources`` (cost 0) over the padded grid, with a bucket queue (Dial's algorithm).

    Keys are binned into buckets of width ``delta`` = the shortest step (the resolution). Every
    edge costs at least ``delta``, so in Dijkstra no voxel in the lowest bucket can improve another
    one in the same bucket: the whole bucket is final, in any order, and the result is exact.
    With A* the key ``g + h`` can stay level along a step, so a voxel improved after its
    expansion is re-queued and expanded again (label correcting); the search stops only once the
    goal's bucket is drained, which keeps it exact. ``n_buckets`` must exceed the largest key
    increase of one step divided by ``delta`` and be a power of two (a circular array of buckets).

    Each bucket is a stack (last in, first out) of entries ``(voxel, g when queued)`` kept in
    ``pool`` = (entries (cap, 2) int32: voxel and the entry below it, g (cap,) float64). A voxel
    whose cost drops is pushed again and its older entry is left in place: an entry is current
    only while its g equals the voxel's g (each push lowers g strictly), so stale entries are
    skipped when they come up. That pops voxels in exactly the order of a doubly linked list per
    bucket with decrease-key (the previous implementation), without three per-voxel link arrays.
    When the pool is full the search stops and returns ``expanded = -1``: the caller grows the
    pool and searches again (passing ``prev`` = the returned count, which resets the voxels this
    attempt reached).

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

    ``w`` = (g, parent, length, done, touched) are kept by the caller between searches, so no page
    of them is allocated or cleared per search. ``g`` is ``inf`` on every voxel the search has not
    reached: the voxels the previous search reached, ``touched[:prev]``, are reset to ``inf`` first
    (a few thousand writes instead of filling 2 M entries), and ``touched[:n]`` lists the voxels
    this one reaches. ``done[t] == -run`` marks a target until it is settled. Stops when every
    target is settled (all voxels when ``targets`` is empty). Returns (expansions, n reached, best
    voxel).

    Each expansion first compares all 26 neighbours without a branch (``g[u] + step + cost[v] <
    g[v]`` is false for rock, whose cost is inf, and for voxels already settled), then updates the
    few that improve, in the same neighbour order as a single loop would: same results, far fewer
    mispredicted branches. It also asks the CPU to fetch the neighbourhood of the next voxel in
    the bucket while this one is worked on.
    """
    g, parent, length, done, touched = w
    ent, eg = pool
    cap = len(eg)
    for i in range(prev):
        g[touched[i]] = INF
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
    nnb = len(off)
    if len(sources) + nnb > cap:
        return -1, 0, -1
    n_ent = 0  # pool entries used (every push takes a new one)
    live = 0  # entries in the buckets, current or stale
    nt = 0
    cur = -1
    for s in sources:
        if g[s] < INF:
            continue
        touched[nt] = s
        nt += 1
        g[s] = 0.0
        parent[s] = -1
        length[s] = 0.0
        hs = _heur(s, goal, sx, sy, res, hfield, hshift) if use_h else 0.0
        if hs == INF:  # cannot reach the goal at all
            continue
        b = int(hs * inv_delta)
        sl = b & mask
        ent[n_ent, 0] = s
        ent[n_ent, 1] = head[sl]
        eg[n_ent] = 0.0
        head[sl] = n_ent
        n_ent += 1
        live += 1
        cur = b if cur < 0 else min(cur, b)
    stop_bucket = -1
    expanded = 0
    better = np.zeros(nnb, dtype=np.bool_)
    while live > 0:
        if stop_bucket >= 0 and cur > stop_bucket:
            break
        sl = cur & mask
        e = head[sl]
        if e < 0:
            cur += 1
            continue
        below = ent[e, 1]
        head[sl] = below
        live -= 1
        u = ent[e, 0]
        gu = g[u]
        if gu != eg[e]:
            continue  # stale: u was improved (or settled) since this entry was pushed
        if below >= 0:  # the next voxel of this bucket, most likely the next one expanded
            nxt = ent[below, 0]
            for a in range(-sx, sx + 1, sx):
                for c in range(-sy, sy + 1, sy):
                    _prefetch(cost, nxt + a + c)
                    _prefetch(g, nxt + a + c)
        if n_targets > 0:
            if done[u] == -run:
                remaining -= 1
            done[u] = run
        expanded += 1
        if n_targets > 0 and remaining == 0:
            if not use_h:
                break
            if stop_bucket < 0:
                stop_bucket = int(gu * inv_delta)
        if use_tree and _clean_path(u, goal, gnext, chg, fid, memo, run, stack):
            c = gu + hfield[u]
            if c < best:
                best = c
                best_node = u
                stop_bucket = int(best * inv_delta)
            continue
        if n_ent + nnb > cap:
            return -1, nt, best_node  # pool full: the caller grows it and searches again
        lu = length[u]
        cu = cost[u]
        # unsigned indices: numba adds no negative-index wraparound to these loads
        if reverse:
            for k in range(nnb):
                v = np.uint64(u + off[k])
                better[k] = (gu + (step[k] + cu) < g[v]) & (cost[v] != INF)
        else:
            for k in range(nnb):
                v = np.uint64(u + off[k])
                better[k] = gu + (step[k] + cost[v]) < g[v]
        for k in range(nnb):
            if not better[k]:
                continue
            v = u + off[k]
            nd = gu + (step[k] + (cu if reverse else cost[v]))
            hv = 0.0
            if use_h:
                hv = _heur(v, goal, sx, sy, res, hfield, hshift)
                if hv == INF:  # the field says v cannot reach the goal: prune it
                    continue
            if g[v] == INF:
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
            sl = max(b, cur) & mask
            ent[n_ent, 0] = v
            ent[n_ent, 1] = head[sl]
            eg[n_ent] = nd
            head[sl] = n_ent
            n_ent += 1
            live += 1
    return expanded, nt, best_node


@njit(cache=True)
def reached_tree(g, length, parent, n):
    """(voxels in increasing order, g, length, parent) of the ``n`` voxels with a finite ``g``
    (any further ones are left out): one pass over the map, cheaper than sorting the voxels a
    search reached."""
    ids = np.empty(n, dtype=np.int64)
    gs = np.empty(n)
    lengths = np.empty(n)
    parents = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(len(g)):
        x = g[i]
        if x < INF and m < n:
            ids[m] = i
            gs[m] = x
            lengths[m] = length[i]
            parents[m] = parent[i]
            m += 1
    return ids, gs, lengths, parents


@njit(cache=True)
def _clean_path(v, goal, gnext, chg, fid, memo, run, stack):
    """Whether the old path from v to the goal (following ``gnext``) enters no voxel changed
    since the field was made; verdicts are memoised for every voxel walked (``memo = ±run``)."""
    n = 0
    x = v
    status = 0
    while True:
        m = memo[x]
        if m == run:
            status = 1
            break
        if m == -run:
            status = -1
            break
        if x == goal:
            status = 1
            break
        y = gnext[x]
        stack[n] = x
        n += 1
        if y < 0 or chg[y] == fid:
            status = -1
            break
        x = y
    for i in range(n):
        memo[stack[i]] = status * run
    return status == 1


@njit(cache=True)
def trace(parent, target, limit):
    """The voxels from the source to ``target`` following ``parent`` (empty if unreached)."""
    out = np.empty(limit, dtype=np.int64)
    n = 0
    p = target
    while p >= 0 and n < limit:
        out[n] = p
        n += 1
        p = parent[p]
    return out[:n][::-1].copy()


# ------------------------------------------------------------------------------------ D* Lite
# The open list is a lazy binary heap ordered by the key pair (k1, k2): an entry is current only
# while ``inq[s]`` is set and its key equals ``(qk1[s], qk2[s])``; others are skipped when they
# reach the top. Callers make room before each expansion (``_reserve``) so that the pushes inside
# never reallocate: no array is returned from the hot helpers.
@njit(cache=True, inline="always")
def _less(a1, a2, b1, b2):
    return a1 < b1 or (a1 == b1 and a2 < b2)


@njit(cache=True)
def _reserve(k1s, k2s, vals, n, room):
    """The heap arrays, grown if fewer than ``room`` free slots remain."""
    if n + room <= len(vals):
        return k1s, k2s, vals
    cap = max(2 * len(vals), n + room)
    nk1 = np.empty(cap, dtype=np.float64)
    nk2 = np.empty(cap, dtype=np.float64)
    nv = np.empty(cap, dtype=np.int64)
    nk1[:n] = k1s[:n]
    nk2[:n] = k2s[:n]
    nv[:n] = vals[:n]
    return nk1, nk2, nv


@njit(cache=True, inline="always")
def _kpush(k1s, k2s, vals, n, k1, k2, v):
    """Push (k1, k2, v) onto a heap of size n (room reserved); returns the new size."""
    i = n
    while i > 0:
        par = (i - 1) >> 1
        if not _less(k1, k2, k1s[par], k2s[par]):
            break
        k1s[i] = k1s[par]
        k2s[i] = k2s[par]
        vals[i] = vals[par]
        i = par
    k1s[i] = k1
    k2s[i] = k2
    vals[i] = v
    return n + 1


@njit(cache=True, inline="always")
def _kpop(k1s, k2s, vals, n):
    """Remove the top of a heap of size n > 0; returns the new size."""
    n -= 1
    if n == 0:
        return 0
    k1 = k1s[n]
    k2 = k2s[n]
    v = vals[n]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= n:
            break
        if c + 1 < n and _less(k1s[c + 1], k2s[c + 1], k1s[c], k2s[c]):
            c += 1
        if not _less(k1s[c], k2s[c], k1, k2):
            break
        k1s[i] = k1s[c]
        k2s[i] = k2s[c]
        vals[i] = vals[c]
        i = c
    k1s[i] = k1
    k2s[i] = k2
    vals[i] = v
    return n


@njit(cache=True, inline="always")
def _best_rhs(u, cost, g, off, step):
    """rhs(u) = min over successors s of c(u, s) + g(s)."""
    best = INF
    for k in range(len(off)):
        v = u + off[k]
        t = step[k] + cost[v] + g[v]
        if t < best:
            best = t
    return best


@njit(cache=True, inline="always")
def _update_vertex(s, g, rhs, start, km, sx, sy, res, k1s, k2s, vals, n, inq, qk1, qk2):
    """D* Lite UpdateVertex: (re)queue s with its key if inconsistent, else drop it. Returns n."""
    gs = g[s]
    rs = rhs[s]
    if gs != rs:
        m = min(gs, rs)
        k1 = m + _octile(start, s, sx, sy, res) + km
        if not inq[s] or k1 != qk1[s] or m != qk2[s]:
            inq[s] = 1
            qk1[s] = k1
            qk2[s] = m
            n = _kpush(k1s, k2s, vals, n, k1, m, s)
    else:
        inq[s] = 0
    return n


@njit(cache=True)
def dstar_compute(
    n, km, goal, g, rhs, cost, off, step, start, sx, sy, res, k1s, k2s, vals, inq, qk1, qk2, limit
):
    """D* Lite ComputeShortestPath (Koenig & Likhachev 2002, Fig. 4) on the padded grid.

    The search runs backwards from the goal: ``g[s]`` is the cost from ``s`` to the goal and
    ``rhs[s] = min_s' c(s, s') + g(s')``. Expands the open voxel with the smallest key
    ``[min(g, rhs) + h(start, s) + km; min(g, rhs)]`` until the start is consistent and no key
    is smaller than its own. Returns (heap arrays, heap size, expansions, ok); ok is False when
    ``limit`` expansions were reached first (the caller then starts afresh).
    """
    expanded = 0
    nnb = len(off)
    while True:
        while n > 0:  # drop stale entries at the top
            u = vals[0]
            if inq[u] and k1s[0] == qk1[u] and k2s[0] == qk2[u]:
                break
            n = _kpop(k1s, k2s, vals, n)
        m = min(g[start], rhs[start])
        if n == 0:
            break  # nothing left to expand (the start may be unreachable)
        top1 = k1s[0]
        top2 = k2s[0]
        # Loop while TopKey < key(start) or the start is overconsistent (Fig. 4, line 10). Keys
        # that tie with the start's in exact arithmetic can differ in the last bits here (h and g
        # are sums of step lengths in different orders), so every key whose k1 is within a
        # relative 1e-9 of the start's is expanded too: extra expansions never hurt correctness,
        # a tie skipped by rounding would.
        ks1 = m + km
        tol = 1e-9 * max(1.0, abs(ks1)) if ks1 < INF else 0.0
        if not (top1 <= ks1 + tol or rhs[start] > g[start]):
            break
        if expanded >= limit:
            return k1s, k2s, vals, n, expanded, False
        k1s, k2s, vals = _reserve(k1s, k2s, vals, n, nnb + 2)
        u = vals[0]
        mu = min(g[u], rhs[u])
        new1 = mu + _octile(start, u, sx, sy, res) + km
        if _less(top1, top2, new1, mu):  # key grew since queued (km moved): requeue
            n = _kpop(k1s, k2s, vals, n)
            qk1[u] = new1
            qk2[u] = mu
            n = _kpush(k1s, k2s, vals, n, new1, mu, u)
            continue
        n = _kpop(k1s, k2s, vals, n)
        inq[u] = 0
        expanded += 1
        cu = cost[u]
        if g[u] > rhs[u]:  # overconsistent: lower g, relax predecessors
            gu = rhs[u]
            g[u] = gu
            for k in range(nnb):
                s = u + off[k]
                if cost[s] == INF or s == goal:
                    continue
                t = step[k] + cu + gu
                if t < rhs[s]:
                    rhs[s] = t
                    n = _update_vertex(
                        s, g, rhs, start, km, sx, sy, res, k1s, k2s, vals, n, inq, qk1, qk2
                    )
        else:  # underconsistent: raise g to inf, re-derive the predecessors that used u
            g_old = g[u]
            g[u] = INF
            for k in range(nnb):
                s = u + off[k]
                if cost[s] == INF:
                    continue
                if s != goal and rhs[s] == step[k] + cu + g_old:
                    rhs[s] = _best_rhs(s, cost, g, off, step)
                n = _update_vertex(
                    s, g, rhs, start, km, sx, sy, res, k1s, k2s, vals, n, inq, qk1, qk2
                )
            n = _update_vertex(u, g, rhs, start, km, sx, sy, res, k1s, k2s, vals, n, inq, qk1, qk2)
    return k1s, k2s, vals, n, expanded, True


@njit(cache=True)
def dstar_edges_changed(
    changed,
    old_cost,
    g,
    rhs,
    cost,
    off,
    step,
    goal,
    start,
    km,
    sx,
    sy,
    res,
    k1s,
    k2s,
    vals,
    n,
    inq,
    qk1,
    qk2,
):
    """D* Lite's reaction to changed edge costs (Fig. 4, lines 31-38): voxel ``v`` changed its
    cost from ``old_cost`` to ``cost[v]``, so every edge ``u → v`` changed; repair ``rhs(u)``.
    Returns (heap arrays, heap size)."""
    nnb = len(off)
    for i in range(len(changed)):
        k1s, k2s, vals = _reserve(k1s, k2s, vals, n, nnb + 2)
        v = changed[i]
        co = old_cost[i]
        cn = cost[v]
        gv = g[v]
        for k in range(nnb):
            u = v - off[k]  # u -> v is the step off[k]
            if cost[u] == INF or u == goal:
                continue
            c_old = step[k] + co
            c_new = step[k] + cn
            if c_old > c_new:
                t = c_new + gv
                if t < rhs[u]:
                    rhs[u] = t
            elif rhs[u] == c_old + gv:
                rhs[u] = _best_rhs(u, cost, g, off, step)
            n = _update_vertex(u, g, rhs, start, km, sx, sy, res, k1s, k2s, vals, n, inq, qk1, qk2)
        if cn != INF and v != goal:
            # v was rock (its rhs was not maintained) or merely changed cost: recompute it.
            rhs[v] = _best_rhs(v, cost, g, off, step)
            n = _update_vertex(v, g, rhs, start, km, sx, sy, res, k1s, k2s, vals, n, inq, qk1, qk2)
    return k1s, k2s, vals, n


@njit(cache=True)
def descend(g, cost, off, step, start, goal, limit):
    """Follow argmin c(s, s') + g(s') from ``start`` to ``goal`` (D* Lite's path extraction).
    Returns the voxels (empty if the descent gets stuck or exceeds ``limit`` steps)."""
    out = np.empty(limit, dtype=np.int64)
    out[0] = start
    n = 1
    s = start
    while s != goal:
        if n >= limit:
            return out[:0].copy()
        best = INF
        nxt = -1
        for k in range(len(off)):
            v = s + off[k]
            cv = cost[v]
            if cv == INF:
                continue
            t = step[k] + cv + g[v]
            if t < best:
                best = t
                nxt = v
        if nxt < 0 or best == INF:
            return out[:0].copy()
        out[n] = nxt
        n += 1
        s = nxt
    return out[:n].copy()


# ------------------------------------------------------------------------------------ segments
@njit(cache=True)
def segment_cost(cost, a, b, sx, sy, res, origin_pad):
    """Cost of the voxels a straight segment a → b (world coordinates) touches in the padded grid.

    Samples the segment every res/8 and takes every voxel within res/8 of a sample on each axis,
    so every voxel the segment passes through is counted, including voxels it only grazes at an
    edge or corner. Returns (max voxel cost, sum over the distinct voxels); the max is ``inf``
    when any of them is occupied or outside the map.
    """
    eps = res / 8.0
    d0 = b[0] - a[0]
    d1 = b[1] - a[1]
    d2 = b[2] - a[2]
    length = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    nsamp = int(length / eps) + 2
    seen = np.empty(nsamp * 8, dtype=np.int64)
    m = 0
    for j in range(nsamp):
        t = j / (nsamp - 1)
        x = a[0] + t * d0 - origin_pad[0]
        y = a[1] + t * d1 - origin_pad[1]
        z = a[2] + t * d2 - origin_pad[2]
        lo0 = int(np.floor((x - eps) / res))
        hi0 = int(np.floor((x + eps) / res))
        lo1 = int(np.floor((y - eps) / res))
        hi1 = int(np.floor((y + eps) / res))
        lo2 = int(np.floor((z - eps) / res))
        hi2 = int(np.floor((z + eps) / res))
        if lo0 < 0 or lo1 < 0 or lo2 < 0 or hi2 >= sy or hi1 * sy >= sx or hi0 * sx >= len(cost):
            return INF, INF
        for ix in range(lo0, hi0 + 1):
            for iy in range(lo1, hi1 + 1):
                for iz in range(lo2, hi2 + 1):
                    seen[m] = ix * sx + iy * sy + iz
                    m += 1
    ids = np.unique(seen[:m])
    worst = 0.0
    total = 0.0
    for p in ids:
        c = cost[p]
        if c == INF:
            return INF, INF
        total += c
        if c > worst:
            worst = c
    return worst, total
