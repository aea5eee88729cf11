"""``btmission bench fleet``: the fleet missions, the repeats' median, the host speed reference, a
real timed run, the files, bad options."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.bench.fleet import (
    CSV_HEAD,
    HEAD,
    TARGETS,
    FleetPoint,
    fleet_mission_text,
    markdown,
    summarise,
)
from btmission.bench.synth import environment, host_speed_ms, host_workload
from btmission.missions import load_mission_text
from btmission.world.checks import check_mission_world
from tests.system.test_cli import run


@pytest.mark.parametrize("drones", [3, 30, 100])
def test_a_fleet_mission_is_valid_and_has_the_field_missions_ratio(drones: int) -> None:
    m = load_mission_text(fleet_mission_text(drones), "fleet.yaml")
    agents, tasks = m.spec.agents, m.spec.tasks
    assert len(agents) == drones and len(tasks) == math.ceil(7 * drones / 3)
    starts = [a.start for a in agents]
    assert min(math.dist(a, b) for i, a in enumerate(starts) for b in starts[i + 1 :]) >= 2.0
    # every start and task lies in open space the drones can reach (the mission checks)
    assert [d for d in check_mission_world(m) if d.severity.value == "error"] == []
    assert fleet_mission_text(drones) == fleet_mission_text(drones)  # deterministic
    assert fleet_mission_text(drones, seed=1) != fleet_mission_text(drones)


def test_a_fleet_too_big_for_the_mine_is_refused() -> None:
    with pytest.raises(ValueError, match="room for"):
        fleet_mission_text(400)


def test_targets_apply_to_the_tracking_controller_only() -> None:
    def point(n: int, ctrl: str, wall: float) -> FleetPoint:
        return FleetPoint(n, 7, ctrl, 1.0, 10.0, 1.0, 60.0, wall, 0, 0)

    assert TARGETS == {3: 100.0, 30: 25.0}
    assert point(3, "track", 0.5).met is True and point(3, "track", 0.7).met is False
    assert point(30, "track", 2.0).met is True and point(30, "track", 2.5).met is False
    assert point(10, "track", 1.0).met is None and point(3, "nmpc", 1.0).met is None


def _run(
    n: int, wall: float, repeat: int = 1, ctrl: str = "track", host: float = 300.0
) -> FleetPoint:
    """A run of ``n`` drones whose 60 s window took ``wall`` s (speed-up 60 / wall)."""
    return FleetPoint(n, 7, ctrl, 1.0, 10.0, 1.0, 60.0, wall, 0, 0, repeat, host)


def test_the_row_is_the_median_run_with_the_min_and_max_beside_it() -> None:
    runs = [_run(3, 0.5, 1, host=250.0), _run(3, 0.8, 2, host=700.0), _run(3, 0.6, 3)]
    runs += [_run(30, 2.0, 1), _run(30, 3.0, 2)]  # an even number: the slower middle run
    runs += [_run(3, 1.0, 1, "nmpc")]  # one run: min = median = max
    fast, even, one = summarise(runs)
    assert fast.median is runs[2] and fast.runs == tuple(runs[:3])  # 100× of 120×, 100×, 75×
    assert (fast.speedup, fast.min_speedup, fast.max_speedup) == (100.0, 75.0, 120.0)
    assert fast.met is True  # the target check uses the median run: 100× ≥ 100×
    assert even.median is runs[4] and (even.min_speedup, even.max_speedup) == (20.0, 30.0)
    assert even.met is False  # 20× (not the mean 25×) against ≥ 25×
    assert one.median is runs[5] and one.min_speedup == one.speedup == one.max_speedup == 60.0
    page = markdown([fast, even, one], environment(), 10.0, 60.0)
    assert "| 3 | 7 | track | 1.00 | 10.0 | 1.0 | 60.0 | 0.6 | 100.0× | ≥ 100× | yes |" in page
    assert "| 0 | 3 | 75.0-120.0× | 300 |" in page and "| 2 | 20.0-30.0× | 300 |" in page
    assert next(line for line in page.splitlines() if line.startswith("|")) == (
        f"| {' | '.join(HEAD)} |"
    )
    assert len([line for line in page.splitlines() if line.startswith("| ")]) == 5  # head, 3


def test_the_host_speed_reference_is_a_fixed_workload() -> None:
    assert host_workload(5000) == host_workload(5000) != host_workload(5001)
    assert 0.0 < host_speed_ms(1000) < 1000.0


def test_the_command_flies_fleets_and_writes_its_tables(runner: CliRunner, tmp_path: Path) -> None:
    args = ("bench", "fleet", "--sizes", "3,4", "--warmup", "1", "--duration", "2")
    code, out, _ = run(runner, *args, "--out", str(tmp_path))
    assert code == 0, out
    md = (tmp_path / "fleet.md").read_text()
    assert "| 3 | 7 | track |" in md and "| 4 | 10 | track |" in md and "- load: " in md
    assert (tmp_path / "fleet.png").stat().st_size > 1000
    rows = (tmp_path / "fleet.csv").read_text().splitlines()
    assert len(rows) == 3
    for line in rows[1:]:
        cells = line.split(",")
        assert float(cells[5]) == pytest.approx(2.0) and float(cells[6]) > 0  # sim s, wall s
    assert "run 1/1: host speed reference " in out
    # repeated: every run in the CSV, the page's row the median with min-max and host ms
    code, out, _ = run(runner, *args, "--sizes", "3", "--repeat", "2", "--out", str(tmp_path))
    assert code == 0, out
    assert "3 drones, track, run 2/2: host speed reference " in out
    md = (tmp_path / "fleet.md").read_text()
    new, _, earlier = md.partition("## Earlier runs")
    assert "| 4 | 10 | track |" in earlier and "| 4 | 10 | track |" not in new
    row = next(line for line in new.splitlines() if line.startswith("| 3 | 7 | track |"))
    runs, spread, host = row.strip("| ").split(" | ")[-3:]
    assert runs == "2" and float(host) > 0
    lo, hi = (float(x) for x in spread.rstrip("×").split("-"))
    table = [line.split(",") for line in (tmp_path / "fleet.csv").read_text().splitlines()]
    assert table[0] == list(CSV_HEAD) and [r[10] for r in table[1:]] == ["1", "2"]
    speedups = sorted(float(r[7]) for r in table[1:])
    assert (lo, hi) == pytest.approx(speedups, abs=0.051) and all(
        float(r[11]) > 0 for r in table[1:]
    )


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--sizes", "0", "from 1 to 150"),
        ("--sizes", "3,x", "got 'x'"),
        ("--sizes", "", "at least one"),
        ("--controllers", "pid", "unknown controller"),
        ("--duration", "-1", "--duration"),
        ("--repeat", "0", "Invalid value for '--repeat': 0 is not in the range x>=1"),
        ("--repeat", "-2", "Invalid value for '--repeat': -2 is not in the range x>=1"),
    ],
)
def test_bad_options_are_one_clear_message(
    runner: CliRunner, option: str, value: str, message: str
) -> None:
    code, out, err = run(runner, "bench", "fleet", option, value, "--out", "/tmp/never-written")
    assert code == 2
    assert message in out + err and "Traceback" not in out + err
