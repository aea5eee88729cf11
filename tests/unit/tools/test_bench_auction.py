"""The auction benchmark's instances, measurements and report (small sizes, no timing asserts)."""

from __future__ import annotations

import csv
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from btmission.bench.auction import (
    CSV_HEADER,
    AuctionBench,
    BenchConfig,
    RoundPoint,
    ScalePoint,
    SweepPoint,
    as_edges,
    instance_costs,
    markdown,
    measure_crossover,
    measure_point,
    measure_rounds,
    measure_scale,
    run_auction_benchmark,
)

TINY = BenchConfig(
    agents=(3, 6),
    tasks=(5, 12),
    participation=(0.5, 1.0),
    repeat=1,
    rounds=3,
    round_size=(6, 12),
    scale=((8, 30),),
    scale_repeat=1,
    crossover=((6, 20),),
    crossover_bids=(2, 0.5),
)


def test_instances_bid_on_the_k_cheapest() -> None:
    c = instance_costs(7, 40, 0.3, seed=1)
    assert c.shape == (7, 40)
    assert (np.isfinite(c).sum(axis=1) == 12).all()  # ceil(0.3 · 40)
    full = instance_costs(7, 40, 1.0, seed=1)
    for i in range(7):  # the kept bids are the cheapest of the agent's full row
        kept = np.sort(c[i][np.isfinite(c[i])])
        np.testing.assert_allclose(kept, np.sort(full[i])[:12])
    np.testing.assert_array_equal(np.isnan(c), np.isnan(instance_costs(7, 40, 0.3, seed=1)))
    e = as_edges(c)
    assert e.n_bids == 84 and e.rows is not None


def test_point_compares_both_solvers() -> None:
    pt = measure_point("fig4", 6, 12, 0.5, TINY)
    assert (pt.agents, pt.tasks, pt.bids, pt.assigned) == (6, 12, 36, 6)
    assert pt.same_optimum is True and pt.scip_solve_ms is not None and pt.speedup is not None
    off = measure_point("fig4", 6, 12, 0.5, TINY, scip=False)
    assert off.scip_solve_ms is None and off.note == "SCIP off" and off.speedup is None
    capped = measure_point("fig5", 6, 12, 0.5, BenchConfig(scip_max_bids=10, repeat=1))
    assert capped.scip_solve_ms is None and capped.note == "SCIP skipped (> 10 bids)"


def test_rounds_scale_and_crossover() -> None:
    r = measure_rounds(TINY)
    assert (r.agents, r.tasks, r.rounds, r.method) == (6, 12, 3, "dense")
    assert 0 < r.median_ms <= r.p90_ms and r.rate_hz == pytest.approx(1e3 / r.median_ms)
    s = measure_scale(8, 30, 1.0, TINY)
    assert (s.bids, s.assigned) == (240, 8)
    assert s.dense_ms is not None and s.same_optimum is True and s.same_pairs is True
    pts = measure_crossover(6, 20, 0.5, TINY)
    assert [p.form for p in pts] == ["matrix", "edges"]
    assert all(p.same_optimum and p.bids_per_agent == 10 for p in pts)
    assert pts[0].density == 0.5 and pts[0].faster in ("dense", "sparse", "pruned")
    assert pts[0].pruned_ms is not None and pts[1].pruned_ms is None  # pruned: matrix only


def test_run_writes_table_csv_and_plot(tmp_path: Path) -> None:
    lines: list[str] = []
    png = tmp_path / "plots" / "fig.png"
    b = run_auction_benchmark(TINY, tmp_path, png=png, echo=lines.append)
    # Fig. 4 at 12 tasks and Fig. 5 at 6 agents; the shared 6x12 point is measured once
    assert [(s.figure, s.agents, s.tasks) for s in b.sweeps][::2] == [
        ("fig4", 3, 12),
        ("fig4", 6, 12),
        ("fig5", 6, 5),
        ("fig5", 6, 12),
    ]
    assert b.sweeps[3].scip_solve_ms == b.sweeps[7].scip_solve_ms
    assert all(s.same_optimum for s in b.sweeps)
    with (tmp_path / "auction.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == CSV_HEADER and all(len(r) == len(CSV_HEADER) for r in rows)
    sections = [r[0] for r in rows[1:]]
    assert sections.count("fig4") == 4 and sections.count("fig5") == 4
    assert sections.count("round") == 1 and sections.count("scale") == 2
    assert sections.count("dense_vs_sparse") == 4
    md = (tmp_path / "auction.md").read_text()
    for head in ("## Fig. 4: time vs agents (12 tasks)", "## Fig. 5: time vs tasks (6 agents)",
                 "## Coordinator round", "## Scale", "## Dense vs sparse", "## Targets"):  # fmt: skip
        assert head in md
    for table in md.split("\n\n"):  # every row of a table has as many cells as its header
        rows = [r for r in table.splitlines() if r.startswith("| ")]
        assert len({r.count(" | ") for r in rows}) <= 1, table
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert lines[-1].startswith("wrote ") and any(line.startswith("target:") for line in lines)


def test_scale_compares_the_pruned_default_with_dense() -> None:
    """Large enough for ``auto`` to prune (500,000 cells, 50× more tasks than agents): the
    same pairs as the dense solver, which the point reports."""
    s = measure_scale(100, 5000, 0.3, BenchConfig(scale_repeat=1))
    assert s.method == "pruned" and s.assigned == 100 and s.bids == 100 * 1500
    assert s.same_optimum is True and s.same_pairs is True and s.dense_ms is not None


def test_a_second_run_keeps_the_first_under_earlier_runs(tmp_path: Path) -> None:
    cfg = replace(TINY, agents=(3,), tasks=(5,), participation=(1.0,), scip=False, crossover=())
    run_auction_benchmark(cfg, tmp_path, echo=lambda _: None)
    first = (tmp_path / "auction.md").read_text()
    run_auction_benchmark(cfg, tmp_path, echo=lambda _: None)
    run_auction_benchmark(cfg, tmp_path, echo=lambda _: None)
    md = (tmp_path / "auction.md").read_text()
    assert md.startswith("# Auction benchmark") and md.count("# Auction benchmark") == 1
    assert md.count("## Earlier runs") == 1 and md.count("### Run before this one") == 2
    body = first.split("\n", 1)[1].strip()
    assert body in md.split("## Earlier runs")[1]  # the first run's tables, word for word


def _sweep(speedup_ms: float, same: bool) -> SweepPoint:
    return SweepPoint("fig4", 50, 400, 0.9, 18000, "dense", 0.5, 50, 5.0, speedup_ms, same)


def test_targets() -> None:
    b = AuctionBench(BenchConfig(), {})
    assert [met for *_, met in b.targets()] == [None, None, None]
    b.sweeps = [_sweep(600.0, True)]
    b.rounds = RoundPoint(50, 400, 0.9, 10, 4.0, 6.0, "dense", 0)
    b.scale = [ScalePoint(1000, 10_000, 0.3, 1, "pruned", 50.0, 1000, 70.0, True, True)]
    assert [met for *_, met in b.targets()] == [True, True, True]
    assert "p = 0.3: 50.0 ms (dense 70.0 ms)" in b.targets()[2][1]
    b.scale = [ScalePoint(1000, 10_000, 0.3, 1, "pruned", 20.0, 1000, 70.0, False, False)]
    assert b.targets()[2][2] is False  # fast but not the same optimum
    b.sweeps = [_sweep(400.0, True)]  # 800x
    b.rounds = RoundPoint(50, 400, 0.9, 10, 5.5, 6.0, "dense", 0)
    b.scale = [ScalePoint(1000, 10_000, 0.3, 1, "dense", 49.0, 1000)]
    b.scale.append(ScalePoint(1000, 10_000, 0.9, 1, "dense", 50.5, 1000))
    assert [met for *_, met in b.targets()] == [False, False, False]
    b.sweeps = [_sweep(6000.0, False)]
    assert b.targets()[0][2] is False and "same optimum: NO" in b.targets()[0][1]
    b.env = {"date": "d", "machine": "m", "cpus": "2", "python": "p", "btmission": "v"}
    assert "| **no** |" in markdown(b)


def test_config_validation_and_quick() -> None:
    q = BenchConfig.quick(seed=3)
    assert q.seed == 3 and q.fixed_tasks == 400 and q.fixed_agents == 50
    for kw in ({"agents": ()}, {"tasks": (0,)}, {"participation": (0.0,)}, {"repeat": 0},
               {"scale": ((0, 5),)}):  # fmt: skip
        with pytest.raises(ValueError):
            BenchConfig(**kw)  # type: ignore[arg-type]
    assert math.isclose(BenchConfig().participation[0], 0.3)
