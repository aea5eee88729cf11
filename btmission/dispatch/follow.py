"""Following a dispatched mission in time: where a truck must be at time t (seed 004 §3.2).

A mission fixes the whole trajectory: the truck stands at ``nodes[i]`` for its initial stop time,
then traverses the segment to ``nodes[i + 1]`` in exactly the segment's traversal time (the plan
fixes durations, not speeds, §1). :func:`mission_state` tells the drive action what to do at
time t — wait at a node, or be a given fraction along a segment — so that the truck keeps to the
collision-free schedule the GA found.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

from btmission.dispatch.evaluate import timeline
from btmission.dispatch.missions import Mission
from btmission.dispatch.topomap import TopoMap


@dataclass(frozen=True)
class MissionState:
    """What the schedule says at one instant."""

    phase: str
    """``waiting`` (standing at ``node`` until ``until``), ``moving`` (from ``node`` to ``next``,
    ``fraction`` of the segment done, arriving at ``until``) or ``done`` (at the end node)."""
    node: int
    next: int
    item: int
    """Index of the current mission item (the last one when done)."""
    fraction: float
    until: float

    @property
    def done(self) -> bool:
        return self.phase == "done"


class MissionFollower:
    """The schedule of one mission, queried by time (precomputed arrival/departure times)."""

    def __init__(self, tmap: TopoMap, mission: Mission) -> None:
        self.tmap = tmap
        self.mission = mission
        self.nodes = [int(x) for x in mission.nodes]
        self.arr, self.dep = timeline(tmap, self.nodes, list(mission.waits), mission.t0)

    @property
    def end_time(self) -> float:
        return self.arr[-1]

    def state(self, t: float) -> MissionState:
        """Where the truck must be at time ``t`` (before t0 it waits at the start node)."""
        q = len(self.nodes) - 1
        if t >= self.arr[-1] or q == 0:
            return MissionState("done", self.nodes[-1], self.nodes[-1], max(q - 1, 0), 1.0, t)
        i = max(bisect.bisect_right(self.arr, t) - 1, 0)  # last node reached at or before t
        if t < self.dep[i]:
            nxt = self.nodes[i + 1]
            return MissionState("waiting", self.nodes[i], nxt, i, 0.0, self.dep[i])
        span = self.arr[i + 1] - self.dep[i]
        frac = (t - self.dep[i]) / span if span > 0 else 1.0
        return MissionState("moving", self.nodes[i], self.nodes[i + 1], i, frac, self.arr[i + 1])
