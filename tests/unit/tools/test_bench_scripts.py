"""The shared benchmark plumbing: ``benchmarks/bench_<name>.py`` scripts run the
``btmission bench <name>`` command (same options and exit statuses; results next to the script by
default), and ``bench synth --shapes`` / bad ``--sizes`` are clear errors (exit 2)."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.cli.bench_cmds import bench, script_main
from btmission.cli.main import cli

ROOT = Path(__file__).resolve().parents[3]
SCRIPTED = (
    "auction",
    "console",
    "control",
    "fleet",
    "planner",
    "reloc",
    "sim",
    "startup",
    "synth",
    "transport",
    "viewer",
)


@pytest.mark.parametrize("name", SCRIPTED)
def test_every_script_is_its_bench_command(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    main = runpy.run_path(str(ROOT / "benchmarks" / f"bench_{name}.py"))["main"]
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"Usage: bench_{name}.py [OPTIONS]")
    for param in bench.commands[name].params:
        assert param.opts[0] in out  # every option of the command, e.g. --out
    with pytest.raises(SystemExit) as exc:
        main(["--no-such-option"])
    assert exc.value.code == 2


def test_script_results_default_next_to_the_script(tmp_path: Path) -> None:
    script = tmp_path / "bench_synth.py"
    assert script_main("synth", str(script), ["--sizes", "3", "--repeat", "1"]) == 0
    assert (tmp_path / "results" / "synth.md").exists()
    assert (tmp_path / "results" / "synth.csv").exists()
    elsewhere = tmp_path / "elsewhere"
    args = ["--sizes", "3", "--repeat", "1", "--shapes", "diamond", f"--out={elsewhere}"]
    assert script_main("synth", str(script), args) == 0
    assert "| diamond |" in (elsewhere / "synth.md").read_text()


def test_bench_synth_shapes_and_bad_values(runner: CliRunner, tmp_path: Path) -> None:
    args = ["--sizes", "4", "--repeat", "1", "--shapes", "fanin,diamond", "--out", str(tmp_path)]
    result = runner.invoke(cli, ["bench", "synth", *args])
    assert result.exit_code == 0, result.output
    shapes = {r.split(",")[0] for r in (tmp_path / "synth.csv").read_text().splitlines()[1:]}
    assert shapes == {"fanin", "diamond"}
    for args, message in (
        (["--shapes", "ring"], "unknown shape(s) 'ring' (choose from chain, fanin, diamond)"),
        (["--shapes", ","], "unknown shape(s) ','"),
        (["--sizes", "0"], "expected positive integers, got '0'"),
        (["--sizes", ""], "expected positive integers, got ''"),
    ):
        result = runner.invoke(cli, ["bench", "synth", *args, "--out", str(tmp_path / "no")])
        assert result.exit_code == 2, (args, result.output)
        assert message in result.stderr and "Traceback" not in result.output
        assert not (tmp_path / "no").exists()


@pytest.mark.parametrize("name", ["planner", "reloc"])
def test_a_mine_too_small_is_a_clear_error(name: str, runner: CliRunner, tmp_path: Path) -> None:
    r = runner.invoke(cli, ["bench", name, "--size", "30", "20", "4", "--out", str(tmp_path)])
    assert r.exit_code == 2 and "--size: a mine needs at least 40 × 30 × 6 m" in r.output
    assert "Traceback" not in r.output


def test_bench_planner_on_a_small_mine_replans_where_it_can(
    runner: CliRunner, tmp_path: Path
) -> None:
    """On a small mine the path is short: the replanning rows leave out the positions where the
    2 m cube would bury the agent or the goal, instead of failing."""
    args = ["--size", "60", "40", "6", "--repeat", "1", "--queries", "2", "--no-peers"]
    r = runner.invoke(cli, ["bench", "planner", *args, "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    table = (tmp_path / "planner.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| replan (")]
    assert len(rows) == 2 and all("MISMATCH" not in row for row in rows)
    assert "| one-to-all while the caller keeps the previous field |" in table
    # a second run keeps the first one's table under "Earlier runs"
    r = runner.invoke(cli, ["bench", "planner", *args, "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    again = (tmp_path / "planner.md").read_text()
    assert again.count("| metric |") == 2 and "## Earlier runs" in again
