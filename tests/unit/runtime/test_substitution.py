"""Leaf substitution (btmission.runtime.substitution) and the fake vehicle provider in runs.

The model is BehaviorTree.CPP's substitution rules: a wildcard pattern per rule, the first
matching rule replaces the leaf, and a test node answers SUCCESS or FAILURE, optionally after a
delay and with a post-condition (here ``effect``)."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import pytest
from py_trees.common import Status

from btmission.backends.fake import FakeVehicle
from btmission.missions import load_mission_text
from btmission.runtime import actions as A
from btmission.runtime.events import Recorder, read_events
from btmission.runtime.leaves import AgentContext, ConditionLeaf, StatefulAction
from btmission.runtime.runner import MissionRun
from btmission.runtime.session import RunSession
from btmission.runtime.substitution import (
    Rule,
    SubstitutionError,
    Substitutions,
    TestAction,
    TestLeaf,
)
from btmission.spec.mission import Mission
from btmission.synthesis.tree import Arg, Kind, Node

MISSION = """
mission: substituted
version: 1
world:
  map: {{generate: empty, size: [30, 20, 6]}}
  resolution: 0.5
agents:
  - {{id: R1, library: aerial, start: [2, 2, 0], backend: {backend}}}
  - {{id: R2, library: aerial, start: [2, 18, 0], backend: {backend}}}
tasks:
  - {{id: T1, type: inspect, location: [25, 5, 2]}}
  - {{id: T2, type: inspect, location: [25, 15, 2]}}
task_types:
  inspect: {{goal: at_goal(location), cost: path_cost(location)}}
default_behavior: {{goal: at_goal(home), idle_timeout_s: 1}}
runtime: {{controller: track, max_duration_s: 120}}
"""


def mission(tmp_path: Path, backend: str = "fake") -> Mission:
    text = textwrap.dedent(MISSION.format(backend=backend)).lstrip()
    path = tmp_path / "m.yaml"
    path.write_text(text)
    return load_mission_text(text, str(path))


def climb(ctx: AgentContext, **_: Any) -> None:
    """A take-off done at once: the fake vehicle is put 2 m up, and held there."""
    assert isinstance(ctx.backend, FakeVehicle)
    p = ctx.telemetry().position
    ctx.backend.teleport((p[0], p[1], p[2] + 2.0))
    ctx.navigator.hold()


def arrive(ctx: AgentContext, goal: Any) -> None:
    """A flight done at once: the fake vehicle is put at the goal's flight target."""
    assert isinstance(ctx.backend, FakeVehicle)
    ctx.backend.teleport(ctx.navigator.flight_target(A.point(goal)))
    ctx.navigator.hold()


FLY = {"takeoff": TestLeaf(effect=climb), "follow_path*": TestLeaf(after_s=2.0, effect=arrive)}


def leaves(run: MissionRun, agent: str, label: str) -> list[Any]:
    """The leaves (not the composites named after them) labelled ``label`` in a tree."""
    found = [b for b in run.agents[agent].root.iterate() if b.name == label and not b.children]
    assert found
    return found


# ------------------------------------------------------------------------------ in a run
def test_a_mission_with_its_flight_leaves_substituted_completes(tmp_path: Path) -> None:
    events = Recorder()
    run = MissionRun(mission(tmp_path), observers=[events], substitutions=FLY)
    # the matching leaves are test leaves; every other leaf is the library's own
    for agent in ("R1", "R2"):
        assert all(isinstance(b, TestAction) for b in leaves(run, agent, "takeoff"))
        assert all(isinstance(b, TestAction) for b in leaves(run, agent, "follow_path(home)"))
        assert all(isinstance(b, A.Arm) for b in leaves(run, agent, "arm"))
        assert all(isinstance(b, A.UpdatePath) for b in leaves(run, agent, "update_path(home)"))
    result = run.run()
    assert result.reason == "completed" and sorted(result.done) == ["T1", "T2"]
    # each flight took the test leaf's 2 s, and ended where the effect put the vehicle
    stages = [(e.t, e.get("agent")) for e in events.of("stage")
              if e.get("action") == "follow_path(location)"]  # fmt: skip
    done = {e.get("task"): e.t for e in events.of("task") if e.get("state") == "done"}
    assert len(stages) == 2 and all(done[t] >= s + 2.0 for (s, _), t in zip(stages, ("T1", "T2")))
    assert max(done.values()) < 10.0  # no 25 m flights: about 6 s of mission time
    homes = {a: run.agents[a].ctx.blackboard["home"] for a in ("R1", "R2")}
    for a, home in homes.items():
        p = run.vehicles[a].backend.telemetry().position
        assert p[:2].tolist() == pytest.approx(list(home[:2])) and p[2] == pytest.approx(2.0)


def test_the_fake_provider_flies_the_same_mission_without_substitutions(tmp_path: Path) -> None:
    """The fake vehicles follow the navigator's setpoints: D*+ routes, track controller."""
    events = Recorder()
    run = MissionRun(mission(tmp_path), observers=[events])
    assert all(v.sensors is None for v in run.vehicles.values())
    result = run.run()
    assert result.reason == "completed" and sorted(result.done) == ["T1", "T2"]
    assert result.collisions == 0
    odometer = {e.get("agent"): e.get("odometer_m") for e in events.of("pose")}
    assert all(d > 40.0 for d in odometer.values())  # there and back: 2 × ~23 m


def test_a_substituted_failure_fails_the_task_with_its_reason(tmp_path: Path) -> None:
    # (before FLY's rules: the first matching rule wins)
    subs = {"R1/follow_path(location)": TestLeaf(Status.FAILURE, reason="blocked by a test"), **FLY}
    with RunSession(mission(tmp_path), log_dir=tmp_path, substitutions=subs) as session:
        result = session.run()
        report = session.report()
    assert result is not None and result.reason == "finished with open tasks"
    # R1's failure: its task fails with the test leaf's reason; R2's flights still succeed
    log = read_events(session.log_path).events  # type: ignore[arg-type]
    failed = [e for e in log if e.kind == "task" and e.get("state") == "failed"]
    assert failed and failed[0].get("agent") == "R1"
    assert failed[0].get("reason") == "follow_path(location): blocked by a test"
    assert report.summary.tasks_done >= 1
    # without a reason, the failure names the rule that substituted the leaf
    run = MissionRun(mission(tmp_path), substitutions={
        "follow_path(location)": TestLeaf(Status.FAILURE), **FLY})  # fmt: skip
    result = run.run(until=5.0)
    reasons = {t.note for t in run.coordinator.state.pool}
    assert "follow_path(location): substituted by rule 'follow_path(location)'" in reasons


def test_after_s_keeps_the_leaf_running_for_that_much_mission_time(tmp_path: Path) -> None:
    finished: dict[str, float] = {}

    def stamp(ctx: AgentContext, **_: Any) -> None:
        finished[ctx.agent_id] = ctx.now()
        climb(ctx)

    events = Recorder()
    run = MissionRun(
        mission(tmp_path),
        observers=[events],
        substitutions={**FLY, "takeoff": TestLeaf(after_s=4.5, effect=stamp)},
    )
    run.run(until=12.0)
    tick = 1.0 / run.mission.spec.runtime.tick_hz
    for agent in ("R1", "R2"):
        stages = [(e.t, e.get("action")) for e in events.of("stage") if e.get("agent") == agent]
        started = next(t for t, action in stages if action == "takeoff")
        assert started + 4.5 <= finished[agent] < started + 4.5 + tick + 1e-9
        # what comes after the take-off in the tree started only once it had finished
        after = next(t for t, action in stages if action == "update_path(location)")
        assert after >= finished[agent]


# ------------------------------------------------------------------------------ patterns
def node(name: str, *args: str, kind: Kind = Kind.ACTION) -> Node:
    return Node(kind, name, tuple(Arg(f"p{i}", a, literal=False) for i, a in enumerate(args)))


@pytest.mark.parametrize(
    ("pattern", "agent", "leaf", "matches"),
    [
        ("takeoff", "R1", node("takeoff"), True),
        ("takeoff", "R1", node("takeoff_now"), False),
        ("follow_path*", "R1", node("follow_path", "goal"), True),  # the name
        ("follow_path(goal)", "R1", node("follow_path", "goal"), True),  # the label
        ("follow_path(goal)", "R1", node("follow_path", "home"), False),
        ("*(home)", "R1", node("update_path", "home"), True),
        ("R1/land", "R1", node("land"), True),
        ("R1/land", "R2", node("land"), False),
        ("R?/follow_path(home)", "R2", node("follow_path", "home"), True),
        ("Takeoff", "R1", node("takeoff"), False),  # case-sensitive
    ],
)
def test_patterns_match_names_labels_and_agents(
    pattern: str, agent: str, leaf: Node, matches: bool
) -> None:
    assert Rule(pattern, TestLeaf()).matches(agent, leaf) is matches


def test_the_first_matching_rule_wins_and_replacements_of_every_kind() -> None:
    class Stay(StatefulAction):
        def on_start(self) -> Status:
            return Status.RUNNING

    def never(ctx: AgentContext, **_: Any) -> bool:
        return False

    subs = Substitutions([("follow_path(home)", Stay), ("follow_path*", TestLeaf()),
                          ("is_*", never)])  # fmt: skip
    assert subs.rule_for("R1", node("follow_path", "home")) is subs.rules[0]
    assert subs.rule_for("R1", node("follow_path", "goal")) is subs.rules[1]
    assert subs.rule_for("R1", node("land")) is None
    ctx: Any = object()
    assert type(subs.leaf("R1", node("follow_path", "home"), ctx)) is Stay
    assert type(subs.leaf("R1", node("follow_path", "goal"), ctx)) is TestAction
    cond = subs.leaf("R1", node("is_armed", kind=Kind.CONDITION), ctx)
    assert isinstance(cond, ConditionLeaf) and cond.fn is never
    assert subs.leaf("R1", node("land"), ctx) is None
    # a test leaf in a condition's place answers at once (a ConditionLeaf: commit points work)
    const = Substitutions({"is_*": TestLeaf(Status.FAILURE)}).leaf(
        "R1", node("is_armed", kind=Kind.CONDITION), ctx
    )
    assert isinstance(const, ConditionLeaf) and const.fn(ctx) is False


def test_a_rule_that_replaces_no_leaf_is_an_error_before_anything_is_written(
    tmp_path: Path,
) -> None:
    m = mission(tmp_path)
    with pytest.raises(SubstitutionError) as exc:
        MissionRun(m, substitutions={"takeof": TestLeaf(), "takeoff": TestLeaf()})
    assert "rule(s) 'takeof' replace no leaf" in str(exc.value)
    assert "takeoff" in str(exc.value) and "follow_path(location)" in str(exc.value)
    # shadowed: every leaf it matches was taken by an earlier rule
    with pytest.raises(SubstitutionError, match=r"'follow_path\(home\)' replace no leaf"):
        MissionRun(m, substitutions=[("follow_path*", TestLeaf()),
                                     ("follow_path(home)", TestLeaf())])  # fmt: skip
    logs = tmp_path / "logs"
    with pytest.raises(SubstitutionError, match="'R3/takeoff'"):
        with RunSession(m, log_dir=logs, substitutions={"R3/takeoff": TestLeaf()}) as session:
            session.run()
    assert not logs.exists() or not any(logs.iterdir())  # no log was started


def test_bad_rules_are_refused() -> None:
    with pytest.raises(SubstitutionError, match="SUCCESS or FAILURE"):
        TestLeaf(Status.RUNNING)
    with pytest.raises(SubstitutionError, match="after_s must be >= 0"):
        TestLeaf(after_s=-1.0)
    with pytest.raises(SubstitutionError, match="rule 'land': the replacement must be"):
        Substitutions({"land": "SUCCESS"})  # type: ignore[dict-item]
    with pytest.raises(SubstitutionError, match="non-empty string"):
        Substitutions({"": TestLeaf()})


def test_a_condition_cannot_be_a_delayed_test_leaf(tmp_path: Path) -> None:
    with pytest.raises(SubstitutionError, match="replaces the condition 'is_flying'"):
        MissionRun(mission(tmp_path), substitutions={"is_flying": TestLeaf(after_s=1.0)})
