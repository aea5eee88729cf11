"""Issue #12 §1: resource budgets on every input. Each hostile or oversized input is refused with
exit 2 and one message naming the limit (and the environment variable that changes it), fast,
without a traceback and before the memory or the time is spent."""

from __future__ import annotations

import io
import os
import threading
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from btmission import limits
from btmission.cli.main import cli
from btmission.diagnostics import SpecError
from btmission.spec.budgets import check_mission_scale
from btmission.spec.source import Source, parse_yaml
from tests.system.test_cli import run

ROOT = Path(__file__).resolve().parents[2]
REFUSED_BEFORE_S = 10.0
"""Not a speed test (those are benchmarks): a bound far above a refusal's time (milliseconds) and
far below what expanding or allocating the input would take (minutes, or the machine's memory),
so the test tells "refused before the work" from "did the work", however loaded the host."""
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
"""


def mission(tmp_path: Path, text: str = MISSION, name: str = "m.yaml") -> str:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return str(p)


def refused(runner: CliRunner, *args: str) -> str:
    """Run the CLI; assert exit 2 and no traceback; the combined output."""
    code, out, err = run(runner, *args)
    assert code == 2, out + err
    return out + err


def laughs(levels: int) -> str:
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------ YAML
def test_yaml_over_the_size_cap_is_refused_before_reading(
    runner: CliRunner, tmp_path: Path
) -> None:
    p = tmp_path / "big.yaml"
    p.write_text(MISSION + "#" * limits.MAX_FILE_BYTES.limit, encoding="utf-8")
    size = p.stat().st_size
    out = refused(runner, "validate", str(p))
    assert (
        f"{p}: file too large: {size:,} bytes, the limit is 4,000,000 bytes "
        "(set BTMISSION_MAX_FILE_BYTES to change it)"
    ) in out


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom"])
def test_devices_are_refused(runner: CliRunner, device: str) -> None:
    out = refused(runner, "validate", device)
    assert f"{device}: not a regular file but a character device" in out


def _in_thread(fn: Any, timeout_s: float = 10.0) -> Any:
    """Run ``fn`` in a daemon thread; fail (instead of hanging the suite) if it blocks."""
    box: dict[str, Any] = {}

    def target() -> None:
        box["result"] = fn()

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(timeout_s)
    assert not t.is_alive(), f"still blocked after {timeout_s} s"
    return box["result"]


def test_fifo_without_writer_does_not_hang(runner: CliRunner, tmp_path: Path) -> None:
    fifo = tmp_path / "m.yaml"
    os.mkfifo(fifo)
    try:
        code, out, err = _in_thread(lambda: run(runner, "validate", str(fifo)))
        assert code == 2
        assert f"{fifo}: not a regular file but a FIFO (named pipe)" in out + err
        code, out, err = _in_thread(lambda: run(runner, "library", "check", str(fifo)))
        assert code == 2 and "not a regular file but a FIFO" in out + err
    finally:
        fifo.unlink()


@pytest.mark.parametrize("command", [["validate"], ["library", "check"]])
def test_billion_laughs_is_refused_in_well_under_a_second(
    runner: CliRunner, tmp_path: Path, command: list[str]
) -> None:
    p = mission(tmp_path, laughs(9), "laughs.yaml")
    t0 = time.perf_counter()
    out = refused(runner, *command, p)
    assert time.perf_counter() - t0 < REFUSED_BEFORE_S
    assert (
        "laughs.yaml:6:5: alias expansion (items repeated through *aliases) is 597,851, the limit "
        "is 100,000 (set BTMISSION_MAX_YAML_ALIAS_NODES to change it)"
    ) in out


def test_recursive_alias_is_refused(runner: CliRunner, tmp_path: Path) -> None:
    p = mission(tmp_path, "mission: m\ng: &g [*g]\n")
    out = refused(runner, "validate", p)
    assert "m.yaml:2:4: recursive alias: this item contains an alias (*name) to itself" in out


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ("x: " + "[" * 10_000 + "]" * 10_000 + "\n", "1:104"),
        ("x: " + "{a: " * 10_000 + "1" + "}" * 10_000 + "\n", "1:404"),
        # block nesting: indentation, checked on the composed graph
        ("".join(" " * i + f"k{i}:\n" for i in range(150)) + " " * 150 + "v: 1\n", "101:101"),
    ],
)
def test_deep_nesting_is_refused(runner: CliRunner, tmp_path: Path, text: str, where: str) -> None:
    p = mission(tmp_path, text)
    t0 = time.perf_counter()
    out = refused(runner, "validate", p)
    assert time.perf_counter() - t0 < REFUSED_BEFORE_S
    assert (
        f"m.yaml:{where}: nesting depth is 101, the limit is 100 levels "
        "(set BTMISSION_MAX_YAML_DEPTH to change it)"
    ) in out


def test_brackets_in_quotes_and_comments_do_not_count_as_nesting() -> None:
    text = "a: '" + "[" * 200 + "'\nb: \"" + "{" * 200 + '"  # ' + "[" * 200 + "\nc: [1, [2]]\n"
    assert parse_yaml(text).data == {"a": "[" * 200, "b": "{" * 200, "c": [1, [2]]}


def test_an_environment_variable_raises_or_lowers_a_yaml_budget(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    text = laughs(4)  # 9**5 = 59,049 items once expanded: within the default budget
    assert len(parse_yaml(text).data["a4"]) == 9
    monkeypatch.setenv("BTMISSION_MAX_YAML_ALIAS_NODES", "10000")
    with pytest.raises(
        SpecError, match=r"the limit is 10,000 \(set BTMISSION_MAX_YAML_ALIAS_NODES"
    ):
        parse_yaml(text)
    wide = "a: &a [" + ", ".join(["x"] * 1000) + "]\nb: [" + ", ".join(["*a"] * 101) + "]\n"
    monkeypatch.delenv("BTMISSION_MAX_YAML_ALIAS_NODES")
    with pytest.raises(SpecError, match=r"is 100,099, the limit is 100,000 \(set BTMISSION_MAX"):
        parse_yaml(wide)  # 100 repeats of 1,001 items: just over the default
    monkeypatch.setenv("BTMISSION_MAX_YAML_ALIAS_NODES", "200_000")
    assert len(parse_yaml(wide).data["b"]) == 101


def test_a_bad_environment_value_warns_and_keeps_the_default(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("BTMISSION_MAX_VOXELS", "lots")
    assert limits.MAX_VOXELS.limit == 40_000_000
    assert "ignoring BTMISSION_MAX_VOXELS='lots' (expected a positive whole number)" in (
        capsys.readouterr().err
    )


# ------------------------------------------------------------------------------------ .npz
def _npy(arr: Any) -> bytes:
    b = io.BytesIO()
    np.lib.format.write_array(b, np.asarray(arr))
    return b.getvalue()


def _bomb_member(shape: tuple[int, ...]) -> bytes:
    """An npy header declaring ``shape`` (uint8) followed by almost no data."""
    b = io.BytesIO()
    header = {"descr": "|u1", "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(b, header)
    return b.getvalue() + bytes(64)


MAP_FIELDS: dict[str, Any] = {
    "format": np.array("btmission-voxelmap"),
    "version": np.array(1),
    "state": np.zeros((4, 4, 4), np.uint8),
    "resolution": np.array(0.5),
    "origin": np.zeros(3),
    "meta": np.array("{}"),
}


def write_npz(path: Path, fields: dict[str, Any], bomb: dict[str, tuple[int, ...]]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, value in fields.items():
            z.writestr(name + ".npy", _npy(value))
        for name, shape in bomb.items():
            z.writestr(name + ".npy", _bomb_member(shape))
    return path


def test_npz_zip_bomb_map_is_refused_in_milliseconds(runner: CliRunner, tmp_path: Path) -> None:
    fields = {k: v for k, v in MAP_FIELDS.items() if k != "state"}
    p = write_npz(tmp_path / "bomb.npz", fields, {"state": (3000, 1000, 1000)})
    t0 = time.perf_counter()
    out = refused(runner, "map", "show", str(p))
    assert time.perf_counter() - t0 < REFUSED_BEFORE_S
    assert (
        f"{p}: field 'state': its size (3,000 × 1,000 × 1,000 values) is 3,000,000,000, the "
        "limit is 40,000,000 (set BTMISSION_MAX_VOXELS to change it)"
    ) in out


def test_npz_zip_bomb_place_database_is_refused(runner: CliRunner, tmp_path: Path) -> None:
    fields = dict(MAP_FIELDS, format=np.array("btmission-reloc-db"))
    p = write_npz(tmp_path / "db.npz", fields, {"polar": (100_000, 20, 60)})
    scan = tmp_path / "scan.npy"
    np.save(scan, np.zeros((10, 3)))
    t0 = time.perf_counter()
    out = refused(runner, "reloc", "query", str(p), str(scan))
    assert time.perf_counter() - t0 < REFUSED_BEFORE_S
    assert f"{p}: field 'polar': its size (100,000 × 20 × 60 values) is 120,000,000" in out


def test_npy_cloud_bomb_is_refused(runner: CliRunner, tmp_path: Path) -> None:
    vm = write_npz(tmp_path / "map.npz", MAP_FIELDS, {})
    cloud = tmp_path / "cloud.npy"
    b = io.BytesIO()
    header = {"descr": "<f8", "fortran_order": False, "shape": (10**10, 3)}
    np.lib.format.write_array_header_1_0(b, header)
    cloud.write_bytes(b.getvalue() + bytes(48))
    t0 = time.perf_counter()
    out = refused(
        runner, "reloc", "build", str(vm), "--cloud", str(cloud), "-o", str(tmp_path / "d.npz")
    )
    assert time.perf_counter() - t0 < REFUSED_BEFORE_S
    assert (
        f"{cloud}: its size (10,000,000,000 × 3 values) is 30,000,000,000, the limit is "
        "40,000,000 (set BTMISSION_MAX_VOXELS to change it)"
    ) in out


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("version", np.array("1"), "field 'version': expected a whole number, found a text"),
        ("version", np.array(1.5), "field 'version': expected a whole number, found a number"),
        ("resolution", np.array("x"), "field 'resolution': expected a number (m), found a text"),
        ("resolution", np.array(-1.0), "field 'resolution': expected a number > 0 (m), found -1"),
        ("meta", np.array(3), "field 'meta': expected a JSON text, found a whole number"),
        ("meta", np.array("{oops"), "field 'meta': expected a JSON text (Expecting property"),
        ("meta", np.array("[1]"), "field 'meta': expected a JSON object {...}, found list"),
        (
            "origin",
            np.zeros(2),
            "field 'origin': expected three numbers [x, y, z], found numbers of shape (2,)",
        ),
        (
            "state",
            np.zeros((2, 2)),
            "field 'state': expected a 3D grid of voxel states (0, 1, 2), "
            "found numbers of shape (2, 2)",
        ),
        ("format", np.array(7), "field 'format': expected a text, found a whole number"),
    ],
)
def test_npz_map_fields_of_the_wrong_type(
    runner: CliRunner, tmp_path: Path, field: str, value: Any, message: str
) -> None:
    p = tmp_path / "map.npz"
    np.savez_compressed(p, **dict(MAP_FIELDS, **{field: value}))
    out = refused(runner, "map", "show", str(p))
    assert f"{p}: {message}" in out


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("version", np.array("1"), "field 'version': expected a whole number, found a text"),
        ("meta", np.array("{oops"), "field 'meta': expected a JSON text"),
        ("sensor", np.array("[]"), "field 'sensor': expected a JSON object {...}, found list"),
        ("descriptor", np.array('{"rings": "x"}'), "field 'descriptor': "),
        (
            "sensor",
            np.array('{"channels": 100000, "azimuths": 100000}'),
            "field 'sensor': its beams (channels × azimuths) is 10,000,000,000, the limit is "
            "20,000,000 (set BTMISSION_MAX_POINTS",
        ),
    ],
)
def test_place_database_fields_of_the_wrong_type(
    runner: CliRunner, tmp_path: Path, field: str, value: Any, message: str
) -> None:
    fields = dict(
        MAP_FIELDS,
        format=np.array("btmission-reloc-db"),
        positions=np.zeros((1, 3)),
        floor_z=np.zeros(1),
        ring_keys=np.zeros((1, 20), np.float32),
        polar=np.zeros((1, 20, 60), np.float32),
        cloud=np.zeros((5, 3), np.float32),
        map_meta=np.array("{}"),
        descriptor=np.array("{}"),
        sensor=np.array("{}"),
    )
    fields[field] = value
    p = tmp_path / "db.npz"
    np.savez_compressed(p, **fields)
    scan = tmp_path / "scan.npy"
    np.save(scan, np.zeros((10, 3)))
    out = refused(runner, "reloc", "query", str(p), str(scan))
    assert f"{p}: {message}" in out


def test_not_a_zip_is_a_clear_error(runner: CliRunner, tmp_path: Path) -> None:
    p = tmp_path / "map.npz"
    p.write_bytes(b"not a zip at all")
    out = refused(runner, "map", "show", str(p))
    assert f"{p}: not a readable .npz file (File is not a zip file)" in out


# ------------------------------------------------------------------------------------ clouds
def test_point_cloud_declaring_too_many_points(runner: CliRunner, tmp_path: Path) -> None:
    p = tmp_path / "c.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 999999999999\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n0 0 0\n"
    )
    out = refused(runner, "map", "show", str(p))
    assert (
        f"{p}: its number of points is 999,999,999,999, the limit is 20,000,000 "
        "(set BTMISSION_MAX_POINTS to change it)"
    ) in out


def test_point_cloud_spanning_too_many_voxels(runner: CliRunner, tmp_path: Path) -> None:
    from btmission.world.io import write_cloud

    p = tmp_path / "far.ply"
    write_cloud(p, {"x": np.array([0.0, 1e6]), "y": np.array([0.0, 1e6]), "z": np.zeros(2)})
    t0 = time.perf_counter()
    out = refused(runner, "map", "show", str(p), "--resolution", "0.5")
    assert time.perf_counter() - t0 < REFUSED_BEFORE_S
    assert f"{p}: 2 points spanning 1e+06 × 1e+06 × 0 m at 0.5 m makes " in out
    assert "voxels; the limit is 40,000,000 (set BTMISSION_MAX_VOXELS to change it)" in out


# ------------------------------------------------------------------------------------ map sizes
@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("resolution: 0.5", "resolution: 0.001",
         "m.yaml:5:15: world.resolution: 12 × 8 × 2 m at 0.001 m makes 12,000 × 8,000 × 2,000 "
         "= 192,000,000,000 voxels; the limit is 40,000,000 (set BTMISSION_MAX_VOXELS"),
        ("resolution: 0.5", "resolution: .inf",
         "m.yaml:5:15: world.resolution: expected a finite number (got inf)"),
        ("resolution: 0.5", "resolution: .nan", "m.yaml:5:15: world.resolution: "),
        ("size: [12, 8, 2]", "size: [.nan, 8, 2]",
         "m.yaml:4:33: world.map.size[0]: expected a finite number (got nan)"),
        ("size: [12, 8, 2]", "size: [1e400, 8, 2]",
         "m.yaml:4:33: world.map.size[0]: expected a finite number (got 1e400)"),
        ("size: [12, 8, 2]", "size: [100000, 100000, 100]",
         "world.resolution: 100000 × 100000 × 100 m at 0.5 m makes 200,000 × 200,000 × 200"),
        ("{generate: empty,", "{generate: mine, seed: -1,",
         "m.yaml:4:31: world.map.seed: Input should be greater than or equal to 0 (got -1)"),
    ],
)  # fmt: skip
def test_mission_map_sizes(
    runner: CliRunner, tmp_path: Path, old: str, new: str, message: str
) -> None:
    assert old in MISSION
    t0 = time.perf_counter()
    out = refused(runner, "validate", mission(tmp_path, MISSION.replace(old, new)))
    assert time.perf_counter() - t0 < REFUSED_BEFORE_S
    assert message in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--seed", "-1"], "Invalid value for '--seed': -1 is not in the range x>=0"),
        (["--size", "nan", "100", "10"], "Invalid value for '--size': 'nan' is not a finite number"),
        (["--size", "inf", "100", "10"], "Invalid value for '--size': 'inf' is not a finite number"),
        (["--size", "100000", "100000", "100"],
         "100000 × 100000 × 100 m at 0.5 m makes 200,000 × 200,000 × 200 = 8,000,000,000,000 "
         "voxels; the limit is 40,000,000 (set BTMISSION_MAX_VOXELS to change it)"),
        (["--resolution", "0.01"], "200 × 120 × 12 m at 0.01 m makes 20,000 × 12,000 × 1,200"),
        (["--resolution", "nan"], "Invalid value for '--resolution': 'nan' is not a finite number"),
    ],
)  # fmt: skip
def test_map_generate_sizes(
    runner: CliRunner, tmp_path: Path, args: list[str], message: str
) -> None:
    out_file = tmp_path / "m.npz"
    t0 = time.perf_counter()
    out = refused(runner, "map", "generate", *args, "-o", str(out_file))
    assert time.perf_counter() - t0 < REFUSED_BEFORE_S
    assert message in out and not out_file.exists()


@pytest.mark.parametrize(
    "args",
    [
        ["map", "show", "MAP", "--z", "nan"],
        ["plan", "MAP", "--from", "7,5,0", "--to", "10,5,0", "--risk-radius", "nan"],
        ["plan", "MAP", "--from", "nan,5,0", "--to", "10,5,0"],
        ["reloc", "scan", "MAP", "--at", "7,5,1", "--yaw", "nan", "-o", "OUT"],
        ["reloc", "scan", "MAP", "--at", "7,5,1", "--dust", "inf", "-o", "OUT"],
        ["reloc", "build", "MAP", "--height", "inf", "-o", "OUT"],
        ["reloc", "scan", "MAP", "--at", "7,5,1", "--seed", "-1", "-o", "OUT"],
    ],
)
def test_map_and_reloc_options_refuse_non_finite_numbers(
    runner: CliRunner, tmp_path: Path, args: list[str]
) -> None:
    map_file = write_npz(tmp_path / "map.npz", MAP_FIELDS, {})
    out_file = tmp_path / "out.ply"
    args = [str(map_file) if a == "MAP" else str(out_file) if a == "OUT" else a for a in args]
    out = refused(runner, *args)
    bad = next(a for a in args if a in ("nan", "inf", "-1") or a.startswith("nan,"))
    assert (
        "Invalid value for '--" in out and f"'{bad}'" in out
    ) or f"{bad} is not in the range" in out
    assert not out_file.exists()


def test_voxel_budget_from_the_environment(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out_file = tmp_path / "m.npz"
    args = ["map", "generate", "--size", "40", "30", "6", "--resolution", "0.25"]
    monkeypatch.setenv("BTMISSION_MAX_VOXELS", "100000")
    out = refused(runner, *args, "-o", str(out_file))
    assert "160 × 120 × 24 = 460,800 voxels; the limit is 100,000" in out
    monkeypatch.delenv("BTMISSION_MAX_VOXELS")
    code, out, _ = run(runner, *args, "-o", str(out_file))
    assert code == 0 and "160×120×24 voxels" in out and out_file.exists()


# ------------------------------------------------------------------------------------ scale
def _source(data: dict[str, Any]) -> Source:
    return Source("big.yaml", data, {(): (1, 1), ("agents",): (6, 1), ("tasks",): (9, 1)},
                  {("agents",): (6, 1), ("tasks",): (9, 1)})  # fmt: skip


def test_5000_agents_and_20000_tasks_are_refused_before_building() -> None:
    agents = [{"id": f"A{i}", "library": "ground", "start": [0, 0, 0]} for i in range(5000)]
    tasks = [{"id": f"T{i}", "type": "inspect"} for i in range(20_000)]
    with pytest.raises(SpecError) as info:
        check_mission_scale(_source({"agents": agents, "tasks": tasks}))
    assert [d.format() for d in info.value.diagnostics] == [
        "big.yaml:6:1: agents: the number of agents is 5,000, the limit is 1,000 "
        "(set BTMISSION_MAX_AGENTS to change it)",
        "big.yaml:9:1: tasks: the number of tasks is 20,000, the limit is 10,000 "
        "(set BTMISSION_MAX_TASKS to change it)",
    ]
    check_mission_scale(_source({"agents": agents[:1000], "tasks": tasks[:10_000]}))


def test_mission_scale_limits_on_the_command_line(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    text = MISSION.replace(
        "tasks:\n", "  - {id: G2, library: ground, start: [2, 1, 0]}\ntasks:\n"
    ).replace("task_types:", "  - {id: T2, type: inspect, location: [5, 3, 0]}\ntask_types:")
    p = mission(tmp_path, text)
    monkeypatch.setenv("BTMISSION_MAX_AGENTS", "1")
    monkeypatch.setenv("BTMISSION_MAX_TASKS", "1")
    t0 = time.perf_counter()
    out = refused(runner, "validate", p)
    assert time.perf_counter() - t0 < REFUSED_BEFORE_S
    assert (
        "m.yaml:6:1: agents: the number of agents is 2, the limit is 1 "
        "(set BTMISSION_MAX_AGENTS to change it)"
    ) in out
    assert "m.yaml:9:1: tasks: the number of tasks is 2, the limit is 1" in out


def test_sim_step_has_a_lower_bound(runner: CliRunner, tmp_path: Path) -> None:
    p = mission(tmp_path, MISSION + "runtime:\n  sim: {step_s: 0.00001}\n")
    out = refused(runner, "validate", p)
    assert (
        "m.yaml:13:17: runtime.sim.step_s: step_s is 1e-05 s, below the smallest step 0.001 s "
        "(set BTMISSION_MIN_STEP_S to change it)"
    ) in out


# ------------------------------------------------------------------------------ event logs
def test_report_reads_only_a_regular_log_within_its_budget(
    runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = refused(runner, "report", "/dev/urandom")
    assert "/dev/urandom: not a regular file but a character device" in out
    fifo = tmp_path / "run.jsonl"
    os.mkfifo(fifo)
    out = _in_thread(lambda: refused(runner, "report", str(fifo)))
    assert "not a regular file but a FIFO (named pipe)" in out
    log = Path(__file__).resolve().parents[2] / "docs" / "examples" / "pick_and_deliver.jsonl"
    monkeypatch.setenv("BTMISSION_MAX_LOG_BYTES", "1000")
    out = refused(runner, "report", str(log))
    assert f"{log}: file too large: {log.stat().st_size:,} bytes, the limit is 1,000 bytes" in out
    assert "(set BTMISSION_MAX_LOG_BYTES to change it)" in out
    monkeypatch.delenv("BTMISSION_MAX_LOG_BYTES")
    r = runner.invoke(cli, ["report", str(log)])
    assert r.exit_code == 0 and "Tasks done              3 of 3" in r.output
