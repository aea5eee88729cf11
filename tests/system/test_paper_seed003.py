"""The seed 003 section of ``btmission bench paper`` (btmission/bench/paper_seed003.py)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from btmission.bench.paper import SectionResult
from btmission.bench.paper_seed003 import (
    KEY,
    Fig4Point,
    HeadOn,
    WarehouseRun,
    run,
    section_markdown,
    warehouse_run,
)


def _run(seed: int, closest: float = 0.31, **kw: object) -> WarehouseRun:
    base = WarehouseRun(
        seed=seed,
        controller="nmpc",
        reason="completed",
        time_s=400.0 + seed,
        wall_s=150.0,
        tasks_done=14,
        tasks_total=14,
        shelf_collisions=0,
        robot_collisions=0,
        min_robot_m=closest,
        min_robot_at=(100.0, "G1", "G2"),
        below_r_obs_s=0.0,
        min_clearance_m=0.18,
        solves=15_000,
        solve_median_ms=5.0,
        solve_p99_ms=20.0,
        solve_max_ms=80.0,
        new_task_latency_s=0.1,
        rounds=3600,
        round_median_ms=0.7,
        reassigned_after_commit=0,
        preempted_by_priority=1,
        distance_m={"G1": 50.0 + seed},
    )
    return replace(base, **kw)  # type: ignore[arg-type]


PAIR = HeadOn(0.317, 0.05, 0)
FIG4 = [Fig4Point(0.9, 18_000, 790.0, 0.3, True), Fig4Point(0.3, 6_000, 130.0, 0.3, True)]


def test_the_page_shows_paper_and_seeds_side_by_side() -> None:
    md = section_markdown([_run(0), _run(1, closest=0.295)], PAIR, FIG4)
    assert KEY == "seed003"
    assert "| paper (lab, TurtleBot3) | all | — | 0 | 0 | ≈ 0.26 m |  | 0.04 m |" in md
    assert "| seed 1 | 14 of 14 | 401 s | 0 | 0 | 0.295 m | +13.5 % | 0.005 m |" in md
    assert "Every seed meets the paper's result" in md and "0.5 cm" in md
    assert "The seeds are different runs" in md
    assert "| 90% (18,000 bids) | 1,450 ms | 790 ms | -45.5 % | 0.30 ms | yes |" in md
    for block in md.split("\n\n"):  # every row of a table has as many cells as its header
        rows = [x for x in block.splitlines() if x.startswith("|")]
        assert len({x.count("|") for x in rows}) <= 1, block
    assert "btmission run missions/warehouse.yaml --controller nmpc --seed 0 --log runs" in md
    assert "closest 0.317 m (without eq. 12: 0.050 m)" in md


def test_the_page_says_when_a_seed_fails_or_two_seeds_are_one_run() -> None:
    md = section_markdown([_run(0), _run(1, closest=0.25)], PAIR, FIG4)
    assert "**Not every seed**" in md
    md = section_markdown([_run(0), replace(_run(0), seed=1)], PAIR, FIG4)
    assert "**Some seeds gave the same run.**" in md
    md = section_markdown([_run(0, shelf_collisions=1)], PAIR, FIG4, quick=True, until=45)
    assert "**Not every seed**" in md and "seed 0 (until 45 s)" in md
    assert "--quick" in md and "--seed 0 --until 45" in md


def test_a_short_warehouse_run_is_measured() -> None:
    """The first 8 s: every robot starts 2 m from the next, nothing has been delivered yet, the
    NMPC solves once per robot every 0.1 s, and every task that arrived was announced within a
    round (9 Hz)."""
    r = warehouse_run(0, until=8.0)
    assert r.reason == "until" and r.time_s == 8.0 and r.tasks_done == 0
    assert r.shelf_collisions == r.robot_collisions == 0
    assert 1.8 < r.min_robot_m <= 2.0 and r.below_r_obs_s == 0
    assert r.solves == 4 * 80 and r.solve_median_ms > 0
    assert r.new_task_latency_s is not None and r.new_task_latency_s <= 1 / 9 + 1e-6
    assert r.rounds == pytest.approx(8 * 9, abs=2)
    assert set(r.distance_m) == {"G1", "G2", "G3", "G4"}
    assert r.min_clearance_m is not None and math.isfinite(r.min_clearance_m)


@pytest.mark.slow
def test_quick_section_runs() -> None:
    lines: list[str] = []
    result = run(True, lines.append)
    assert isinstance(result, SectionResult)
    assert len(result.data["warehouse"]) == 2 and len(result.data["fig4"]) == 2
    assert "seed 0 (until 45 s)" in result.markdown and "--quick" in result.markdown
    assert any("warehouse seed 1" in x for x in lines)


def test_the_page_can_be_rebuilt_from_stored_numbers() -> None:
    import json
    from dataclasses import asdict

    from btmission.bench.paper_seed003 import markdown_from_data

    runs = [_run(0), _run(1)]
    data = {
        "warehouse": [asdict(r) for r in runs],
        "head_on": asdict(PAIR),
        "fig4": [asdict(p) for p in FIG4],
    }
    stored = json.loads(json.dumps(data))  # as the section's JSON file has it
    assert markdown_from_data(stored) == section_markdown(runs, PAIR, FIG4)
