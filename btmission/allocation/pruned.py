"""The pruned assignment solver: each agent's few best bids, proven enough by the duals.

For a large dense bid matrix (1,000 agents × 10,000 tasks: 10 million cells, of which one agent
can use one) most cells can never be in the optimum, and the dense solver spends its time on
them: filling the ``n_agents × n_tasks`` matrix of shifted costs, then scanning every column of
it on every augmenting path. This solver reads the matrix once instead:

1. **Scan** (numba, one pass; two threads take blocks of rows in turn when there are two
   cores): each agent's ``k`` best bids by ``x = cost − bonus`` (its incumbent task always kept too), the
   smallest ``x`` it leaves out, its number of bids, and the ranges the profit transform needs.
2. **Solve** the small problem — those edges, with exactly the shifted costs ``q`` of the dense
   solver (:func:`btmission.allocation.solvers._dense_q`: same float operations), plus a private
   dummy task per agent at ``BIG`` (no task) — by successive shortest augmenting paths, which
   also give the dual solution ``(u, v)``: ``u_i + v_j ≤ q_ij`` on its edges, ``v ≤ 0``, ``v = 0``
   on every task left unassigned.
3. **Prove** it optimal for the whole matrix: extend ``v`` by 0 to the tasks the small problem
   did not have; then the duals are feasible for every left-out bid of agent ``i`` exactly when
   ``u_i ≤`` its smallest left-out ``q`` (``v ≤ 0`` everywhere). Feasible duals with complementary
   slackness prove the matching optimal for the full problem (LP duality of the assignment
   problem). Agents that fail the test are scanned again with ``8 k`` best bids, and the small
   problem solved again; after ``MAX_ROUNDS``, or when more than a quarter of the agents fail,
   the dense solver takes over (never on the benchmark instances, where ``k = 12`` proves the
   first solution).

The objective is the dense solver's: ``Σ q`` with ``BIG`` for an agent without a task, i.e. most
tasks assigned, then most value, then incumbents on exact ties (:mod:`.solvers` docstring). When
the optimum is unique (random real costs) the matching is the dense solver's; among exactly equal
optima it may pick another one with the same count and value (property tests check both).
"""

from __future__ import annotations

import itertools
import os
import threading
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from btmission.allocation.solvers import (
    MAX_COST,
    AssignmentProblem,
    IntArray,
    Matching,
    _check_range,
    _finite_range,
    _make_shift,
    _Shift,
)
from btmission.types import FloatArray

DEFAULT_K = 12
"""Best bids kept per agent in the first round. At 1,000 × 10,000 on the benchmark instances even
6 proves the optimum with no rescan; 12 leaves a margin and took ~20 % less CPU than 24 (every
entry among the best so far is an insertion into a sorted list of k). Smaller k costs more
rescans on crowded instances, larger k a longer scan."""
GROW = 8
"""Agents that fail the optimality test are scanned again with this many times more bids."""
MAX_ROUNDS = 3
"""Rounds of scan-solve-prove before handing the problem to the dense solver."""
MAX_FAILED_SHARE = 0.25
"""More agents than this share failing the proof: the dense solver takes over at once."""
PARALLEL_MIN_CELLS = 1_000_000
"""Scan with two threads from this many matrix cells (below, a thread costs more than it saves)."""
BLOCK_CELLS = 200_000
"""Cells per block of rows the scan threads take in turn (~0.4 ms of work each)."""
MIN_CELLS = 500_000
"""``auto`` uses this solver for dense problems from this many cells (and at least twice as many
tasks as agents: :func:`worth_it`)."""

STAT_XHI, STAT_LO, STAT_HI = range(3)


def _kernels() -> Any:
    from btmission.allocation import _prune_kernel

    return _prune_kernel


def worth_it(problem: AssignmentProblem) -> bool:
    """Whether ``auto`` should prune: a large dense matrix with at least twice as many tasks as
    agents. (With as many agents as tasks or more, the agents left without a task can only be
    proven right with all their bids: measured here, 1,000 × 1,000 failed the proof for 96 % of
    the agents, while 700 × 1,000 and 1,000 × 2,000 passed it at once.)"""
    return (
        problem.is_dense
        and problem.n_agents * problem.n_tasks >= MIN_CELLS
        and problem.n_tasks >= max(2 * problem.n_agents, 4 * DEFAULT_K)
    )


def _threads() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


@dataclass(frozen=True)
class _Scan:
    """What :func:`_scan` found for some rows (one entry per row, in the order asked)."""

    cols: IntArray
    """``(rows, k)``: the best columns (``-1`` past the row's bids), incumbent left out."""
    x: FloatArray
    """``(rows, k)``: their ``cost − bonus`` (+inf past the row's bids)."""
    next_x: FloatArray
    """The smallest ``cost − bonus`` left out (incumbent aside; +inf if none)."""
    stats: FloatArray
    """``(rows, 3)``: max ``x``, min cost (−inf included), max finite cost."""


def _scan(
    costs: FloatArray, bonus: FloatArray | None, incumbent: IntArray, rows: IntArray, k: int
) -> _Scan:
    """Run :func:`scan_rows` on ``rows`` in blocks of rows, which two threads take in turn when it
    pays. Each block is a pure function of the input, written to its own arrays; the first
    result of a block is kept. When the calling thread runs out of blocks it computes any block
    the helper thread still holds instead of waiting for it (on a busy machine the helper may
    not get a core for tens of milliseconds), so the helper can only save time, never cost it,
    and the result does not depend on the scheduling."""
    scan_rows = _kernels().scan_rows
    n, nt = len(rows), costs.shape[1]
    step = max(1, BLOCK_CELLS // max(nt, 1))
    starts = list(range(0, n, step))
    done: list[tuple[IntArray, FloatArray, FloatArray] | None] = [None] * len(starts)
    claims = itertools.count()  # next() is atomic under the GIL
    lock = threading.Lock()

    def block(b: int) -> None:
        sub = rows[starts[b] : starts[b] + step]
        cols = np.full((len(sub), k + 1), -1, dtype=np.int64)
        x = np.full((len(sub), k + 1), np.inf)
        stats = np.empty((len(sub), 3))
        scan_rows(costs, bonus, incumbent, sub, cols, x, stats)
        with lock:
            if done[b] is None:
                done[b] = (cols, x, stats)

    def helper() -> None:
        try:
            while (b := next(claims)) < len(starts):
                block(b)
        except Exception:  # the caller computes every block left undone itself (and raises)
            return

    if n * nt >= PARALLEL_MIN_CELLS and len(starts) > 1 and _threads() >= 2:
        threading.Thread(target=helper, name="btmission-prune-scan", daemon=True).start()
    while (b := next(claims)) < len(starts):
        block(b)
    for b in range(len(starts)):  # blocks the helper has not finished (yet)
        if done[b] is None:
            block(b)
    parts = cast(list[tuple[IntArray, FloatArray, FloatArray]], done)
    cols = np.concatenate([c for c, _, _ in parts])
    x = np.concatenate([v for _, v, _ in parts])
    stats = np.concatenate([st for _, _, st in parts])
    return _Scan(cols[:, :k], x[:, :k], x[:, k].copy(), stats)


def solve_pruned(problem: AssignmentProblem, k: int | None = None) -> Matching | None:
    """Optimal matching of a dense ``problem`` (module docstring), keeping ``k`` best bids per
    agent at first (default :data:`DEFAULT_K`), or None when the proof failed ``MAX_ROUNDS``
    times (the caller then solves it densely). Raises ``ValueError`` on a bid out of range,
    like the other solvers."""
    if not problem.is_dense:
        raise ValueError("the pruned solver needs a dense problem")
    na, nt = problem.n_agents, problem.n_tasks
    empty = np.zeros(0, dtype=np.intp)
    if na == 0 or nt == 0:
        return Matching(empty, empty, "pruned")
    costs = np.ascontiguousarray(problem.costs, dtype=np.float64)
    bonus = problem.bonus
    if bonus is not None and not np.all(np.isfinite(bonus)):
        return None
    inc = np.full(na, -1, dtype=np.int64)
    if problem.incumbent is not None:
        inc[:] = problem.incumbent
    k = max(1, min(DEFAULT_K if k is None else k, nt))
    scan = _scan(costs, bonus, inc, np.arange(na, dtype=np.int64), k)
    st = scan.stats
    inc_x = _incumbent_x(costs, bonus, inc)
    # each row's smallest x is its first kept one or its incumbent's
    row_lo = np.fmin(scan.x[:, 0], inc_x)  # NaN (no incumbent bid) ignored
    if not np.any(row_lo < np.inf):  # no bids (as the other solvers: nothing to check)
        return Matching(empty, empty, "pruned")
    if st[:, STAT_LO].min() < 0 or st[:, STAT_HI].max() > MAX_COST:
        _check_range(*_finite_range(costs))  # the other solvers' message
    shift = _make_shift(float(row_lo.min()), float(st[:, STAT_XHI].max()), min(na, nt))
    cols, x, nxt = scan.cols, scan.x, scan.next_x
    for _ in range(MAX_ROUNDS):
        col4row, failed = _solve_small(cols, x, nxt, inc, inc_x, shift, nt)
        if len(failed) == 0:
            keep = col4row >= 0
            return Matching(np.nonzero(keep)[0].astype(np.intp), col4row[keep], "pruned")
        if len(failed) > MAX_FAILED_SHARE * na:  # pruning does not fit this problem
            return None
        k = min(k * GROW, nt)
        more = _scan(costs, bonus, inc, failed.astype(np.int64), k)
        width = max(cols.shape[1], k)
        cols = _widen(cols, width, -1)
        x = _widen(x, width, np.inf)
        cols[failed] = _widen(more.cols, width, -1)
        x[failed] = _widen(more.x, width, np.inf)
        nxt[failed] = more.next_x
    return None


def _widen(a: np.ndarray, width: int, fill: float) -> np.ndarray:
    if a.shape[1] == width:
        return a
    out = np.full((a.shape[0], width), fill, dtype=a.dtype)
    out[:, : a.shape[1]] = a
    return out


def _incumbent_x(costs: FloatArray, bonus: FloatArray | None, inc: IntArray) -> FloatArray:
    """``cost − bonus`` of each agent's incumbent task (NaN: none, or no bid on it)."""
    out = np.full(len(inc), np.nan)
    a = np.nonzero(inc >= 0)[0]
    c = costs[a, inc[a]]
    bid = np.abs(c) < np.inf  # NaN and ±inf: no bid
    a, c = a[bid], c[bid]
    out[a] = c if bonus is None else c - bonus[inc[a]]
    return out


def _solve_small(
    cols: IntArray,
    x: FloatArray,
    nxt: FloatArray,
    inc: IntArray,
    inc_x: FloatArray,
    s: _Shift,
    nt: int,
) -> tuple[IntArray, IntArray]:
    """Solve the kept edges (plus incumbents) exactly; returns each agent's task (-1: none) and
    the agents whose left-out bids the duals do not cover (empty: proven optimal)."""
    sh = s.offset + s.delta
    # exactly _dense_q's arithmetic: (cost − bonus) + (offset + δ), incumbents then − δ
    q = x + sh
    has_inc = ~np.isnan(inc_x)
    all_cols = np.concatenate([cols, np.where(has_inc, inc, -1)[:, None]], axis=1)
    all_q = np.concatenate([q, (inc_x + sh)[:, None] - s.delta], axis=1)
    present = np.zeros(nt + 1, dtype=bool)  # (the last slot takes the -1s)
    present[all_cols] = True
    used = np.nonzero(present[:nt])[0]
    local = np.full(nt + 1, -1, dtype=np.int64)  # the last slot maps -1 to -1
    local[used] = np.arange(len(used))
    small = local[all_cols]
    col4row, u, _ = _kernels().shortest_augmenting_paths(small, all_q, len(used), s.big)
    failed = np.nonzero(u > nxt + sh)[0]
    task = np.where(col4row < len(used), used[np.minimum(col4row, len(used) - 1)], -1)
    return task.astype(np.intp), failed.astype(np.intp)
