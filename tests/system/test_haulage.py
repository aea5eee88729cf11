"""The haulage capability library (seed 004 integration) and the mine_haulage mission."""

from __future__ import annotations

import itertools
import math
import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from btmission.allocation.bidder import AgentState, BidError, StraightLine
from btmission.allocation.tasks import TaskInfo
from btmission.backends.fake import FakeProvider
from btmission.backends.sim import SimConfig
from btmission.cli.main import cli
from btmission.diagnostics import SpecError
from btmission.dispatch.dynamic import DynamicConfig, executed_tracks
from btmission.dispatch.evaluate import evaluate_reference, timeline
from btmission.dispatch.follow import MissionFollower
from btmission.dispatch.ga import GAParams
from btmission.dispatch.maps import mine_map
from btmission.dispatch.missions import Mission
from btmission.dispatch.service import FleetDispatcher, missions_from_records
from btmission.dispatch.static import StaticInstance, plan_static
from btmission.dispatch.topomap import Node, NodeKind, Segment, TopoMap
from btmission.missions import load_mission, load_mission_text
from btmission.plugins import load_library
from btmission.runtime.events import Recorder
from btmission.runtime.mission_auction import bidder_for_agent
from btmission.runtime.navcontrol import track_unicycle
from btmission.runtime.report import build_report, dispatch_png
from btmission.runtime.roads import RoadCosts, RoadMapError
from btmission.runtime.runner import MissionRun
from btmission.runtime.taskcheck import TaskError
from tests.unit.dispatch.test_dispatch import assert_causal

ROOT = Path(__file__).resolve().parents[2]
MISSION = ROOT / "missions" / "mine_haulage.yaml"


def test_library_is_registered_runnable_and_strictly_clean(runner: CliRunner) -> None:
    loaded = load_library("haulage")
    assert loaded.runnable and loaded.origin.startswith("entry point")
    r = runner.invoke(cli, ["library", "check", "haulage", "--strict"])
    assert r.exit_code == 0 and "0 error(s), 0 warning(s)" in r.output


def test_mission_validates(runner: CliRunner) -> None:
    r = runner.invoke(cli, ["validate", str(MISSION), "--strict"])
    assert r.exit_code == 0, r.output
    m = load_mission(MISSION)
    assert m.spec.world.topomap == "mine" and len(m.agents) == 3


def test_topomap_key_is_checked(tmp_path: Path) -> None:
    text = MISSION.read_text()
    with pytest.raises(SpecError) as exc:
        load_mission_text(
            text.replace("topomap: mine ", "topomap: nope.yaml "), str(tmp_path / "m.yaml")
        )
    d = exc.value.diagnostics[0]
    line = next(i for i, t in enumerate(text.splitlines(), 1) if t.strip().startswith("topomap:"))
    assert (
        d.item == "world.topomap" and "neither a built-in map" in d.message and d.where.line == line
    )
    bad = tmp_path / "loop.yaml"
    bad.write_text("topomap: x\nversion: 1\nnodes: {A: {kind: terminal}, B: {kind: terminal}}\n"
                   "segments:\n  - {from: A, to: C, time: 1}\n")  # fmt: skip
    with pytest.raises(SpecError) as exc2:
        load_mission_text(
            text.replace("topomap: mine ", "topomap: loop.yaml "), str(tmp_path / "m.yaml")
        )
    messages = [d.message for d in exc2.value.diagnostics]
    assert any("has errors" in m for m in messages) and any(
        "unknown node 'C'" in m for m in messages
    )
    # without the key, node names are not places: every such cost argument is reported
    with pytest.raises(SpecError) as exc3:
        load_mission_text(text.replace("  topomap: mine", "  # no topomap"), "m.yaml")
    d3 = exc3.value.diagnostics[0]
    assert d3.item == "tasks[0].pickup" and "needs a world.topomap" in d3.message
    assert len(exc3.value.diagnostics) == 2 * len(load_mission(MISSION).tasks)
    # with it, a name that is not a node of the map is an error with a suggestion
    with pytest.raises(SpecError) as exc4:
        load_mission_text(text.replace("pickup: L2n", "pickup: L2nn"), str(MISSION))
    d4 = exc4.value.diagnostics[0]
    assert d4.item == "tasks[1].pickup" and "'L2nn' is not a node" in d4.message
    assert "did you mean 'L2n'" in d4.message and d4.where.line == next(
        i for i, t in enumerate(text.splitlines(), 1) if "pickup: L2n" in t
    )


# ----------------------------------------------------------------------------- follower
def _plan(tmap: TopoMap) -> tuple[Mission, ...]:
    inst = StaticInstance((tmap.id("L1n"), tmap.id("O")), (tmap.id("O"), tmap.id("L2s")))
    run = plan_static(
        tmap, inst, GAParams(max_generations=300, budget_s=60), np.random.default_rng(2)
    )
    assert run.result.feasible
    return run.result.best


def test_follower_reproduces_the_schedule() -> None:
    tmap = mine_map()
    m = _plan(tmap)[1]
    f = MissionFollower(tmap, m)
    arr, dep = timeline(tmap, m.nodes.tolist(), list(m.waits), m.t0)
    for i in range(m.items):
        mid = (dep[i] + arr[i + 1]) / 2
        st = f.state(mid)
        assert (st.phase, st.node, st.next) == ("moving", m.nodes[i], m.nodes[i + 1])
        assert st.fraction == pytest.approx(0.5)
        if dep[i] > arr[i]:
            w = f.state((arr[i] + dep[i]) / 2)
            assert (w.phase, w.node, w.until) == ("waiting", m.nodes[i], dep[i])
    assert f.state(arr[-1]).done and f.state(arr[-1] + 100).node == m.end


# ----------------------------------------------------------------------------- dispatcher service
def _dispatcher(**starts: str) -> tuple[FleetDispatcher, list[dict[str, Any]]]:
    tmap = mine_map()
    cfg = DynamicConfig(
        vehicles=len(starts), opt_time_s=3.0, ga=GAParams(max_generations=150, budget_s=60), seed=1
    )
    events: list[dict[str, Any]] = []

    def emit(kind: str, **data: Any) -> None:
        events.append({"ev": kind, **data})

    d = FleetDispatcher(tmap, {n: tmap.id(s) for n, s in starts.items()}, cfg, emit)
    return d, events


def _serve(d: FleetDispatcher, t: float) -> float:
    """Step until no request is queued or optimising; the time it took."""
    while d.queue or d.pending is not None:
        d.step(t)
        t += 0.5
    return t


def test_dispatcher_serves_a_prioritised_inbound_mission_after_the_optimisation() -> None:
    d, events = _dispatcher(H1="L1n")
    tmap = d.tmap
    d.request("H1", tmap.id("O"))
    d.step(0.0)
    assert d.pending is not None and d.mission("H1").items == 0  # optimising: no plan yet
    d.step(2.9)
    assert d.mission("H1").items == 0  # causality: adopted opt_time_s after the request
    d.step(3.0)
    m = d.mission("H1")
    assert m.nodes.tolist() == tmap.path(tmap.id("L1n"), tmap.id("O"))  # Π0, no pause visits
    assert m.prioritized and m.waits[0] + m.t0 >= 3.0 and not m.waits[1:].any()  # never stops
    assert d.primary("H1") == tmap.id("O") and not d.waiting("H1")
    assert [e["event"] for e in events] == ["requested", "adopted"]


def _both_to_o() -> tuple[FleetDispatcher, list[dict[str, Any]], float]:
    """H1 (at L1n) and H2 (at L2n) both ask for O; both requests served."""
    d, events = _dispatcher(H1="L1n", H2="L2n")
    d.request("H1", d.tmap.id("O"))
    d.request("H2", d.tmap.id("O"))
    return d, events, _serve(d, 0.0)


def test_second_truck_waits_at_a_pause_node_and_gets_its_onward_mission() -> None:
    d, _, t = _both_to_o()
    tmap = d.tmap
    o = tmap.id("O")
    h1, h2 = d.mission("H1"), d.mission("H2")
    assert h1.end == o and d.primary("H2") == o
    assert tmap.is_pause[h2.end] and h2.end in tmap.nodes_of(NodeKind.PAUSE)  # secondary dest.
    # H1 arrives at O and leaves for a loading site: H2's onward mission comes with that plan
    arrive = MissionFollower(tmap, h1).end_time
    d.step(max(t, arrive))
    d.request("H1", tmap.id("L3s"))
    _serve(d, max(t, arrive))
    assert d.mission("H1").end == tmap.id("L3s") and d.mission("H2").end == o
    conflicts, _ = evaluate_reference(tmap, (d.mission("H1"), d.mission("H2")))
    assert conflicts == []


def test_dispatcher_replanning_is_causal() -> None:
    d, _ = _dispatcher(H1="L1n", H2="L2n", H3="L3n")
    tmap = d.tmap
    seen: list[set[int]] = []

    def check(t_done, before, after, changed) -> None:  # type: ignore[no-untyped-def]
        assert_causal(tmap, t_done, before, after, changed)
        seen.append(changed)

    d.planner.on_adopt = check
    t = 0.0
    goals = {"H1": ["O", "L1s", "O"], "H2": ["O", "L2s", "O"], "H3": ["O", "L3s", "O"]}
    while (any(goals.values()) or d.queue or d.pending is not None) and t < 20000:
        for truck, left in goals.items():
            st = MissionFollower(tmap, d.mission(truck)).state(t)
            if left and st.done and not d.waiting(truck) and st.node == d.primary(truck):
                d.request(truck, tmap.id(left.pop(0)))
        d.step(t)
        t += 1.0
    assert not any(goals.values()) and len(seen) >= 9
    assert any(len(c) > 1 for c in seen)  # some plans also released a truck from a pause node


def test_request_while_driving_to_a_terminal_waits_for_the_arrival() -> None:
    d, _ = _dispatcher(H1="L1n")
    tmap = d.tmap
    d.request("H1", tmap.id("O"))
    _serve(d, 0.0)
    m = d.mission("H1")
    arrive = MissionFollower(tmap, m).end_time
    d.request("H1", tmap.id("L2s"))
    d.step(arrive / 2)
    assert d.waiting("H1") and d.mission("H1") is m  # no stop at a terminal mid-mission
    _serve(d, arrive)
    assert d.mission("H1").nodes[0] == tmap.id("O") and d.mission("H1").end == tmap.id("L2s")


def test_park_goes_to_the_nearest_free_pause_node() -> None:
    d, _ = _dispatcher(H1="L1n", H2="L2n")
    tmap = d.tmap
    d.park("H1")
    _serve(d, 0.0)
    assert d.mission("H1").end == tmap.id("PM1")  # the pause node next to M1
    d.park("H2")
    _serve(d, 0.0)
    h2 = d.mission("H2").end
    assert tmap.is_pause[h2] and h2 != tmap.id("PM1")
    best = min((p for p in tmap.pauses if p != tmap.id("PM1")),
               key=lambda p: tmap.dist[tmap.id("L2n"), p])  # fmt: skip
    assert h2 == best


# ----------------------------------------------------------------------------- road costs, places
def test_road_costs_follow_the_roads() -> None:
    tmap = mine_map()
    roads = RoadCosts(tmap, lambda x, y: 0.0)
    xy = {n.name: np.array(n.xy) for n in tmap.nodes}
    path = [tmap.nodes[i].name for i in tmap.path(tmap.id("O"), tmap.id("L3s"))]
    length = sum(float(np.hypot(*(xy[b] - xy[a]))) for a, b in itertools.pairwise(path))
    o, l3s = roads.place("O"), roads.place("L3s")
    assert roads.path_cost(o, l3s) == pytest.approx(length)
    assert length > 1.5 * math.dist(o, l3s)  # the ramp: far longer than the straight line
    # half-way along a segment, 10 m off the road
    a, b = xy["J0"], xy["J1"]
    mid = (*(0.5 * (a + b) + np.array([0.0, 10.0])), 0.0)
    assert roads.path_cost(mid, o) == pytest.approx(10.0 + 50.0 + 100.0)
    assert roads.path_cost(o, o) == 0.0
    # off the network: the fallback provider answers (none: unreachable)
    far = (float(xy["O"][0]), float(xy["O"][1]) + 500.0, 0.0)
    assert roads.path_cost(far, o) == math.inf
    assert RoadCosts(tmap, lambda x, y: 0.0, StraightLine()).path_cost(far, o) == 500.0
    no_xy = TopoMap.build("t", [Node("A", NodeKind.TERMINAL), Node("B", NodeKind.TERMINAL)],
                          [Segment("A", "B", 1.0, 1.0)])  # fmt: skip
    with pytest.raises(RoadMapError, match="A, B have no xy"):
        RoadCosts(no_xy, lambda x, y: 0.0)


def test_bidder_resolves_place_names() -> None:
    m = load_mission(MISSION)
    roads = RoadCosts(mine_map(), lambda x, y: 0.0)
    bidder = bidder_for_agent(m, "H1", provider=roads, places=roads.places)
    task = next(t for t in m.tasks if t.id == "C4")
    info = TaskInfo(task.id, task.type, dict(task.fields))
    state = AgentState("H1", roads.place("O"), None, False)
    expect = roads.path_cost(roads.place("O"), roads.place("L1s")) + roads.path_cost(
        roads.place("L1s"), roads.place("O")
    )
    assert bidder.f_cost(info, state) == pytest.approx(expect)
    bad = TaskInfo("X", "haul", {"pickup": "nowhere", "dropoff": "O"})
    with pytest.raises(BidError, match="'nowhere' is not a place"):
        bidder.f_cost(bad, state)


# ----------------------------------------------------------------------------- schedule tracking
def test_track_unicycle_keeps_to_a_moving_reference() -> None:
    p, east = np.zeros(2), np.array([5.0, 0.0])
    on, _ = track_unicycle(p, 0.0, np.zeros(2), east, 12.0)
    behind, _ = track_unicycle(p, 0.0, np.array([10.0, 0.0]), east, 12.0)
    ahead, _ = track_unicycle(p, 0.0, np.array([-4.0, 0.0]), east, 12.0)
    assert on == pytest.approx(5.0) and behind > on > ahead >= 0.0
    assert track_unicycle(p, 0.0, np.array([100.0, 0.0]), east, 12.0)[0] == 12.0  # capped
    assert track_unicycle(p, 0.0, np.array([0.3, 0.0]), np.zeros(2), 12.0) == (0.0, 0.0)
    v, w = track_unicycle(p, 0.0, np.array([-20.0, 0.0]), -east, 12.0)  # way back: turn first
    assert v == 0.0 and abs(w) == 1.5


# ----------------------------------------------------------------------------- the mission
def test_mine_haulage_runs_every_haul_on_schedule(tmp_path: Path) -> None:
    """The whole mission, on fake vehicles (the simulator's unicycle kinematics without its
    physics: this test is about the dispatching and the schedule; ``docs/dispatch.md`` runs the
    mission in the simulator). The simulator's collision check is made here: the trucks' body
    spheres never overlap (the map is open ground: there is no rock to hit)."""
    events = Recorder()
    run = MissionRun(load_mission(_variant(tmp_path, _fake(MISSION.read_text()))), seed=0,
                     observers=[events])  # fmt: skip
    assert isinstance(run.provider, FakeProvider)
    fleet = run.services["haulage"]["fleet"]
    tmap = fleet.tmap
    errors: list[float] = []
    closest = math.inf
    while run.finished() is None and run.now() < 7200:
        run.step()
        pos = {a: run.vehicles[a].backend.telemetry().position for a in run.agents}
        closest = min(closest, *(float(np.linalg.norm(pos[a] - pos[b]))
                                 for a, b in itertools.combinations(pos, 2)))  # fmt: skip
        if run.steps % 5:
            continue  # compare once a second of mission time
        for a in run.agents:
            ref, _ = fleet.reference(fleet.state(a, run.now()))
            errors.append(float(np.hypot(*(pos[a][:2] - ref[:2]))))
    result = run.result(run.finished() or "time limit")
    assert result.reason == "completed" and len(result.done) == 6 and result.collisions == 0
    assert closest > 2 * SimConfig().ground_radius_m  # no two trucks ever touched
    hauled = {k: v for t in fleet.trucks.values() for k, v in t.hauled.items()}
    assert hauled == {t.id: (t.fields["pickup"], t.fields["dropoff"]) for t in run.mission.tasks}
    # the trucks kept to the dispatched schedule (turns on the spot at pause bays lag most)
    assert np.percentile(errors, 95) < 2.0 and max(errors) < 25.0
    # the plan they drove was collision-free (seed 004 §4.2 evaluation of the executed tracks)
    hist = SimpleNamespace(histories=[v.history for v in fleet.dispatcher.planner.veh])
    conflicts, _ = evaluate_reference(tmap, executed_tracks(hist))
    assert conflicts == []
    # every truck ended parked at its own pause node
    ends = [fleet.state(a, run.now()) for a in run.agents]
    assert all(st.done and tmap.is_pause[st.node] for st in ends)
    assert len({st.node for st in ends}) == len(ends)
    # the log holds every adopted mission: the report rebuilds each truck's exact history
    rep = build_report(events.events)
    for k, a in enumerate(fleet.dispatcher.names):
        logged = missions_from_records(tmap, rep.dispatched[a])
        history = [m for m in fleet.dispatcher.planner.veh[k].history if m.items]
        assert [m.nodes.tolist() for m in logged] == [m.nodes.tolist() for m in history]
        assert [m.prioritized for m in logged] == [m.prioritized for m in history]
        np.testing.assert_allclose(
            np.concatenate([m.waits for m in logged]),
            np.concatenate([m.waits for m in history]),
            atol=1e-3,
        )
    png = dispatch_png(rep, tmp_path / "dispatch.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    kinds = [e.get("event") for e in events.of("dispatch")]
    assert kinds.count("adopted") >= 12 and "requested" in kinds
    assert {e.get("agent") for e in events.of("load")} == set(run.agents)


def test_haulage_bad_inputs_are_reported(runner: CliRunner, tmp_path: Path) -> None:
    text = MISSION.read_text()
    off = tmp_path / "off.yaml"
    off.write_text(text.replace("start: [850, 480, 0]", "start: [900, 600, 0]"))
    r = runner.invoke(cli, ["run", str(off), "--until", "1"])
    assert r.exit_code == 2 and "agent 'H1' starts" in r.output and "L1n" in r.output
    assert "Traceback" not in r.output


def test_withdrawn_request_is_dropped_and_the_truck_not_sent_on() -> None:
    d, events, t = _both_to_o()
    tmap = d.tmap
    o = tmap.id("O")
    assert d.primary("H2") == o and tmap.is_pause[d.mission("H2").end]  # secondary destination
    d.withdraw("H2")  # its haul went to another truck
    assert d.primary("H2") == d.mission("H2").end
    arrive = MissionFollower(tmap, d.mission("H1")).end_time
    d.request("H1", tmap.id("L3s"))  # O is free again: nothing sends H2 there now
    _serve(d, max(t, arrive))
    assert d.mission("H2").end != o
    d.request("H2", tmap.id("L1s"))
    d.withdraw("H2")
    assert not d.waiting("H2") and not d.queue
    assert [e["event"] for e in events if e["truck"] == "H2"][-2:] == ["requested", "withdrawn"]


def _one_pause_map() -> TopoMap:
    nodes = [Node("O", NodeKind.TERMINAL, True, xy=(0.0, 0.0)),
             Node("J", NodeKind.TRANSIT, xy=(100.0, 0.0)),
             Node("P", NodeKind.PAUSE, xy=(100.0, 40.0)),
             Node("A", NodeKind.TERMINAL, xy=(200.0, 40.0)),
             Node("B", NodeKind.TERMINAL, xy=(200.0, -40.0))]  # fmt: skip
    segs = [Segment(a, b, 10.0, 10.0) for a, b in (("O", "J"), ("J", "P"), ("J", "A"), ("J", "B"))]
    return TopoMap.build("one_pause", nodes, segs)


def test_park_falls_back_to_a_free_terminal_and_requests_wait_without_failing() -> None:
    tmap = _one_pause_map()
    cfg = DynamicConfig(vehicles=2, ga=GAParams(max_generations=50, budget_s=60), seed=0)
    events: list[dict[str, Any]] = []
    d = FleetDispatcher(tmap, {"H1": tmap.id("A"), "H2": tmap.id("O")}, cfg,
                        lambda kind, **data: events.append(data))  # fmt: skip
    d.park("H1")
    t = _serve(d, 0.0)
    assert d.mission("H1").end == tmap.id("P")
    assert d.park_target("H2") == tmap.id("A")  # P is taken: the nearest free terminal (H1 left A)
    # H2 asks for P, which H1 holds, and there is no other pause node: it waits (no GA run)
    d.request("H2", tmap.id("P"))
    for _ in range(20):
        d.step(t)
        t += 1.0
    assert d.failed == 0 and d.waiting("H2")
    assert [e["event"] for e in events].count("deferred") == 1


def _variant(tmp_path: Path, text: str) -> Path:
    f = tmp_path / "variant.yaml"
    f.write_text(text)
    return f


def _with_tasks(*tasks: str) -> str:
    """mine_haulage.yaml with these task lines instead of its own."""
    text = MISSION.read_text()
    lines = "".join(f"  - {t}\n" for t in tasks)
    return (
        text.split("tasks:")[0] + "tasks:\n" + lines + "task_types:" + text.split("task_types:")[1]
    )


def _fake(text: str) -> str:
    """The mission with every truck on the fake vehicle provider (btmission.backends.fake):
    the same kinematic unicycles and cmd_vel rules, without the simulator's physics and
    collision checks — for tests of the dispatching and the trees, not of the driving."""
    agent = r"(  - \{id: H\d, library: haulage, start: \[[^]]*\])\}"
    return re.sub(agent, r"\1, backend: fake}", text)


def test_an_idle_truck_moves_out_of_the_way_without_a_default_behaviour(tmp_path: Path) -> None:
    text = _with_tasks(
        "{id: C1, type: haul, pickup: L1n, dropoff: O}",
        "{id: C2, type: haul, pickup: L2n, dropoff: O}",
    ).replace("default_behavior: {goal: parked, idle_timeout_s: 60}\n", "")
    run = MissionRun(load_mission(_variant(tmp_path, _fake(text))), seed=0)
    assert isinstance(run.provider, FakeProvider)
    result = run.run()
    assert result.reason == "completed" and sorted(result.done) == ["C1", "C2"]


def test_a_repeated_haul_is_hauled_again(tmp_path: Path) -> None:
    text = _with_tasks(
        "{id: C1, type: haul, pickup: L1n, dropoff: O}",
        "{id: C2, type: haul, pickup: L1n, dropoff: O, at: 10}",
    ).replace("  - {id: H2, library: haulage, start: [1350, 480, 0]}    # L2n\n", "")
    text = text.replace("  - {id: H3, library: haulage, start: [1850, 480, 0]}    # L3n\n", "")
    events = Recorder()
    run = MissionRun(load_mission(_variant(tmp_path, _fake(text))), seed=0, observers=[events])
    assert isinstance(run.provider, FakeProvider)
    result = run.run()
    assert result.reason == "completed" and sorted(result.done) == ["C1", "C2"]
    loads = [e for e in events.of("load")]
    offloads = [e for e in events.of("offload")]
    assert len(loads) == 2 and len(offloads) == 2  # the second haul really happened


def test_haulage_runtime_inputs_are_checked(tmp_path: Path) -> None:
    text = MISSION.read_text()
    same = text.replace("start: [1350, 480, 0]", "start: [850, 480, 0]")
    with pytest.raises(SpecError) as exc:
        MissionRun(load_mission(_variant(tmp_path, same)), seed=0)
    assert "'H1' and 'H2' both start at node L1n" in exc.value.diagnostics[0].message
    run = MissionRun(load_mission(MISSION), seed=0)
    no_place = "^task field 'pickup': 'nowhere' is not a node of the topological map 'mine'"
    with pytest.raises(TaskError, match=no_place):
        run.add_task({"id": "X", "type": "haul", "pickup": "nowhere", "dropoff": "O"})


def test_haulage_without_a_topomap_is_exit_2(runner: CliRunner, tmp_path: Path) -> None:
    text = MISSION.read_text().replace("  topomap: mine", "  # no topomap")
    text = text.split("tasks:")[0] + "tasks: []\ntask_types:" + text.split("task_types:")[1]
    r = runner.invoke(
        cli, ["run", str(_variant(tmp_path, text)), "--quiet", "--log", str(tmp_path)]
    )
    assert r.exit_code == 2 and "library 'haulage' needs a topological map" in r.output
    assert "Traceback" not in r.output
