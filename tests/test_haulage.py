"""The haulage capability library (seed 004 integration) and the mine_haulage mission."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import py_trees
import pytest
from click.testing import CliRunner

from btmission.cli.main import cli
from btmission.diagnostics import SpecError
from btmission.dispatch.evaluate import timeline
from btmission.dispatch.follow import MissionFollower, MissionState
from btmission.dispatch.ga import GAParams
from btmission.dispatch.maps import mine_map
from btmission.dispatch.missions import Mission
from btmission.dispatch.static import StaticInstance, plan_static
from btmission.dispatch.topomap import TopoMap
from btmission.plugins import load_library
from btmission.spec.mission import load_mission, load_mission_text
from btmission_library import haulage

ROOT = Path(__file__).resolve().parents[1]
MISSION = ROOT / "missions" / "mine_haulage.yaml"
Status = py_trees.common.Status


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
    # without the key, missions load as before (the key is optional)
    assert (
        load_mission_text(
            text.replace("  topomap: mine", "  # no topomap"), "m.yaml"
        ).spec.world.topomap
        is None
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


@dataclass
class FakeDispatcher:
    tmap: TopoMap
    plans: dict[str, Mission]
    primaries: dict[str, int]
    requests: list[tuple[str, int]] = field(default_factory=list)

    def request(self, truck: str, goal: int) -> None:
        self.requests.append((truck, goal))

    def mission(self, truck: str) -> Mission | None:
        return self.plans.get(truck)

    def primary(self, truck: str) -> int | None:
        return self.primaries.get(truck)

    def park(self, truck: str) -> None:
        self.requests.append((truck, -1))


@dataclass
class FakeContext:
    truck: str
    dispatcher: FakeDispatcher
    t: float = 0.0
    cargo: str | None = None
    hauls: set[tuple[str, str]] = field(default_factory=set)
    commands: list[MissionState] = field(default_factory=list)

    def now(self) -> float:
        return self.t

    def command(self, state: MissionState) -> None:
        self.commands.append(state)

    def process(self, kind: str, node: int) -> bool:
        return True


def test_drive_action_follows_the_dispatched_plan() -> None:
    tmap = mine_map()
    plan = _plan(tmap)
    disp = FakeDispatcher(tmap, {}, {})
    ctx = FakeContext("H2", disp)
    req = haulage.RequestDispatch(goal="L2s")
    req.setup(ctx=ctx)
    req.tick_once()
    assert req.status is Status.RUNNING and disp.requests == [("H2", tmap.id("L2s"))]
    disp.plans["H2"], disp.primaries["H2"] = plan[1], tmap.id("L2s")
    req.tick_once()
    assert req.status is Status.SUCCESS and haulage.dispatched(ctx, goal="L2s")
    drive = haulage.DriveMission(goal="L2s")
    drive.setup(ctx=ctx)
    follower = MissionFollower(tmap, plan[1])
    for t in np.linspace(0, follower.end_time - 1, 40):
        ctx.t = float(t)
        drive.tick_once()
        assert drive.status is Status.RUNNING
        assert ctx.commands[-1] == follower.state(float(t))  # exactly the dispatcher's schedule
    ctx.t = follower.end_time
    drive.tick_once()
    assert drive.status is Status.SUCCESS and haulage.at_node(ctx, goal="L2s")
    load = haulage.Load(pickup="L2s")
    load.setup(ctx=ctx)
    load.tick_once()
    assert load.status is Status.SUCCESS and haulage.loaded(ctx, pickup="L2s")


def test_wait_at_pause_holds_until_the_onward_mission() -> None:
    tmap = mine_map()
    to_pause = Mission(np.array([tmap.id("L1n"), tmap.id("M1"), tmap.id("PM1")], np.int32),
                       np.zeros(3), 0.0)  # fmt: skip
    disp = FakeDispatcher(tmap, {"H1": to_pause}, {"H1": tmap.id("O")})
    ctx = FakeContext("H1", disp, t=1e6)
    wait = haulage.WaitAtPause(goal="O")
    wait.setup(ctx=ctx)
    wait.tick_once()
    assert wait.status is Status.RUNNING and not haulage.released(ctx, goal="O")
    onward = Mission(np.array(tmap.path(tmap.id("PM1"), tmap.id("O")), np.int32),
                     np.zeros(len(tmap.path(tmap.id("PM1"), tmap.id("O")))), 1e6)  # fmt: skip
    disp.plans["H1"] = onward
    wait.tick_once()
    assert wait.status is Status.SUCCESS


def test_leaves_need_a_context() -> None:
    with pytest.raises(KeyError, match="needs ctx"):
        haulage.DriveMission(goal="O").setup()
