"""Loading library and mission files: every problem reported, each with file:line:col and item."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from btmission.diagnostics import Severity, SpecError
from btmission.missions import load_mission, load_mission_text
from btmission.spec.costexpr import CostExprError, parse_cost
from btmission.spec.library import load_library_file, load_library_text
from btmission.spec.refs import RefSyntaxError, parse_ref
from btmission.spec.schema import json_schema

ROOT = Path(__file__).resolve().parents[3]


def problems(fn, text: str) -> list[str]:  # type: ignore[no-untyped-def]
    with pytest.raises(SpecError) as exc:
        fn(textwrap.dedent(text).lstrip("\n"), "f.yaml")
    return [d.format() for d in exc.value.diagnostics]


# ---- YAML and schema ----------------------------------------------------------------------------
def test_yaml_syntax_error_reports_its_line() -> None:
    out = problems(
        load_library_text,
        """
        library: x
        version: 1
        conditions:
          a: {doc: "unterminated}
        actions: {}
    """,
    )
    assert len(out) == 1 and out[0].startswith("f.yaml:4:") and "YAML syntax error" in out[0]


def test_bad_indentation_reports_its_line() -> None:
    out = problems(load_library_text, "library: x\nversion: 1\nconditions:\n  a: 1\n b: 2\n")
    assert out[0].startswith("f.yaml:5:")


def test_duplicate_keys_are_errors_not_silently_overwritten() -> None:
    out = problems(
        load_library_text,
        """
        library: x
        version: 1
        conditions: {a: ""}
        actions:
          go: {post: [a]}
          go: {post: [a]}
    """,
    )
    assert out == ["f.yaml:6:3: actions.go: duplicate key 'go' (first defined on line 5)"]


def test_empty_and_non_mapping_files() -> None:
    assert problems(load_library_text, "") == ["f.yaml:1:1: the file is empty"]
    assert "top level" in problems(load_library_text, "- a\n- b\n")[0]


def test_every_schema_problem_is_reported_with_its_line() -> None:
    out = problems(
        load_library_text,
        """
        library: bad name
        version: 2
        colour: red
        conditions:
          a: {doc: x, parms: [p]}
        actions:
          go: {post: a, cost: -1}
    """,
    )
    joined = "\n".join(out)
    assert "f.yaml:1:10: library: 'bad name' is not a valid name" in joined
    assert "f.yaml:2:10: version: got 2, expected 1" in joined
    assert "f.yaml:3:1: colour: unknown key 'colour'" in joined
    assert "f.yaml:5:15: conditions.a.parms: unknown key 'parms'" in joined
    assert "f.yaml:7:14: actions.go.post:" in joined
    assert "f.yaml:7:23: actions.go.cost:" in joined and "greater than or equal to 0" in joined
    assert len(out) == 6, out


def test_flow_list_comma_trap_is_explained() -> None:
    _lib, diags = load_library_text(
        textwrap.dedent("""
        library: x
        version: 1
        conditions: {d: {params: [a, b]}}
        actions:
          go: {params: [a, b], post: [d(a, b)]}
    """).lstrip(),
        "f.yaml",
    )
    assert any("quote references with several arguments" in d.message for d in diags)


def test_missing_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(SpecError) as exc:
        load_library_file(tmp_path / "nope.yaml")
    assert exc.value.diagnostics[0].message == "file not found"


@pytest.mark.parametrize(
    ("text", "ok"),
    [
        ("a", True),
        ("a()", True),
        ("a(x, y)", True),
        ("a(x, y=z)", True),
        ("a(x=y, z)", False),
        ("a(1)", False),
        ("a(x", False),
        ("1a", False),
        ("a(x, x=y)", True),
        ("a(p=x, p=y)", False),
    ],
)
def test_reference_syntax(text: str, ok: bool) -> None:
    if ok:
        parse_ref(text)
    else:
        with pytest.raises(RefSyntaxError):
            parse_ref(text)


def test_cost_expressions() -> None:
    c = parse_cost("path_cost(pickup) + path_cost(pickup, dropoff)")
    assert c.symbols == ("dropoff", "pickup")
    calls: list[tuple[str, tuple[object, ...]]] = []

    def fake(fn: str, args: tuple[object, ...]) -> float:
        calls.append((fn, args))
        return 10.0 if len(args) == 1 else 5.0

    assert c.evaluate(fake, {"pickup": "P", "dropoff": "D"}) == 15.0
    assert calls == [("path_cost", ("P",)), ("path_cost", ("P", "D"))]
    assert parse_cost("2 * distance(a) - 1").evaluate(lambda f, a: 3.0, {"a": 0}) == 5.0
    for bad in [
        "",
        "path_cost(a) ** 2",
        "open('x')",
        "path_cost(a, b, c)",
        "path_cost(1)",
        "a.b",
        "'s'",
        "path_cost(",
    ]:
        with pytest.raises(CostExprError):
            parse_cost(bad)


def test_json_schemas_are_generated() -> None:
    lib = json_schema("library")
    mis = json_schema("mission")
    assert lib["$schema"].endswith("2020-12/schema")
    assert set(lib["required"]) == {"library", "version", "conditions", "actions"}
    assert {"mission", "version", "world", "agents", "task_types"} <= set(mis["required"])
    assert lib["additionalProperties"] is False


# ---- missions -----------------------------------------------------------------------------------
MISSION = """
mission: m
version: 1
world:
  map: {generate: mine, seed: 1, size: [50, 30, 8]}
agents:
  - {id: R1, library: aerial, start: [1, 1, 0]}
  - {id: G1, library: ground, start: [2, 1, 0]}
tasks:
  - {id: T1, type: inspect, location: [10, 2, 2]}
  - {id: P1, type: pick_and_deliver, pickup: [3, 3, 0], dropoff: [9, 9, 0], at: 5}
task_types:
  inspect: {goal: at_goal(location), cost: path_cost(location)}
  pick_and_deliver:
    goal: delivered(pickup, dropoff)
    commit_after: holding(pickup)
    cost: path_cost(pickup) + path_cost(pickup, dropoff)
    priority: 2
default_behavior: {goal: at_goal(home), idle_timeout_s: 4}
"""


def test_valid_mission_loads_with_typed_model() -> None:
    m = load_mission_text(MISSION, "m.yaml")
    assert [a.id for a in m.agents] == ["R1", "G1"]
    p1 = m.tasks[1]
    assert (p1.type, p1.at, p1.priority, dict(p1.fields)) == (
        "pick_and_deliver",
        5.0,
        2.0,
        {"pickup": [3, 3, 0], "dropoff": [9, 9, 0]},
    )
    tt = m.task_types["pick_and_deliver"]
    assert str(tt.commit_after) == "holding(pickup)" and tt.fields == ("dropoff", "pickup")
    # the aerial library has no 'delivered': its agents cannot do that type (a note, not an error)
    notes = [d for d in m.diagnostics if d.code == "cannot-do"]
    assert len(notes) == 1 and notes[0].severity is Severity.INFO and "R1" in notes[0].message


@pytest.mark.parametrize("name", ["mine_inspection", "pick_and_deliver"])
def test_shipped_missions_validate(name: str) -> None:
    m = load_mission(ROOT / "missions" / f"{name}.yaml")
    assert not [d for d in m.diagnostics if d.severity is not Severity.INFO]


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        (
            "id: G1",
            "id: R1",
            "f.yaml:7:10: agents[1].id: duplicate agent id 'R1' (first used on line 6)",
        ),
        (
            "id: P1",
            "id: T1",
            "f.yaml:10:10: tasks[1].id: duplicate task id 'T1' (first used on line 9)",
        ),
        (
            "library: ground",
            "library: grund",
            "f.yaml:7:23: agents[1].library: unknown library 'grund'",
        ),
        (
            "type: inspect",
            "type: inspekt",
            "f.yaml:9:20: tasks[0].type: unknown task type 'inspekt' (did you mean 'inspect'?)",
        ),
        (
            "location: [10, 2, 2]",
            "place: [10, 2, 2]",
            "f.yaml:9:5: tasks[0]: task 'T1' of type 'inspect' lacks field 'location'",
        ),
        (
            "location: [10, 2, 2]}",
            "location: [10, 2, 2], colour: red}",
            "f.yaml:9:51: tasks[0].colour: unknown key 'colour' for a task of type 'inspect'",
        ),
        (
            "location: [10, 2, 2]",
            "location: [10, 2]",
            "f.yaml:9:39: tasks[0].location: task field 'location': expected a position [x, y, z]",
        ),
        (
            "goal: at_goal(location)",
            "goal: at_gaol(location)",
            "f.yaml:12:19: task_types.inspect.goal: undefined condition 'at_gaol' (did you mean 'at_goal'?)",
        ),
        (
            "cost: path_cost(location)}",
            "cost: path_cost(location) ** 2}",
            "f.yaml:12:44: task_types.inspect.cost: operator ** is not allowed",
        ),
        (
            "commit_after: holding(pickup)",
            "commit_after: holding(dropoff)",
            "f.yaml:15:19: task_types.pick_and_deliver.commit_after: 'holding(dropoff)' never occurs",
        ),
        (
            "commit_after: holding(pickup)",
            "commit_after: holding(thing)",
            "uses thing, which the goal does not",
        ),
        (
            "start: [1, 1, 0]}",
            "start: [1, 1, 0], backend: 'Mavlink sim'}",
            "f.yaml:6:58: agents[0].backend: expected 'sim' or a vehicle provider's URL "
            "<scheme>://<address>",
        ),
        (
            "goal: at_goal(home)",
            "goal: at_goal(spot)",
            "f.yaml:18:26: default_behavior.goal: the default behaviour has no task, but its goal uses spot",
        ),
        (
            "size: [50, 30, 8]",
            "size: [50, 0, 8]",
            "f.yaml:4:40: world.map.size: every size component must be > 0",
        ),
        (
            "{generate: mine, seed: 1, size: [50, 30, 8]}",
            "{file: maps/none.npz}",
            "f.yaml:4:15: world.map.file: map file 'maps/none.npz' not found",
        ),
        ("version: 1", "version: 3", "f.yaml:2:10: version: got 3, expected 1"),
    ],
)
def test_bad_missions_name_file_line_and_item(old: str, new: str, expected: str) -> None:
    assert old in MISSION
    out = problems(load_mission_text, MISSION.replace(old, new, 1))
    assert any(expected in line for line in out), "\n".join(out)


def test_max_attempts_and_the_retry_settings_of_coordination() -> None:
    """A task type's ``max_attempts`` (default 3) reaches each task's pool entry; the
    coordination's ``cooldown_s`` (30) and ``exclude_after`` (3) the auction's config."""
    from btmission.allocation.auction import AuctionConfig
    from btmission.runtime.mission_auction import pool_from_mission

    m = load_mission_text(MISSION, "m.yaml")
    assert m.task_types["inspect"].max_attempts == 3
    text = MISSION.replace("priority: 2", "priority: 2\n    max_attempts: 5")
    text += "coordination: {cooldown_s: 12.5, exclude_after: 0}\n"
    m = load_mission_text(text, "m.yaml")
    pool = pool_from_mission(m)
    assert (pool["T1"].info.max_attempts, pool["P1"].info.max_attempts) == (3, 5)
    cfg = AuctionConfig.from_spec(m.spec.coordination)
    assert (cfg.cooldown_s, cfg.exclude_after) == (12.5, 0)
    for bad, expected in [
        (
            "max_attempts: 0",
            "18:19: task_types.pick_and_deliver.max_attempts: Input should be "
            "greater than or equal to 1 (got 0)",
        ),
        ("max_attempts: 1.5", "18:19: task_types.pick_and_deliver.max_attempts:"),
    ]:
        out = problems(load_mission_text, MISSION.replace("priority: 2", f"priority: 2\n    {bad}"))
        assert any(expected in line for line in out), "\n".join(out)
    out = problems(load_mission_text, MISSION + "coordination: {cooldown_s: -1}\n")
    assert any("coordination.cooldown_s" in line for line in out), "\n".join(out)
    schema = json_schema("mission")["$defs"]
    assert schema["TaskTypeSpec"]["properties"]["max_attempts"]["default"] == 3
    assert set(schema["CoordinationSpec"]["properties"]) >= {"cooldown_s", "exclude_after"}


def test_many_mission_problems_are_reported_together() -> None:
    text = (
        MISSION.replace("id: G1", "id: R1")
        .replace("type: inspect", "type: nope")
        .replace("auction", "x")
    )
    out = problems(load_mission_text, text)
    assert len(out) >= 2


def test_mission_library_by_relative_path(tmp_path: Path) -> None:
    (tmp_path / "libs").mkdir()
    (tmp_path / "libs" / "mini.yaml").write_text(
        "library: mini\nversion: 1\nconditions: {at_goal: {params: [goal]}}\n"
        "actions:\n  go: {params: [goal], post: [at_goal(goal)]}\n"
    )
    (tmp_path / "m.yaml").write_text(
        "mission: m\nversion: 1\nworld: {map: {generate: empty, size: [10, 10, 3]}}\n"
        "agents: [{id: A, library: libs/mini.yaml, start: [0, 0, 0]}]\n"
        "tasks: [{id: T, type: go, location: [1, 1, 0]}]\n"
        "task_types: {go: {goal: at_goal(location), cost: distance(location)}}\n"
    )
    m = load_mission(tmp_path / "m.yaml")
    assert m.library_of("A").library.name == "mini"


def test_shipped_files_validate_against_the_published_json_schemas() -> None:
    """Editors use `btmission schema`: our own libraries and missions must pass it (including the
    `name: "doc"` shorthand)."""
    import jsonschema
    import yaml

    for kind, files in (
        ("library", sorted((ROOT / "library").glob("*.yaml"))),
        ("mission", sorted((ROOT / "missions").glob("*.yaml"))),
    ):
        validator = jsonschema.Draft202012Validator(json_schema(kind))
        assert files
        for f in files:
            errs = [e.message for e in validator.iter_errors(yaml.safe_load(f.read_text()))]
            assert errs == [], f"{f.name}: {errs}"


def test_exponent_numbers_read_as_numbers_as_in_yaml_1_2() -> None:
    """PyYAML (YAML 1.1) would read 1e5 as the string '1e5'; btmission reads it as a number."""
    from btmission.spec.source import parse_yaml

    data = parse_yaml("a: [1e5, 2.5e-3, -1E+2, .5e1, 12, 1.5, '1e5', 1e, e5]").data
    assert data == {"a": [1e5, 2.5e-3, -100.0, 5.0, 12, 1.5, "1e5", "1e", "e5"]}
    assert type(data["a"][4]) is int


def test_subsystem_configs_come_from_their_sections_by_name() -> None:
    """config_from carries every field a section and its config share (no hand-copied lists);
    the section fields no config takes are the ones read elsewhere, and no others."""
    import dataclasses

    from btmission.backends.mavlink_link import MavlinkOptions
    from btmission.backends.sim import SimConfig
    from btmission.spec.common import config_from
    from btmission.spec.sections import MavlinkSpec, SimSpec

    read_elsewhere = {
        (SimSpec, SimConfig): {"artifacts"},  # placed in the world (sim_provider.mission_artifacts)
        (MavlinkSpec, MavlinkOptions): {"map_sensors"},  # the provider factory's choice
    }
    for (section, config), elsewhere in read_elsewhere.items():
        assert set(section.model_fields) - {f.name for f in dataclasses.fields(config)} == elsewhere
    sim = SimSpec(step_s=0.1, lidar_range_m=3.0, dust_points=4, pose_noise_m=0.2)
    made = config_from(SimConfig, sim)
    assert (made.step_s, made.lidar_range_m, made.dust_points, made.pose_noise_m) == (
        0.1,
        3.0,
        4,
        0.2,
    )
    assert made.body_radius_m == SimConfig().body_radius_m  # not in the file: its default
    options = config_from(MavlinkOptions, MavlinkSpec(setpoint_hz=30.0), signing_key=b"k" * 32)
    assert options.setpoint_hz == 30.0 and options.signing_key == b"k" * 32
