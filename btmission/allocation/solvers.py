"""Exact assignment solvers for the auction's task-allocation problem (seed 003 §IV-A, eq. 3-7).

The problem: agents ``k`` bid costs ``c[k, j] ≥ 0`` on some tasks ``j`` (an absent bid means the
agent does not take part for that task); task ``j`` carries a priority bonus ``b[j]``
(``priority_scale · priority``, seed 003 scenario 3). Find a matching ``x`` (each agent at most one
task, each task at most one agent, eq. 7) that, in this order,

1. assigns as many tasks as possible (eq. 6 with profits that keep every bid worth more than no
   assignment: "maximize the sum of the profits … and at the same time … assign maximum number of
   tasks");
2. maximizes ``Σ (b[j] − c[k, j])`` over the assigned pairs — with equal priorities this is the
   minimum total cost of eq. 1;
3. among exact ties, keeps every agent on its current task (its *incumbent*), so equal bids never
   make agents swap back and forth. (The assignment solvers honour this exactly; the tie-break is
   below SCIP's tolerances, so the ILP returns one of the tied optima.)

**Profits (eq. 4-5).** Costs become profits "in a way that preserves the inverse order":
``q = c − b`` shifted to ``q ≥ 0`` (plus a tie-break ``δ`` on every non-incumbent pair), then
``ρ = BIG − q`` with ``BIG = (K + 1) · (max q + u) + u``, ``K = min(n_agents, n_tasks)`` and
``u`` the span of ``q`` (the cost scale; 1 if all are equal). One more
assigned pair then always outweighs any change in the costs of the others, which is exactly the
order above (1, 2, 3). The paper's ILP (eq. 6-7) maximizes ``Σ ρ x``.

**Solvers** (all exact; :func:`solve` picks one):

``dense``
    :func:`scipy.optimize.linear_sum_assignment` (shortest augmenting path, Crouse's rectangular
    Jonker-Volgenant) on the ``n_agents × n_tasks`` matrix of ``q``, with ``BIG`` where there is
    no bid. A full matching of size ``K`` has the constant ``Σ BIG`` part, so minimizing
    ``Σ q`` (pairs at ``BIG`` are then dropped) maximizes ``Σ ρ``. Minimizing this form is 2-4×
    faster in SciPy than maximizing ``ρ`` (measured here, 1,000 × 10,000).
``sparse``
    :func:`scipy.sparse.csgraph.min_weight_full_bipartite_matching` (LAPJVsp) on the bid edges
    only, weights ``q + u`` (it needs non-zero weights), plus one private dummy task per agent at
    ``BIG + u`` so a full matching always exists. Faster when the bids are few: below about 1 %
    of the pairs when they come as a matrix, up to about 30 % when they come as edges
    (:func:`estimate_us`, fitted to ``btmission bench auction``).
``pruned``
    For a large bid matrix: each agent's few best bids, read in one pass over the matrix, solved
    exactly by shortest augmenting paths, the answer proven optimal for the whole matrix by the
    duals (else more bids, else ``dense``); :mod:`btmission.allocation.pruned`. ``auto`` picks
    it from 500,000 cells with at least twice as many tasks as agents.
``ilp-scip``
    The paper's reference: the ILP of eq. 6-7 with one binary variable per bid, built with
    OR-Tools' model builder and solved by SCIP (default settings, ``limits/gap = 0``). Seconds at
    50 × 400, so it is the reference, not the default.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, cast

import numpy as np
from numpy.typing import NDArray

from btmission.errors import BtmissionError
from btmission.types import FloatArray

IntArray = NDArray[np.intp]

Method = Literal["auto", "dense", "sparse", "pruned", "ilp-scip"]
METHODS: tuple[str, ...] = ("auto", "dense", "sparse", "pruned", "ilp-scip")

MISSION_SOLVERS = {"assignment": "auto", "ilp-scip": "ilp-scip"}
"""``coordination.solver`` in a mission → solver method."""

TIE_EPS = 1e-9
"""Relative size of the incumbent tie-break ``δ`` (of the largest shifted cost ``max q``): value
differences below ``K · δ`` count as ties and the current holder keeps its task."""

MAX_COST = 1e12
"""Bids above this are rejected (they would swamp the profit transform in floating point)."""

# Cost model for ``auto``, fitted to `btmission bench auction` runs on this 2-core machine
# (50 × 400 to 1,000 × 10,000, 5 bids per agent to all): the dense solver costs about
# DENSE_NS_PER_CELL per matrix cell (plus filling the matrix when the bids come as edges), the
# sparse one SPARSE_NS_PER_EDGE per bid plus a per-agent overhead (plus scanning the matrix when
# the bids come dense).
DENSE_FIXED_US = 100.0
DENSE_NS_PER_CELL = 5.0
FILL_NS_PER_CELL = 1.0
FILL_NS_PER_EDGE = 13.0
SPARSE_FIXED_US = 300.0
SPARSE_US_PER_AGENT = 4.0
SPARSE_NS_PER_EDGE = 38.0
SCAN_NS_PER_CELL = 2.5
SCAN_NS_PER_EDGE = 8.0


class SolverError(BtmissionError, RuntimeError):
    """A solver failed or is unavailable (e.g. SCIP missing from the OR-Tools build)."""


@dataclass(frozen=True, eq=False)
class AssignmentProblem:
    """Bids of ``n_agents`` agents on ``n_tasks`` tasks, as a dense matrix or as edges.

    Dense: ``costs`` is ``n_agents × n_tasks``; NaN or +inf means no bid (negative costs,
    ``-inf`` included, are rejected). Edges (``rows``,
    ``cols``, ``costs`` of equal length): one finite bid each, no duplicate pair. ``bonus`` (per
    task, default 0) is added to the value of assigning the task (priority); ``incumbent`` (per
    agent, task index or -1) is the agent's current task, kept on exact ties.
    """

    n_agents: int
    n_tasks: int
    costs: FloatArray
    rows: IntArray | None = None
    cols: IntArray | None = None
    bonus: FloatArray | None = None
    incumbent: IntArray | None = None
    _edges: tuple[IntArray, IntArray, FloatArray] | None = field(
        default=None, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        if self.n_agents < 0 or self.n_tasks < 0:
            raise ValueError("negative problem size")
        if self.rows is None:
            if self.costs.shape != (self.n_agents, self.n_tasks):
                raise ValueError(
                    f"cost matrix is {self.costs.shape}, expected ({self.n_agents}, {self.n_tasks})"
                )
        else:
            if self.cols is None or not (len(self.rows) == len(self.cols) == len(self.costs)):
                raise ValueError("rows, cols and costs must have the same length")
            if len(self.rows) and (
                self.rows.min() < 0
                or self.rows.max() >= self.n_agents
                or self.cols.min() < 0
                or self.cols.max() >= self.n_tasks
            ):
                raise ValueError("edge index out of range")
            if not np.all(np.isfinite(self.costs)):
                raise ValueError("edge costs must be finite (leave out pairs without a bid)")
        if self.bonus is not None and self.bonus.shape != (self.n_tasks,):
            raise ValueError(f"bonus has shape {self.bonus.shape}, expected ({self.n_tasks},)")
        if self.incumbent is not None and self.incumbent.shape != (self.n_agents,):
            raise ValueError(
                f"incumbent has shape {self.incumbent.shape}, expected ({self.n_agents},)"
            )

    @classmethod
    def dense(
        cls,
        costs: FloatArray | Sequence[Sequence[float]],
        bonus: FloatArray | Sequence[float] | None = None,
        incumbent: IntArray | Sequence[int] | None = None,
    ) -> AssignmentProblem:
        """From a matrix of bids (NaN/inf = no bid)."""
        c = np.asarray(costs, dtype=np.float64)
        if c.ndim != 2:
            raise ValueError(f"expected a 2-D cost matrix, got {c.ndim}-D")
        na, nt = c.shape
        return cls(na, nt, c, bonus=_opt_float(bonus), incumbent=_opt_int(incumbent))

    @classmethod
    def sparse(
        cls,
        n_agents: int,
        n_tasks: int,
        rows: IntArray | Sequence[int],
        cols: IntArray | Sequence[int],
        costs: FloatArray | Sequence[float],
        bonus: FloatArray | Sequence[float] | None = None,
        incumbent: IntArray | Sequence[int] | None = None,
    ) -> AssignmentProblem:
        """From bid edges (agent index, task index, cost)."""
        return cls(
            n_agents,
            n_tasks,
            np.asarray(costs, dtype=np.float64),
            np.asarray(rows, dtype=np.intp),
            np.asarray(cols, dtype=np.intp),
            _opt_float(bonus),
            _opt_int(incumbent),
        )

    @property
    def is_dense(self) -> bool:
        return self.rows is None

    def finite(self) -> NDArray[np.bool_]:
        """Dense problems: the mask of pairs with a bid (computed once)."""
        cached = self.__dict__.get("_finite")
        if cached is None:
            cached = np.isfinite(self.costs)
            object.__setattr__(self, "_finite", cached)
        return cached  # type: ignore[no-any-return]

    def edges(self) -> tuple[IntArray, IntArray, FloatArray]:
        """The bids as (rows, cols, costs), row-major; computed once for a dense problem."""
        if self.rows is not None:
            assert self.cols is not None
            return self.rows, self.cols, self.costs
        if self._edges is None:
            r, c = np.nonzero(self.finite())
            object.__setattr__(self, "_edges", (r, c, self.costs[r, c]))
        assert self._edges is not None
        return self._edges

    @property
    def n_bids(self) -> int:
        if self.rows is not None:
            return len(self.rows)
        cached = self.__dict__.get("_n_bids")
        if cached is None:
            cached = int(np.count_nonzero(self.finite()))
            object.__setattr__(self, "_n_bids", cached)
        return cached  # type: ignore[no-any-return]

    def cost(self, k: int, j: int) -> float:
        """The bid of agent ``k`` on task ``j`` (NaN when there is none)."""
        if self.rows is None:
            v = float(self.costs[k, j])
            return v if math.isfinite(v) else math.nan
        r, c, w = self.edges()
        hit = np.nonzero((r == k) & (c == j))[0]
        return float(w[hit[0]]) if len(hit) else math.nan


def _opt_float(a: FloatArray | Sequence[float] | None) -> FloatArray | None:
    return None if a is None else np.asarray(a, dtype=np.float64)


def _opt_int(a: IntArray | Sequence[int] | None) -> IntArray | None:
    return None if a is None else np.asarray(a, dtype=np.intp)


@dataclass(frozen=True, eq=False)
class Matching:
    """Assigned pairs (agent index ``rows[i]`` ↔ task index ``cols[i]``), sorted by agent."""

    rows: IntArray
    cols: IntArray
    method: str
    """The solver that produced it: ``dense``, ``sparse`` or ``ilp-scip``."""

    def __len__(self) -> int:
        return len(self.rows)

    def as_dict(self) -> dict[int, int]:
        return {int(k): int(j) for k, j in zip(self.rows, self.cols)}


@dataclass(frozen=True)
class Objective:
    """The lexicographic objective of a matching: more assigned pairs first, then more value."""

    assigned: int
    value: float
    """``Σ (bonus[j] − cost[k, j])``: minus the total cost when there are no priorities."""
    cost: float
    """``Σ cost[k, j]`` over the assigned pairs."""

    def better_than(self, other: Objective, rel: float = 1e-9) -> bool:
        if self.assigned != other.assigned:
            return self.assigned > other.assigned
        return self.value > other.value + rel * (1.0 + abs(other.value))

    def same_as(self, other: Objective, rel: float = 1e-7) -> bool:
        return self.assigned == other.assigned and math.isclose(
            self.value, other.value, rel_tol=rel, abs_tol=rel
        )


def evaluate(problem: AssignmentProblem, matching: Matching) -> Objective:
    """Objective of ``matching`` on ``problem``; raises ``ValueError`` if it is not a valid
    matching of bid pairs (a task or agent used twice, or a pair without a bid)."""
    rows, cols = matching.rows, matching.cols
    if len(set(rows.tolist())) != len(rows) or len(set(cols.tolist())) != len(cols):
        raise ValueError("not a matching: an agent or a task is used twice")
    if problem.rows is None:
        c = problem.costs[rows, cols] if len(rows) else np.zeros(0)
    else:
        lookup = {(int(k), int(j)): float(w) for k, j, w in zip(*problem.edges())}
        c = np.array([lookup.get((int(k), int(j)), math.nan) for k, j in zip(rows, cols)])
    if not np.all(np.isfinite(c)):
        raise ValueError("matching uses a pair without a bid")
    b = problem.bonus[cols] if problem.bonus is not None and len(cols) else np.zeros(len(cols))
    return Objective(len(rows), float(np.sum(b - c)), float(np.sum(c)))


# --------------------------------------------------------------------------------------------
# The profit transform (eq. 4-5)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Shift:
    offset: float
    """``q = c − bonus + offset`` is ≥ 0 on every bid."""
    delta: float
    """Tie-break added to every non-incumbent pair."""
    unit: float
    """Scale of the costs (their span, or 1): keeps sparse weights non-zero."""
    big: float
    """Shifted cost of "no assignment"; more than any ``K`` bids together."""


MIN_SPAN = 1e-6
"""Cost spans below this are treated as equal costs (scale 1): a denormal span would make every
profit underflow below the solvers' tolerances, and SCIP would then see nothing worth assigning."""


def _make_shift(lo: float, hi: float, k: int) -> _Shift:
    span = hi - lo
    unit = span if span >= MIN_SPAN else 1.0
    delta = TIE_EPS * unit
    big = (k + 1) * (span + delta + unit) + unit
    return _Shift(-lo, delta, unit, big)


def _check_range(lo: float, hi: float) -> None:
    if lo < 0 or hi > MAX_COST:
        raise ValueError(f"bid costs must be in [0, {MAX_COST:g}] (got {lo:g} … {hi:g})")


def _edge_q(problem: AssignmentProblem) -> tuple[IntArray, IntArray, FloatArray, _Shift]:
    """Shifted costs ``q`` (with the incumbent tie-break) on the bid edges, and the shift."""
    if problem.is_dense:  # a -inf is not an edge but must still be rejected
        _check_range(*_finite_range(problem.costs))
    rows, cols, costs = problem.edges()
    k = min(problem.n_agents, problem.n_tasks)
    if len(costs) == 0:
        return rows, cols, costs, _make_shift(0.0, 0.0, k)
    _check_range(float(costs.min()), float(costs.max()))
    q = costs - problem.bonus[cols] if problem.bonus is not None else costs.copy()
    s = _make_shift(float(q.min()), float(q.max()), k)
    q += s.offset + s.delta
    if problem.incumbent is not None:
        q[problem.incumbent[rows] == cols] -= s.delta
    np.maximum(q, 0.0, out=q)
    return rows, cols, q, s


def _finite_range(a: FloatArray) -> tuple[float, float]:
    """(min, max) of the finite entries of ``a``, NaN ignored; (inf, -inf) when there are none.
    A ``-inf`` comes back as the minimum (and is then rejected as a negative cost)."""
    if a.size == 0:
        return math.inf, -math.inf
    flat = a.reshape(-1)
    lo = float(np.fmin.reduce(flat))
    hi = float(np.fmax.reduce(flat))
    if hi == math.inf:  # some +inf (no bid): the largest finite value the slow way
        fin = flat[np.isfinite(flat)]
        hi = float(fin.max()) if fin.size else -math.inf
        if lo == math.inf:
            lo = float(fin.min()) if fin.size else math.inf
    if math.isnan(lo):  # all NaN
        return math.inf, -math.inf
    return lo, hi


def _dense_q(problem: AssignmentProblem) -> tuple[FloatArray, _Shift]:
    """Shifted costs as an ``n_agents × n_tasks`` matrix with ``BIG`` where there is no bid.

    Done in a few whole-array passes (this is most of the time at 1,000 × 10,000 besides the
    solve itself).
    """
    k = min(problem.n_agents, problem.n_tasks)
    if problem.rows is not None:
        rows, cols, q, s = _edge_q(problem)
        m = np.full((problem.n_agents, problem.n_tasks), s.big)
        m[rows, cols] = q
        return m, s
    # NaN-ignoring reductions are ~20× faster than masked ones (``where=``); +inf (no bid) only
    # needs the slow path when present.
    c = problem.costs
    raw_lo, raw_hi = _finite_range(c)
    _check_range(raw_lo, raw_hi)
    if problem.bonus is not None:
        m = c - problem.bonus
        s = _make_shift(*_finite_range(m), k)
        m += s.offset + s.delta
    else:
        s = _make_shift(raw_lo, raw_hi, k)
        m = c + (s.offset + s.delta)
    # q ≥ 0 exactly: x − min(x) ≥ 0 in IEEE arithmetic, and the incumbents get δ back below
    np.fmin(m, s.big, out=m)  # NaN and +inf (no bid) → BIG; fmin returns the non-NaN operand
    if problem.incumbent is not None:
        a = np.nonzero(problem.incumbent >= 0)[0]
        j = problem.incumbent[a]
        bid = m[a, j] < s.big
        m[a[bid], j[bid]] -= s.delta
    return m, s


# --------------------------------------------------------------------------------------------
# Solvers
# --------------------------------------------------------------------------------------------
def estimate_us(problem: AssignmentProblem) -> dict[str, float]:
    """Predicted solve time (µs) of the dense and sparse solvers on ``problem`` (cost model)."""
    cells = problem.n_agents * problem.n_tasks
    nnz = problem.n_bids
    dense = DENSE_FIXED_US + DENSE_NS_PER_CELL * cells / 1e3
    sparse = (
        SPARSE_FIXED_US + SPARSE_US_PER_AGENT * problem.n_agents + SPARSE_NS_PER_EDGE * nnz / 1e3
    )
    if problem.is_dense:
        sparse += (SCAN_NS_PER_CELL * cells + SCAN_NS_PER_EDGE * nnz) / 1e3
    else:
        dense += (FILL_NS_PER_CELL * cells + FILL_NS_PER_EDGE * nnz) / 1e3
    return {"dense": dense, "sparse": sparse}


def choose_method(problem: AssignmentProblem) -> str:
    """``pruned`` for a large bid matrix (:func:`btmission.allocation.pruned.worth_it`), else
    ``dense`` or ``sparse``, whichever the measured cost model predicts to be faster."""
    from btmission.allocation.pruned import worth_it

    if worth_it(problem):
        return "pruned"
    est = estimate_us(problem)
    return "sparse" if est["sparse"] < est["dense"] else "dense"


def solve(problem: AssignmentProblem, method: str = "auto") -> Matching:
    """Optimal matching (module docstring) by ``method``: auto, dense, sparse, pruned or
    ilp-scip. ``pruned`` hands the problem to ``dense`` when it cannot prove its answer."""
    if method == "auto":
        method = choose_method(problem)
    if method == "pruned":  # before n_bids: it counts the bids in its own pass
        from btmission.allocation.pruned import solve_pruned

        if problem.is_dense:
            found = solve_pruned(problem)
            if found is not None:
                return found
        method = "dense" if problem.is_dense else choose_method(problem)
    if problem.n_agents == 0 or problem.n_tasks == 0 or problem.n_bids == 0:
        empty = np.zeros(0, dtype=np.intp)
        return Matching(empty, empty, method)
    if method == "dense":
        return _solve_dense(problem)
    if method == "sparse":
        return _solve_sparse(problem)
    if method == "ilp-scip":
        return _solve_ilp_scip(problem)
    raise ValueError(f"unknown solver method '{method}' (expected one of: {', '.join(METHODS)})")


def _solve_dense(problem: AssignmentProblem) -> Matching:
    from scipy.optimize import linear_sum_assignment

    m, s = _dense_q(problem)
    r, c = linear_sum_assignment(m)
    keep = m[r, c] < s.big
    return Matching(r[keep].astype(np.intp), c[keep].astype(np.intp), "dense")


def _solve_sparse(problem: AssignmentProblem) -> Matching:
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import min_weight_full_bipartite_matching

    rows, cols, q, s = _edge_q(problem)
    na, nt = problem.n_agents, problem.n_tasks
    dummy = np.arange(na, dtype=np.intp)
    graph = csr_matrix(
        (
            np.concatenate([q + s.unit, np.full(na, s.big + s.unit)]),
            (np.concatenate([rows, dummy]), np.concatenate([cols, nt + dummy])),
        ),
        shape=(na, nt + na),
    )
    r, c = min_weight_full_bipartite_matching(graph)
    real = c < nt
    order = np.argsort(r[real], kind="stable")
    return Matching(r[real][order].astype(np.intp), c[real][order].astype(np.intp), "sparse")


@dataclass(frozen=True)
class IlpModel:
    """The paper's ILP (eq. 6-7) ready for SCIP: one binary per bid edge."""

    rows: IntArray
    cols: IntArray
    profit: FloatArray
    helper: Any
    """OR-Tools ``ModelBuilderHelper`` holding the model."""


def _mbh() -> Any:
    from ortools.linear_solver.python import model_builder_helper

    return cast(Any, model_builder_helper)


def build_ilp(problem: AssignmentProblem) -> IlpModel:
    """Build ``max Σ ρ x  s.t.  Σ_k x ≤ 1 ∀ task, Σ_j x ≤ 1 ∀ agent, x ∈ {0, 1}`` (eq. 6-7).

    Variables exist only for bid pairs (an agent that does not bid on a task cannot get it), as
    in the paper's participation study. Built from sparse arrays with OR-Tools' model builder.
    """
    from scipy.sparse import csr_matrix

    rows, cols, q, s = _edge_q(problem)
    profit = s.big - q
    n = len(rows)
    na, nt = problem.n_agents, problem.n_tasks
    e = np.arange(n)
    a = csr_matrix(
        (np.ones(2 * n), (np.concatenate([rows, na + cols]), np.concatenate([e, e]))),
        shape=(na + nt, n),
    )
    helper = _mbh().ModelBuilderHelper()
    helper.fill_model_from_sparse_data(
        np.zeros(n), np.ones(n), profit, np.zeros(na + nt), np.ones(na + nt), a
    )
    for i in range(n):
        helper.set_var_integrality(i, True)
    helper.set_maximize(True)
    return IlpModel(rows, cols, profit, helper)


def solve_ilp(model: IlpModel, *, time_limit_s: float | None = None) -> Matching:
    """Solve a built ILP with SCIP; raises :class:`SolverError` if SCIP is missing or fails."""
    mbh = _mbh()
    solver = mbh.ModelSolverHelper("scip")
    if not solver.solver_is_supported():
        raise SolverError("this OR-Tools build has no SCIP solver")
    solver.set_solver_specific_parameters("limits/gap = 0")
    if time_limit_s is not None:
        solver.set_time_limit_in_seconds(time_limit_s)
    solver.solve(model.helper)
    status = solver.status()
    if status != mbh.SolveStatus.OPTIMAL:
        raise SolverError(f"SCIP did not prove optimality: {status.name}")
    x = solver.variable_values() > 0.5
    r, c = model.rows[x], model.cols[x]
    order = np.argsort(r, kind="stable")
    return Matching(r[order].astype(np.intp), c[order].astype(np.intp), "ilp-scip")


def _solve_ilp_scip(problem: AssignmentProblem) -> Matching:
    return solve_ilp(build_ilp(problem))
