"""``btmission bench fleet``: the fleet missions, a real timed run, the files, bad options."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.bench.fleet import TARGETS, FleetPoint, fleet_mission_text
from btmission.spec.mission import load_mission_text
from btmission.world.checks import check_mission_world
from tests.test_cli import run


@pytest.mark.parametrize("drones", [3, 30, 100])
def test_a_fleet_mission_is_valid_and_has_the_field_missions_ratio(drones: int) -> None:
    m = load_mission_text(fleet_mission_text(drones), "fleet.yaml")
    agents, tasks = m.spec.agents, m.spec.tasks
    assert len(agents) == drones and len(tasks) == math.ceil(7 * drones / 3)
    starts = [a.start for a in agents]
    assert min(math.dist(a, b) for i, a in enumerate(starts) for b in starts[i + 1 :]) >= 2.0
    # every start and task lies in open space the drones can reach (the mission checks)
    assert [d for d in check_mission_world(m) if d.severity.value == "error"] == []
    assert fleet_mission_text(drones) == fleet_mission_text(drones)  # deterministic
    assert fleet_mission_text(drones, seed=1) != fleet_mission_text(drones)


def test_a_fleet_too_big_for_the_mine_is_refused() -> None:
    with pytest.raises(ValueError, match="room for"):
        fleet_mission_text(400)


def test_targets_apply_to_the_tracking_controller_only() -> None:
    def point(n: int, ctrl: str, wall: float) -> FleetPoint:
        return FleetPoint(n, 7, ctrl, 1.0, 10.0, 1.0, 60.0, wall, 0, 0)

    assert TARGETS == {3: 100.0, 30: 25.0}
    assert point(3, "track", 0.5).met is True and point(3, "track", 0.7).met is False
    assert point(30, "track", 2.0).met is True and point(30, "track", 2.5).met is False
    assert point(10, "track", 1.0).met is None and point(3, "nmpc", 1.0).met is None


def test_the_command_flies_fleets_and_writes_its_tables(runner: CliRunner, tmp_path: Path) -> None:
    args = ("bench", "fleet", "--sizes", "3,4", "--warmup", "1", "--duration", "2")
    code, out, _ = run(runner, *args, "--out", str(tmp_path))
    assert code == 0, out
    md = (tmp_path / "fleet.md").read_text()
    assert "| 3 | 7 | track |" in md and "| 4 | 10 | track |" in md and "- load: " in md
    assert (tmp_path / "fleet.png").stat().st_size > 1000
    rows = (tmp_path / "fleet.csv").read_text().splitlines()
    assert len(rows) == 3
    for line in rows[1:]:
        cells = line.split(",")
        assert float(cells[5]) == pytest.approx(2.0) and float(cells[6]) > 0  # sim s, wall s
    code, out, _ = run(runner, *args, "--sizes", "3", "--out", str(tmp_path))
    assert code == 0, out
    md = (tmp_path / "fleet.md").read_text()
    assert "## Earlier runs" in md and "| 4 | 10 | track |" in md.split("## Earlier runs")[1]


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--sizes", "0", "from 1 to 150"),
        ("--sizes", "3,x", "got 'x'"),
        ("--sizes", "", "at least one"),
        ("--controllers", "pid", "unknown controller"),
        ("--duration", "-1", "--duration"),
    ],
)
def test_bad_options_are_one_clear_message(
    runner: CliRunner, option: str, value: str, message: str
) -> None:
    code, out, err = run(runner, "bench", "fleet", option, value, "--out", "/tmp/never-written")
    assert code == 2
    assert message in out + err and "Traceback" not in out + err
