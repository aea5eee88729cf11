"""Auction benchmark: seed 003 Fig. 4 and 5, both solvers side by side, plus round rate and scale.

``btmission bench auction`` (or ``python benchmarks/bench_auction.py``) measures, on generated
instances:

* **Fig. 4** — solve time against the number of agents at a fixed number of tasks (the largest
  ``--tasks``), and **Fig. 5** — against the number of tasks at a fixed number of agents (the
  largest ``--agents``), for each participation (the fraction of the tasks each agent bids on,
  30/60/90 % in the paper). Each point times the default exact assignment solver
  (:func:`~btmission.allocation.solvers.solve`, ``auto``: profit transform + scipy; median of
  ``repeat`` runs) and the paper's ILP (eq. 6-7) on OR-Tools + SCIP (model build and solve timed
  apart, one run), and checks that both reach the same optimum (assigned count and total value).
  SCIP is skipped above ``scip_max_bids`` bid variables (said in the table).
* **Round rate** — a whole coordinator round through :class:`~btmission.allocation.loop.AuctionLoop`
  with in-memory bids: announce, collect (bid messages built from precomputed costs that change
  from round to round), allocate (:func:`~btmission.allocation.auction.auction_round`: board,
  matrix, solve, pool update with reasons), publish. Median and 90th percentile over the rounds.
* **Scale** — the assignment solver alone at 1,000 agents × 10,000 tasks: the default (``auto``,
  which picks the pruned solver there) and the dense solver (the default before issue 19) on the
  same instances, interleaved, with their optima compared.
* **Dense vs sparse** — both assignment solvers on the same bids given as edges, from a handful
  to most tasks per agent: where each is faster (the ``auto`` choice's cost model comes from it);
  the pruned solver beside them when the bids come as a matrix.

Instances: agents and tasks uniformly random in a 100 m × 100 m area, costs the straight-line
distances, each agent bidding on its ``ceil(p · n_tasks)`` cheapest tasks (as an agent following
:class:`~btmission.allocation.bidder.Bidder` would). The same seed gives the same instances.
"""

from __future__ import annotations

import csv
import gc
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TypeVar, cast

import numpy as np

from btmission.allocation.auction import AuctionConfig, AuctionState, Bid, participation_k
from btmission.allocation.loop import AuctionLoop, ManualClock, RoundResult
from btmission.allocation.solvers import (
    AssignmentProblem,
    Matching,
    build_ilp,
    evaluate,
    solve,
    solve_ilp,
)
from btmission.allocation.tasks import TaskInfo, TaskPool
from btmission.bench.synth import _median_ms as median_ms
from btmission.bench.synth import environment, header_lines, own_heap, write_page
from btmission.types import FloatArray

T = TypeVar("T")

AREA_M = 100.0
TARGET_SPEEDUP = 1000.0
"""At 50 agents × 400 tasks, p = 0.9: the assignment solver ≥ this many times faster than SCIP."""
TARGET_ROUND_HZ = 200.0
"""A coordinator round at 50 × 400 at this rate or faster."""
TARGET_SCALE_MS = 50.0
"""1,000 agents × 10,000 tasks solved in at most this (issue 19; it was < 100 ms before)."""
TARGET_POINT = (50, 400, 0.9)


@dataclass(frozen=True)
class BenchConfig:
    """What to measure (the defaults are the full run; :meth:`quick` a short one)."""

    agents: tuple[int, ...] = (10, 20, 30, 40, 50)
    tasks: tuple[int, ...] = (50, 100, 200, 300, 400)
    participation: tuple[float, ...] = (0.3, 0.6, 0.9)
    repeat: int = 5
    scip: bool = True
    scip_max_bids: int = 20_000
    round_size: tuple[int, int] = (50, 400)
    round_participation: float = 0.9
    rounds: int = 300
    scale: tuple[tuple[int, int], ...] = ((1000, 10_000),)
    scale_repeat: int = 7
    crossover: tuple[tuple[int, int], ...] = ((200, 2000), (1000, 10_000))
    crossover_bids: tuple[float, ...] = (5, 50, 0.1, 0.3, 0.9)
    """Bids per agent: a count when ≥ 1, else a fraction of the tasks."""
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.agents or not self.tasks or not self.participation:
            raise ValueError("agents, tasks and participation need at least one value each")
        if min(self.agents) < 1 or min(self.tasks) < 1:
            raise ValueError("numbers of agents and tasks must be ≥ 1")
        if any(not 0 < p <= 1 for p in self.participation):
            raise ValueError("participation values must be in (0, 1]")
        if self.repeat < 1 or self.scale_repeat < 1 or self.rounds < 1:
            raise ValueError("repeat, scale_repeat and rounds must be ≥ 1")
        for na, nt in (*self.scale, *self.crossover, self.round_size):
            if na < 1 or nt < 1:
                raise ValueError(f"bad size {na}x{nt}")

    @classmethod
    def quick(cls, **overrides: object) -> BenchConfig:
        base = cls(
            agents=(10, 30, 50),
            tasks=(100, 400),
            repeat=3,
            rounds=100,
            scale_repeat=3,
            crossover=((200, 2000),),
            crossover_bids=(5, 0.9),
        )
        return replace(base, **overrides)  # type: ignore[arg-type]

    @property
    def fixed_tasks(self) -> int:
        """Fig. 4: the number of tasks while the agents vary."""
        return max(self.tasks)

    @property
    def fixed_agents(self) -> int:
        """Fig. 5: the number of agents while the tasks vary."""
        return max(self.agents)


# --------------------------------------------------------------------------------------------
# Instances
# --------------------------------------------------------------------------------------------
def instance_costs(n_agents: int, n_tasks: int, participation: float, seed: int) -> FloatArray:
    """Straight-line costs, each agent keeping its ``ceil(p · n)`` cheapest (NaN elsewhere)."""
    rng = np.random.default_rng([seed, n_agents, n_tasks])
    agents = rng.uniform(0, AREA_M, (n_agents, 2))
    tasks = rng.uniform(0, AREA_M, (n_tasks, 2))
    costs = np.sqrt(((agents[:, None, :] - tasks[None, :, :]) ** 2).sum(axis=2))
    return keep_cheapest(costs, participation_k(participation, n_tasks))


def keep_cheapest(costs: FloatArray, k: int) -> FloatArray:
    """Each row's ``k`` smallest entries, NaN elsewhere (in place)."""
    n = costs.shape[1]
    if k < n:
        drop = np.argpartition(costs, k - 1, axis=1)[:, k:]
        np.put_along_axis(costs, drop, np.nan, axis=1)
    return costs


def as_edges(costs: FloatArray) -> AssignmentProblem:
    r, c = np.nonzero(np.isfinite(costs))
    return AssignmentProblem.sparse(costs.shape[0], costs.shape[1], r, c, costs[r, c])


def _median_ms(fn: Callable[[], T], repeat: int) -> tuple[float, T]:
    """Median wall time (ms) of ``repeat`` calls after one untimed warm-up call (imports, page
    faults), and the last result."""
    fn()
    ms, out = median_ms(fn, repeat)
    return ms, cast(T, out)


# --------------------------------------------------------------------------------------------
# Measurements
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SweepPoint:
    """One point of Fig. 4 or 5: both solvers on the same instance."""

    figure: str
    agents: int
    tasks: int
    participation: float
    bids: int
    method: str
    assignment_ms: float
    assigned: int
    scip_build_ms: float | None = None
    scip_solve_ms: float | None = None
    same_optimum: bool | None = None
    note: str = ""

    @property
    def speedup(self) -> float | None:
        """SCIP solve time (build excluded) over the assignment solver's whole time."""
        if self.scip_solve_ms is None:
            return None
        return self.scip_solve_ms / max(self.assignment_ms, 1e-6)


def measure_point(
    figure: str, na: int, nt: int, p: float, cfg: BenchConfig, scip: bool = True
) -> SweepPoint:
    costs = instance_costs(na, nt, p, cfg.seed)
    ms, match = _median_ms(lambda: solve(AssignmentProblem.dense(costs)), cfg.repeat)
    problem = AssignmentProblem.dense(costs)
    ours = evaluate(problem, match)
    point = SweepPoint(figure, na, nt, p, problem.n_bids, match.method, ms, ours.assigned)
    if not (cfg.scip and scip):
        return replace(point, note="SCIP off")
    if problem.n_bids > cfg.scip_max_bids:
        return replace(point, note=f"SCIP skipped (> {cfg.scip_max_bids:,} bids)")
    gc.collect()
    t0 = time.perf_counter()
    model = build_ilp(problem)
    t1 = time.perf_counter()
    ref = solve_ilp(model)
    t2 = time.perf_counter()
    same = evaluate(problem, ref).same_as(ours)
    return replace(
        point,
        scip_build_ms=(t1 - t0) * 1e3,
        scip_solve_ms=(t2 - t1) * 1e3,
        same_optimum=same,
    )


@dataclass(frozen=True)
class RoundPoint:
    agents: int
    tasks: int
    participation: float
    rounds: int
    median_ms: float
    p90_ms: float
    method: str
    changes: int
    """Tasks that changed hands over all rounds (the bids move a little every round)."""

    @property
    def rate_hz(self) -> float:
        return 1e3 / self.median_ms


def measure_rounds(cfg: BenchConfig) -> RoundPoint:
    """Whole coordinator rounds (announce, collect, allocate, publish) with in-memory bids."""
    na, nt = cfg.round_size
    p = cfg.round_participation
    rng = np.random.default_rng([cfg.seed, 7])
    task_xy = rng.uniform(0, AREA_M, (nt, 2))
    pool = TaskPool().add_all(
        TaskInfo(f"T{j:05d}", "inspect", {"location": [*task_xy[j], 0.0]}) for j in range(nt)
    )
    state = AuctionState(AuctionConfig(participation=p), pool)
    agent_ids = [f"R{i:04d}" for i in range(na)]
    k = participation_k(p, nt)
    # the agents move 0.1 m per round (1 m/s at 10 Hz): bids change a little every round
    pos = rng.uniform(0, AREA_M, (na, 2))
    heading = rng.uniform(0, 2 * np.pi, na)
    step_xy = 0.1 * np.stack([np.cos(heading), np.sin(heading)], axis=1)
    variants = []
    for _ in range(cfg.rounds + 1):
        pos = pos + step_xy
        c = np.sqrt(((pos[:, None, :] - task_xy[None, :, :]) ** 2).sum(axis=2))
        variants.append(keep_cheapest(c, k))
    clock = ManualClock()
    published: list[int] = [0]

    def collect(ann: object, now: float) -> list[Bid]:
        rows = variants[published[0] % len(variants)]
        return [Bid.aligned(a, now, ann, rows[i]) for i, a in enumerate(agent_ids)]  # type: ignore[arg-type]

    def publish(result: RoundResult) -> None:
        published[0] += 1

    loop = AuctionLoop(state, clock, collect, publish)
    loop.step()  # warm-up: first announcement, imports
    times: list[float] = []
    changes = 0
    method = "none"
    gc.collect()
    for _ in range(cfg.rounds):
        clock.advance(loop.period_s)
        t0 = time.perf_counter()
        result = loop.step()
        times.append((time.perf_counter() - t0) * 1e3)
        changes += len(result.report.changes)
        method = result.report.method
    times.sort()
    return RoundPoint(
        na,
        nt,
        p,
        cfg.rounds,
        statistics.median(times),
        times[min(len(times) - 1, int(0.9 * len(times)))],
        method,
        changes,
    )


@dataclass(frozen=True)
class ScalePoint:
    agents: int
    tasks: int
    participation: float
    bids: int
    method: str
    solve_ms: float
    """The default solver (``auto``), median."""
    assigned: int
    dense_ms: float | None = None
    """The dense solver on the same instance (the default before issue 19), median."""
    same_optimum: bool | None = None
    """Both assign as many tasks with the same total value."""
    same_pairs: bool | None = None
    """Both return the very same pairs."""


def measure_scale(na: int, nt: int, p: float, cfg: BenchConfig) -> ScalePoint:
    """The default solver and the dense one on the same instance, alternately (one untimed
    warm-up call each), so that both see the same machine load; medians of ``scale_repeat``."""
    costs = instance_costs(na, nt, p, cfg.seed)
    runs: dict[str, list[float]] = {"auto": [], "dense": []}
    out: dict[str, Matching] = {}
    gc.collect()
    for i in range(cfg.scale_repeat + 1):
        for method in runs:
            t0 = time.perf_counter()
            out[method] = solve(AssignmentProblem.dense(costs), method)
            if i:
                runs[method].append((time.perf_counter() - t0) * 1e3)
    problem = AssignmentProblem.dense(costs)
    ours, dense = out["auto"], out["dense"]
    return ScalePoint(
        na,
        nt,
        p,
        problem.n_bids,
        ours.method,
        statistics.median(runs["auto"]),
        len(ours),
        statistics.median(runs["dense"]),
        evaluate(problem, ours).same_as(evaluate(problem, dense)),
        bool(np.array_equal(ours.rows, dense.rows) and np.array_equal(ours.cols, dense.cols)),
    )


@dataclass(frozen=True)
class CrossPoint:
    agents: int
    tasks: int
    bids_per_agent: int
    form: str
    """How the bids come: ``matrix`` (as from the auctioneer) or ``edges``."""
    dense_ms: float
    sparse_ms: float
    auto: str
    same_optimum: bool
    """All the solvers timed reach the same optimum."""
    pruned_ms: float | None = None
    """The pruned solver (bids as a matrix only)."""

    @property
    def density(self) -> float:
        return self.bids_per_agent / self.tasks

    @property
    def faster(self) -> str:
        """The fastest solver of those timed."""
        times = {"dense": self.dense_ms, "sparse": self.sparse_ms, "pruned": self.pruned_ms}
        return min((t, m) for m, t in times.items() if t is not None)[1]


def measure_crossover(na: int, nt: int, bids: float, cfg: BenchConfig) -> list[CrossPoint]:
    """Both assignment solvers on the same bids, given as a matrix and as edges, and the pruned
    one on the matrix."""
    from btmission.allocation.solvers import choose_method

    k = min(nt, int(bids) if bids >= 1 else max(1, math.ceil(bids * nt)))
    costs = instance_costs(na, nt, k / nt, cfg.seed)
    edges = as_edges(costs)
    assert edges.rows is not None and edges.cols is not None
    rows, cols, w = edges.rows, edges.cols, edges.costs
    makers: dict[str, Callable[[], AssignmentProblem]] = {
        "matrix": lambda: AssignmentProblem.dense(costs),
        "edges": lambda: AssignmentProblem.sparse(na, nt, rows, cols, w),
    }
    reps = max(1, min(cfg.repeat, 3))
    out = []
    for form, make in makers.items():
        d_ms, dm = _median_ms(lambda: solve(make(), "dense"), reps)  # noqa: B023
        s_ms, sm = _median_ms(lambda: solve(make(), "sparse"), reps)  # noqa: B023
        same = evaluate(edges, dm).same_as(evaluate(edges, sm))
        p_ms = None
        if form == "matrix":
            p_ms, pm = _median_ms(lambda: solve(make(), "pruned"), reps)  # noqa: B023
            same = same and evaluate(edges, dm).same_as(evaluate(edges, pm))
        out.append(CrossPoint(na, nt, k, form, d_ms, s_ms, choose_method(make()), same, p_ms))
    return out


# --------------------------------------------------------------------------------------------
# The whole run
# --------------------------------------------------------------------------------------------
@dataclass
class AuctionBench:
    config: BenchConfig
    env: dict[str, str]
    sweeps: list[SweepPoint] = field(default_factory=list)
    rounds: RoundPoint | None = None
    scale: list[ScalePoint] = field(default_factory=list)
    crossover: list[CrossPoint] = field(default_factory=list)

    def point(self, na: int, nt: int, p: float) -> SweepPoint | None:
        for s in self.sweeps:
            if (s.agents, s.tasks) == (na, nt) and math.isclose(s.participation, p):
                return s
        return None

    def targets(self) -> list[tuple[str, str, bool | None]]:
        """(target, measured, met) — met is None when the run did not measure it."""
        out: list[tuple[str, str, bool | None]] = []
        na, nt, p = TARGET_POINT
        pt = self.point(na, nt, p)
        name = f"{na}×{nt}, p = {p:g}: assignment ≥ {TARGET_SPEEDUP:,.0f}× faster than SCIP, same optimum"
        if pt is None or pt.speedup is None:
            out.append((name, "not measured", None))
        else:
            out.append(
                (
                    name,
                    f"{pt.speedup:,.0f}× (SCIP {pt.scip_solve_ms:.0f} ms vs {pt.assignment_ms:.2f} ms); "
                    f"same optimum: {'yes' if pt.same_optimum else 'NO'}",
                    pt.speedup >= TARGET_SPEEDUP and bool(pt.same_optimum),
                )
            )
        r = self.rounds
        name = f"coordinator round at {TARGET_POINT[0]}×{TARGET_POINT[1]} ≥ {TARGET_ROUND_HZ:g} Hz"
        if r is None or (r.agents, r.tasks) != TARGET_POINT[:2]:
            out.append((name, "not measured", None))
        else:
            out.append(
                (
                    name,
                    f"{r.rate_hz:,.0f} Hz (median {r.median_ms:.2f} ms)",
                    r.rate_hz >= TARGET_ROUND_HZ,
                )
            )
        big = [s for s in self.scale if (s.agents, s.tasks) == (1000, 10_000)]
        name = f"1,000 × 10,000 solved in ≤ {TARGET_SCALE_MS:g} ms, same optimum as dense"
        if not big:
            out.append((name, "not measured", None))
        else:
            worst = max(big, key=lambda s: s.solve_ms)
            shown = ", ".join(
                f"p = {s.participation:g}: {s.solve_ms:.1f} ms"
                + ("" if s.dense_ms is None else f" (dense {s.dense_ms:.1f} ms)")
                for s in big
            )
            same = all(s.same_optimum is not False for s in big)
            out.append((name, shown, worst.solve_ms <= TARGET_SCALE_MS and same))
        return out


def _row(cells: Sequence[object]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _head(cols: Sequence[str], right_from: int = 1) -> list[str]:
    return [_row(cols), _row(["---" if i < right_from else "---:" for i in range(len(cols))])]


def _opt(v: float | None, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def _yes(v: bool | None) -> str:
    return "—" if v is None else ("yes" if v else "**NO**")


SWEEP_COLS = (
    "figure",
    "agents",
    "tasks",
    "participation",
    "bids",
    "assignment ms",
    "solver",
    "SCIP build ms",
    "SCIP solve ms",
    "speed-up",
    "same optimum",
    "note",
)


def _sweep_cells(s: SweepPoint) -> list[str]:
    return [
        s.figure,
        f"{s.agents:,}",
        f"{s.tasks:,}",
        f"{s.participation:.0%}",
        f"{s.bids:,}",
        f"{s.assignment_ms:.3f}",
        s.method,
        _opt(s.scip_build_ms, ".1f"),
        _opt(s.scip_solve_ms, ".1f"),
        "—" if s.speedup is None else f"{s.speedup:,.0f}×",
        _yes(s.same_optimum),
        s.note,
    ]


ROUND_COLS = (
    "agents",
    "tasks",
    "participation",
    "rounds",
    "median ms",
    "p90 ms",
    "rate Hz",
    "solver",
    "changes",
)


def _round_cells(r: RoundPoint) -> list[str]:
    return [
        f"{r.agents:,}",
        f"{r.tasks:,}",
        f"{r.participation:.0%}",
        str(r.rounds),
        f"{r.median_ms:.2f}",
        f"{r.p90_ms:.2f}",
        f"{r.rate_hz:,.0f}",
        r.method,
        str(r.changes),
    ]


SCALE_COLS = (
    "agents",
    "tasks",
    "participation",
    "bids",
    "solver",
    "solve ms",
    "assigned",
    "dense ms",
    "speed-up",
    "same optimum",
    "same pairs",
)


def _scale_cells(s: ScalePoint) -> list[str]:
    return [
        f"{s.agents:,}",
        f"{s.tasks:,}",
        f"{s.participation:.0%}",
        f"{s.bids:,}",
        s.method,
        f"{s.solve_ms:.1f}",
        f"{s.assigned:,}",
        _opt(s.dense_ms, ".1f"),
        "—" if s.dense_ms is None else f"{s.dense_ms / max(s.solve_ms, 1e-6):.1f}×",
        _yes(s.same_optimum),
        _yes(s.same_pairs),
    ]


CROSS_COLS = (
    "agents",
    "tasks",
    "bids/agent",
    "density",
    "bids as",
    "dense ms",
    "sparse ms",
    "pruned ms",
    "faster",
    "auto picks",
    "same optimum",
)


def _cross_cells(c: CrossPoint) -> list[str]:
    return [
        f"{c.agents:,}",
        f"{c.tasks:,}",
        f"{c.bids_per_agent:,}",
        f"{c.density:.1%}",
        c.form,
        f"{c.dense_ms:.2f}",
        f"{c.sparse_ms:.2f}",
        _opt(c.pruned_ms, ".2f"),
        c.faster,
        c.auto,
        "yes" if c.same_optimum else "**NO**",
    ]


CSV_HEADER = (
    "section",
    "agents",
    "tasks",
    "participation",
    "bids",
    "solver",
    "assignment_ms",
    "scip_build_ms",
    "scip_solve_ms",
    "speedup",
    "same_optimum",
    "round_median_ms",
    "round_p90_ms",
    "rate_hz",
    "dense_ms",
    "sparse_ms",
    "note",
)


def _f(v: float | None, digits: int = 4) -> str:
    return "" if v is None else f"{v:.{digits}f}"


def _b(v: bool | None) -> str:
    return "" if v is None else str(v).lower()


def csv_rows(b: AuctionBench) -> list[list[str]]:
    rows: list[list[str]] = []
    for s in b.sweeps:
        rows.append(
            [s.figure, str(s.agents), str(s.tasks), f"{s.participation:g}", str(s.bids), s.method,
             _f(s.assignment_ms), _f(s.scip_build_ms), _f(s.scip_solve_ms), _f(s.speedup, 1),
             _b(s.same_optimum), "", "", "", "", "", s.note]
        )  # fmt: skip
    if b.rounds is not None:
        r = b.rounds
        rows.append(
            ["round", str(r.agents), str(r.tasks), f"{r.participation:g}", "", r.method, "", "",
             "", "", "", _f(r.median_ms), _f(r.p90_ms), _f(r.rate_hz, 1), "", "", f"{r.rounds} rounds"]
        )  # fmt: skip
    for s2 in b.scale:
        rows.append(
            ["scale", str(s2.agents), str(s2.tasks), f"{s2.participation:g}", str(s2.bids),
             s2.method, _f(s2.solve_ms), "", "", "", _b(s2.same_optimum), "", "", "",
             _f(s2.dense_ms), "", "" if s2.same_pairs is None else f"same pairs: {_b(s2.same_pairs)}"]
        )  # fmt: skip
    for c in b.crossover:
        rows.append(
            ["dense_vs_sparse", str(c.agents), str(c.tasks), f"{c.density:g}",
             str(c.bids_per_agent * c.agents), c.auto, "", "", "", "", _b(c.same_optimum), "", "",
             "", _f(c.dense_ms), _f(c.sparse_ms),
             f"bids as {c.form}; faster: {c.faster}"
             + ("" if c.pruned_ms is None else f"; pruned_ms: {c.pruned_ms:.4f}")]
        )  # fmt: skip
    return rows


def markdown(b: AuctionBench) -> str:
    cfg, env = b.config, b.env
    lines = [
        "# Auction benchmark (seed 003 Fig. 4 and 5)",
        "",
        *header_lines(env),
        "",
        "Instances: agents and tasks uniformly random in a 100 m × 100 m area, straight-line costs, "
        "each agent bidding on its ⌈p·n⌉ cheapest tasks (seed "
        f"{cfg.seed}). *assignment* = the default exact solver (`solve`, `auto`: profit transform + "
        f"scipy), median of {cfg.repeat} run(s); *SCIP* = the paper's ILP (eq. 6-7) built with "
        "OR-Tools' model builder and solved by SCIP with its defaults, one run, build and solve "
        "timed apart; *speed-up* = SCIP solve ÷ assignment. *same optimum*: both assign the same "
        "number of tasks with the same total value. SCIP is skipped above "
        f"{cfg.scip_max_bids:,} bids.",
        "",
        f"## Fig. 4: time vs agents ({cfg.fixed_tasks:,} tasks)",
        "",
        *_head(SWEEP_COLS),
        *(_row(_sweep_cells(s)) for s in b.sweeps if s.figure == "fig4"),
        "",
        f"## Fig. 5: time vs tasks ({cfg.fixed_agents:,} agents)",
        "",
        *_head(SWEEP_COLS),
        *(_row(_sweep_cells(s)) for s in b.sweeps if s.figure == "fig5"),
        "",
    ]
    if b.rounds is not None:
        lines += [
            "## Coordinator round",
            "",
            "A whole round through `AuctionLoop.step` (announce, collect in-memory bids, "
            "`auction_round`, publish) with bids that move every round.",
            "",
            *_head(ROUND_COLS),
            _row(_round_cells(b.rounds)),
            "",
        ]
    if b.scale:
        lines += [
            "## Scale",
            "",
            f"The assignment solver alone: the default (`auto`) and the dense solver (the default "
            f"before issue 19) on the same instance, alternately, median of {cfg.scale_repeat} "
            "each; *same optimum*: as many tasks with the same total value; *same pairs*: the "
            "very same matching.",
            "",
            *_head(SCALE_COLS),
            *(_row(_scale_cells(s)) for s in b.scale),
            "",
        ]
    if b.crossover:
        lines += [
            "## Dense vs sparse assignment solver",
            "",
            "The same bids given as a matrix (as the auctioneer holds them) and as edges; *dense* = "
            "`linear_sum_assignment` on the full matrix, *sparse* = "
            "`min_weight_full_bipartite_matching` on the edges, each including the conversion it "
            "needs; *pruned* = the pruned solver on the matrix (`btmission.allocation.pruned`); "
            "*auto picks* = `choose_method` (pruned for a large matrix with twice as many tasks "
            "as agents, else the cost model `estimate_us`); *same optimum*: every solver timed.",
            "",
            *_head(CROSS_COLS),
            *(_row(_cross_cells(c)) for c in b.crossover),
            "",
        ]
    lines += ["## Targets", "", *_head(("target", "measured", "met"), 2)]
    for name, measured, met in b.targets():
        lines.append(_row([name, measured, "—" if met is None else ("yes" if met else "**no**")]))
    lines += [
        "",
        "Regenerate with `btmission bench auction` (plot: `auction.png`) or "
        "`python benchmarks/bench_auction.py`.",
        "",
    ]
    return "\n".join(lines)


def plot(b: AuctionBench, path: Path) -> None:
    """Fig. 4 and 5 side by side (log time), SCIP solid, assignment dashed, one colour per p."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, figure, xname, fixed in (
        (axes[0], "fig4", "agents", f"{b.config.fixed_tasks} tasks"),
        (axes[1], "fig5", "tasks", f"{b.config.fixed_agents} agents"),
    ):
        for i, p in enumerate(b.config.participation):
            pts = sorted(
                (s for s in b.sweeps if s.figure == figure and math.isclose(s.participation, p)),
                key=lambda s: getattr(s, xname),
            )
            xs = [getattr(s, xname) for s in pts]
            col = colours[i % len(colours)]
            scip = [(x, s.scip_solve_ms) for x, s in zip(xs, pts) if s.scip_solve_ms is not None]
            if scip:
                ax.plot(*zip(*scip), "o-", color=col, label=f"SCIP ILP, {p:.0%}")
            ax.plot(
                xs, [s.assignment_ms for s in pts], "s--", color=col, label=f"assignment, {p:.0%}"
            )
        ax.set_yscale("log")
        ax.set_xlabel(f"number of {xname} ({fixed})")
        ax.set_ylabel("solve time [ms]")
        ax.grid(True, which="both", alpha=0.3)
        ax.set_title("Fig. 4: time vs agents" if figure == "fig4" else "Fig. 5: time vs tasks")
    axes[1].legend(fontsize=8, ncol=2)
    fig.suptitle(f"Task allocation solve time — {b.env['machine']}, {b.env['date']}", fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


@own_heap()
def run_auction_benchmark(
    cfg: BenchConfig,
    out_dir: Path | str = Path("benchmarks/results"),
    png: Path | str | None = None,
    echo: Callable[[str], object] = print,
) -> AuctionBench:
    """Measure everything ``cfg`` asks for, echoing rows as they come; write ``auction.md``,
    ``auction.csv`` and the plot (``png``, default ``out_dir/auction.png``); the previous
    ``auction.md``'s tables are kept under "Earlier runs"."""
    out = Path(out_dir)
    env = environment()
    b = AuctionBench(cfg, env)
    echo(
        f"auction benchmark: Fig. 4 agents {list(cfg.agents)} × {cfg.fixed_tasks} tasks, Fig. 5 "
        f"tasks {list(cfg.tasks)} × {cfg.fixed_agents} agents, participation "
        f"{', '.join(f'{p:.0%}' for p in cfg.participation)}; {env['machine']}, {env['cpus']} CPU(s)"
    )
    if cfg.scip:  # load OR-Tools/SCIP before timing anything
        solve(AssignmentProblem.dense(np.ones((2, 2))), "ilp-scip")
    cache: dict[tuple[int, int, float], SweepPoint] = {}
    cases = [("fig4", na, cfg.fixed_tasks) for na in cfg.agents] + [
        ("fig5", cfg.fixed_agents, nt) for nt in cfg.tasks
    ]
    echo("")
    for line in _head(SWEEP_COLS):
        echo(line)
    for figure, na, nt in cases:
        for p in cfg.participation:
            key = (na, nt, p)
            if key in cache:
                pt = replace(cache[key], figure=figure)
            else:
                pt = measure_point(figure, na, nt, p, cfg)
                cache[key] = pt
            b.sweeps.append(pt)
            echo(_row(_sweep_cells(pt)))
    echo("")
    echo(f"  … coordinator rounds at {cfg.round_size[0]}×{cfg.round_size[1]} ({cfg.rounds} rounds)")
    b.rounds = measure_rounds(cfg)
    echo(_row(_round_cells(b.rounds)))
    for na, nt in cfg.scale:
        for p in cfg.participation:
            echo(f"  … scale {na:,}×{nt:,}, p = {p:g}")
            s = measure_scale(na, nt, p, cfg)
            b.scale.append(s)
            echo(_row(_scale_cells(s)))
    for na, nt in cfg.crossover:
        for k in cfg.crossover_bids:
            echo(f"  … dense vs sparse {na:,}×{nt:,}, {k:g} bids per agent")
            for c in measure_crossover(na, nt, k, cfg):
                b.crossover.append(c)
                echo(_row(_cross_cells(c)))

    out.mkdir(parents=True, exist_ok=True)
    md_path, csv_path = out / "auction.md", out / "auction.csv"
    write_page(md_path, markdown(b))  # issue 19: the previous numbers stay beside the new ones
    with csv_path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_HEADER)
        w.writerows(csv_rows(b))
    png_path = Path(png) if png is not None else out / "auction.png"
    plot(b, png_path)
    echo("")
    for name, measured, met in b.targets():
        verdict = "not measured" if met is None else ("met" if met else "NOT met")
        echo(f"target: {name} — {measured} — {verdict}")
    echo(f"wrote {md_path}, {csv_path} and {png_path}")
    return b
