"""The commands a :class:`~btmission.runtime.navigation.Navigator` carries out.

One record per command (hold, take off, follow a route, go to a local waypoint, track a moving
reference, land), holding what the navigator needs to carry it out; ``name`` is what
:attr:`NavStatus.command <btmission.runtime.navconfig.NavStatus>` reports. Private to the
navigator (and the fleet control step, :mod:`btmission.runtime.fleetstep`, which steps the
drones following a route together).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from btmission.runtime.navcontrol import Polyline
from btmission.types import FloatArray


class _Command:
    name = "hold"


@dataclass
class _Hold(_Command):
    point: FloatArray
    name: str = "hold"


@dataclass
class _Takeoff(_Command):
    point: FloatArray
    name: str = "takeoff"


@dataclass
class _Follow(_Command):
    route: Polyline
    target: FloatArray
    ground_goal: bool
    seg: int = 0
    best_left: float = math.inf
    progress_t: float = 0.0
    name: str = "follow"


@dataclass
class _Goto(_Command):
    waypoint: FloatArray
    yaw: float | None
    yaw_rate: float
    name: str = "goto"


@dataclass
class _Track(_Command):
    point: FloatArray
    velocity: FloatArray
    t0: float
    name: str = "track"

    def reference(self, now: float) -> FloatArray:
        out: FloatArray = self.point + self.velocity * max(0.0, now - self.t0)
        return out


@dataclass
class _Land(_Command):
    hold: FloatArray | None = None
    name: str = "land"
