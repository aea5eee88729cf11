"""Mission fields for MAVLink frames: an agent's ``origin:`` (where its EKF origin and its north
are in the world) and ``world.origin`` (the world on the globe), with the accessors the MAVLink
provider calls (btmission.backends.mavlink_frames.agent_frame / mission_geodetic_origin)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from btmission.backends.mavlink_frames import (
    GeodeticOrigin,
    LocalFrame,
    agent_frame,
    local_frame,
    mission_geodetic_origin,
)
from btmission.cli.main import cli
from btmission.diagnostics import SpecError
from btmission.missions import load_mission, load_mission_text
from btmission.spec.schema import json_schema

ROOT = Path(__file__).resolve().parents[3]
GOOD = ROOT / "docs" / "examples" / "mavlink_origin.yaml"
BAD = ROOT / "docs" / "examples" / "bad_mavlink_origin.yaml"

MISSION = """\
mission: m
version: 1
world:
  map: {{generate: empty, size: [20, 20, 4]}}
{world}agents:
  - {{id: R1, library: aerial, start: [2, 2, 0], backend: {backend}{agent}}}
tasks:
  - {{id: T1, type: inspect, location: [10, 10, 1.5]}}
task_types:
  inspect: {{goal: at_goal(location), cost: path_cost(location)}}
"""
UDP = '"mavlink+udp://127.0.0.1:14540"'


def mission_text(world: str = "", agent: str = "", backend: str = UDP) -> str:
    return MISSION.format(world=world and f"  origin: {world}\n", agent=agent, backend=backend)


def problems(text: str) -> list[str]:
    with pytest.raises(SpecError) as exc:
        load_mission_text(text, "f.yaml")
    return [d.format() for d in exc.value.diagnostics]


def test_the_documented_example_validates_and_gives_each_agent_its_frame() -> None:
    r = CliRunner().invoke(cli, ["validate", str(GOOD)])
    assert r.exit_code == 0 and "mission 'mavlink_origin' OK — 3 agent(s)" in r.stdout
    m = load_mission(GOOD)
    # R1: no origin — its start, north along world +y
    assert agent_frame(m, "R1") == LocalFrame((2.0, 2.0, 0.0), math.pi / 2)
    np.testing.assert_allclose(agent_frame(m, "R1").to_local((2, 3, 0)), [1, 0, 0], atol=1e-12)
    # R2: origin [3, 2, 0], the shorthand; its start is 1 m east (+x) of it
    r2 = agent_frame(m, "R2")
    assert r2.origin == (3.0, 2.0, 0.0) and r2.north_yaw == math.pi / 2
    np.testing.assert_allclose(r2.to_local((4, 2, 0)), [0, 1, 0], atol=1e-12)
    # R3: north along world +x: world +y is its west, local -y; world yaw 0 is heading north
    r3 = agent_frame(m, "R3")
    assert r3.north_yaw == 0.0
    np.testing.assert_allclose(r3.to_local((7, 3, 1)), [1, -1, -1], atol=1e-12)
    assert r3.yaw_to_local(0.0) == 0.0 and r3.yaw_to_local(math.pi / 2) == -math.pi / 2
    assert mission_geodetic_origin(m) == GeodeticOrigin(47.397742, 8.545594, 488.0)


def test_no_world_origin_gives_none_and_an_unknown_agent_a_key_error() -> None:
    m = load_mission_text(mission_text(), "f.yaml")
    assert mission_geodetic_origin(m) is None
    with pytest.raises(KeyError):
        agent_frame(m, "R9")


def test_sim_agents_accept_and_ignore_the_fields() -> None:
    m = load_mission_text(
        mission_text("{lat: 0, lon: 0}", ", origin: [1, 1, 0]", backend="sim"), "f.yaml"
    )
    assert m.agents[0].start == (2.0, 2.0, 0.0)  # the simulator spawns it at its start
    assert agent_frame(m, "R1").origin == (1.0, 1.0, 0.0)


@pytest.mark.parametrize(
    ("deg", "rad"),
    [(90, math.pi / 2), (450, math.pi / 2), (270, -math.pi / 2), (-45, -math.pi / 4)],
)
def test_north_yaw_is_degrees_counter_clockwise_from_x_wrapped(deg: float, rad: float) -> None:
    assert local_frame((0, 0, 0), deg).north_yaw == pytest.approx(rad)
    m = load_mission_text(
        mission_text(agent=f", origin: {{position: [0, 0, 0], north_yaw_deg: {deg}}}"), "f.yaml"
    )
    assert agent_frame(m, "R1").north_yaw == pytest.approx(rad)


@pytest.mark.parametrize("lon", [-180, 180, 0.5])
def test_longitudes_at_the_date_line_are_accepted(lon: float) -> None:
    m = load_mission_text(mission_text(f"{{lat: -89.9, lon: {lon}, alt: -12.5}}"), "f.yaml")
    assert mission_geodetic_origin(m) == GeodeticOrigin(-89.9, float(lon), -12.5)


@pytest.mark.parametrize(
    ("world", "expected"),
    [
        (
            "{lat: 90, lon: 0}",
            "5:17: world.origin.lat: expected a latitude in degrees, -90 < lat < 90 (got 90)",
        ),
        (
            "{lat: -91.5, lon: 0}",
            "5:17: world.origin.lat: expected a latitude in degrees, -90 < lat < 90 (got -91.5)",
        ),
        (
            "{lat: 1, lon: 180.5}",
            "5:25: world.origin.lon: expected a longitude in degrees, "
            "-180 <= lon <= 180 (got 180.5)",
        ),
        (
            "{lat: 1, lon: -181}",
            "5:25: world.origin.lon: expected a longitude in degrees, "
            "-180 <= lon <= 180 (got -181)",
        ),
        (
            "{lat: 1, lon: 2, alt: .inf}",
            "5:33: world.origin.alt: expected a finite number (got inf)",
        ),
        ("{lat: true, lon: 2}", "5:17: world.origin.lat: expected a number (got true)"),
        ("{lat: 1}", "5:3: world.origin.lon: missing required key 'lon'"),
        ("{lat: 1, lon: 2, height: 3}", "5:28: world.origin.height: unknown key 'height'"),
        ("[47.4, 8.5]", "5:11: world.origin: expected a mapping of keys"),
    ],
)
def test_bad_world_origin_is_refused_at_its_line(world: str, expected: str) -> None:
    out = problems(mission_text(world))
    assert len(out) == 1 and out[0].startswith(f"f.yaml:{expected}"), out


@pytest.mark.parametrize(
    ("agent", "expected"),
    [
        (
            ", origin: [1, 2]",
            "6:99: agents[0].origin: expected [x, y, z] or "
            "{position: [x, y, z], north_yaw_deg: 90}, with finite numbers (got [1, 2])",
        ),
        (
            ", origin: [1, 2, .nan]",
            "6:99: agents[0].origin: expected [x, y, z] or "
            "{position: [x, y, z], north_yaw_deg: 90}, with finite numbers (got [1, 2, nan])",
        ),
        (
            ", origin: home",
            "6:99: agents[0].origin: expected [x, y, z] or "
            "{position: [x, y, z], north_yaw_deg: 90} (got 'home')",
        ),
        (
            ", origin: {north_yaw_deg: 0}",
            "6:91: agents[0].origin.position: missing required key 'position'",
        ),
        (
            ", origin: {position: [1, 2, 3], north_yaw_deg: .nan}",
            "6:136: agents[0].origin.north_yaw_deg: expected a finite number (got nan)",
        ),
        (
            ", origin: {position: [1, 2, 3], north_yaw_deg: east}",
            "6:136: agents[0].origin.north_yaw_deg: Input should be a valid number",
        ),
        (
            ", origin: {position: [1, 2, 3], yaw: 90}",
            "6:121: agents[0].origin.yaw: unknown key 'yaw'",
        ),
    ],
)
def test_bad_agent_origin_is_refused_at_its_line(agent: str, expected: str) -> None:
    out = problems(mission_text(agent=agent))
    assert len(out) == 1 and out[0].startswith(f"f.yaml:{expected}"), out


def test_the_bad_example_exits_2_with_every_problem_and_its_line() -> None:
    r = CliRunner().invoke(cli, ["validate", str(BAD)])
    assert r.exit_code == 2 and "Traceback" not in r.output
    f = str(BAD)
    lines = r.output.splitlines()
    assert [line.split(": ", 1)[0].removeprefix(f) for line in lines[:-1]] == [
        ":6:17",
        ":6:39",
        ":8:57",
        ":9:79",
        ":10:57",
    ]
    assert lines[-1] == "Error: 5 problem(s) found; nothing was run"


def test_the_schema_describes_both_forms_of_origin_and_the_geodetic_origin() -> None:
    schema = json_schema("mission")
    defs = schema["$defs"]
    origin = defs["AgentSpec"]["properties"]["origin"]
    kinds = {v.get("type") or v.get("$ref", "").rsplit("/", 1)[-1] for v in origin["anyOf"]}
    assert kinds == {"array", "OriginSpec", "null"}
    assert set(defs["OriginSpec"]["properties"]) == {"position", "north_yaw_deg"}
    assert defs["OriginSpec"]["properties"]["north_yaw_deg"]["default"] == 90.0
    world = defs["WorldSpec"]["properties"]["origin"]
    assert {"$ref": "#/$defs/GeodeticSpec"} in world["anyOf"]
    assert set(defs["GeodeticSpec"]["required"]) == {"lat", "lon"}
