"""The relocalization benchmark's runner and command (tiny runs; no timing assertions)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from click.testing import CliRunner

import btmission.localization.database as database
from btmission.bench.reloc import CSV_HEADER, run_reloc_benchmark
from tests.reloc_helpers import SIZE, small_database
from tests.system.test_cli import run


@pytest.fixture()
def cached_databases(monkeypatch: pytest.MonkeyPatch) -> None:
    """The benchmark builds the databases of the mines it generates: hand it the session's."""
    monkeypatch.setattr(database, "build_database", lambda vm: small_database(vm.meta["seed"]))


@pytest.mark.slow  # a benchmark end to end (~15 s); `make test-all` runs it
def test_runner_counts_every_scan_and_writes_the_tables(
    tmp_path: Path, cached_databases: None
) -> None:
    lines: list[str] = []
    rows = run_reloc_benchmark(
        (1, 2), poses=5, size=SIZE, robustness=2, out_dir=tmp_path, echo=lines.append
    )
    by = {t.method: t for t in rows}
    assert [t.n for t in rows[:5]] == [5] * 5
    assert by["ours, 5 % dust"].n == by["ours, occluding object"].n == 4
    assert by["ours, scan from another mine"].n == 4
    for t in rows:
        assert t.success + t.wrong + t.not_localised == t.n == len(t.times_ms)
    assert by["descriptor guess only"].not_localised == 0  # peers always answer
    assert by["plain ICP from the identity"].success == 0  # the origin is in rock, far away
    md = (tmp_path / "reloc.md").read_text()
    assert "| ours | 5 |" in md and "by confidence" in md
    with (tmp_path / "reloc.csv").open() as fh:
        table = list(csv.reader(fh))
    assert tuple(table[0]) == CSV_HEADER and len(table) == len(rows) + 1
    assert any(line.startswith("| ours |") for line in lines)


def test_runner_refuses_empty_runs(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="at least one"):
        run_reloc_benchmark((), poses=1, out_dir=tmp_path)


def test_command_help_and_bad_seeds(runner: CliRunner) -> None:
    code, out, _ = run(runner, "bench", "reloc", "--help")
    assert code == 0 and "bench reloc --quick" in out
    code, out, err = run(runner, "bench", "reloc", "--seeds", "a,b")
    assert code == 2 and "comma-separated integers" in out + err
