"""``btmission control plot`` and ``btmission bench control`` (CliRunner; no timing assertions)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.bench.control import CSV_HEADER, PARTS, run_control_benchmark
from btmission.cli.main import cli


def test_plot_writes_an_image(runner: CliRunner, tmp_path: Path) -> None:
    out = tmp_path / "dphr.png"
    result = runner.invoke(cli, ["control", "plot", "dphr", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    svg = tmp_path / "dphr.svg"
    assert runner.invoke(cli, ["control", "plot", "dphr", "-o", str(svg)]).exit_code == 0
    assert "<svg" in svg.read_text(encoding="utf-8")


def test_the_closed_loop_figures_draw_short_runs() -> None:
    """docs/control.md draws the apf, unicycle and compra figures from the full scenarios
    (marked slow there); here the same plotting code draws short runs of the same scenarios."""
    import matplotlib.pyplot as plt

    from btmission.control.examples import corridor_flight, explore_tunnel, head_on
    from btmission.control.plots import FIGURES, plot_corridor, plot_exploration, plot_head_on

    assert {"apf", "unicycle", "compra"} <= set(FIGURES)
    figures = [
        (plot_corridor(corridor_flight(steps=20)), 3),
        (plot_head_on(head_on(steps=20)), 2),
        (plot_exploration(explore_tunnel(mission_time_s=2.0, max_time_s=6.0)), 1),
    ]
    for fig, axes in figures:
        assert len(fig.axes) == axes and all(ax.lines for ax in fig.axes)
        plt.close(fig)


def test_plot_bad_inputs_exit_2(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(cli, ["control", "plot", "dphr", "-o", str(tmp_path / "x.gif")])
    assert result.exit_code == 2
    assert "unknown image type '.gif'" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "x.gif").exists()
    result = runner.invoke(cli, ["control", "plot", "lqr", "-o", str(tmp_path / "x.png")])
    assert result.exit_code == 2 and "'lqr' is not one of" in result.output
    result = runner.invoke(cli, ["control", "plot", "apf"])
    assert result.exit_code == 2 and "Missing option '-o'" in result.output
    assert (
        "btmission control plot apf -o apf.png"
        in runner.invoke(cli, ["control", "plot", "--help"]).output
    )


def test_bench_control_runs_and_writes_tables(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(
        cli, ["bench", "control", "--only", "apf,dphr", "--repeat", "4", "--out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    assert "target apf [30,000-point scan]: median ≤ 1 ms" in result.output
    md = (tmp_path / "control.md").read_text(encoding="utf-8")
    assert "| apf | 30,000-point scan | 4 |" in md and "| dphr | 640×480 depth image | 1 |" in md
    with (tmp_path / "control.csv").open(encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == CSV_HEADER
    assert [r[0] for r in rows[1:]] == ["apf", "dphr"]
    assert all(float(r[3]) > 0 for r in rows[1:])
    # a second run keeps the first one's table under "Earlier runs" (issue 19)
    first_table = md.split("\n| component")[1].split("\n\n")[0]
    result = runner.invoke(
        cli, ["bench", "control", "--only", "apf", "--repeat", "2", "--out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    again = (tmp_path / "control.md").read_text(encoding="utf-8")
    new, _, kept = again.partition("## Earlier runs")
    assert "| apf | 30,000-point scan | 2 |" in new and "| dphr |" not in new
    assert first_table in kept


def test_bench_control_nmpc_compares_both_solvers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import btmission.bench.control as bench

    # the runtime row as configured, but on the SX solver: no 20 s compile in a test
    monkeypatch.setitem(bench.RUNTIME_NMPC, "compiled", False)
    lines: list[str] = []
    rows = run_control_benchmark(["nmpc"], steps=8, out_dir=tmp_path, echo=lines.append)
    assert [(r.component, r.case) for r in rows] == [
        ("nmpc (MAV, N=20)", "fatrop"),
        ("nmpc (MAV, N=20)", "ipopt"),
        ("nmpc (MAV, N=20)", "fatrop, compiled, warm μ (runtime)"),
        ("nmpc (unicycle, N=50)", "fatrop"),
        ("nmpc (unicycle, N=50)", "ipopt"),
        ("nmpc (unicycle, N=50, shelves)", "fatrop"),
    ]
    assert rows[0].runs == 8 and rows[3].runs == 8  # 4 steps × 2 robots
    assert rows[0].met is not None and rows[3].met is None  # targets only for the MAV NMPC
    assert any("0 failed" in line for line in lines)


def test_bench_control_bad_inputs(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(cli, ["bench", "control", "--only", "apf,lqr", "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "unknown part(s) 'apf,lqr'" in result.output and "Traceback" not in result.output
    result = runner.invoke(cli, ["bench", "control", "--steps", "0", "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert not (tmp_path / "control.md").exists()
    with pytest.raises(ValueError, match="unknown part"):
        run_control_benchmark(["lqr"], out_dir=tmp_path)
    assert set(PARTS) == {"nmpc", "apf", "dphr"}


def test_bench_script_uses_the_same_runner(tmp_path: Path) -> None:
    import runpy

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_control.py"
    main = runpy.run_path(str(script))["main"]
    assert main(["--only", "apf", "--repeat", "2", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "control.csv").exists()
    with pytest.raises(SystemExit) as exc:
        main(["--only", "lqr"])
    assert exc.value.code == 2


def test_control_modules_import_heavy_libraries_lazily() -> None:
    """casadi only when an NMPC is built, matplotlib only when a figure is drawn."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import btmission.cli.main, btmission.control.apf, btmission.control.dphr\n"
        "import btmission.control.compra, btmission.control.nmpc, btmission.control.examples\n"
        "import btmission.bench.control\n"
        "heavy = [m for m in ('casadi', 'matplotlib') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
