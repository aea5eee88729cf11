"""numba core of the GA (Alg. 1-3): selection, mutation and evaluation of whole generations.

Imported lazily by :mod:`btmission.dispatch.ga`, which documents the algorithm. A population is a
set of flat buffers: ``nodes[i, :total[i]]`` and ``waits[i, :total[i]]`` hold individual i's
missions back to back, ``offs[i, k]:offs[i, k + 1]`` being vehicle k's part. Per-vehicle
constraints (prioritised, frozen, head, min_wait, t0) are shared by all individuals.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from btmission.dispatch import _kernel
from btmission.dispatch._kernel import evaluate_kernel
from btmission.kernelcache import key_on_callees


@njit(cache=True)
def seed(s):  # type: ignore[no-untyped-def]
    """Seed numba's random generator (it is separate from numpy's)."""
    np.random.seed(s)


@njit(cache=True)
def score(nodes, waits, offs, tot, veh, mp, prm):  # type: ignore[no-untyped-def]
    """Eq. 1 / eq. 2 for one individual (arguments as for :func:`mutate`)."""
    t0 = veh[4]
    ttime, edge, is_pause = mp[0], mp[1], mp[2]
    delta, beta, xi_min, t_ref = prm[0], prm[1], prm[2], prm[3]
    n_veh = offs.size - 1
    n_nodes = is_pause.size
    n_c, t_first, t_end = evaluate_kernel(
        nodes[:tot], waits[:tot], offs, t0, ttime, edge, n_nodes, delta
    )
    if n_c > 0:
        tc = t_first - t_ref
        if tc < 0.0:
            tc = 0.0
        b = beta * tc
        if b > 0.999:
            b = 0.999
        return -n_c + b
    te = t_end - t_ref
    if te < 1e-9:
        te = 1e-9
    items = tot - n_veh
    if items < 1:
        items = 1
    return (1.0 / te) * (xi_min / items)


@njit(cache=True)
def _new_wait(old, lo, wait_max, p_reset, creep):  # type: ignore[no-untyped-def]
    if np.random.random() < p_reset:
        return lo + np.random.random() * wait_max
    w = old + np.random.normal(0.0, creep * wait_max)
    return w if w > lo else lo


@njit(cache=True)
def mutate(nodes, waits, offs, tot, veh, mp, prm, bufs):  # type: ignore[no-untyped-def]
    """Alg. 3 in place on one individual; returns its new total length.

    ``veh`` = (prio, frozen, head, min_wait, t0) per vehicle; ``mp`` = (ttime, edge, is_pause,
    is_transit, pn_ptr, pn_idx) of the map; ``prm`` = (delta, beta, xi_min, t_ref, p_tour, p_rel,
    wait_max, p_reset, creep); ``bufs`` = scratch (slot_buf, slot_veh, cand_buf).
    """
    prio, frozen, head, min_wait, _ = veh
    _, _, is_pause, is_transit, pn_ptr, pn_idx = mp
    p_rel, wait_max, p_reset, creep = prm[5], prm[6], prm[7], prm[8]
    slot_buf, slot_veh, cand_buf = bufs
    n_veh = offs.size - 1
    cap = nodes.size
    # ---- parametric: every mutable stop time with probability p_rel / κ
    kappa = 0
    for k in range(n_veh):
        lo = offs[k]
        q = offs[k + 1] - lo - 1
        if q <= 0:
            continue
        if frozen[k] <= head[k] and head[k] < q:
            slot_buf[kappa] = lo + head[k]
            slot_veh[kappa] = k
            kappa += 1
        if not prio[k]:
            start = frozen[k] if frozen[k] > 1 else 1
            for i in range(start, q):
                if i != head[k] and is_pause[nodes[lo + i]]:
                    slot_buf[kappa] = lo + i
                    slot_veh[kappa] = k
                    kappa += 1
    if kappa > 0:
        p_mut = p_rel / kappa
        for s in range(kappa):
            if np.random.random() < p_mut:
                a = slot_buf[s]
                k = slot_veh[s]
                lo_w = min_wait[k] if a - offs[k] == frozen[k] else 0.0
                waits[a] = _new_wait(waits[a], lo_w, wait_max, p_reset, creep)
    # ---- structural: per non-prioritised mission with probability p_rel / L
    p_struct = p_rel / n_veh
    for k in range(n_veh):
        if np.random.random() >= p_struct or prio[k]:
            continue
        lo = offs[k]
        hi = offs[k + 1]
        q = hi - lo - 1
        lock = frozen[k] if frozen[k] > head[k] else head[k]
        if np.random.random() < 0.5:
            # insert a pause visit at a transit node of T1 (a pause neighbour not yet visited)
            if tot + 2 > cap:
                continue
            nc = 0
            start = lock if lock > 1 else 1
            for i in range(start, q):
                x = nodes[lo + i]
                if not is_transit[x]:
                    continue
                for e in range(pn_ptr[x], pn_ptr[x + 1]):
                    p = pn_idx[e]
                    seen = False
                    for j in range(lo, hi):
                        if nodes[j] == p:
                            seen = True
                            break
                    if not seen:
                        cand_buf[nc, 0] = i
                        cand_buf[nc, 1] = p
                        nc += 1
            if nc == 0:
                continue
            c = np.random.randint(nc)
            i = cand_buf[c, 0]
            p = cand_buf[c, 1]
            x = nodes[lo + i]
            for j in range(tot - 1, lo + i, -1):
                nodes[j + 2] = nodes[j]
                waits[j + 2] = waits[j]
            nodes[lo + i + 1] = p
            waits[lo + i + 1] = np.random.random() * wait_max
            nodes[lo + i + 2] = x
            waits[lo + i + 2] = 0.0
            tot += 2
            for kk in range(k + 1, n_veh + 1):
                offs[kk] += 2
        else:
            # remove a pause visit (set T2): x -> pause -> x
            nc = 0
            start = lock + 1 if lock + 1 > 1 else 1
            for i in range(start, q):
                if is_pause[nodes[lo + i]] and nodes[lo + i - 1] == nodes[lo + i + 1]:
                    cand_buf[nc, 0] = i
                    nc += 1
            if nc == 0:
                continue
            i = cand_buf[np.random.randint(nc), 0]
            for j in range(lo + i, tot - 2):
                nodes[j] = nodes[j + 2]
                waits[j] = waits[j + 2]
            tot -= 2
            for kk in range(k + 1, n_veh + 1):
                offs[kk] -= 2
    return tot


@njit(cache=True)
def generations(pop, new, best, best_score, scores, new_scores, veh, mp, prm, n_gen):  # type: ignore[no-untyped-def]
    """Run ``n_gen`` generations of Alg. 1; the population stays in ``pop``.

    ``pop``, ``new`` = (nodes, waits, offs, tot) buffers of the current and the next population,
    ``best`` = (nodes, waits, offs, tot) of the best individual so far, ``best_score`` its score
    (a 1-element array); the other arguments as for :func:`mutate`.
    """
    pop_nodes, pop_waits, pop_offs, pop_tot = pop
    new_nodes, new_waits, new_offs, new_tot = new
    best_nodes, best_waits, best_offs, best_tot = best
    p_tour = prm[4]
    alpha = scores.size
    cap = pop_nodes.shape[1]
    bufs = (
        np.empty(cap, np.int64),
        np.empty(cap, np.int64),
        np.empty((cap * 4 + 4, 2), np.int64),
    )
    for _ in range(n_gen):
        for i in range(1, alpha):
            # Alg. 2: tournament of two
            i1 = np.random.randint(alpha)
            i2 = np.random.randint(alpha)
            hi_i, lo_i = (i1, i2) if scores[i1] >= scores[i2] else (i2, i1)
            sel = hi_i if np.random.random() < p_tour else lo_i
            t = pop_tot[sel]
            new_nodes[i, :t] = pop_nodes[sel, :t]
            new_waits[i, :t] = pop_waits[sel, :t]
            new_offs[i, :] = pop_offs[sel, :]
            t = mutate(new_nodes[i], new_waits[i], new_offs[i], t, veh, mp, prm, bufs)
            new_tot[i] = t
            new_scores[i] = score(new_nodes[i], new_waits[i], new_offs[i], t, veh, mp, prm)
        # elitism: the best individual so far, unchanged, in slot 1
        t = best_tot[0]
        new_nodes[0, :t] = best_nodes[:t]
        new_waits[0, :t] = best_waits[:t]
        new_offs[0, :] = best_offs
        new_tot[0] = t
        new_scores[0] = best_score[0]
        b = 0
        for i in range(alpha):
            t = new_tot[i]
            pop_nodes[i, :t] = new_nodes[i, :t]
            pop_waits[i, :t] = new_waits[i, :t]
            pop_offs[i, :] = new_offs[i, :]
            pop_tot[i] = t
            scores[i] = new_scores[i]
            if scores[i] > scores[b]:
                b = i
        if scores[b] > best_score[0]:
            t = pop_tot[b]
            best_nodes[:t] = pop_nodes[b, :t]
            best_waits[:t] = pop_waits[b, :t]
            best_offs[:] = pop_offs[b, :]
            best_tot[0] = t
            best_score[0] = scores[b]
    return n_gen


# every kernel here may inline the evaluation of btmission/dispatch/_kernel.py (score does)
key_on_callees([seed, score, _new_wait, mutate, generations], _kernel)
