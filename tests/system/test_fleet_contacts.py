"""``btmission bench fleet``'s 30 drones in the seed 000 mine, through the start-up window the
benchmark times (take-off, departure from pads 2 m apart, the first tasks): no drone touches
another (issue 36 item 9), and the separation rule does not keep any on its pad."""

from __future__ import annotations

import json
import math

import pytest

from btmission.bench.fleet import DURATION_S, WARMUP_S, fleet_mission_text
from btmission.missions import load_mission_text
from btmission.runtime.events import Event
from btmission.runtime.runner import MissionRun

DRONES = 30


class Seen:
    """The collisions, each agent's highest point above its start and farthest distance from
    its start (horizontal), and the agents that adopted a route."""

    def __init__(self, starts: dict[str, tuple[float, float, float]]) -> None:
        self.starts = starts
        self.collisions: list[tuple[str, str]] = []
        self.climb = dict.fromkeys(starts, 0.0)
        self.away = dict.fromkeys(starts, 0.0)
        self.routed: set[str] = set()

    def on_event(self, event: Event) -> None:
        data = json.loads(event.to_json())
        kind, agent = data["ev"], data.get("agent")
        if kind == "collision":
            self.collisions.append((agent, data["other"]))
        elif kind == "pose":
            (x, y, z), p = self.starts[agent], data["p"]
            self.climb[agent] = max(self.climb[agent], p[2] - z)
            self.away[agent] = max(self.away[agent], math.hypot(p[0] - x, p[1] - y))
        elif kind == "route":
            self.routed.add(agent)


@pytest.mark.slow
def test_thirty_drones_take_off_and_depart_without_touching() -> None:
    mission = load_mission_text(fleet_mission_text(DRONES), "fleet.yaml")
    starts = {
        a.id: (float(a.start[0]), float(a.start[1]), float(a.start[2])) for a in mission.spec.agents
    }
    seen = Seen(starts)
    run = MissionRun(mission, controller="track", observers=[seen])
    try:
        res = run.run(until=WARMUP_S + DURATION_S)
    finally:
        run.close()
    between = [c for c in seen.collisions if c[1] != "rock"]
    assert between == []
    assert res.collisions == 0  # nor into rock (the agents' push once drove one into a wall)
    assert all(h > 1.5 for h in seen.climb.values()), seen.climb  # every drone airborne
    assert seen.routed == set(starts)  # every drone given a route ...
    assert all(d > 10.0 for d in seen.away.values()), seen.away  # ... and gone from its pad
    assert len(res.done) >= 10
