"""``btmission dispatch`` and ``btmission bench dispatch`` through CliRunner."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.cli.main import cli
from btmission.spec.topomap import load_topomap


def run(runner: CliRunner, *args: str) -> tuple[int, str, str]:
    r = runner.invoke(cli, list(args))
    assert "Traceback" not in r.output + r.stderr, r.output + r.stderr
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        raise r.exception
    return r.exit_code, r.stdout, r.stderr


@pytest.mark.parametrize(
    "args",
    [["dispatch"], ["dispatch", "static"], ["dispatch", "dynamic"], ["dispatch", "plan"],
     ["dispatch", "map"], ["bench", "dispatch"]],
)  # fmt: skip
def test_dispatch_commands_have_help_with_an_example(runner: CliRunner, args: list[str]) -> None:
    code, out, _ = run(runner, *args, "--help")
    assert code == 0 and ("btmission dispatch" in out or "btmission bench dispatch" in out)


def test_map_export_roundtrips(runner: CliRunner, tmp_path: Path) -> None:
    out = tmp_path / "mine.yaml"
    code, _, err = run(runner, "dispatch", "map", "mine", "-o", str(out))
    assert code == 0 and "7 terminals" in err and "loop-free" in err
    assert load_topomap(out).n == 25
    code, _, _ = run(runner, "dispatch", "map", str(out), "-o", str(tmp_path / "m.png"))
    assert code == 0 and (tmp_path / "m.png").read_bytes()[:4] == b"\x89PNG"


def test_bad_map_file_exit_2_with_location(runner: CliRunner, tmp_path: Path) -> None:
    f = tmp_path / "loop.yaml"
    f.write_text(
        "topomap: loop\nversion: 1\nnodes:\n  A: {kind: terminal}\n  B: {kind: transit}\n"
        "  C: {kind: transit}\nsegments:\n  - {from: A, to: B, time: 1}\n"
        "  - {from: B, to: C, time: 1}\n  - {from: C, to: B, time: 1}\n"
    )
    code, _, err = run(runner, "dispatch", "map", str(f))
    assert code == 2 and f"{f}:10:" in err and "given twice" in err
    code, _, err = run(runner, "dispatch", "static", "--map", "nowhere.yaml")
    assert code == 2 and "no map 'nowhere.yaml'" in err and "static_npr" in err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--vehicles", "3"], "even number of vehicles"),
        (["--vehicles", "2,x"], "comma-separated integers"),
        (["--vehicles", "14"], "need 7 on each side"),
        (["--budget", "-1"], "budget must be >= 0"),
    ],
)
def test_static_bad_input_exit_2(runner: CliRunner, args: list[str], message: str) -> None:
    code, _, err = run(runner, "dispatch", "static", "--map", "static_npr", "--runs", "1", *args)
    assert code == 2 and message in err


def test_static_prints_ga_and_push_and_swap_and_a_gantt(runner: CliRunner, tmp_path: Path) -> None:
    png = tmp_path / "g.png"
    code, out, _ = run(
        runner, "dispatch", "static", "--map", "static_spr", "--vehicles", "2,4", "--runs", "2",
        "--budget", "0.3", "--gantt", str(png),
    )  # fmt: skip
    assert code == 0, out
    rows = [line for line in out.splitlines() if line.startswith("| static_spr")]
    assert len(rows) == 4 and {r.split("|")[2].strip() for r in rows} == {"GA", "push-and-swap"}
    assert "Σ (%)" in out and "mean r" in out and "σ(ξ)" in out
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_dynamic_prints_table_6_columns(runner: CliRunner, tmp_path: Path) -> None:
    code, out, _ = run(
        runner, "dispatch", "dynamic", "--vehicles", "2", "--hours", "0.3", "--budget", "0.05",
        "--generations", "40", "--gantt", str(tmp_path / "d.png"),
    )  # fmt: skip
    assert code == 0, out
    assert "| vehicles | runs | C | i_t | i_p |" in out
    row = next(line for line in out.splitlines() if line.startswith("| 2 |"))
    assert "±" in row
    assert (tmp_path / "d.png").exists()
    assert "not settled" not in out
    code, out, _ = run(
        runner, "dispatch", "dynamic", "--map", "mine_table6", "--vehicles", "2", "--hours",
        "0.2", "--budget", "0.05", "--generations", "20", "--no-settle",
    )  # fmt: skip
    assert code == 0, out
    assert "map mine_table6" in out and "plans not settled" in out


def test_dynamic_bad_map_exit_2(runner: CliRunner) -> None:
    code, _, err = run(runner, "dispatch", "dynamic", "--map", "static_npr", "--hours", "0.1")
    assert code == 2 and "exactly one prioritized terminal" in err


def test_plan_and_its_bad_input(runner: CliRunner, tmp_path: Path) -> None:
    code, out, _ = run(
        runner, "dispatch", "plan", "--map", "mine", "--vehicle", "L1n:O", "--vehicle", "O:L2s",
        "--budget", "0.3", "-o", str(tmp_path / "p.png"),
    )  # fmt: skip
    assert code == 0 and "v1 (prioritized): L1n" in out and "feasible" in out
    code, _, err = run(runner, "dispatch", "plan", "--map", "mine", "--vehicle", "L1n-O")
    assert code == 2 and "expected START:END" in err
    code, _, err = run(runner, "dispatch", "plan", "--map", "mine", "--vehicle", "L9:O")
    assert code == 2 and "no node 'L9'" in err


def test_bench_dispatch_writes_results(runner: CliRunner, tmp_path: Path) -> None:
    code, out, _ = run(
        runner, "bench", "dispatch", "--vehicles", "2", "--runs", "1", "--tau", "0.1",
        "--out", str(tmp_path),
    )  # fmt: skip
    assert code == 0, out
    assert "evaluations/s" in out
    with (tmp_path / "dispatch.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert {(r["map"], r["method"]) for r in rows} == {
        ("static_npr", "GA"), ("static_npr", "push-and-swap"),
        ("static_spr", "GA"), ("static_spr", "push-and-swap"),
    }  # fmt: skip
    assert "evaluations/s" in (tmp_path / "dispatch.md").read_text()


def test_bench_dispatch_dynamic_writes_results(runner: CliRunner, tmp_path: Path) -> None:
    code, out, _ = run(
        runner, "bench", "dispatch-dynamic", "--vehicles", "2", "--runs", "1", "--hours", "0.2",
        "--budget", "0.05", "--out", str(tmp_path),
    )  # fmt: skip
    assert code == 0, out
    first = (tmp_path / "dispatch_dynamic.md").read_text()
    assert "| 2 | 1 |" in out and "Table 6" in first and "Map `mine_table6`" in first
    assert "Earlier runs" not in first
    # a second run keeps the first one's table below its own, and so on
    for _ in range(2):
        code, out, _ = run(
            runner, "bench", "dispatch-dynamic", "--vehicles", "2", "--runs", "1", "--hours",
            "0.1", "--budget", "0.05", "--map", "mine", "--out", str(tmp_path),
        )  # fmt: skip
        assert code == 0, out
    text = (tmp_path / "dispatch_dynamic.md").read_text()
    head, _, earlier = text.partition("## Earlier runs")
    assert "Map `mine` " in head and text.count("## Earlier runs") == 1
    assert earlier.count("### Run before this one") == 2 and "Map `mine_table6`" in earlier
    assert earlier.count("| vehicles | runs |") == 2
    code, _, err = run(runner, "bench", "dispatch", "--vehicles", "x", "--out", str(tmp_path))
    assert code == 2 and "comma-separated integers" in err
