"""``btmission bench viewer``: a run watched through the live viewer's stream delivers every
task event of its log, poses of every agent, and ends as the run without a viewer does (tiny
fleet; no timing is asserted)."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.bench.synth import environment
from btmission.bench.viewer import (
    LOSSY_KINDS,
    TASK_KINDS,
    ClientStats,
    RunPoint,
    ViewerBenchError,
    ViewerConfig,
    bench_mission,
    check_run,
    log_records,
    markdown,
    run_once,
    wall_at,
    write_csv,
)
from btmission.cli.main import cli
from btmission.runtime.events import read_events

pytestmark = pytest.mark.slow  # runs of 30 agents' floor with a server and readers: make test-slow

pytest.importorskip("uvicorn")
pytest.importorskip("fastapi")

AGENTS, TASKS, DURATION = 6, 12, 30.0


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[RunPoint, Path]]:
    """The same mission without the viewer, with it (two readers), and with a slow reader."""
    mission = bench_mission(AGENTS, TASKS)
    out = {}
    for variant, clients, pause in (("none", 0, 0.0), ("viewer", 2, 0.0), ("slow", 1, 0.2)):
        logs = tmp_path_factory.mktemp(variant)
        point = run_once(mission, variant, DURATION, clients=clients, pause_s=pause, log_dir=logs)
        out[variant] = (point, next(logs.glob("*.jsonl")))
    return out


@pytest.mark.parametrize("variant", ["viewer", "slow"])
def test_readers_get_every_task_event_and_every_agent(
    runs: dict[str, tuple[RunPoint, Path]], variant: str
) -> None:
    point, log = runs[variant]
    events = read_events(log).events
    task_events = [e for e in events if e.kind in TASK_KINDS]
    assert any(e.kind == "task" and e.get("state") == "done" for e in task_events)
    kept = [r for r in log_records(log) if r["ev"] not in LOSSY_KINDS]
    assert point.clients and point.log_task_events == len(task_events)
    for c in point.clients:
        assert c.complete and not c.error
        assert c.task_events() == len(task_events)  # none dropped, none lost on the way
        assert c.kept == kept  # every record but poses and routes, in the log's order
        assert [r["ev"] for r in c.kept][-1] == "end"
        assert set(c.pose_times) == {a.id for a in bench_mission(AGENTS, TASKS).agents}
        assert min(len(ts) for ts in c.pose_times.values()) >= 2  # poses that move on
        assert c.messages > 0 and c.bytes > 0 and c.lags
    assert not {k: n for k, n in point.dropped.items() if k not in LOSSY_KINDS}
    from btmission.runtime.events import Recorder
    from btmission.viz.live import ViewerKinds

    queued = Recorder()  # what the run hands the viewer's queue: the kinds the page draws
    kinds = ViewerKinds(queued)
    for ev in events:
        kinds.on_event(ev)
    assert point.samples > 0
    assert point.delivered == len(queued.events) - sum(point.dropped.values())


def test_the_viewer_changes_nothing_in_the_run(runs: dict[str, tuple[RunPoint, Path]]) -> None:
    base = runs["none"][0]
    assert base.done and not base.clients
    for variant in ("viewer", "slow"):
        point = runs[variant][0]
        assert point.done == base.done  # the same tasks done
        assert point.sim_s == base.sim_s == DURATION
        assert point.log_task_events == base.log_task_events


def test_results_tables(runs: dict[str, tuple[RunPoint, Path]], tmp_path: Path) -> None:
    points = [runs[v][0] for v in ("none", "viewer", "slow")]
    cfg = ViewerConfig(agents=AGENTS, tasks=TASKS, duration_s=DURATION, repeats=1)
    md = markdown(cfg, points, environment(), "btmission bench viewer --agents 6")
    assert "- command: `btmission bench viewer --agents 6`" in md and "- load: " in md
    assert "| no viewer | 1 |" in md and "| viewer, slow reader | 1 |" in md
    assert "No task event was dropped" in md
    write_csv(tmp_path / "viewer.csv", points)
    rows = (tmp_path / "viewer.csv").read_text().splitlines()
    assert rows[0].startswith("repeat,variant,") and len(rows) == 1 + 1 + 2 + 1


def test_check_run_refuses_a_dropped_or_lost_task_event() -> None:
    kept = [{"t": 0.0, "ev": "task", "task": "T0", "state": "open"}, {"t": 1.0, "ev": "end"}]
    reader = ClientStats(kept=list(kept), complete=True)
    point = RunPoint("viewer", 0, 1, 1.0, 1.0, 0.0, (), 1, 2, 0, [reader], {"pose": 5})
    check_run(point, kept)  # superseded poses may go
    point.dropped = {"pose": 5, "task": 1}
    with pytest.raises(ViewerBenchError, match="dropped events that must arrive"):
        check_run(point, kept)
    point.dropped = {}
    reader.kept = kept[1:]
    with pytest.raises(ViewerBenchError, match="1 missing"):
        check_run(point, kept)
    reader.complete = False  # a reader cut off before the end is not compared
    check_run(point, kept)


def test_wall_at_interpolates_the_run_clock() -> None:
    clock = [(0.0, 10.0), (1.0, 10.5), (2.0, 11.5)]
    assert wall_at(clock, 0.5) == pytest.approx(10.25)
    assert wall_at(clock, 1.5) == pytest.approx(11.0)
    assert wall_at(clock, -1.0) == 10.0 and wall_at(clock, 9.0) == 11.5


def test_bench_viewer_command(runner: CliRunner, tmp_path: Path) -> None:
    args = ["--agents", "3", "--duration", "3", "--repeats", "1", "--slow-pause", "0"]
    result = runner.invoke(cli, ["bench", "viewer", *args, "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    md = (tmp_path / "viewer.md").read_text()
    assert "| no viewer | 1 |" in md and "| viewer | 1 |" in md and "slow reader" not in md
    bad = runner.invoke(cli, ["bench", "viewer", "--clients", "0", "--out", str(tmp_path)])
    assert bad.exit_code == 2
