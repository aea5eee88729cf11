"""The transport benchmark's code path on a tiny size (no timing asserts), its options, and its
clear error without eclipse-zenoh."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.bench.transport import (
    CSV_HEADER,
    Layout,
    TransportBenchConfig,
    measure_in_memory,
    measure_zenoh,
    message_sizes,
    run_transport_benchmark,
    with_earlier_runs,
)
from btmission.cli.main import cli
from tests.zenoh_helpers import need_zenoh

TINY = TransportBenchConfig(sizes=((3, 6),), rounds=4, warmup=1, timeout_s=30.0)


def test_layouts_parse_and_say_what_they_are() -> None:
    assert Layout.parse("1:each") == Layout(1, False)
    assert Layout.parse("2:shared").label == "2:shared"
    assert Layout.parse("thread:each") == Layout(0, False)
    for bad in ("each", "0:each", "x:each", "1:some", "-1:each"):
        with pytest.raises(ValueError, match="is not a layout"):
            Layout.parse(bad)
    assert Layout(2, True).describe(50) == "agents in 2 process(es), one session per process"
    with pytest.raises(ValueError):
        TransportBenchConfig(layouts=())


def test_in_memory_rounds_and_message_sizes() -> None:
    point, times = measure_in_memory(3, 6, TINY)
    assert point.rounds == 4 and point.transport == "in-memory" and point.rate_hz > 0
    assert len(times.assignments) == 3 and all(len(a) == 3 for a in times.assignments)
    sizes = message_sizes(3, 6, TINY)
    assert sizes == point.sizes and 0 < sizes.status < sizes.bid < sizes.announcement
    assert sizes.assignment > sizes.announcement > sizes.assignment_named


@pytest.mark.slow
def test_the_benchmark_runs_end_to_end_on_a_tiny_size(tmp_path: Path) -> None:
    """Both transports, the agents in a process of their own and in a thread, same assignments
    as in memory; the tables are written."""
    need_zenoh()
    cfg = TransportBenchConfig(
        sizes=((3, 6),), rounds=4, warmup=1, timeout_s=30.0,
        layouts=(Layout(1, False), Layout(2, True), Layout(0, False)),
    )  # fmt: skip
    lines: list[str] = []
    b = run_transport_benchmark(cfg, tmp_path, echo=lines.append)
    assert [(p.transport, p.layout) for p in b.points] == [
        ("in-memory", "—"), ("zenoh", "1:each"), ("zenoh", "2:shared"), ("zenoh", "thread:each"),
    ]  # fmt: skip
    for p in b.points[1:]:
        assert p.same_assignments is True and p.rounds == 4 and p.bytes_per_round > 0
    assert b.points[1].agents_cpu_ms is not None and b.points[3].agents_cpu_ms is None
    md = (tmp_path / "transport.md").read_text()
    assert "| zenoh | 2:shared | 3 | 6 | 4 |" in md and "## Message sizes" in md
    assert "not measured in this run" in md  # the 50x400 target needs that size
    rows = list(csv.reader((tmp_path / "transport.csv").read_text().splitlines()))
    assert tuple(rows[0]) == CSV_HEADER and len(rows) == 5
    assert any(line.startswith("wrote ") for line in lines)


def _page(date: str, rate: str, version: int = 2) -> str:
    return (
        f"# Transport\n\n- date: {date}\n- load: quiet\n\n(`btmission.links.wire`, "
        f"v{version})\n\n| transport | rate Hz |\n| --- | ---: |\n| zenoh | {rate} |\n\n"
        "## Target\n\nRegenerate with `btmission bench transport`.\n"
    )


def test_a_new_page_keeps_the_earlier_runs_main_tables_newest_first() -> None:
    first = _page("day 1", "27", 1)
    assert with_earlier_runs(first, None) == first
    second = with_earlier_runs(_page("day 2", "47"), first)
    third = with_earlier_runs(_page("day 3", "52"), second)
    assert third.startswith(_page("day 3", "52").rstrip())
    earlier = third.split("## Earlier runs", 1)[1]
    assert third.count("## Earlier runs") == 1
    assert earlier.index("### day 2 (wire format 2)") < earlier.index("### day 1 (wire format 1)")
    assert "| zenoh | 47 |" in earlier and "| zenoh | 27 |" in earlier
    assert "| zenoh | 52 |" not in earlier and earlier.count("- load: quiet") == 2


@pytest.mark.slow
def test_measure_zenoh_with_a_shared_session(tmp_path: Path) -> None:
    need_zenoh()
    ref = measure_in_memory(4, 8, TINY)[1]
    p = measure_zenoh(4, 8, TINY, Layout(1, True), ref)
    assert p.same_assignments is True and p.layout == "1:shared"


def test_bad_options_are_exit_2(tmp_path: Path) -> None:
    runner = CliRunner()
    for args, message in (
        (["--sizes", "3"], "is not AGENTSxTASKS"),
        (["--layouts", "1:many"], "is not a layout"),
        (["--rounds", "0"], "0 is not in the range"),
        (["--timeout", "0"], "--timeout"),
    ):
        result = runner.invoke(cli, ["bench", "transport", *args, "--out", str(tmp_path / "r")])
        assert result.exit_code == 2, (args, result.output)
        assert message in result.output and "Traceback" not in result.output
    assert not (tmp_path / "r").exists()


def test_without_zenoh_the_command_says_how_to_install_it(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setitem(sys.modules, "zenoh", None)
    import btmission.transport.zenoh_session as zs

    monkeypatch.setattr(zs, "zenoh_available", lambda: False)
    result = CliRunner().invoke(cli, ["bench", "transport", "--out", str(tmp_path / "r")])
    assert result.exit_code == 2, result.output
    assert "pip install 'btmission[net]'" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "r").exists()
