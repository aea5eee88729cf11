"""``btmission bench startup``: cases timed round-robin, medians against the targets, files."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from click.testing import CliRunner

from btmission.bench.startup import CASES, Case, Sample, case_env, measure, rows
from tests.system.test_cli import run


def test_cases_are_timed_round_robin_after_a_warm_up_and_judged_by_their_median(
    tmp_path: Path,
) -> None:
    calls: list[str] = []
    fake = {"a": [9.0, 1.0, 2.0, 3.0], "b": [9.0, 0.1, 0.3, 0.2]}
    caches: set[str | None] = set()

    def clock(argv: Sequence[str], env: Mapping[str, str]) -> Sample:
        calls.append(argv[0])
        caches.add(env.get("PYTHONPYCACHEPREFIX"))
        wall = fake[argv[0]].pop(0)
        return Sample(wall, wall / 2)

    cases = [Case("A", ("a",), 1.5), Case("B", ("b",), 0.25)]
    timings = measure(cases, 3, clock, tmp_path)
    assert calls == ["a", "b"] * 4  # one warm-up each, then alternating
    assert caches == {str(tmp_path)}  # one bytecode cache, which the warm-up fills
    assert [t.times_s for t in timings] == [(1.0, 2.0, 3.0), (0.1, 0.3, 0.2)]
    assert rows(timings) == [
        ["A", "2.000", "1.000", "≤ 1.5", "no", "1.000"],
        ["B", "0.200", "0.100", "≤ 0.25", "yes", "0.100"],
    ]


def test_runs_have_a_bytecode_cache_unless_the_case_says_otherwise(tmp_path: Path) -> None:
    base = {"PATH": "/bin", "PYTHONDONTWRITEBYTECODE": "1", "PYTHONPYCACHEPREFIX": "/elsewhere"}
    cached = case_env(Case("c", ("-c", "pass")), tmp_path, base)
    assert cached == {"PATH": "/bin", "PYTHONPYCACHEPREFIX": str(tmp_path)}
    compiled = case_env(Case("s", ("-c", "pass"), bytecode=False), tmp_path, base)
    assert compiled == {"PATH": "/bin", "PYTHONDONTWRITEBYTECODE": "1"}
    assert [c.bytecode for c in CASES].count(False) == 1  # the last row, for earlier runs


def test_the_issue_targets_are_the_cases_targets() -> None:
    targets = {c.name: c.target_s for c in CASES}
    assert targets["btmission --help"] == 0.15
    assert targets["btmission validate missions/mine_inspection.yaml"] == 0.5
    assert CASES[0].argv == ("-c", "pass")  # the interpreter alone is the peer row


def test_the_command_times_real_runs_and_writes_its_tables(
    runner: CliRunner, tmp_path: Path
) -> None:
    code, out, _ = run(runner, "bench", "startup", "--repeat", "1", "--out", str(tmp_path))
    assert code == 0, out
    md = (tmp_path / "startup.md").read_text()
    assert "| btmission --help |" in md and "- load: " in md
    csv_rows = (tmp_path / "startup.csv").read_text().splitlines()
    assert csv_rows[0] == "command,median_s,best_s,target_s,cpu_median_s,run0"
    assert len(csv_rows) == 1 + len(CASES)
    for line in csv_rows[1:]:
        cpu, wall = (float(x) for x in line.rsplit(",", 2)[1:])
        assert wall > 0 and cpu > 0  # measured times, not placeholders
    # a second run keeps the first one's table under "Earlier runs"
    code, _, _ = run(runner, "bench", "startup", "--repeat", "1", "--out", str(tmp_path))
    page = (tmp_path / "startup.md").read_text()
    assert code == 0 and page.count("| btmission --help |") == 2
    assert page.index("## Earlier runs") > page.index("| btmission --help |")
    code, _, err = run(runner, "bench", "startup", "--repeat", "0", "--out", str(tmp_path))
    assert code == 2 and "--repeat" in err
