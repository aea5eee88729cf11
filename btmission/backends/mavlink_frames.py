"""Frames between a mission's world and a MAVLink vehicle's local frame (pure functions).

A mission's world is **ENU**: metres, x and y in the horizontal plane, z up, yaw counter-clockwise
from +x (DESIGN.md §6). A MAVLink autopilot's local frame (``LOCAL_POSITION_NED``,
``SET_POSITION_TARGET_LOCAL_NED``) is **NED** relative to its EKF origin: x north, y east, z
down, yaw clockwise from north. Each agent has its own :class:`LocalFrame`: where its EKF origin
is in the world (by default its mission ``start``, where the vehicle boots) and which world
direction its "north" is (``north_yaw``: the world yaw of the local +x axis; π/2 when the world's
+y is true north, as for a mission laid out on a map; for a vehicle underground without a compass,
whatever heading its EKF took as north — usually the one it booted facing).

With a world map origin on the globe (``world.origin: {lat, lon, alt}``),
:func:`world_to_geodetic` and :func:`geodetic_to_world` convert between world ENU and WGS-84
latitude, longitude and altitude on a local tangent plane (exact enough over a mine's few
kilometres: the error grows with the square of the distance, about a centimetre at 1 km), e.g.
for ``SET_GPS_GLOBAL_ORIGIN`` on a vehicle without GPS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from btmission.spec.mission import NORTH_YAW_DEG  # the file model's default
from btmission.types import FloatArray, Vec3

if TYPE_CHECKING:
    from btmission.spec.mission import Mission

WGS84_A = 6378137.0
"""Semi-major axis (m)."""
WGS84_E2 = 6.69437999014e-3
"""First eccentricity squared."""


def wrap_pi(angle: float) -> float:
    """``angle`` in (−π, π]."""
    a = math.remainder(angle, math.tau)
    return math.pi if a == -math.pi else a


@dataclass(frozen=True)
class LocalFrame:
    """One vehicle's NED local frame in the mission world (module docstring)."""

    origin: Vec3
    """Where the EKF origin is, world ENU (m)."""
    north_yaw: float = math.pi / 2
    """World yaw (rad, counter-clockwise from world +x) of the local frame's +x (north) axis."""

    @property
    def _axes(self) -> tuple[FloatArray, FloatArray]:
        c, s = math.cos(self.north_yaw), math.sin(self.north_yaw)
        return np.array([c, s]), np.array([s, -c])  # north, east (90° clockwise of north)

    def to_local(self, p: Vec3 | FloatArray) -> FloatArray:
        """World ENU point → local NED point (m)."""
        d = np.asarray(p, dtype=float) - np.asarray(self.origin, dtype=float)
        return self.vector_to_local(d)

    def to_world(self, p: Vec3 | FloatArray) -> FloatArray:
        """Local NED point → world ENU point (m)."""
        out: FloatArray = self.vector_to_world(p) + np.asarray(self.origin, dtype=float)
        return out

    def vector_to_local(self, v: Vec3 | FloatArray) -> FloatArray:
        """World ENU vector (a velocity, a displacement) → local NED vector."""
        v = np.asarray(v, dtype=float)
        north, east = self._axes
        return np.array([v[:2] @ north, v[:2] @ east, -v[2]])

    def vector_to_world(self, v: Vec3 | FloatArray) -> FloatArray:
        """Local NED vector → world ENU vector."""
        v = np.asarray(v, dtype=float)
        north, east = self._axes
        xy = v[0] * north + v[1] * east
        return np.array([xy[0], xy[1], -v[2]])

    def yaw_to_local(self, yaw: float) -> float:
        """World yaw (counter-clockwise from +x) → NED yaw (clockwise from north), in (−π, π]."""
        return wrap_pi(self.north_yaw - yaw)

    def yaw_to_world(self, yaw: float) -> float:
        """NED yaw (clockwise from north) → world yaw (counter-clockwise from +x), in (−π, π]."""
        return wrap_pi(self.north_yaw - yaw)

    def yaw_rate_to_local(self, rate: float) -> float:
        """World yaw rate (counter-clockwise positive) → NED yaw rate (clockwise positive)."""
        return -rate

    def yaw_rate_to_world(self, rate: float) -> float:
        return -rate


@dataclass(frozen=True)
class GeodeticOrigin:
    """Where the world's (0, 0, 0) is on the globe, with the world's +y pointing true north."""

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0
    """Altitude above the WGS-84 ellipsoid (m)."""

    def __post_init__(self) -> None:
        if not (-90.0 < self.lat_deg < 90.0 and -180.0 <= self.lon_deg <= 180.0):
            raise ValueError(
                f"origin latitude must be in (-90, 90) and longitude in [-180, 180] degrees, got "
                f"{self.lat_deg}, {self.lon_deg}"
            )

    def _radii(self) -> tuple[float, float]:
        """Meridian and prime-vertical radii of curvature at the origin (m)."""
        s = math.sin(math.radians(self.lat_deg))
        w = math.sqrt(1.0 - WGS84_E2 * s * s)
        return WGS84_A * (1.0 - WGS84_E2) / w**3, WGS84_A / w


def world_to_geodetic(p: Vec3 | FloatArray, origin: GeodeticOrigin) -> tuple[float, float, float]:
    """World ENU point → (latitude °, longitude °, altitude m) on the origin's tangent plane."""
    e, n, u = (float(x) for x in np.asarray(p, dtype=float))
    m, nr = origin._radii()
    lat = origin.lat_deg + math.degrees(n / m)
    lon = origin.lon_deg + math.degrees(e / (nr * math.cos(math.radians(origin.lat_deg))))
    return lat, lon, origin.alt_m + u


def geodetic_to_world(
    lat_deg: float, lon_deg: float, alt_m: float, origin: GeodeticOrigin
) -> FloatArray:
    """(latitude °, longitude °, altitude m) → world ENU point (the inverse of
    :func:`world_to_geodetic`)."""
    m, nr = origin._radii()
    n = math.radians(lat_deg - origin.lat_deg) * m
    e = math.radians(lon_deg - origin.lon_deg) * nr * math.cos(math.radians(origin.lat_deg))
    return np.array([e, n, alt_m - origin.alt_m])


def local_frame(origin: Vec3, north_yaw_deg: float = NORTH_YAW_DEG) -> LocalFrame:
    """The :class:`LocalFrame` of a vehicle whose EKF origin is at ``origin`` (world ENU, m) with
    its north ``north_yaw_deg`` degrees counter-clockwise from world +x (a mission's units)."""
    x, y, z = (float(c) for c in origin)
    return LocalFrame((x, y, z), wrap_pi(math.radians(north_yaw_deg)))


def agent_frame(mission: Mission, agent_id: str) -> LocalFrame:
    """Agent ``agent_id``'s world ↔ local NED frame: its ``origin:`` if the mission gives one,
    else its ``start`` with north along world +y."""
    spec = next((a for a in mission.spec.agents if a.id == agent_id), None)
    if spec is None:
        raise KeyError(agent_id)
    if spec.origin is None:
        return local_frame(spec.start)
    return local_frame(spec.origin.position, spec.origin.north_yaw_deg)


def mission_geodetic_origin(mission: Mission) -> GeodeticOrigin | None:
    """The mission's ``world.origin`` (where world (0, 0, 0) is on the globe), or None."""
    o = mission.spec.world.origin
    return None if o is None else GeodeticOrigin(o.lat, o.lon, o.alt)
