"""``btmission reloc build|query|scan|try`` through CliRunner: files, output, exit codes (0 ok,
1 not localised, 2 bad input) and never a traceback."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from btmission.localization.database import load_database
from btmission.world.io import save_map, write_cloud
from btmission.world.minegen import generate_mine, survey_point_cloud
from tests.reloc_helpers import OTHER_SEED, SIZE, small_mine
from tests.system.test_cli import run

ROOT = Path(__file__).resolve().parents[2]
MISSION = str(ROOT / "docs" / "examples" / "reloc_mine.yaml")
AT, YAW = "32,15,2", "40"


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A database of the docs' small mine and a scan of it, made through the CLI."""
    d = tmp_path_factory.mktemp("reloc")
    runner = CliRunner()
    code, out, err = run(runner, "reloc", "build", MISSION, "-o", str(d / "db.npz"))
    assert code == 0, err
    assert "places" in out and "wrote" in err
    code, out, _ = run(
        runner, "reloc", "scan", MISSION, "--at", AT, "--yaw", YAW, "-o", str(d / "scan.ply")
    )
    assert code == 0 and "points from os1-32" in out
    return d / "db.npz", d / "scan.ply"


@pytest.mark.parametrize(
    "args", [["reloc"], ["reloc", "build"], ["reloc", "query"], ["reloc", "scan"], ["reloc", "try"]]
)
def test_help(runner: CliRunner, args: list[str]) -> None:
    code, out, _ = run(runner, *args, "--help")
    assert code == 0 and "Usage:" in out and "btmission reloc" in out


def test_build_writes_a_loadable_database(built: tuple[Path, Path]) -> None:
    db = load_database(built[0])
    assert len(db) > 100 and db.voxel_map.shape == small_mine().map.shape


def test_query_localises_the_scan(runner: CliRunner, built: tuple[Path, Path]) -> None:
    db, scan = built
    code, out, _ = run(runner, "reloc", "query", str(db), str(scan), "--truth", f"{AT},{YAW}")
    assert code == 0, out
    assert out.startswith("localised at x 32.0") and "within 0.3 m / 3°" in out
    code, out, _ = run(runner, "reloc", "query", str(db), str(scan), "--json")
    d = json.loads(out)
    assert code == 0 and d["localized"] and abs(d["pose"]["yaw_deg"] - 40) < 3
    assert d["confidence"] >= 0.2 and len(d["candidates"]) >= 1


def test_query_with_a_wrong_truth_exits_1(runner: CliRunner, built: tuple[Path, Path]) -> None:
    db, scan = built
    code, out, err = run(runner, "reloc", "query", str(db), str(scan), "--truth", "30,15,2,40")
    assert code == 1 and "outside 0.3 m / 3°" in out and "pose error too large" in err


def test_a_scan_of_another_mine_is_not_localised(
    runner: CliRunner, built: tuple[Path, Path], tmp_path: Path
) -> None:
    other = save_map(small_mine(OTHER_SEED).map, tmp_path / "other.npz")
    x, y, z = small_mine(OTHER_SEED).tunnels[1].point(0.5, 2.0)
    scan = tmp_path / "other.npy"
    code, _, _ = run(runner, "reloc", "scan", str(other), "--at", f"{x},{y},{z}", "-o", str(scan))
    assert code == 0 and np.load(scan).shape[1] == 3
    code, out, err = run(runner, "reloc", "query", str(built[0]), str(scan))
    assert code == 1 and "not localised" in out and "not localised" in err


def test_try_builds_in_memory_or_uses_a_database(
    runner: CliRunner, built: tuple[Path, Path]
) -> None:
    code, out, _ = run(
        runner, "reloc", "try", MISSION, "--at", "50,21.5,2", "--yaw", "-100", "--spacing", "2"
    )
    assert code == 0 and "within 0.3 m / 3°" in out, out
    code, out, _ = run(
        runner,
        "reloc",
        "try",
        MISSION,
        "--db",
        str(built[0]),
        "--at",
        AT,
        "--dust",
        "0.05",
        "--json",
    )
    assert code == 0 and json.loads(out)["error"]["translation_m"] < 0.3


def test_build_from_a_plain_survey_uses_its_points(runner: CliRunner, tmp_path: Path) -> None:
    """A closed survey (no unknown patches): its free space is what its walls enclose."""
    pts = survey_point_cloud(generate_mine(1, SIZE, 0.5, unknown=False).map, seed=1)
    survey = tmp_path / "survey.ply"
    write_cloud(survey, {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]})
    out_db = tmp_path / "survey_db.npz"
    code, _, err = run(
        runner,
        "reloc",
        "build",
        str(survey),
        "--resolution",
        "0.5",
        "--spacing",
        "3",
        "-o",
        str(out_db),
    )
    assert code == 0, err
    db = load_database(out_db)
    assert len(db.cloud) == len(pts) and len(db) > 10


def test_a_survey_with_holes_needs_a_trajectory(runner: CliRunner, tmp_path: Path) -> None:
    pts = survey_point_cloud(small_mine().map, seed=1)  # the unknown patches leave holes
    survey = tmp_path / "survey.ply"
    write_cloud(survey, {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]})
    code, _, err = run(
        runner, "reloc", "build", str(survey), "--resolution", "0.5", "-o", str(tmp_path / "d.npz")
    )
    assert code == 2 and "--trajectory" in err


def test_build_along_a_trajectory(runner: CliRunner, tmp_path: Path) -> None:
    t = small_mine().tunnels[1]
    traj = tmp_path / "run.csv"
    traj.write_text(
        "# x, y, z\n" + "\n".join(",".join(f"{v}" for v in t.point(f, 2.0)) for f in (0, 0.5, 1))
    )
    out_db = tmp_path / "traj_db.npz"
    code, _, err = run(
        runner,
        "reloc",
        "build",
        MISSION,
        "--trajectory",
        str(traj),
        "--spacing",
        "2",
        "-o",
        str(out_db),
    )
    assert code == 0, err
    db = load_database(out_db)
    assert 0.6 * t.length / 2 <= len(db) <= t.length / 2 + 1
    steps = np.linalg.norm(np.diff(db.positions, axis=0), axis=1)
    assert np.all(np.isclose(steps % 2.0, 0.0, atol=1e-6) | np.isclose(steps % 2.0, 2.0, atol=1e-6))


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["build", MISSION, "-o", "db.txt"], "written as .npz"),
        (["build", "nope.npz", "-o", "db.npz"], "no such file"),
        (["build", MISSION, "--trajectory", "t.json", "-o", "db.npz"], "cannot read a trajectory"),
        (["build", MISSION, "--cloud", "missing.ply", "-o", "db.npz"], "no such file"),
        (["scan", MISSION, "--at", "32,15,2", "-o", "scan.txt"], ".ply, .pcd or .npy"),
        (["scan", MISSION, "--at", "500,15,2", "-o", "scan.ply"], "outside the map"),
        (["scan", MISSION, "--at", "1,1,1", "-o", "scan.ply"], "inside rock"),
        (["scan", MISSION, "--at", "1,1", "-o", "scan.ply"], "X,Y,Z"),
        (["try", MISSION, "--at", "32,15,2", "--db", "missing.npz"], "no such file"),
    ],
)
def test_bad_input_exits_2(
    runner: CliRunner,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    args: list[str],
    message: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "t.json").write_text("{}")
    code, out, err = run(runner, "reloc", *args)
    assert code == 2 and message in out + err, out + err


def test_query_bad_files_exit_2(
    runner: CliRunner, built: tuple[Path, Path], tmp_path: Path
) -> None:
    db, scan = built
    vm_file = save_map(small_mine().map, tmp_path / "map.npz")
    cases = [
        ([str(vm_file), str(scan)], "reloc build"),
        ([str(db), str(tmp_path / "none.ply")], "no such file"),
        ([str(db), str(scan), "--truth", "1,2,3"], "X,Y,Z,YAW"),
    ]
    flat = tmp_path / "flat.npy"
    np.save(flat, np.zeros((10, 2)))
    cases.append(([str(db), str(flat)], "N × 3"))
    bad = tmp_path / "bad.pcd"
    bad.write_text("garbage")
    cases.append(([str(db), str(bad)], "not a readable PCD"))
    for args, message in cases:
        code, out, err = run(runner, "reloc", "query", *args)
        assert code == 2 and message in out + err, (args, out + err)


def test_a_map_without_floors_cannot_be_built(runner: CliRunner, tmp_path: Path) -> None:
    room = tmp_path / "room.yaml"
    room.write_text(
        "mission: room\nversion: 1\nworld: {map: {generate: empty, size: [6, 6, 3]}, resolution: 0.5}\n"
        "agents: [{id: R1, library: aerial_mine, start: [1, 1, 0]}]\n"
        "tasks: [{id: T1, type: inspect, location: [4, 4, 1]}]\n"
        "task_types: {inspect: {goal: at_goal(location), cost: path_cost(location)}}\n"
    )
    code, _, err = run(runner, "reloc", "build", str(room), "-o", str(tmp_path / "db.npz"))
    assert code == 2 and "no place" in err


def test_aerial_mine_checks_clean(runner: CliRunner) -> None:
    code, out, _ = run(runner, "library", "check", "aerial_mine", "--strict")
    assert code == 0 and "0 error(s), 0 warning(s)" in out
