"""``btmission bench sim`` runs and writes its tables (tiny sizes: speed is not asserted)."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.bench.sim import scale_mission_text
from btmission.cli.main import cli
from btmission.missions import load_mission_text

ROOT = Path(__file__).resolve().parents[3]


@pytest.mark.slow  # a benchmark end to end (~13 s); `make test-all` runs it
def test_bench_sim_writes_its_tables(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(
        cli,
        [
            "bench",
            "sim",
            "--controllers",
            "track",
            "--scale",
            "4x12",
            "--duration",
            "2",
            "--out",
            str(tmp_path),
        ],
    )
    assert result.exit_code == 0, result.output
    md = (tmp_path / "sim.md").read_text()
    assert "| track |" in md and "7/7" in md and "| 4 × 12 |" in md
    rows = (tmp_path / "sim.csv").read_text().splitlines()
    assert rows[0].startswith("kind,") and len(rows) == 3


def test_bench_sim_rejects_bad_options(runner: CliRunner, tmp_path: Path) -> None:
    for args in (["--controllers", "pid"], ["--scale", "50by400"], ["--scale", "0x3"]):
        result = runner.invoke(cli, ["bench", "sim", *args, "--out", str(tmp_path)])
        assert result.exit_code == 2, (args, result.output)


def test_the_scaling_mission_is_valid() -> None:
    m = load_mission_text(scale_mission_text(5, 20, 0.3, seed=1), "scale.yaml")
    assert len(m.agents) == 5 and len(m.tasks) == 20
    assert m.spec.coordination.participation == 0.3


def test_the_scaling_point_alone_keeps_the_earlier_runs(runner: CliRunner, tmp_path: Path) -> None:
    """`--controllers ''` measures the scaling point alone; the page says the mission was not
    measured and keeps the previous page (its numbers) under "Earlier runs"."""
    (tmp_path / "sim.md").write_text("# Simulator benchmark\n\n| track | 1.00 | 36.5× |\n")
    args = ["bench", "sim", "--controllers", "", "--scale", "3x6", "--duration", "1"]
    result = runner.invoke(cli, [*args, "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    md = (tmp_path / "sim.md").read_text()
    new, _, earlier = md.partition("## Earlier runs")
    assert "| 3 × 6 |" in new and "Not measured in this run (`--controllers ''`)" in new
    assert "| track | 1.00 | 36.5× |" in earlier


def test_the_solver_ceiling_is_simulated_time_over_solver_cpu_per_core() -> None:
    """The NMPC row's ceiling: 420 simulated s whose solves took 40 CPU s on 2 cores allow at
    most 21×; the tracking controller's row has no solver and shows a dash."""
    from btmission.bench.sim import MissionPoint, _mission_cells

    nmpc = MissionPoint("nmpc", 3.0, 420.0, 42.0, 7, 7, 0, "completed", 40.0, 2)
    assert nmpc.solver_ceiling == pytest.approx(21.0)
    assert _mission_cells(nmpc)[-2:] == ["40.0", "21.0×"]
    track = MissionPoint("track", 3.0, 440.0, 5.0, 7, 7, 0, "completed")
    assert _mission_cells(track)[-2:] == ["–", "–"]
