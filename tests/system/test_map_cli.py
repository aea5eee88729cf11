"""``btmission map generate|show``, ``btmission plan`` and ``validate`` against the map, through
CliRunner: outputs, files, exit codes (0 ok, 1 no path, 2 bad input) and never a traceback."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from btmission.world.io import load_map, read_cloud, save_map
from btmission.world.voxel import OCCUPIED, VoxelMap
from tests.system.test_cli import run

ROOT = Path(__file__).resolve().parents[2]
MINE = str(ROOT / "missions" / "mine_inspection.yaml")


@pytest.mark.parametrize(
    "args", [["map"], ["map", "generate"], ["map", "show"], ["plan"], ["bench", "planner"]]
)
def test_help(runner: CliRunner, args: list[str]) -> None:
    code, out, _ = run(runner, *args, "--help")
    assert code == 0 and "Usage:" in out and "btmission" in out


def test_generate_show_and_survey(runner: CliRunner, tmp_path: Path) -> None:
    out_map = tmp_path / "mine.npz"
    scan = tmp_path / "scan.pcd"
    code, out, err = run(
        runner,
        "map",
        "generate",
        "--seed",
        "3",
        "--size",
        "80",
        "50",
        "8",
        "-o",
        str(out_map),
        "--survey",
        str(scan),
    )
    assert code == 0 and "mine seed 3: 160×100×16 voxels" in out and f"wrote {scan}" in err
    vm = load_map(out_map)
    assert vm.meta["seed"] == 3 and vm.shape == (160, 100, 16)
    cols, _ = read_cloud(scan)
    assert len(cols["x"]) > 10_000
    png = tmp_path / "top.png"
    code, out, _ = run(runner, "map", "show", str(out_map), "--png", str(png))
    assert code == 0 and "risk layer: r = 1.5 m, c_u = 10" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, out, _ = run(runner, "map", "show", MINE, "--png", str(png), "--z", "2")
    assert code == 0 and "400×240×24 voxels" in out


def test_generate_bad_inputs(runner: CliRunner, tmp_path: Path) -> None:
    code, _, err = run(
        runner, "map", "generate", "--size", "10", "10", "3", "-o", str(tmp_path / "m.npz")
    )
    assert code == 2 and "a mine needs at least 40 × 30 × 6 m" in err
    code, _, err = run(runner, "map", "generate", "-o", str(tmp_path / "m.obj"))
    assert code == 2 and "unknown map format '.obj'" in err
    code, _, err = run(
        runner,
        "map",
        "generate",
        "-o",
        str(tmp_path / "m.npz"),
        "--survey",
        str(tmp_path / "s.npz"),
    )
    assert code == 2 and "use .ply or .pcd" in err


def test_show_bad_inputs(runner: CliRunner, tmp_path: Path) -> None:
    code, _, err = run(runner, "map", "show", str(tmp_path / "nope.npz"))
    assert code == 2 and "no such file" in err
    bad = tmp_path / "bad.yaml"
    bad.write_text("mission: x\nversion: 1\n")
    code, _, err = run(runner, "map", "show", str(bad))
    assert code == 2 and "bad.yaml" in err


def _wall_map(tmp_path: Path) -> Path:
    st_ = np.zeros((20, 10, 3), np.uint8)
    st_[10, :, :] = OCCUPIED
    p = tmp_path / "wall.npz"
    save_map(VoxelMap(st_, 0.5), p)
    return p


def test_plan_text_json_png(runner: CliRunner, tmp_path: Path) -> None:
    png = tmp_path / "path.png"
    code, out, _ = run(
        runner, "plan", MINE, "--from", "7,5,0", "--to", "64.4,9.6,3", "--png", str(png)
    )
    assert code == 0 and out.startswith("path (7, 5, 0) → (64.4, 9.6, 3): cost ")
    assert png.read_bytes()[:4] == b"\x89PNG"
    code, out, _ = run(runner, "plan", MINE, "--from", "7,5,0", "--to", "64.4,9.6,3", "--json")
    data = json.loads(out)
    assert data["cost"] >= data["length_m"] > 57.0
    assert data["waypoints"][0] == data["path"][0] and data["waypoints"][-1] == data["path"][-1]
    assert len(data["waypoints"]) < len(data["path"])


def test_plan_bad_inputs(runner: CliRunner, tmp_path: Path) -> None:
    m = str(_wall_map(tmp_path))
    code, _, err = run(runner, "plan", m, "--from", "1,1", "--to", "2,2,0.5")
    assert code == 2 and "expected X,Y,Z in metres" in err
    code, _, err = run(runner, "plan", m, "--from", "1,1,0.5", "--to", "99,1,0.5")
    assert code == 2 and "goal (99, 1, 0.5) is outside the map" in err
    code, _, err = run(runner, "plan", m, "--from", "5.1,1,0.5", "--to", "2,2,0.5")
    assert code == 2 and "start (5.1, 1, 0.5) is inside rock" in err and "snap" in err
    code, _, err = run(runner, "plan", m, "--from", "5.1,1,0.5", "--to", "2,2,0.5", "--snap")
    assert code == 0 and "warning: start (5.1, 1, 0.5) is inside rock" in err and "snapped" in err
    code, _, err = run(
        runner, "plan", m, "--from", "1,1,0.5", "--to", "2,2,0.5", "--unknown-cost", "1e9"
    )
    assert code == 2 and "unknown cost c_u must be a number in [0, 100000]" in err
    code, _, err = run(runner, "plan", m, "--from", "1,1,0.5", "--to", "8,1,0.5")
    assert code == 1 and "no path from (1, 1, 0.5) to (8, 1, 0.5)" in err


def test_validate_reports_map_problems(runner: CliRunner, tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        Path(MINE)
        .read_text()
        .replace("start: [4, 5, 0]", "start: [4, 5, -0.5]")  # in the floor
        .replace("location: [91.7, 44.8, 2]", "location: [91.7, 44.8, 40]")  # above the map
        .replace("location: [33, 73.6, 2]", "location: [33, 60, 2]")  # in rock
    )
    code, out, err = run(runner, "validate", str(bad))
    assert code == 2 and out == ""
    lines = [line for line in err.splitlines() if line.startswith(str(bad))]
    assert lines == [
        f"{bad}:13:5: agents[0].start: agent R1 starts at [4, 5, -0.5] is inside rock (an occupied voxel); "
        "the nearest free voxel is at [3.75, 4.75, 0.25]",
        f"{bad}:18:5: tasks[1].location: task T2: location [91.7, 44.8, 40] is outside the map "
        "(x [0, 200), y [0, 120), z [-1, 11))",
        f"{bad}:20:5: tasks[3].location: task T4: location [33, 60, 2] is inside rock (an occupied voxel)",
    ]
