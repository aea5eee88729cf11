"""The fleet's control step (:mod:`btmission.runtime.fleetstep`) gives the per-drone loop's run to
the bit, takes most drone steps where it applies, and stays out where it does not."""

from __future__ import annotations

import json
from typing import Any

import pytest

from btmission.bench.fleet import fleet_mission_text
from btmission.missions import load_mission_text
from btmission.runtime.commands import KillAgent
from btmission.runtime.events import Event
from btmission.runtime.runner import MissionRun

WALL = {"wall_s", "build_s", "started_unix", "solve_ms", "solve_s", "elapsed_s", "step_ms"}
"""Fields that measure the machine, not the run."""


class Lines:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def on_event(self, event: Event) -> None:
        data = json.loads(event.to_json())
        self.lines.append(json.dumps({k: v for k, v in data.items() if k not in WALL}))


def _run(
    text: str, until: float, fleet_step: bool, kill: tuple[float, str] | None = None
) -> tuple[list[str], MissionRun]:
    rec = Lines()
    run = MissionRun(load_mission_text(text, "fleet.yaml"), observers=[rec], fleet_step=fleet_step)
    if kill is not None:
        run.at(kill[0], KillAgent(kill[1]))
    run.run(until=until)
    return rec.lines, run


def _same_run(
    text: str, until: float, kill: tuple[float, str] | None = None
) -> tuple[list[str], MissionRun]:
    one_by_one, plain = _run(text, until, False, kill)
    together, batched = _run(text, until, True, kill)
    assert plain._fleet is None and batched._fleet is not None
    assert len(together) == len(one_by_one)
    for i, (a, b) in enumerate(zip(one_by_one, together)):
        assert a == b, f"event {i} differs"
    return together, batched


def test_a_fleet_runs_the_same_with_its_steps_computed_together() -> None:
    """10 drones for 30 s (they take off, fly routes, meet each other, some arrive: the
    per-drone path decides those): the same events, and most drone steps were batched."""
    lines, run = _same_run(fleet_mission_text(10), 30.0)
    assert run._fleet is not None
    flown = 10 * run.steps
    assert run._fleet.batched > 0.5 * flown  # most steps of a fleet follow routes
    kinds = [json.loads(x)["ev"] for x in lines]
    assert kinds.count("task") > 10 and "route" in kinds  # tasks won, routes flown


@pytest.mark.slow
def test_a_fleet_with_an_agent_killed_runs_the_same() -> None:
    """The killed drone's row on the bus is gone (no neighbour query returns it): the fleet step
    goes on for the others, and the run is the per-drone loop's."""
    lines, run = _same_run(fleet_mission_text(10), 25.0, kill=(12.0, "R3"))
    assert run._fleet is not None and not run.agents["R3"].alive
    assert any('"ev": "agent_killed"' in x or '"kill_agent"' in x for x in lines)
    at_kill: list[int] = []
    again = MissionRun(load_mission_text(fleet_mission_text(10), "fleet.yaml"))
    again.at(12.0, KillAgent("R3"))
    again.at(12.5, lambda r: at_kill.append(r._fleet.batched if r._fleet else 0))
    again.run(until=25.0)
    assert again._fleet is not None and at_kill
    steps_after = round((25.0 - 12.5) / again.dt)
    assert again._fleet.batched - at_kill[0] > 0.5 * 9 * steps_after  # still batched after


def _noisy(text: str) -> str:
    return text.replace(
        "runtime: {controller: track",
        "runtime: {controller: track, sim: {pose_noise_m: 0.05, heading_noise_rad: 0.02, "
        "velocity_noise: 0.1}",
    )


@pytest.mark.slow
def test_noisy_estimates_and_a_small_fleet_run_the_same() -> None:
    """Pose noise (the estimate the navigator uses is not where the LiDAR is) on 4 drones (the
    bus's small-fleet neighbour query), flown until tasks are done at their goals."""
    text = _noisy(fleet_mission_text(4))
    assert "pose_noise_m" in text
    lines, run = _same_run(text, 120.0)
    assert run._fleet is not None and run._fleet.batched > 0
    done = [json.loads(x) for x in lines if '"state": "done"' in x]
    assert done  # arrivals happened (the per-drone path's cases)


def test_the_fleet_step_stays_out_where_it_would_change_the_run() -> None:
    def fleet(text: str, **kw: Any) -> object:
        return MissionRun(load_mission_text(text, "f.yaml"), **kw)._fleet

    text = fleet_mission_text(3)
    assert fleet(text) is not None
    assert fleet(text, fleet_step=False) is None
    assert fleet(text, controller="nmpc") is None  # the NMPC's own path
    dusty = text.replace("runtime: {controller: track", "runtime: {controller: track, sim: "
                         "{dust_points: 5}")  # fmt: skip
    assert fleet(dusty) is None  # dust draws from the generator in the agents' order
    one = fleet_mission_text(1)
    assert fleet(one) is None  # nothing to batch


def test_sharing_positions_at_once_is_sharing_them_one_by_one() -> None:
    import numpy as np

    from btmission.links.bus import SMALL_FLEET, InMemoryBus

    def fill(bus: InMemoryBus, t: float) -> None:
        for i in range(SMALL_FLEET + 2):
            bus.share_prediction(f"A{i}", t, np.array([[float(i), 1.0, 2.0]]))

    one, all_, rows = InMemoryBus(), InMemoryBus(), InMemoryBus()
    for bus in (one, all_, rows):
        fill(bus, 0.0)
    moved = [(f"A{i}", np.array([[i + 0.5, 2.0, 3.0]])) for i in (3, 0, 5)]
    for agent, pts in moved:
        one.share_prediction(agent, 0.1, pts)
    all_.share_positions(0.1, moved)
    stacked = np.concatenate([p for _, p in moved])  # (the fleet step's form: rows and block)
    rows.share_positions(0.1, moved, (np.array([3, 0, 5], dtype=np.int64), stacked))
    here = np.array([0.0, 1.0, 2.0])
    for bus in (all_, rows):
        for agent in ("A0", "A4"):
            assert np.array_equal(
                one.neighbour_positions(agent, 0.1, 0.1, here, 6.0),
                bus.neighbour_positions(agent, 0.1, 0.1, here, 6.0),
            )
        assert list(one._predictions) == list(bus._predictions)
        assert np.array_equal(one._starts, bus._starts, equal_nan=True)
        for agent, pred in one._predictions.items():
            other = bus._predictions[agent]
            assert (pred.time_s, pred.positions.tolist()) == (
                other.time_s,
                other.positions.tolist(),
            )
    new = InMemoryBus()  # an agent the bus has not seen yet: shared one by one, in order
    new.share_positions(0.0, [("B", np.array([[1.0, 1.0, 1.0]])), ("C", np.zeros((1, 3)))])
    assert new._row_names == ["B", "C"] and new._starts[:2].tolist() == [[1, 1, 1], [0, 0, 0]]


def test_the_fleet_step_is_the_providers_offer_and_nobody_elses() -> None:
    """The runtime names no provider: the batch comes from the provider's ``fleet_sensing``.
    The simulator offers it (not with dust: it draws from the simulator's generator); the fake
    provider, whose vehicles have no LiDAR to batch, does not."""
    text = fleet_mission_text(4)
    run = MissionRun(load_mission_text(text, "fleet.yaml"))
    sensing = run.provider.fleet_sensing()
    assert sensing is not None and run._fleet is not None
    for agent in run.agents.values():
        nav = agent.navigator
        assert sensing.covers(nav.backend, nav.sensors)
        assert not sensing.covers(nav.backend, None)  # its LiDAR replaced: not the batch's
    poses = sensing.true_poses([a.navigator.backend for a in run.agents.values()])
    assert poses.shape == (4, 4)
    fake = MissionRun(load_mission_text(text.replace("backend: sim", "backend: fake"), "f.yaml"))
    assert fake.provider.fleet_sensing() is None and fake._fleet is None
    dusty = text.replace(
        "runtime: {controller: track}", "runtime: {controller: track, sim: {dust_points: 5}}"
    )
    assert "dust_points" in dusty
    assert MissionRun(load_mission_text(dusty, "d.yaml"))._fleet is None
