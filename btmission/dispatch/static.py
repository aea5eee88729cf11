"""Static fleet mission planning (seed 004 §4, §6.1): instances, one GA run, batches vs push and swap.

An instance of the §6.1 batch with L vehicles (L even): the first L/2 vehicles start at distinct
random terminals of the left half, the others at distinct random terminals of the right half; the
end nodes of the first half are the start nodes of the second half, in order, and vice versa — so
every vehicle swaps places with a partner and F0 is sure to collide. The minimum number of items is
ξ0 = ξ_min + 2·(L/2) (one pause visit per pair), and r = ξ/ξ0 (Tables 2-3).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from btmission.dispatch.evaluate import DEFAULT_GRAZING_WINDOW_S, Evaluator, default_beta
from btmission.dispatch.ga import GAParams, GAResult, default_wait_max, optimize
from btmission.dispatch.missions import fleet_items, initial_fleet
from btmission.dispatch.push_and_swap import PasResult, push_and_swap
from btmission.dispatch.topomap import TopoMap


@dataclass(frozen=True)
class StaticInstance:
    """Start and end node of every vehicle."""

    starts: tuple[int, ...]
    ends: tuple[int, ...]

    @property
    def vehicles(self) -> int:
        return len(self.starts)


def side_terminals(tmap: TopoMap) -> tuple[list[int], list[int]]:
    """Terminals of the ``left`` and ``right`` groups (the two halves of the Fig. 6 map)."""
    left = [i for i in tmap.terminals if tmap.nodes[i].group == "left"]
    right = [i for i in tmap.terminals if tmap.nodes[i].group == "right"]
    return left, right


def random_instance(tmap: TopoMap, vehicles: int, rng: np.random.Generator) -> StaticInstance:
    """One §6.1 instance (module docstring). Raises ValueError when the map cannot host it."""
    if vehicles < 2 or vehicles % 2:
        raise ValueError(f"the static batch needs an even number of vehicles >= 2, got {vehicles}")
    left, right = side_terminals(tmap)
    half = vehicles // 2
    if len(left) < half or len(right) < half:
        raise ValueError(
            f"map '{tmap.name}' has {len(left)} left and {len(right)} right terminals "
            f"(group: left/right); {vehicles} vehicles need {half} on each side"
        )
    a = [int(x) for x in rng.choice(left, half, replace=False)]
    b = [int(x) for x in rng.choice(right, half, replace=False)]
    return StaticInstance(tuple(a + b), tuple(b + a))


@dataclass(frozen=True)
class StaticRun:
    """One GA run on one instance."""

    instance: StaticInstance
    result: GAResult
    xi_min: int

    @property
    def xi0(self) -> int:
        """ξ0 = ξ_min + 2·(L/2)."""
        return self.xi_min + 2 * (self.instance.vehicles // 2)


def plan_static(
    tmap: TopoMap,
    instance: StaticInstance,
    params: GAParams = GAParams(),
    rng: np.random.Generator | None = None,
    delta: float = DEFAULT_GRAZING_WINDOW_S,
) -> StaticRun:
    """F0 for the instance, then Alg. 1 for the budget D = L × τ (or ``params.budget_s``)."""
    fleet0 = initial_fleet(tmap, list(zip(instance.starts, instance.ends)))
    xi_min = fleet_items(fleet0)
    wait_max = params.wait_max if params.wait_max is not None else default_wait_max(tmap)
    ev = Evaluator(tmap, xi_min, default_beta(tmap, fleet0, wait_max), delta)
    result = optimize(tmap, fleet0, ev, params, rng)
    return StaticRun(instance, result, xi_min)


@dataclass
class Summary:
    """Table 2/3/5 columns for one method and one fleet size (averages over successful runs)."""

    method: str
    vehicles: int
    runs: int = 0
    successes: int = 0
    items: list[int] = field(default_factory=list)
    ratios: list[float] = field(default_factory=list)
    durations: list[float] = field(default_factory=list)

    def add(self, success: bool, items: int, xi0: int, duration: float) -> None:
        self.runs += 1
        if success:
            self.successes += 1
            self.items.append(items)
            self.ratios.append(items / xi0)
            self.durations.append(duration)

    @property
    def success_rate(self) -> float:
        """Σ in %."""
        return 100.0 * self.successes / self.runs if self.runs else math.nan

    @staticmethod
    def _mean(xs: Sequence[float]) -> float:
        return statistics.fmean(xs) if xs else math.nan

    @property
    def mean_items(self) -> float:
        return self._mean(self.items)

    @property
    def mean_ratio(self) -> float:
        return self._mean(self.ratios)

    @property
    def mean_duration(self) -> float:
        return self._mean(self.durations)

    @property
    def std_items(self) -> float:
        """σ of ξ (Table 5)."""
        return statistics.pstdev(self.items) if len(self.items) > 1 else 0.0


@dataclass
class BatchResult:
    """GA and push-and-swap summaries for every fleet size, plus evaluation throughput."""

    map_name: str
    budget_per_vehicle_s: float | None
    budget_total_s: float | None
    summaries: list[Summary]
    evaluations: int = 0
    eval_seconds: float = 0.0
    generations: list[int] = field(default_factory=list)


def run_static_batch(
    tmap: TopoMap,
    vehicles: Sequence[int],
    runs: int,
    params: GAParams,
    seed: int | None = 0,
    delta: float = DEFAULT_GRAZING_WINDOW_S,
    *,
    on_run: Callable[[int, int, bool, bool], None] | None = None,
) -> BatchResult:
    """``runs`` random instances per fleet size, each solved by the GA and by push and swap.

    ``on_run(vehicles, run, ga_ok, pas_ok)`` is called after each instance (progress bars).
    """
    if runs < 1:
        raise ValueError("runs must be >= 1")
    rng = np.random.default_rng(seed)
    out = BatchResult(
        tmap.name, None if params.budget_s is not None else params.tau_s, params.budget_s, []
    )
    for L in vehicles:
        ga_sum, pas_sum = Summary("GA", L), Summary("push-and-swap", L)
        for k in range(runs):
            inst = random_instance(tmap, L, rng)
            run = plan_static(tmap, inst, params, np.random.default_rng(rng.integers(2**63)), delta)
            res = run.result
            ga_sum.add(res.feasible, res.evaluation.items, run.xi0, res.evaluation.duration)
            out.evaluations += res.evaluations
            out.eval_seconds += res.elapsed_s
            out.generations.append(res.generations)
            pas: PasResult = push_and_swap(tmap, inst.starts, inst.ends)
            pas_sum.add(pas.success, pas.items, run.xi0, pas.serial_duration)
            if on_run is not None:
                on_run(L, k, res.feasible, pas.success)
        out.summaries += [ga_sum, pas_sum]
    return out
