"""Honest clocks (issue #36 item 3): the mission's time is 0 when the provider starts, whatever
connecting took, and a run that cannot keep up with its vehicles' clock says so, judged in their
time (:mod:`btmission.runtime.pacing`). (Wall-time link loss: tests/unit/backends/
test_mavlink_link_timeout.py.)

The vehicles here live on a clock the test drives (a :class:`ManualClock` where real vehicles
have the wall clock): connecting takes :data:`CONNECT_S` of it, a step ``step_cost_s``, and the
pacer's waits jump it — every run is deterministic and nothing sleeps."""

from __future__ import annotations

from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import ClassVar

import pytest
from click.testing import CliRunner

from btmission.backends.fake import FakeProvider
from btmission.cli.main import cli
from btmission.missions import load_mission_text
from btmission.runtime.eventkinds import WarningEvent
from btmission.runtime.events import Event, Recorder
from btmission.runtime.pacing import BEHIND_WINDOW_S, Pacer
from btmission.runtime.report import build_report
from btmission.runtime.runner import MissionRun
from btmission.spec.mission import Mission
from btmission.spec.vehicleref import SIM, VehicleRef
from btmission.types import Vec3
from btmission.vehicles import provider as registry
from btmission.vehicles.base import VehicleKind
from btmission.vehicles.clock import ManualClock
from btmission.vehicles.provider import (
    ENTRY_POINT_GROUP,
    AttachOptions,
    ProviderBase,
    Vehicle,
    VehicleEvent,
)
from btmission.world.voxel import VoxelMap

CONNECT_S = 600.0
"""Vehicle time one vehicle takes to connect (an estimator that takes its time)."""

DT = 0.05


class Connecting(ProviderBase):
    """Fake vehicles on their own clock, which passes on its own as real vehicles' does
    (``realtime``): attaching one takes :data:`CONNECT_S` of it, :meth:`start` restarts it at
    zero (as the MAVLink provider's), each step takes :attr:`step_cost_s` of it."""

    realtime = True
    step_cost_s: ClassVar[float] = 0.0
    made: ClassVar[list[Connecting]] = []

    def __init__(self, voxel_map: VoxelMap) -> None:
        self.fake = FakeProvider(voxel_map)
        self.clock = ManualClock(0.0)
        self.started_at: float | None = None
        Connecting.made.append(self)

    def attach(
        self,
        agent_id: str,
        kind: VehicleKind,
        start: Vec3,
        ref: VehicleRef = SIM,
        options: AttachOptions = AttachOptions(),
    ) -> Vehicle:
        self.clock.advance(CONNECT_S)
        return self.fake.attach(agent_id, kind, start, ref, options)

    def start(self) -> None:
        self.started_at = self.clock.now()
        self.clock.t = 0.0

    def step(self, dt: float) -> Sequence[VehicleEvent]:
        self.clock.advance(self.step_cost_s)
        return self.fake.step(dt)

    def close(self) -> None:
        self.fake.close()


def connecting(mission: Mission, voxel_map: VoxelMap, seed: int) -> Connecting:
    return Connecting(voxel_map)


@pytest.fixture
def slow_to_connect(monkeypatch: pytest.MonkeyPatch) -> None:
    """The scheme ``connecting``: :class:`Connecting` vehicles, installed like a plugin's."""
    real = registry.installed_providers

    def installed() -> dict[str, metadata.EntryPoint]:
        ep = metadata.EntryPoint("connecting", f"{__name__}:connecting", ENTRY_POINT_GROUP)
        return {**real(), "connecting": ep}

    monkeypatch.setattr(registry, "installed_providers", installed)
    monkeypatch.setattr(Connecting, "step_cost_s", 0.0)
    Connecting.made.clear()


MISSION = """\
mission: clocks
version: 1
world:
  map: {generate: empty, size: [30, 30, 8]}
  resolution: 0.5
agents:
  - {id: R1, library: aerial, start: [5, 5, 0], backend: connecting}
  - {id: R2, library: aerial, start: [8, 5, 0], backend: connecting}
tasks:
  - {id: T1, type: inspect, location: [13, 7, 2]}
task_types:
  inspect: {goal: at_goal(location), cost: path_cost(location)}
default_behavior: {goal: landed_at_home, idle_timeout_s: 2}
runtime: {controller: track, max_duration_s: 200}
"""


def falls_behind(events: Sequence[Event]) -> list[Event]:
    return [e for e in events if e.kind == "warning" and "falls behind" in e.get("message")]


# ------------------------------------------------------------------------------ t = 0 at the start
def test_what_happens_while_vehicles_connect_is_at_0_and_the_report_lasts_the_run(
    slow_to_connect: None,
) -> None:
    """Two vehicles take 1200 s of their clock to connect: the events made meanwhile (the
    header, the vehicles without sensors) are at 0, nothing after is pushed to the connecting
    clock's time, and the report's duration is the flight's (the issue's log had all 935
    events at t = 1214.5 s and a 1214.5 s mission for a 217.8 s run)."""
    rec = Recorder()
    run = MissionRun(load_mission_text(MISSION, "clocks.yaml"), observers=[rec])
    try:
        result = run.run()
        run.end(result)
    finally:
        run.close()
    (provider,) = Connecting.made
    assert provider.started_at == 2 * CONNECT_S  # connecting did take that long
    assert result.done == ["T1"]
    evs = rec.events
    assert [e.kind for e in evs[:3]] == ["header", "warning", "built"]
    assert "R1, R2: no exteroceptive sensors" in evs[1].get("message")
    assert [e.t for e in evs[:3]] == [0.0, 0.0, 0.0]
    assert all(e.get("reported_s") is None for e in evs[:3])
    times = [e.t for e in evs]
    assert times == sorted(times)
    lags = [e.t - e.get("reported_s") for e in evs if e.get("reported_s") is not None]
    assert all(lag < 2.0 for lag in lags), lags  # reports a round took late, nothing more
    end = evs[-1]
    assert end.kind == "end" and end.t == pytest.approx(run.now())
    duration = build_report(evs).summary.duration_s
    assert duration == end.t and 10.0 < duration < 100.0  # the flight, not the connecting
    assert not falls_behind(evs)  # steps on time: no warning


# ------------------------------------------------------------------------------ falling behind
def paced(step_cost: float, steps: int, *, stall: tuple[int, float] | None = None) -> list[str]:
    """Run a pacer against real vehicles' clock for ``steps`` steps of ``step_cost`` vehicle
    seconds each (``stall``: step i takes that long instead); the warnings it gave."""
    clock = ManualClock(0.0)
    said: list[str] = []
    pacer = Pacer(
        clock,
        DT,
        vehicles_realtime=True,
        realtime=True,
        speed=1.0,
        emit=lambda ev: said.append(ev.message if isinstance(ev, WarningEvent) else ev.kind),
    )
    pacer.start(0)
    for i in range(1, steps + 1):
        clock.advance(stall[1] if stall is not None and i == stall[0] else step_cost)
        pacer.after_step(i)
    return said


def test_a_run_making_one_step_per_vehicle_second_warns_once_within_its_first_window() -> None:
    """The issue's worst runs made one step per vehicle-second: 400 steps were never reached."""
    said = paced(1.0, int(BEHIND_WINDOW_S) + 1)
    assert len(said) == 1
    assert said[0].startswith("the run falls behind its vehicles' clock (5 of 100 steps made in ")
    assert "cannot keep up; lower runtime.mavlink.time_scale" in said[0]
    assert paced(1.0, int(BEHIND_WINDOW_S) - 1) == []  # (not before a window is over)
    assert len(paced(1.0, 100)) == 1  # once


@pytest.mark.parametrize(("share", "warns"), [(0.4, True), (0.6, False), (1.0, False)])
def test_fewer_than_half_the_due_steps_in_a_window_is_falling_behind(
    share: float, warns: bool
) -> None:
    """Steps costing 1/share of a step: that share of the due steps is made."""
    said = paced(DT / share * 1.0001 if share < 1 else 0.2 * DT, 2000)
    assert bool(said) is warns, said


def test_one_slow_step_is_no_falling_behind() -> None:
    """A 2 s stall (an auction round's searches) in steps on time: most of its window's
    steps were still made."""
    assert paced(0.2 * DT, 1000, stall=(150, 2.0)) == []
    assert paced(0.2 * DT, 1000, stall=(150, 3.0))  # more than half the window lost


def test_a_clock_set_forward_is_no_falling_behind() -> None:
    """An agent process's clock set to its coordinator's (a jump of 30 s) restarts the pacing."""
    clock = ManualClock(0.0)
    said: list[object] = []
    pacer = Pacer(clock, DT, vehicles_realtime=True, realtime=True, speed=1.0, emit=said.append)
    pacer.start(0)
    for i in range(1, 1000):
        clock.advance(0.2 * DT)
        if i == 300:
            clock.advance(30.0)
            pacer.start(i)  # what MissionRun.clock_set does
        pacer.after_step(i)
    assert said == []


def test_a_simulated_run_never_falls_behind() -> None:
    """The simulator's clock is its steps: however slow the machine, no warning."""
    clock = ManualClock(0.0)
    said: list[object] = []
    for realtime in (False, True):
        pacer = Pacer(
            clock, DT, vehicles_realtime=False, realtime=realtime, speed=1000.0, emit=said.append
        )
        pacer.start(0)
        for i in range(1, 400):
            clock.advance(DT)
            pacer.after_step(i)
    assert said == []


def test_a_run_that_falls_behind_says_so_on_stderr_and_in_its_log(
    slow_to_connect: None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each step takes a second of the vehicles' time: ``run`` prints the warning once, with
    the advice, and the log has it, about one window into the mission."""
    monkeypatch.setattr(Connecting, "step_cost_s", 1.0)
    path = tmp_path / "clocks.yaml"
    path.write_text(MISSION)
    logs = tmp_path / "logs"
    result = CliRunner().invoke(
        cli,
        ["run", str(path), "--until", "20", "--no-png", "--quiet", "--log", str(logs)],
        catch_exceptions=False,
    )
    assert result.exit_code in (0, 1), result.output
    lines = [x for x in result.stderr.splitlines() if "falls behind" in x]
    assert len(lines) == 1
    assert lines[0].startswith("warning: the run falls behind its vehicles' clock (")
    assert "lower runtime.mavlink.time_scale" in lines[0]
    (log,) = logs.glob("*.jsonl")
    evs = [Event.from_json(line) for line in log.read_text().splitlines()]
    (warning,) = falls_behind(evs)
    assert BEHIND_WINDOW_S <= warning.t <= BEHIND_WINDOW_S + 1.0
