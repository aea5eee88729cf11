"""The seed 002 section of ``btmission bench paper``: quick mode's structure and numbers."""

from __future__ import annotations

import math

import pytest

from btmission.bench import paper_seed002 as sec


def test_exploration_stats_from_events() -> None:
    events = [
        {"ev": "stage", "t": 1.0, "action": "takeoff"},
        {"ev": "stage", "t": 2.0, "action": "explore"},
        *[
            {
                "ev": "pose",
                "t": 2.0 + k * 0.5,
                "p": [k * 1.0, 0.0, 1.5],
                "v": [2.0, 0, 0],
                "clearance_m": 1.0 - 0.1 * k,
            }
            for k in range(11)
        ],
        {"ev": "collision", "t": 4.0, "other": "rock"},
        {"ev": "stage", "t": 7.0, "action": "return_breadcrumbs"},
        {"ev": "end", "t": 10.0, "wall_s": 2.0},
    ]
    st = sec.exploration_stats(events)
    assert st["speed_m_s"] == pytest.approx(2.0)
    assert st["min_clearance_m"] == pytest.approx(0.0)
    assert st["collisions"] == 1 and st["realtime_factor"] == pytest.approx(5.0)
    with pytest.raises(ValueError, match="never started exploring"):
        sec.exploration_stats([])


def test_quick_section_runs_and_reports_measured_numbers() -> None:
    res = sec.run(True, lambda _: None)
    run = res.data["runs"][0]
    assert run["speed_m_s"] > 1.0 and math.isfinite(run["min_clearance_m"])
    assert f"{run['speed_m_s']:.2f}" in res.markdown and "| quantity |" in res.markdown
