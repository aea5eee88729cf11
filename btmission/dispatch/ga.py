"""The modified genetic algorithm of seed 004 §4.3 (Alg. 1-3) with the Table 1 defaults.

* Alg. 1: the population starts as α copies of F0; each generation is formed by tournament
  selection and mutation, the best individual so far is copied unchanged into slot 1 (elitism), and
  the loop runs until the time budget τ_max (and optionally a generation cap) is spent. No crossover.
* Alg. 2: tournament of two, the better one wins with probability p_tour.
* Alg. 3: per mission, the first item's t_w is mutated with probability p_mut = p_rel/κ (κ: the
  number of mutable stop times in the fleet mission); for non-prioritised missions also every
  stop time at a pause node, and with probability p_struct = p_rel/L a structural mutation that
  inserts (set T1) or removes (set T2) a pause-node visit with equal probability.

How a stop time is modified is not specified in the paper; here it is redrawn uniformly in
[lower bound, lower bound + wait_max] with probability ``p_reset`` and otherwise moved by a normal
step of standard deviation ``creep × wait_max`` (clipped at the lower bound). An inserted pause
visit gets a uniformly drawn stop time. Every Bernoulli draw of Alg. 3 is made, but vectorised.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from btmission.dispatch.evaluate import Evaluation, Evaluator
from btmission.dispatch.missions import FleetMission, mutable_slots
from btmission.dispatch.topomap import TopoMap


@dataclass(frozen=True)
class GAParams:
    """GA settings; the defaults are Table 1 (α = 50, p_tour = 0.8, p_rel = 2, τ = 3 s/vehicle)."""

    population: int = 50
    p_tour: float = 0.8
    p_rel: float = 2.0
    tau_s: float = 3.0
    """Optimisation time per vehicle (s): the budget is D = L × τ (§6.1)."""
    budget_s: float | None = None
    """Total budget D in s; overrides ``tau_s`` when given."""
    max_generations: int | None = None
    """Stop after this many generations even if time is left (for reproducible runs)."""
    wait_max: float | None = None
    """Range of stop times drawn by the mutations (default: the longest Π0 traversal of the map)."""
    p_reset: float = 0.5
    creep: float = 0.1

    def __post_init__(self) -> None:
        if self.population < 2:
            raise ValueError("the population needs at least 2 individuals")
        if not 0.0 <= self.p_tour <= 1.0:
            raise ValueError("p_tour must be in [0, 1]")
        if self.p_rel <= 0:
            raise ValueError("p_rel must be > 0")
        if self.budget_s is not None and self.budget_s < 0:
            raise ValueError("the budget must be >= 0 s")
        if self.tau_s < 0:
            raise ValueError("tau must be >= 0 s")
        if self.max_generations is not None and self.max_generations < 0:
            raise ValueError("max_generations must be >= 0")

    def budget(self, vehicles: int) -> float:
        """D: the optimisation time for ``vehicles`` vehicles."""
        return self.budget_s if self.budget_s is not None else self.tau_s * vehicles


@dataclass(frozen=True)
class GAResult:
    """The best fleet mission found, its evaluation and how the search went."""

    best: FleetMission
    evaluation: Evaluation
    generations: int
    evaluations: int
    elapsed_s: float
    first_feasible_generation: int | None
    """Generation at which a feasible fleet mission was first found (0: F0 itself)."""

    @property
    def feasible(self) -> bool:
        return self.evaluation.feasible


def default_wait_max(tmap: TopoMap) -> float:
    """The longest Π0 traversal between terminals: long enough to let any vehicle cross the map."""
    terms = tmap.terminals or list(range(tmap.n))
    sub = tmap.dist[np.ix_(terms, terms)]
    return float(sub.max()) if sub.size else 1.0


class _Buffers:
    """Flat numpy buffers of a population for the numba core (see ``_ga_kernel``)."""

    def __init__(self, tmap: TopoMap, fleet0: FleetMission, alpha: int) -> None:
        L = len(fleet0)
        self.fleet0 = fleet0
        nodes = np.concatenate([m.nodes for m in fleet0]).astype(np.int32)
        waits = np.concatenate([m.waits for m in fleet0]).astype(np.float64)
        total = len(nodes)
        self.cap = total + 2 * L * (len(tmap.pauses) + 1)
        self.pop_nodes = np.zeros((alpha, self.cap), np.int32)
        self.pop_waits = np.zeros((alpha, self.cap))
        self.pop_nodes[:, :total] = nodes
        self.pop_waits[:, :total] = waits
        offs = np.zeros(L + 1, np.int64)
        np.cumsum([len(m.nodes) for m in fleet0], out=offs[1:])
        self.pop_offs = np.tile(offs, (alpha, 1))
        self.pop_tot = np.full(alpha, total, np.int64)
        self.new_nodes = self.pop_nodes.copy()
        self.new_waits = self.pop_waits.copy()
        self.new_offs = self.pop_offs.copy()
        self.new_tot = self.pop_tot.copy()
        self.best_nodes = self.pop_nodes[0].copy()
        self.best_waits = self.pop_waits[0].copy()
        self.best_offs = offs.copy()
        self.best_tot = np.array([total], np.int64)
        self.prio = np.array([m.prioritized for m in fleet0], np.bool_)
        self.frozen = np.array([m.frozen for m in fleet0], np.int64)
        self.head = np.array([m.head for m in fleet0], np.int64)
        self.min_wait = np.array([m.min_wait for m in fleet0], np.float64)
        self.t0 = np.array([m.t0 for m in fleet0], np.float64)
        ptr = np.zeros(tmap.n + 1, np.int64)
        np.cumsum([len(p) for p in tmap.pause_neighbors], out=ptr[1:])
        self.pn_ptr = ptr
        self.pn_idx = np.array([p for ps in tmap.pause_neighbors for p in ps], np.int32)
        self.is_pause = np.array(tmap.is_pause, np.bool_)
        self.is_transit = np.array(tmap.is_transit, np.bool_)

    def best_fleet(self, tmap: TopoMap) -> FleetMission:
        """The best individual as missions (same per-vehicle constraints as F0)."""
        out = []
        for k, m in enumerate(self.fleet0):
            lo, hi = int(self.best_offs[k]), int(self.best_offs[k + 1])
            nodes = self.best_nodes[lo:hi].copy()
            slots = mutable_slots(tmap, nodes, m.prioritized, m.frozen, m.head)
            out.append(replace(m, nodes=nodes, waits=self.best_waits[lo:hi].copy(), slots=slots))
        return tuple(out)


def optimize(
    tmap: TopoMap,
    fleet0: FleetMission,
    evaluator: Evaluator,
    params: GAParams = GAParams(),
    rng: np.random.Generator | None = None,
    *,
    progress: Callable[[int, float], None] | None = None,
) -> GAResult:
    """Alg. 1: optimise F0 for ``params.budget(L)`` seconds (or ``max_generations``).

    The generations run in a numba core, in batches between which the clock is checked; the
    kernels are compiled (or loaded from numba's cache) before the clock starts.
    """
    from btmission.dispatch import _ga_kernel as K

    rng = rng if rng is not None else np.random.default_rng()
    wait_max = params.wait_max if params.wait_max is not None else default_wait_max(tmap)
    alpha = params.population
    budget = params.budget(len(fleet0))
    buf = _Buffers(tmap, fleet0, alpha)
    K.seed(int(rng.integers(2**31)))
    ev = evaluator
    veh = (buf.prio, buf.frozen, buf.head, buf.min_wait, buf.t0)
    mp = (ev._ttime, ev._edge, buf.is_pause, buf.is_transit, buf.pn_ptr, buf.pn_idx)
    prm = (ev.delta, ev.beta, float(ev.xi_min), ev.t_ref, params.p_tour, params.p_rel,
           wait_max, params.p_reset, params.creep)  # fmt: skip
    pop = (buf.pop_nodes, buf.pop_waits, buf.pop_offs, buf.pop_tot)
    new = (buf.new_nodes, buf.new_waits, buf.new_offs, buf.new_tot)
    elite = (buf.best_nodes, buf.best_waits, buf.best_offs, buf.best_tot)

    def run(n: int) -> None:
        K.generations(pop, new, elite, best_score, scores, new_scores, veh, mp, prm, n)

    s0 = evaluator(fleet0)
    scores = np.full(alpha, s0)
    new_scores = scores.copy()
    best_score = np.array([s0])
    run(0)  # compile / load the kernels before the clock starts
    t_start = time.perf_counter()
    gen, batch = 0, 1
    first_feasible: int | None = 0 if s0 > 0 else None
    while True:
        elapsed = time.perf_counter() - t_start
        left = budget - elapsed
        if left <= 0 or (params.max_generations is not None and gen >= params.max_generations):
            break
        n = batch if params.max_generations is None else min(batch, params.max_generations - gen)
        t_batch = time.perf_counter()
        run(n)
        gen += n
        dt = time.perf_counter() - t_batch
        if first_feasible is None and best_score[0] > 0:
            first_feasible = gen
        if progress is not None:
            progress(gen, float(best_score[0]))
        # aim at batches of ~20 ms (or the time left) so the budget is kept closely
        per_gen = dt / n
        batch = max(1, min(int(min(0.02, left - dt) / per_gen) if per_gen > 0 else 1, 1000))
    elapsed = time.perf_counter() - t_start
    best = buf.best_fleet(tmap)
    return GAResult(
        best=best,
        evaluation=evaluator.evaluate(best),
        generations=gen,
        evaluations=1 + gen * (alpha - 1),
        elapsed_s=elapsed,
        first_feasible_generation=first_feasible,
    )
