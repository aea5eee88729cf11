"""Seed 004 (Wahde, Bellone & Torabi 2019) in ``btmission bench paper``: GA fleet dispatch.

Reproduced: Table 6 (dynamic planning on the Fig. 1 mine: traversals per vehicle C and the idle
fractions i_t, i_p for 2-5 trucks), the static success rates and item ratios of Tables 2 and 3
(Fig. 6 map, NPR and SPR) and Table 5's GA / push-and-swap comparison. The runs are shorter than
the paper's protocol (see :data:`FULL` and the page's own text) so that the section takes under
about ten minutes on a 2-core machine.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from btmission.bench.dispatch import TABLE6, dynamic_runs
from btmission.bench.paper import SectionResult, table
from btmission.bench.paper import pct as _pct

KEY = "seed004"
TITLE = "Seed 004 GA fleet dispatch (Tables 2, 3, 5 and 6)"

SIZES_STATIC = (2, 4, 6, 8, 10)
SIZES_DYNAMIC = (2, 3, 4, 5)

# the paper's static tables (1,000 instances per size, τ = 3 s per vehicle)
SIGMA_NPR = (100.0, 100.0, 100.0, 100.0, 98.6)
R_NPR = (1.0000, 1.0013, 1.0054, 1.0112, 1.0233)
SIGMA_SPR = (100.0, 100.0, 100.0, 99.9, 99.3)
R_SPR = (1.0000, 1.0006, 1.0039, 1.0025, 1.0031)
GA_XI_T5 = (23.99, 48.73, 73.69, 97.93, 123.34)
PAS_XI_T5 = (49.39, 99.05, 148.17, 196.81, 245.48)


@dataclass(frozen=True)
class Protocol:
    """How much is run: dynamic runs × hours per fleet size, static instances per size and map."""

    dyn_runs: int
    dyn_hours: float
    dyn_budget_s: float
    dyn_generations: int | None
    static_runs: int
    tau_s: float


FULL = Protocol(dyn_runs=5, dyn_hours=4.0, dyn_budget_s=0.5, dyn_generations=None,
                static_runs=10, tau_s=0.3)  # fmt: skip
"""The page's run: five 4-h runs per fleet size (as the paper), 10 static instances per size
and map (the paper: 1,000) with τ = 0.3 s per vehicle (the paper: 3 s)."""
QUICK = Protocol(dyn_runs=1, dyn_hours=0.5, dyn_budget_s=0.05, dyn_generations=40,
                 static_runs=1, tau_s=0.02)  # fmt: skip


def pct(ours: float, paper: float) -> str:
    """:func:`btmission.bench.paper.pct`, with a dash where we have no number."""
    return "–" if math.isnan(ours) else _pct(ours, paper)


def _f(x: float, nd: int) -> str:
    return "–" if math.isnan(x) else f"{x:.{nd}f}"


def _mean(xs: Sequence[float]) -> float:
    return statistics.fmean(xs) if xs else math.nan


def _sd(xs: Sequence[float]) -> float:
    return statistics.pstdev(xs) if len(xs) > 1 else 0.0


def run(quick: bool, echo: Callable[[str], None]) -> SectionResult:
    """Run the section (see the module docstring); ``quick``: a smoke-sized version."""
    from btmission.dispatch.ga import GAParams
    from btmission.dispatch.maps import TABLE6_SCALE, static_map
    from btmission.dispatch.static import run_static_batch

    p = QUICK if quick else FULL
    # ---- Table 6
    _, dyn = dynamic_runs(
        SIZES_DYNAMIC, p.dyn_runs, p.dyn_hours, p.dyn_budget_s, 0, "mine_table6", 3.0,
        generations=p.dyn_generations, echo=echo,
    )  # fmt: skip
    scale = 4.0 / p.dyn_hours  # C grows with the run's length; compare per 4 h
    rows6 = []
    data6: dict[str, dict[str, float]] = {}
    within = []
    for L in SIZES_DYNAMIC:
        rs = dyn[L]
        c = [r.traversals_per_vehicle * scale for r in rs]
        it = [r.idle_terminal for r in rs]
        ip = [r.idle_pause for r in rs]
        pc, pit, pip = TABLE6[L]
        mc, mit, mip = _mean(c), _mean(it), _mean(ip)
        dev = (mc - pc) / pc
        within.append(abs(dev) <= 0.10)
        data6[str(L)] = {"C": mc, "C_sd": _sd(c), "i_t": mit, "i_p": mip,
                         "optimisations": _mean([r.optimisations for r in rs]),
                         "failures": sum(r.failures for r in rs)}  # fmt: skip
        rows6.append([L, pc, f"{mc:.1f} ± {_sd(c):.1f}", pct(mc, pc), f"{pit:.3f}", f"{mit:.3f}",
                      pct(mit, pit), f"{pip:.3f}", f"{mip:.3f}", pct(mip, pip)])  # fmt: skip
    # ---- Tables 2, 3, 5
    params = GAParams(tau_s=p.tau_s)
    batches = {}
    for variant in ("npr", "spr"):
        echo(f"static batch {variant.upper()}: {p.static_runs} instance(s) per size")
        batches[variant] = run_static_batch(
            static_map(variant), SIZES_STATIC, p.static_runs, params, seed=0
        )
    rows_s: list[list[object]] = []
    data_s: dict[str, dict[str, float]] = {}
    for variant, sig_p, r_p in (("npr", SIGMA_NPR, R_NPR), ("spr", SIGMA_SPR, R_SPR)):
        ga_rows = [s for s in batches[variant].summaries if s.method == "GA"]
        for k, s in enumerate(ga_rows):
            rows_s.append([variant.upper(), s.vehicles, sig_p[k], _f(s.success_rate, 1),
                           f"{r_p[k]:.4f}", _f(s.mean_ratio, 4), pct(s.mean_ratio, r_p[k])])  # fmt: skip
            data_s[f"{variant}_{s.vehicles}"] = {"sigma": s.success_rate, "r": s.mean_ratio,
                                                 "xi": s.mean_items}  # fmt: skip
    npr = batches["npr"].summaries
    rows5 = []
    data5: dict[str, dict[str, float]] = {}
    extra = []
    for k, L in enumerate(SIZES_STATIC):
        ga = next(s for s in npr if s.method == "GA" and s.vehicles == L)
        pas = next(s for s in npr if s.method != "GA" and s.vehicles == L)
        ratio = ga.mean_items / pas.mean_items if pas.items and ga.items else math.nan
        p_ratio = GA_XI_T5[k] / PAS_XI_T5[k]
        # PAS items beyond ξ_min per pair (ξ_min = GA ξ / r − L)
        p_extra = (PAS_XI_T5[k] - (GA_XI_T5[k] / R_NPR[k] - L)) / (L / 2)
        xi_min = _mean([x / r - L for x, r in zip(ga.items, ga.ratios, strict=True)])
        same = ga.successes == pas.successes == ga.runs  # the same instances on both sides
        o_extra = (pas.mean_items - xi_min) / (L / 2) if same else math.nan
        extra.append(o_extra)
        data5[str(L)] = {"ga_xi": ga.mean_items, "pas_xi": pas.mean_items, "ratio": ratio,
                         "pas_extra_per_pair": o_extra}  # fmt: skip
        rows5.append([L, f"{p_ratio:.2f}", _f(ratio, 2), pct(ratio, p_ratio),
                      f"{p_extra:.1f}", _f(o_extra, 1)])  # fmt: skip
    # ---- the page
    sigmas = [d["sigma"] for d in data_s.values()]
    min_sig = min(sigmas) if sigmas else math.nan
    rdevs = [
        abs(data_s[f"{v}_{L}"]["r"] - r) / r * 100
        for v, rs in (("npr", R_NPR), ("spr", R_SPR))
        for L, r in zip(SIZES_STATIC, rs, strict=True)
        if not math.isnan(data_s[f"{v}_{L}"]["r"])
    ]
    max_rdev = max(rdevs) if rdevs else math.nan
    p_extra_mean = _mean(
        [
            (PAS_XI_T5[k] - (GA_XI_T5[k] / R_NPR[k] - L)) / (L / 2)
            for k, L in enumerate(SIZES_STATIC)
        ]
    )
    idle_sum = [data6[str(L)]["i_t"] + data6[str(L)]["i_p"] for L in SIZES_DYNAMIC]
    paper_idle = [TABLE6[L][1] + TABLE6[L][2] for L in SIZES_DYNAMIC]
    c_devs = [(data6[str(L)]["C"] - TABLE6[L][0]) / TABLE6[L][0] * 100 for L in SIZES_DYNAMIC]
    n_within = sum(within)
    c2, c5 = data6["2"]["C"], data6[str(SIZES_DYNAMIC[-1])]["C"]
    drop = (1 - c5 / c2) * 100 if c2 > 0 else math.nan
    fails = sum(int(d["failures"]) for d in data6.values())
    ratios = [d["ratio"] for d in data5.values() if not math.isnan(d["ratio"])]
    md = f"""
**What is reproduced.** Table 6: trucks shuttle for 4 h between six loading sites and the single
prioritised offloading site of the Fig. 1 mine, re-planned by the GA after every loading (2-5 min)
and offloading (30-60 s); C is terminal-to-terminal traversals per truck, i_t and i_p the idle
fractions at terminals (after loading/offloading: queue, optimisation, initial stop) and at pause
nodes. Tables 2, 3 and 5: static instances on the Fig. 6 map (L/2 trucks on each side trading
places), solved by the GA and by push and swap.

**Reconstruction choices.** The paper gives its maps as pictures. The mine is rebuilt from the
text (`mine`: a 30/20/10 km/h ramp with two passing bays, three pause nodes near the offloading
site, six loading sites) and run here as **`mine_table6`**, its distances scaled by
{TABLE6_SCALE:g}: a *calibration* to Table 6 itself (its 2-truck row leaves ≈ 888 s of driving per
round trip once loading, offloading and idle time are taken out; `mine` drives 1,249 s, the scaled
mine 874 s). The paper's text ("outbound on the order of 500 s, inbound 800 s") would cap C near
18.5 at 2 trucks; it agrees with Table 6 only if those times include the waits on the way (Table 6's
5-truck row: ≈ 1,280 s per round trip, waits included). Each optimisation is charged D = 3 s × L of
simulated time (Table 1's τ, as the paper's real-time runs spent it) while our GA runs
{p.dyn_budget_s:g} s of wall-clock time (the paper: D). Plans are *settled* before adoption: stop
times on eq. 2's plateau (a truck that does not finish last can wait longer at no cost) are
shortened as far as the plan stays collision-free, which is what the paper's small idle fractions
imply (docs/dispatch.md, "Dynamic planning", has the time breakdown with and without it).

**Protocol.** {p.dyn_runs} run(s) of {p.dyn_hours:g} h per fleet size (the paper: five 4-h runs;
C is given per 4 h); static: {p.static_runs} instance(s) per size and map (the paper: 1,000) with
τ = {p.tau_s:g} s per vehicle (the paper: 3 s).

```sh
btmission bench paper --only seed004
btmission bench dispatch-dynamic            # Table 6, five 4-h runs per size (about 12 min)
btmission dispatch dynamic --map mine_table6 --vehicles 2 --hours 4 --runs 5 --opt-time 6  # one row, D = 3 s × L
btmission dispatch static --map static_npr --vehicles 2,4,6,8,10 --runs 1000   # Tables 2, 5
```

**Table 6** (dynamic, `mine_table6`):

{
        table(
            [
                "L",
                "paper C",
                "btmission C",
                "Δ C",
                "paper i_t",
                "i_t",
                "Δ i_t",
                "paper i_p",
                "i_p",
                "Δ i_p",
            ],
            rows6,
        )
    }

C is within 10 % of the paper's for {n_within} of {len(SIZES_DYNAMIC)} fleet sizes (deviations
{", ".join(f"{d:+.1f} %" for d in c_devs)}); it falls by {drop:.0f} % from 2 to 5 trucks (the
paper: 27 %). The two-truck row is the one `mine_table6`'s trip length is calibrated to; the
others follow from the planner. Each row is the mean of {p.dyn_runs} run(s), and the runs' spread
(±) is about how far a row moves with other seeds; `btmission bench dispatch-dynamic` runs five
per size, as the paper did. {fails} optimisation(s) failed and were queued again (§7).

The idle fractions differ more than C, in how they split more than in their sum (i_t + i_p:
{idle_sum[0]:.3f} against the paper's {paper_idle[0]:.3f} at 2 trucks, {idle_sum[-1]:.3f} against
{paper_idle[-1]:.3f} at {SIZES_DYNAMIC[-1]}): when two trucks must be kept apart, the GA can hold
the outbound one at the offloading site (i_t) or send it into a pause node on the way (i_p), and
eq. 2 charges the pause visit two mission items while the wait costs nothing unless that truck
arrives last. How long trucks idle also depends on details the paper leaves open (how many pause
nodes are near the offloading site and where the passing bays are). With more trucks the single
offloading site is the bottleneck, as the paper says: a truck that has offloaded waits there for
a gap in the incoming trucks (inbound trucks may not stop), loaded trucks park at the pause nodes
near it, and outbound trucks wait in the ramp's bays while loaded ones climb at 10 km/h.

**Tables 2 and 3** (GA, static; Σ success rate in %, r = ξ/ξ0):

{table(["map", "L", "paper Σ", "btmission Σ", "paper r", "btmission r", "Δ r"], rows_s)}

With {p.tau_s:g} s per vehicle (the paper: 3 s) and {p.static_runs} instance(s) per size, the GA's
success rate is {_f(min_sig, 1)} % at the lowest (the paper: 98.6 % at 10 trucks on NPR) and r
deviates from the paper's by {_f(max_rdev, 1)} % at most (r is ≥ 1 by definition; the paper's is
within 2.4 % of 1 everywhere).

**Table 5** (NPR; GA items / push-and-swap items, and push and swap's items beyond ξ_min per pair
of trucks):

{
        table(
            [
                "L",
                "paper GA/PAS",
                "btmission GA/PAS",
                "Δ",
                "paper PAS extra/pair",
                "btmission PAS extra/pair",
            ],
            rows5,
        )
    }

Our GA needs {_f(_mean(ratios), 2)} of push and swap's items, not the paper's ≈ 0.5. It is not
how items are counted: §7 equates mission items with traversed segments, and one push-and-swap
move is one traversed segment. Ours makes exactly one swap per pair of trucks: the partner waits
in a dead-end terminal and cannot be pushed away, so the two back up d hops to the nearest node
with three or more neighbours, swap (6 moves) and replay the backing up, 4d + 4 moves beyond Π0;
that node is one hop back (d = 1: 8 moves; measured
{_f(_mean([x for x in extra if not math.isnan(x)]), 1)} per pair). The paper's push and swap adds
{p_extra_mean:.1f} items per pair at every fleet size, i.e. d ≈ {(p_extra_mean - 4) / 4:.1f}: its
pairs backed up to about the middle of the map, which Luna and Bekris's nearest-junction rule does
not do on a map shaped like Fig. 6. The paper does not describe its push and swap beyond that
(§6.1.1), so ours keeps the published rule; docs/dispatch.md gives the argument in full.
"""
    data = {"table6": data6, "static": data_s, "table5": data5, "protocol": p.__dict__,
            "table6_within_10pct": n_within}  # fmt: skip
    return SectionResult(markdown=md.strip(), data=data)
