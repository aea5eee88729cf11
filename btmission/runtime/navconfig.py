"""The navigator's settings, status and route points (:mod:`btmission.runtime.navigation`).

:class:`NavConfig` (its settings, declared with their docs for users: :data:`SETTINGS_DOC`),
:class:`NavState` and :class:`NavStatus` (what a behaviour-tree action polls), and the points a
``route`` event carries (:func:`route_points`). Kept apart from the :class:`Navigator` so that
whoever only reads settings or statuses (run checks, actions, events) does not load the control
laws; :mod:`btmission.runtime.navigation` re-exports every name.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike

from btmission.settings import declared_settings

ROUTE_EVENT_POINTS = 200
"""A ``route`` event carries at most this many points of the path (:func:`route_points`)."""


class NavState(str, Enum):
    IDLE = "idle"
    RUNNING = "running"
    ARRIVED = "arrived"
    FAILED = "failed"


@dataclass(frozen=True)
class NavStatus:
    state: NavState
    reason: str = ""
    command: str = "hold"


def _doc(text: str) -> dict[str, str]:
    """A setting's doc for users (:class:`~btmission.settings.Setting`, :data:`SETTINGS_DOC`);
    the attribute docstring under the field says why, for readers of the code."""
    return {"doc": text}


@dataclass(frozen=True)
class NavConfig:
    """Motion settings (a mission's ``runtime.settings`` override them by name; so do a
    library's declared defaults: ``ground`` drives at 0.4 m/s). A run builds it once from its
    settings (:meth:`btmission.settings.RunSettings.of`)."""

    speed_m_s: float = field(default=1.5, metadata=_doc("cruise speed along a route (m/s)"))
    """Cruise speed along a route."""
    lookahead_m: float = field(default=2.0, metadata=_doc("carrot distance ahead on the route (m)"))
    """Carrot distance ahead of the closest point of the route."""
    tolerance_m: float = field(
        default=0.5, metadata=_doc("distance within which a goal counts as reached (m)")
    )
    """A goal is reached within this distance (horizontally and vertically)."""
    altitude_m: float = field(
        default=2.0,
        metadata=_doc("flight height above the ground for take-off and ground-level goals (m)"),
    )
    """Flight height above the ground for take-off and for goals on the ground (e.g. home)."""
    stuck_s: float = field(
        default=20.0, metadata=_doc("a route with no progress for this long is replanned (s)")
    )
    """A route with no progress for this long is replanned from where the vehicle is."""
    replans: int = field(
        default=5, metadata=_doc("replans of a route with no progress before the task fails")
    )
    """Replans after which a route with no progress fails (the task fails with the reason)."""
    apf_gain: float = field(
        default=0.075,
        metadata=_doc("APF gain L per m² of rock surface seen by the LiDAR (seed 002 eq. 3)"),
    )
    """APF gain L per point (seed 002 eq. 3), for the simulated LiDAR's one point per rock
    voxel face (0.5 m maps); the paper's VLP-16 scans are far denser (ApfConfig: 0.001)."""
    clearance_m: float = field(
        default=0.5,
        metadata=_doc("paths keep this far from rock: the map is inflated by it for planning (m)"),
    )
    """Paths keep voxel centres at least this far from rock (the vehicle's radius and a margin)."""


SETTINGS_DOC: Mapping[str, str] = MappingProxyType(
    {name: s.doc for name, s in declared_settings(NavConfig).items()}
)
"""The navigator's settings and what each does, for users: the fields' docs (read-only)."""


def route_points(points: ArrayLike, max_points: int = ROUTE_EVENT_POINTS) -> list[list[float]]:
    """A path's points for a ``route`` event: without the interior points where it goes
    straight on (a D*+ path steps voxel by voxel), then, if still more than ``max_points``,
    evenly spaced ones; the ends kept; in mm."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(pts) > 2:
        d = np.diff(pts, axis=0)
        n = np.linalg.norm(d, axis=1)
        u = d / np.where(n > 0, n, 1.0)[:, None]
        bend = np.linalg.norm(np.diff(u, axis=0), axis=1) > 1e-6  # interior point i+1 turns
        keep = np.concatenate([[True], bend, [True]])
        pts = pts[keep]
    if len(pts) > max_points >= 2:
        pts = pts[np.unique(np.linspace(0, len(pts) - 1, max_points).round().astype(int))]
    return [[round(float(v), 3) for v in p] for p in pts]
