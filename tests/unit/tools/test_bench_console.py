"""``btmission bench console``: the benchmark's runs on a tiny setting (a short mine run, a small
flood): every add the console accepted is in the run's log, refused adds never reach the run, an
idle console changes nothing, and the tables have their rows (no timing is asserted)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.bench.console import (
    FLOOD_CLIENT,
    RUNS_HEAD,
    SUMMARY_HEAD,
    VARIANTS,
    ConsoleBenchError,
    ConsoleConfig,
    FloodSpec,
    LoadLog,
    Request,
    RunPoint,
    add_bodies,
    check_adds,
    load_bench_mission,
    markdown,
    mission_map,
    percentiles,
    run_once,
    sim_at,
    write_csv,
)
from btmission.bench.synth import environment
from btmission.cli.main import cli
from btmission.runtime.events import read_events

pytestmark = pytest.mark.slow  # runs with a server and three client processes: make test-slow

pytest.importorskip("uvicorn")
pytest.importorskip("fastapi")

MISSION = Path(__file__).resolve().parents[3] / "missions" / "mine_inspection.yaml"
DURATION = 40.0
"""Simulated seconds: about a wall second unpaced, a few under the flood."""


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[RunPoint, Path]]:
    """The mine for DURATION s in each variant, with a small flood."""
    mission = load_bench_mission(MISSION)
    good, bad, _ = add_bodies(mission, mission_map(mission))
    out = {}
    for variant in VARIANTS:
        spec = FloodSpec(
            burst=120,
            adds=30,
            threads=4,
            every_s=0.5,
            add_body=bad if variant == "refused" else good,
        )
        logs = tmp_path_factory.mktemp(variant)
        point = run_once(mission, variant, DURATION, controller="track", spec=spec, log_dir=logs)
        out[variant] = (point, next(logs.glob("*.jsonl")))
    return out


def flood_adds_in_log(log: Path) -> list[str]:
    return [
        str(e.get("task"))
        for e in read_events(log).events
        if e.kind == "task_added" and str(e.get("by", "")).startswith(f"{FLOOD_CLIENT}@")
    ]


def test_every_accepted_add_is_in_the_log(runs: dict[str, tuple[RunPoint, Path]]) -> None:
    point, log = runs["flood"]
    assert point.flood is not None and point.flood.bursts
    adds = [r for r in point.flood.requests if r.kind == "add"]
    accepted = [r.task for r in adds if r.status == 201]
    assert accepted, Counter(r.status for r in adds)  # the flood added tasks
    assert len(set(accepted)) == len(accepted)  # each its own id
    logged = flood_adds_in_log(log)
    assert set(accepted) <= set(logged)
    assert set(logged) <= {r.task for r in adds if r.status in (201, 202)}
    assert point.logged_adds == len(logged)
    assert point.tasks == len(load_bench_mission(MISSION).tasks) + len(logged)
    codes = point.statuses()
    assert set(codes) <= {200, 201, 202, 409, 429}, codes
    assert codes[200] and all(r.task == "" for r in point.flood.requests if r.kind == "status")


def test_refused_adds_never_reach_the_run(runs: dict[str, tuple[RunPoint, Path]]) -> None:
    point, log = runs["refused"]
    assert point.flood is not None
    adds = Counter(r.status for r in point.flood.requests if r.kind == "add")
    assert adds[422] and set(adds) <= {409, 422, 429}, adds  # 409: the pool is full
    assert flood_adds_in_log(log) == [] and point.logged_adds == 0
    assert point.done == runs["viewer"][0].done
    assert point.tasks == len(load_bench_mission(MISSION).tasks)


def test_an_idle_console_changes_nothing(runs: dict[str, tuple[RunPoint, Path]]) -> None:
    base, idle = runs["viewer"][0], runs["idle"][0]
    assert base.poll is None and base.flood is None  # the viewer only: nothing polls
    assert idle.poll is not None and idle.poll.requests and idle.flood is None
    assert {r.status for r in idle.poll.requests} == {200}
    assert idle.done == base.done and idle.sim_s == base.sim_s == DURATION


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_the_stream_reader_saw_the_whole_run(
    runs: dict[str, tuple[RunPoint, Path]], variant: str
) -> None:
    point = runs[variant][0]
    assert point.reader is not None and point.reader.complete and not point.reader.error
    assert not {k: n for k, n in point.dropped.items() if k not in ("pose", "route")}
    assert point.clock[0][0] == 0.0 and point.clock[-1][0] == DURATION
    if point.cpu_s:  # Linux: the threads' CPU time
        assert set(point.cpu_s) == {"run", "server", "viewer"} and point.cpu_s["run"] > 0


def test_results_tables(runs: dict[str, tuple[RunPoint, Path]], tmp_path: Path) -> None:
    points = [runs[v][0] for v in VARIANTS]
    cfg = ConsoleConfig(mission=str(MISSION), duration_s=DURATION, pairs=1, burst=120, adds=30)
    md = markdown(cfg, points, environment(), "btmission bench console --pairs 1", "inside rock")
    assert "- command: `btmission bench console --pairs 1`" in md and "- load: " in md
    assert "**Checked in every run:**" in md
    lines = md.splitlines()
    head = lines.index("| " + " | ".join(SUMMARY_HEAD) + " |")
    rows = [ln for ln in lines[head + 2 : head + 2 + len(VARIANTS)]]
    assert [r.split(" | ")[0][2:] for r in rows] == list(VARIANTS.values())
    assert all(r.count(" | ") == len(SUMMARY_HEAD) - 1 for r in rows)
    assert "| console, idle | 1 |" in md and "| viewer only | 1 |" in md
    runs_head = lines.index("| " + " | ".join(RUNS_HEAD) + " |")
    assert lines[runs_head + 2].startswith("| 1 | viewer only |")
    assert len([ln for ln in lines[runs_head + 2 :] if ln.startswith("| ")]) == len(points)
    write_csv(tmp_path / "console.csv", points)
    csv_rows = (tmp_path / "console.csv").read_text().splitlines()
    assert csv_rows[0].startswith("repeat,variant,sim_s,wall_s,speed,drop,")
    assert len(csv_rows) == 1 + len(points)


def _point(variant: str, adds: list[tuple[int, str]], logged: int = 0) -> RunPoint:
    flood = LoadLog([Request("add", 0, 0.0, 0.01, status, task) for status, task in adds])
    return RunPoint(variant, 0, 1.0, 1.0, 0.0, (), 0, flood=flood, logged_adds=logged)


def test_check_adds_refuses_what_breaks_a_promise() -> None:
    check_adds(_point("flood", [(201, "T8"), (429, ""), (202, "T9")]), ["T8", "T9"])
    check_adds(_point("flood", [(201, "T8"), (0, "")]), ["T8", "T9"])  # T9: its answer was lost
    with pytest.raises(ConsoleBenchError, match="answered 201 are not in the log: T9"):
        check_adds(_point("flood", [(201, "T8"), (201, "T9")]), ["T8"])
    with pytest.raises(ConsoleBenchError, match="were not answered 201 or 202: T9"):
        check_adds(_point("flood", [(201, "T8")]), ["T8", "T9"])
    with pytest.raises(ConsoleBenchError, match="5xx"):
        check_adds(_point("flood", [(500, "")]), [])
    check_adds(_point("refused", [(422, ""), (429, "")]), [])
    with pytest.raises(ConsoleBenchError, match="should refuse"):
        check_adds(_point("refused", [(201, "T8")]), ["T8"])


def test_add_bodies_on_rock_and_on_a_floor() -> None:
    mine = load_bench_mission(MISSION)
    good, bad, what = add_bodies(mine, mission_map(mine))
    assert good == {"type": "inspect", "location": [64.4, 9.6, 2.5]}  # T1's, no id
    assert what == "inside rock" and mission_map(mine).state_at(bad["location"]) == 1
    _, bad, what = add_bodies(mine, mission_map(mine), "outside")
    assert what == "outside the map" and mission_map(mine).state_at(bad["location"]) is None
    floor = load_bench_mission(None, 2, 3)
    good, bad, what = add_bodies(floor, mission_map(floor))
    assert what == "outside the map" and mission_map(floor).state_at(bad["location"]) is None


def test_sim_at_and_percentiles() -> None:
    clock = [(0.0, 10.0), (1.0, 10.5), (2.0, 11.5)]
    assert sim_at(clock, 10.25) == pytest.approx(0.5)
    assert sim_at(clock, 11.0) == pytest.approx(1.5)
    assert sim_at(clock, 9.0) == 0.0 and sim_at(clock, 20.0) == 2.0
    assert percentiles([]) is None
    assert percentiles([float(i) for i in range(1, 101)]) == (50.5, 99.0)


def test_bench_console_command(runner: CliRunner, tmp_path: Path) -> None:
    args = ["--seconds", "20", "--pairs", "1", "--flood", "refused", "--burst", "60"]
    args += ["--burst-adds", "10", "--threads", "4", "--every", "0.5"]
    result = runner.invoke(cli, ["bench", "console", *args, "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    md = (tmp_path / "console.md").read_text()
    assert "| viewer only | 1 |" in md and "| console, flood (refused adds) | 1 |" in md
    assert "valid adds) | 1 |" not in md
    assert len((tmp_path / "console.csv").read_text().splitlines()) == 1 + 3
    bad = runner.invoke(cli, ["bench", "console", "--burst", "10", "--burst-adds", "20"])
    assert bad.exit_code == 2 and "--burst-adds" in bad.output
    missing = runner.invoke(cli, ["bench", "console", "--mission", str(tmp_path / "no.yaml")])
    assert missing.exit_code == 2 and "--mission" in missing.output
    help_text = runner.invoke(cli, ["bench", "console", "--help"]).output
    assert "btmission bench console --seconds" in help_text  # the example
