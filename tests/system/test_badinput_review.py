"""Bad inputs found by a review sweep after issue #12 landed (each ended in a traceback, a hang
or silent acceptance). Every one is refused with exit 2 and one message naming the file:line:col
and the item, without a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from tests.system.test_cli import run

MISSION = """\
mission: m
version: 1
world:
  map: {generate: empty, size: [12, 8, 2]}
  resolution: 0.5
agents:
  - {id: G1, library: ground, start: [1, 1, 0]}
tasks:
  - {id: T1, type: inspect, location: [4, 3, 0]}
task_types:
  inspect: {goal: at_goal(location), cost: path_cost(location)}
default_behavior: {goal: at_goal(home), idle_timeout_s: 5}
"""


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


def mission(tmp_path: Path, old: str = "", new: str = "", extra: str = "") -> str:
    assert old in MISSION
    p = tmp_path / "m.yaml"
    p.write_text(MISSION.replace(old, new, 1) + extra, encoding="utf-8")
    return str(p)


def refused(runner: CliRunner, *args: str) -> str:
    """Run the CLI; assert exit 2 and no traceback; the combined output."""
    code, out, err = run(runner, *args)
    assert code == 2, out + err
    assert "internal error" not in out + err, out + err
    return out + err


# ------------------------------------------------------------------------------ YAML values
@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("!foo bar", "1:10: mission: cannot read this value: could not determine a constructor "
                     "for the tag '!foo'"),
        ("1" + "0" * 5000, "1:10: mission: cannot read this value: exceeds the limit (4300 "
                           "digits) for integer string conversion"),
    ],
)  # fmt: skip
def test_yaml_values_that_cannot_be_constructed(
    runner: CliRunner, tmp_path: Path, value: str, message: str
) -> None:
    p = tmp_path / "m.yaml"
    p.write_text(f"mission: {value}\n", encoding="utf-8")
    assert f"{p}:{message}" in refused(runner, "validate", str(p))


# ------------------------------------------------------------------------------ cost expressions
def test_a_very_long_cost_expression_is_refused(runner: CliRunner, tmp_path: Path) -> None:
    cost = "+".join(["1"] * 20000)
    out = refused(runner, "validate", mission(tmp_path, "path_cost(location)}", cost + "}"))
    assert "m.yaml:11:44: task_types.inspect.cost: the expression is 39,999 " \
        "characters long; the limit is 10,000" in out  # fmt: skip


def test_a_deeply_nested_cost_expression_is_refused(runner: CliRunner, tmp_path: Path) -> None:
    cost = "+".join(["1"] * 2000)
    out = refused(runner, "validate", mission(tmp_path, "path_cost(location)}", cost + "}"))
    assert "task_types.inspect.cost: '1+1+1+" in out
    assert "nests more than 200 operations deep" in out


# ------------------------------------------------------------------------------ goals
@pytest.mark.parametrize(
    ("old", "new", "where"),
    [
        ("goal: at_goal(location),", "goal: [],", "11:19:"),
        ("goal: at_goal(home),", "goal: [],", "12:26:"),
    ],
)
def test_an_empty_goal_list_is_refused(
    runner: CliRunner, tmp_path: Path, old: str, new: str, where: str
) -> None:
    out = refused(runner, "validate", mission(tmp_path, old, new))
    assert f"m.yaml:{where}" in out
    assert "goal: expected a goal condition or a non-empty list of them (got [])" in out
    assert "Input should be" not in out


# ------------------------------------------------------------------------------ map sizes
def test_a_size_resolution_ratio_that_overflows_is_refused(
    runner: CliRunner, tmp_path: Path
) -> None:
    p = mission(tmp_path, "size: [12, 8, 2]}\n  resolution: 0.5",
                "size: [1e300, 8, 2]}\n  resolution: 1e-300")  # fmt: skip
    out = refused(runner, "validate", p)
    assert "m.yaml:5:15: world.resolution: 1e+300 × 8 × 2 m at 1e-300 m makes more voxels than " \
        "can be counted; the limit is 40,000,000" in out  # fmt: skip


# ------------------------------------------------------------------------------ priorities
def test_a_priority_that_overflows_the_auction_is_refused(
    runner: CliRunner, tmp_path: Path
) -> None:
    p = mission(tmp_path, "location: [4, 3, 0]}", "location: [4, 3, 0], priority: 1e308}")
    for command in ("validate", "auction"):
        out = refused(runner, command, p)
        assert "m.yaml:9:60: tasks[0].priority: task 'T1': priority 1e+308 × " \
            "coordination.priority_scale 1000 is inf; the auction takes at most 1e+12" in out  # fmt: skip


def test_a_huge_priority_scale_is_blamed_once(runner: CliRunner, tmp_path: Path) -> None:
    extra = "coordination: {priority_scale: 1e300}\n"
    text = MISSION.replace("  - {id: T1,", "  - {id: T0, type: inspect, location: [5, 3, 0]}\n"
                           "  - {id: T1,")  # fmt: skip
    p = tmp_path / "m.yaml"
    p.write_text(text + extra, encoding="utf-8")
    out = refused(runner, "validate", str(p))
    assert out.count("coordination.priority_scale: task") == 1
    assert "m.yaml:14:32: coordination.priority_scale: task 'T0': priority 1 × " in out


def test_the_priority_bound_is_the_solvers() -> None:
    from btmission.allocation.solvers import MAX_COST
    from btmission.spec.mission import MAX_PRIORITY_WEIGHT

    assert MAX_PRIORITY_WEIGHT == MAX_COST


# ------------------------------------------------------------------------------ event logs
LOG = Path(__file__).resolve().parents[2] / "docs" / "examples" / "pick_and_deliver.jsonl"


def test_a_deeply_nested_log_line_is_an_unreadable_line(runner: CliRunner, tmp_path: Path) -> None:
    p = tmp_path / "deep.jsonl"
    p.write_text("[" * 100_000 + "]" * 100_000 + "\n", encoding="utf-8")
    out = refused(runner, "report", str(p))
    assert (
        f"{p}: not a btmission event log (the first line must be a 'btmission-log' header)" in out
    )


def test_log_events_with_fields_of_the_wrong_type_are_skipped(
    runner: CliRunner, tmp_path: Path
) -> None:
    lines = LOG.read_text(encoding="utf-8").splitlines()
    pose = next(i for i, line in enumerate(lines) if '"ev":"pose"' in line)
    added = next(i for i, line in enumerate(lines) if '"ev":"task_added"' in line)
    lines[pose] = lines[pose].replace('"odometer_m":', '"odometer_m":"far","x":')
    lines[added] = lines[added].replace('"problems":[]', '"problems":7')
    assert '"problems":7' in lines[added]
    p = tmp_path / "bad.jsonl"
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    code, out, err = run(runner, "report", str(p), "--png", str(tmp_path))
    assert code == 0, out + err
    assert f"warning: unreadable lines skipped: {sorted([added + 1, pose + 1])}" in err


@pytest.mark.parametrize(
    ("field", "value"), [("agents", '"x"'), ("agents", "null"), ("world", "[]"), ("tasks", "3")]
)
def test_a_log_header_with_a_field_of_the_wrong_type_is_refused(
    runner: CliRunner, tmp_path: Path, field: str, value: str
) -> None:
    import json

    lines = LOG.read_text(encoding="utf-8").splitlines()
    header = json.loads(lines[0])
    header[field] = json.loads(value)
    p = tmp_path / "bad.jsonl"
    p.write_text("\n".join([json.dumps(header), *lines[1:]]) + "\n", encoding="utf-8")
    out = refused(runner, "report", str(p))
    assert f"{p}:1: header: field '{field}' has the wrong type (got {value})" in out


# ------------------------------------------------------------------------------ budgets
def test_a_budget_beyond_any_file_size_reads_files_as_usual(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("BTMISSION_MAX_FILE_BYTES", "9" * 26)  # was OverflowError in read()
    code, out, err = run(runner, "validate", mission(tmp_path))
    assert code == 0, out + err
    assert "mission 'm' OK" in out


def test_a_large_budget_does_not_allocate_it(tmp_path: Path) -> None:
    """read(limit + 1) allocated the whole budget: a 5 GB log budget was a MemoryError under a
    4 GB address-space cap for a 20 kB log."""
    import subprocess
    import sys

    code = (
        "import resource, sys\n"
        "resource.setrlimit(resource.RLIMIT_AS, (3_000_000_000, 3_000_000_000))\n"
        "from btmission import limits\n"
        "from btmission.spec.source import read_regular_file\n"
        "from pathlib import Path\n"
        "print(len(read_regular_file(Path(sys.argv[1]), limits.MAX_LOG_BYTES)))\n"
    )
    env = {**__import__("os").environ, "BTMISSION_MAX_LOG_BYTES": "5000000000"}
    r = subprocess.run(
        [sys.executable, "-c", code, str(LOG)], capture_output=True, text=True, env=env, timeout=60
    )
    assert r.returncode == 0, r.stderr
    assert int(r.stdout) == LOG.stat().st_size


@pytest.mark.parametrize(
    ("vehicles", "message"),
    [
        ("3", "--vehicles: the static batch needs an even number of vehicles >= 2, got 3 "
              "(map static_npr)"),
        ("40", "--vehicles: map 'static_npr' has 6 left and 6 right terminals (group: "
               "left/right); 40 vehicles need 20 on each side (map static_npr)"),
    ],
)  # fmt: skip
def test_bench_dispatch_checks_fleet_sizes_first(
    runner: CliRunner, tmp_path: Path, vehicles: str, message: str
) -> None:
    out = refused(runner, "bench", "dispatch", "--vehicles", vehicles, "--out", str(tmp_path))
    assert message in out
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("auction", "--scale", "100000x100000", "--quick"),
         "Invalid value for --scale: the number of agents is 100,000, the limit is 1,000 (set "
         "BTMISSION_MAX_AGENTS to change it)"),
        (("auction", "--tasks", "20000"),
         "Invalid value for --tasks: the number of tasks is 20,000, the limit is 10,000 (set "
         "BTMISSION_MAX_TASKS to change it)"),
        (("sim", "--scale", "1000000x1"),
         "Invalid value for --scale: the number of agents is 1,000,000, the limit is 1,000"),
        (("dispatch-dynamic", "--hours", "1e9"),
         "Invalid value for '--hours': 1000000000.0 is not in the range 0<x<=1000."),
    ],
)  # fmt: skip
def test_bench_sizes_beyond_the_budgets_are_refused_before_building(
    runner: CliRunner, tmp_path: Path, args: tuple[str, ...], message: str
) -> None:
    out = refused(runner, "bench", *args, "--out", str(tmp_path))
    assert message in out


def test_dispatch_dynamic_hours_are_bounded(runner: CliRunner) -> None:
    out = refused(runner, "dispatch", "dynamic", "--hours", "1e9")
    assert "Invalid value for '--hours': 1000000000.0 is not in the range 0<x<=1000." in out


# ------------------------------------------------------------------------------ maps
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--z", "1e300", "--png", "PNG"), "--z 1e+300 is outside the map (z from 0 to 2 m)"),
        (("--z", "-5", "--png", "PNG"), "--z -5 is outside the map (z from 0 to 2 m)"),
        (("--z", "1"), "--z selects the slice drawn by --png; give --png FILE too"),
    ],
)
def test_map_show_z_must_be_a_slice_of_the_map(
    runner: CliRunner, tmp_path: Path, args: tuple[str, ...], message: str
) -> None:
    png = tmp_path / "top.png"
    argv = [str(png) if a == "PNG" else a for a in args]
    out = refused(runner, "map", "show", mission(tmp_path), *argv)
    assert message in out
    assert not png.exists()


def test_a_cut_off_ascii_pcd_is_refused(runner: CliRunner, tmp_path: Path) -> None:
    p = tmp_path / "cut.pcd"
    p.write_text(
        "# .PCD\nVERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 5\n"
        "HEIGHT 1\nPOINTS 5\nDATA ascii\n1 2 3\n4 5 6\n",
        encoding="ascii",
    )
    out = refused(runner, "map", "show", str(p), "--resolution", "0.5")
    assert f"{p}: the header declares 5 points but the file holds 2 (cut off?)" in out


def test_a_cost_that_is_a_list_gets_one_message(runner: CliRunner, tmp_path: Path) -> None:
    out = refused(runner, "validate", mission(tmp_path, "path_cost(location)}", "[1]}"))
    assert "m.yaml:11:44: task_types.inspect.cost: expected a cost expression such as " \
        "path_cost(location) or a number ≥ 0 (got [1])" in out  # fmt: skip
    assert ".str:" not in out


def test_a_cost_error_quotes_a_long_expression_shortened(runner: CliRunner, tmp_path: Path) -> None:
    cost = "(" * 300 + "1" + ")" * 300
    out = refused(runner, "validate", mission(tmp_path, "path_cost(location)}", cost + "}"))
    assert "task_types.inspect.cost: '" + "(" * 60 + "…' is not a valid expression " \
        "(too many nested parentheses)" in out  # fmt: skip


def test_a_voxel_count_past_1e15_is_shown_in_scientific_notation(
    runner: CliRunner, tmp_path: Path
) -> None:
    p = mission(tmp_path, "resolution: 0.5", "resolution: 1e-300")
    out = refused(runner, "validate", p)
    assert "world.resolution: 12 × 8 × 2 m at 1e-300 m makes 1.20e+301 × 7.99e+300 × " \
        "1.99e+300 = 1.91e+902 voxels; the limit is 40,000,000" in out  # fmt: skip


# ------------------------------------------------------------------------------ place databases
def test_a_place_database_with_nan_positions_is_refused(runner: CliRunner, tmp_path: Path) -> None:
    import numpy as np

    from btmission.localization.database import PlaceDatabase, save_database
    from btmission.localization.descriptor import DescriptorParams
    from btmission.world.voxel import VoxelMap

    params = DescriptorParams()
    db = PlaceDatabase(
        positions=np.array([[1.0, 1.0, 1.0]]),
        floor_z=np.array([0.0]),
        ring_keys=np.zeros((1, params.key_size), np.float32),
        polar=np.zeros((1, params.rings, params.sectors), np.float32),
        cloud=np.zeros((4, 3), np.float32),
        voxel_map=VoxelMap(np.zeros((4, 4, 4), np.uint8), 0.5),
    )
    good = save_database(db, tmp_path / "db.npz")
    arrays = dict(np.load(good))
    arrays["positions"] = np.array([[np.nan, 1.0, 1.0]])
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    scan = tmp_path / "scan.npy"
    np.save(scan, np.ones((10, 3)))
    out = refused(runner, "reloc", "query", str(bad), str(scan))
    assert f"{bad}: inconsistent place database: positions has NaN or infinite values" in out


def test_a_point_far_outside_the_map_is_outside_without_a_numpy_warning(
    runner: CliRunner, tmp_path: Path
) -> None:
    import warnings

    import numpy as np

    from btmission.world.voxel import VoxelMap

    vm = VoxelMap(np.zeros((4, 4, 4), np.uint8), 0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the float → int64 cast of 1e301 warned
        inside = vm.contains([[1e300, 0, 0], [np.nan, 0, 0], [-np.inf, 1, 1], [1, 1, 1]])
    assert inside.tolist() == [False, False, False, True]
    code, out, err = run(runner, "plan", mission(tmp_path), "--from", "1e300,1,0", "--to", "2,2,0")
    assert code == 2
    assert "RuntimeWarning" not in out + err
    assert "start (1e+300, 1, 0) is outside the map (x [0, 12), y [0, 8), z [0, 2))" in out + err


# ------------------------------------------------------------------------------ topological maps
TOPO = """\
topomap: tiny
version: 1
nodes:
  A: {kind: terminal, prioritized: true, xy: [0, 0]}
  X: {kind: transit, xy: [100, 0]}
  P: {kind: pause, xy: [100, 30]}
  B: {kind: terminal, xy: [200, 0], group: right}
segments:
  - {from: A, to: X, time: 12}
  - {from: X, to: B, time: [12, 18]}
  - {from: X, to: P, time: 5}
"""


def test_a_topological_map_over_the_node_budget_is_refused(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """20,000 nodes in a 1.3 MB file needed 1.5 GB for one n × n array of the path matrix."""
    p = tmp_path / "t.yaml"
    p.write_text(TOPO, encoding="utf-8")
    code, out, err = run(runner, "dispatch", "map", str(p))
    assert code == 0 and "4 nodes" in err
    monkeypatch.setenv("BTMISSION_MAX_TOPOMAP_NODES", "3")
    out = refused(runner, "dispatch", "map", str(p))
    assert f"{p}:4:3: nodes: the number of nodes is 4, the limit is 3 (set " \
        "BTMISSION_MAX_TOPOMAP_NODES to change it)" in out  # fmt: skip


def test_a_trajectory_that_is_a_device_is_not_called_missing(
    runner: CliRunner, tmp_path: Path
) -> None:
    out = refused(runner, "reloc", "build", mission(tmp_path), "-o", str(tmp_path / "db.npz"),
                  "--trajectory", "/dev/zero")  # fmt: skip
    assert "/dev/zero: not a regular file" in out


def test_the_schema_says_a_goal_list_is_not_empty(runner: CliRunner) -> None:
    import json

    code, out, _ = run(runner, "schema", "mission")
    assert code == 0
    defs = json.loads(out)["$defs"]
    for model in ("TaskTypeSpec", "DefaultBehaviorSpec"):
        branches = defs[model]["properties"]["goal"]["anyOf"]
        assert {"items": {"type": "string"}, "minItems": 1, "type": "array"} in branches


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("origin", "origin must be three finite numbers, got (nan, 0, 0)"),
        ("state", "voxel state 77 is not one of 0 (free), 1 (occupied), 2 (unknown)"),
    ],
)
def test_a_npz_map_refused_by_the_grid_checks_names_the_file(
    runner: CliRunner, tmp_path: Path, change: str, message: str
) -> None:
    import numpy as np

    from btmission.world.io import save_map
    from btmission.world.voxel import VoxelMap

    good = tmp_path / "good.npz"
    save_map(VoxelMap(np.zeros((4, 4, 4), np.uint8), 0.5), good)
    arrays = dict(np.load(good))
    if change == "origin":
        arrays["origin"] = np.array([np.nan, 0.0, 0.0])
    else:
        arrays["state"] = np.full((4, 4, 4), 77, np.uint8)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    out = refused(runner, "plan", str(bad), "--from", "0.2,0.2,0.2", "--to", "1,1,1")
    assert f"{bad}: {message}" in out


def test_an_empty_library_reference_is_named_as_such(runner: CliRunner, tmp_path: Path) -> None:
    out = refused(runner, "library", "show", "")
    assert "<command line>: empty library reference: give an installed library (" in out
    assert "not a regular file" not in out
    out = refused(runner, "validate", mission(tmp_path, "library: ground", "library: ''"))
    assert "m.yaml:7:23: agents[0].library: empty library reference" in out
