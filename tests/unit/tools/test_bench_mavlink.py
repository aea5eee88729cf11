"""``btmission bench mavlink``: a tiny fleet end to end, its bad options, its CPU burners."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.bench.stress import cpu_burners
from btmission.cli.main import cli


@pytest.mark.slow
def test_a_two_vehicle_run_measures_rates_jitter_and_cpu(tmp_path: Path) -> None:
    result = CliRunner().invoke(
        cli, [*"bench mavlink --vehicles 2 --seconds 1 --no-peer --out".split(), str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    assert "2 vehicle(s) connected in" in result.output
    with (tmp_path / "mavlink.csv").open() as f:
        (row,) = list(csv.DictReader(f))
    assert row["vehicles"] == "2" and row["client"] == "btmission"
    assert 15.0 < float(row["setpoint_rate"]) < 25.0  # 20 Hz asked
    assert 35.0 < float(row["telemetry_rate"]) < 65.0  # 50 Hz asked
    assert 0.0 <= float(row["jitter_p50_ms"]) <= float(row["jitter_p99_ms"]) < 50.0
    assert float(row["cpu_ms_per_vehicle"]) > 0 and float(row["sim_cpu_ms_per_vehicle"]) > 0
    assert 0.0 < float(row["heard_s"]) <= float(row["connect_s"])  # heard, then connected
    md = (tmp_path / "mavlink.md").read_text()
    assert "| btmission | 2 | " in md and "jitter p99 [ms]" in md and "heard [s]" in md


def test_bad_options_exit_2_naming_the_option(tmp_path: Path) -> None:
    for args, want in (
        (["--vehicles", "0"], "--vehicles"),
        (["--vehicles", "101"], "fleet sizes must be 1-100"),
        (["--setpoint-hz", "1"], "PX4's minimum"),
        (["--seconds", "nan"], "--seconds"),
        (["--stress", "-1"], "--stress"),
        (["--stress", "65"], "--stress"),
    ):
        result = CliRunner().invoke(cli, ["bench", "mavlink", *args, "--out", str(tmp_path)])
        assert result.exit_code == 2, (args, result.output)
        assert want in result.output, (args, result.output)
    assert not (tmp_path / "mavlink.md").exists()


def test_cpu_burners_run_and_end_with_the_block() -> None:
    with cpu_burners(2) as pids:
        assert len(pids) == 2
        for pid in pids:
            os.kill(pid, 0)  # alive
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)  # ended and reaped
    with pytest.raises(ValueError, match="CPU burners must be 0-64"):
        with cpu_burners(-1):
            pass
