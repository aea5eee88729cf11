"""The navigator's route geometry and control laws, with their constants.

What :class:`~btmission.runtime.navigation.Navigator` computes with, each a function of its
arguments (no navigator state):

* carrot chasing on a route: :class:`Polyline` (its projection and carrots are compiled:
  :mod:`btmission.runtime._route_kernels`), searching :data:`CARROT_WINDOW` segments ahead;
* multirotors: the APF sized for the cruise speed (:func:`multirotor_apf_config`, with
  :func:`braking_decel` and :data:`BRAKE_REACTION_S`), seed 002's eq. 4 as a speed factor
  (:func:`adaptive_speed_scale`), the approach-speed bound's constants (``APPROACH_*``), and the
  APF on the other agents' shared positions (:data:`AGENT_APF`) and the separation rule on its
  velocity (:data:`AGENT_SEPARATION`);
* ground robots: the unicycle tracker of a moving reference (:func:`track_unicycle`) and the
  LiDAR points that bound the NMPC's safe corridor (:func:`ground_obstacle_points`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from btmission.control.apf import ApfConfig, SeparationConfig, influence_radius_for_speed
from btmission.control.mav_model import wrap_angle, yaw_frame_to_world
from btmission.types import FloatArray
from btmission.vehicles.base import VehicleKind

GROUND_OBSTACLE_BAND_M = (0.05, 0.35)
"""LiDAR points between these heights above a ground robot's base are obstacles for its NMPC
(the floor is below; a TurtleBot-sized body, 0.3 m across, below the top)."""
SHARED_BODY_M = 0.35
"""LiDAR points this close (x-y) to another robot's shared position are that robot."""
CARROT_WINDOW = 8
"""Route segments searched for the closest point, from the last one (it only moves forward)."""
BRAKE_REACTION_S = 0.4
"""Time before full braking acts (APF rate saturation, the NMPC's tilt-rate limit of eq. 2,
attitude lag): with the MAV's tilt-limited deceleration it sizes the APF's radius of influence
for the cruise speed (:func:`~btmission.control.apf.influence_radius_for_speed`)."""
APPROACH_REACTION_S = 0.6
"""Reaction time the approach-speed bound counts on: the NMPC's measured lag in following a
lowered velocity reference (its velocity weight against the position lead, the attitude lag)."""
APPROACH_CORRIDOR_M = 1.0
"""The approach bound counts the rock within this of the MAV's line of motion (its velocity
reference's and its actual velocity's): r_c, the body and a margin. The floor 1.5 m below and
the walls of a tunnel's middle lie outside it, so cruising level down a tunnel is not slowed."""
APPROACH_MARGIN_M = 0.1
"""The approach-speed bound stops the MAV this much outside the safety-critical radius r_c."""
APPROACH_DECEL_M_S2 = 1.5
"""Deceleration the approach-speed bound counts on (with :data:`APPROACH_REACTION_S`). The NMPC
stops from 2.3 m/s in 1.9 m when its velocity reference steps to zero (1.7 m/s² on average, the
attitude lag and the tilt-rate limit of eq. 2 included), but the bound lowers the reference
progressively, which the closed loop follows more slowly (~1.55 m/s² in the COMPRA runs). Fitting
the hard stop instead (2.5 m/s², 0.45 s) gained 0.05-0.09 m/s on average and let the MAV within
0.17 m of a wall; the full tilt's 3.6 m/s² let it stop ~0.2 m inside the stand-off."""


def braking_decel(model_g: float = 9.81, tilt_max_rad: float = 0.35) -> float:
    """The MAV's horizontal deceleration at full tilt, g·tan(θ_max) (NMPC and autopilot alike
    limit the tilt to ~0.35 rad: 3.6 m/s²)."""
    return model_g * math.tan(tilt_max_rad)


def adaptive_speed_scale(force_norm: float) -> float:
    """Seed 002 eq. 4 as a speed factor: Q_p(‖F_r‖) / Q_p,max ∈ (Q_p,min/Q_p,max, 1].

    In the paper the speed comes from the position weight alone (the carrot is the only
    reference), so lowering Q_p near obstacles slows the MAV ("the dips ... where the adaptive
    weights scheme reduced the speed due to the proximity of an obstacle", §4.3). Here the
    cruise speed is also a velocity reference, which eq. 4 alone would leave untouched; scaling
    it (and the position lead) by the same ratio gives the slow-down the paper describes.
    """
    from btmission.control.nmpc import NmpcConfig, adaptive_position_weight

    nc = NmpcConfig()
    q = adaptive_position_weight(force_norm, nc.q_position_min[0], nc.q_position[0], nc.force_gain)
    return float(q) / nc.q_position[0]


def multirotor_apf_config(gain: float, speed_m_s: float) -> ApfConfig:
    """The multirotor APF for a cruise speed: gain L per point, r_F widened with the braking
    distance (:func:`~btmission.control.apf.influence_radius_for_speed`; unchanged up to
    1.5 m/s)."""
    base = ApfConfig(gain=(gain, gain, gain))
    r_f = influence_radius_for_speed(speed_m_s, base, braking_decel(), BRAKE_REACTION_S)
    return ApfConfig(gain=(gain, gain, gain), r_influence_m=r_f)


class Polyline:
    """A route as a polyline with its arc length, for carrot chasing (the projection and the
    carrot are compiled: :mod:`btmission.runtime._route_kernels`)."""

    def __init__(self, points: FloatArray) -> None:
        self.points = np.asarray(points, dtype=float).reshape(-1, 3)
        if len(self.points) == 0:
            raise ValueError("a route needs at least one point")
        seg = np.diff(self.points, axis=0)
        self.seg = seg
        self.seg_len2 = np.einsum("ij,ij->i", seg, seg)
        self.seg_len = np.sqrt(self.seg_len2)
        self.arc = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        """Arc length (m) at each point."""
        n = len(self.points)
        table = np.zeros((n, 9))
        table[:, 0:3] = self.points
        table[: n - 1, 3:6] = seg
        table[: n - 1, 6] = self.seg_len2
        table[: n - 1, 7] = self.seg_len
        table[:, 8] = self.arc
        self._table = table
        self._length = float(self.arc[-1])

    @property
    def length(self) -> float:
        """Arc length (m) of the whole route."""
        return self._length

    def project(self, position: FloatArray, start: int = 0) -> tuple[int, float]:
        """(segment, arc length) of the point of the route closest to ``position``, searching
        ``CARROT_WINDOW`` segments forward from ``start`` (progress only moves forward)."""
        from btmission.runtime._route_kernels import project

        seg, arc = project(
            self._table, float(position[0]), float(position[1]), float(position[2]),
            int(start), CARROT_WINDOW,
        )  # fmt: skip
        return int(seg), float(arc)

    def carrots(
        self, position: FloatArray, start: int, ahead1: float, ahead2: float
    ) -> tuple[int, float, FloatArray, FloatArray]:
        """:meth:`project`, then :meth:`at` ``ahead1`` and ``ahead2`` past the projection, in
        one compiled call (the carrot and the point the heading looks at, every control step):
        (segment, arc length, point 1, point 2)."""
        from btmission.runtime._route_kernels import carrots

        out = carrots(
            self._table, float(position[0]), float(position[1]), float(position[2]),
            int(start), CARROT_WINDOW, float(ahead1), float(ahead2),
        )  # fmt: skip
        return int(out[0]), float(out[1]), out[2:5], out[5:8]

    def at(self, s: float) -> FloatArray:
        """The point at arc length ``s`` (clamped to the ends)."""
        from btmission.runtime._route_kernels import point_at

        out: FloatArray = point_at(self._table, float(s))
        return out


AGENT_APF = {
    VehicleKind.MULTIROTOR: ApfConfig(
        r_influence_m=2.5,
        r_critical_m=0.9,
        gain=(2.0, 2.0, 2.0),
        gain_critical=1.0,
        dust_points=0,
    ),
    VehicleKind.GROUND: ApfConfig(
        r_influence_m=1.0,
        r_critical_m=0.4,
        gain=(1.5, 1.5, 0.0),
        gain_critical=1.0,
        dust_points=0,
    ),
}
"""Seed 002 eq. 3 for the other agents' shared positions ρ_j (one point per agent)::

    F^r_agents = Σ_{‖ρ_j‖ ≤ r_F} L (1 − ‖ρ_j‖/r_F)² (−ρ_j/‖ρ_j‖) + Σ_{‖ρ_j‖ ≤ r_c} L_c (−ρ_j/‖ρ_j‖)

so a larger radius and gain than for LiDAR points on rock (smaller for TurtleBot-sized ground
robots in 2 m aisles). It steers (the sidestep of two drones meeting head-on); the separation
itself is :data:`AGENT_SEPARATION`'s. A multirotor's L = 2, L_c = 1: at L = 4, L_c = 2 the push
between two drones outweighed the LiDAR's repulsion from the rock beside them (shaped by Alg. 1
to the same F_max), and drove a drone into a wall at 30 drones in ``btmission bench fleet``."""

AGENT_SEPARATION = {
    VehicleKind.MULTIROTOR: SeparationConfig(
        stand_off_m=1.0, decel_m_s2=3.6, reaction_s=0.85, share=0.5, lead_decel_m_s2=0.8
    ),
    VehicleKind.GROUND: SeparationConfig(stand_off_m=0.0),
}
"""The separation rule between agents (:func:`~btmission.control.apf.separation_bound`) on
the APF's velocity: a multirotor approaches another no faster than it can stop within half the
gap beyond s = 1 m (two 0.25 m bodies and 0.5 m), plus what a neighbour moving away still covers.

Its own stop v·t_r + v²/(2a) with t_r = 0.85 s (the autopilot's velocity loop, 1/1.2 s) and
a = 3.6 m/s² (the tilt limit): 0.46 m from 0.5 m/s and 1.59 m from 1.5 m/s, where the embedded
simulator's autopilot, its velocity setpoint dropped to zero, stops in 0.47 m and 1.40 m. A
neighbour moving away at w covers w²/(2·0.8 m/s²): 1.41 m from 1.5 m/s, the simulator's 1.40 m,
and less than it below cruise. (With the tilt limit for a_j too, drones following one another
out of the start area kept ~3.6 m apart and 100 drones did 64 tasks in 70 s instead of 74.)
t_r = 1.1 s would keep two drones meeting head-on at 1.5 m/s 1.09 m apart instead of 0.72 m,
for 68 tasks. Off
for ground robots: their NMPC keeps eq. 12 itself, and their pure pursuit steers at the APF's
point, not at a velocity."""


TRACK_LOOKAHEAD_S = 1.0
"""How far ahead of the schedule reference :func:`track_unicycle` steers (s of travel)."""
TRACK_GAIN = 0.5
"""Speed added per metre of along-track lag (1/s)."""
TRACK_STOP_M = 0.5
"""A standing reference closer than this is reached: stop instead of creeping."""


def track_unicycle(
    p: FloatArray, yaw: float, ref: FloatArray, v_ref: FloatArray, v_max: float
) -> tuple[float, float]:
    """[u_v, u_ω] for a unicycle keeping to a moving reference ``ref`` with velocity ``v_ref``.

    Pure pursuit of the point ``TRACK_LOOKAHEAD_S`` ahead of the reference, at the reference's
    speed plus ``TRACK_GAIN`` × the along-track lag (so a vehicle behind catches up and one ahead
    slows down), capped at ``v_max``; it turns on the spot when the way ahead is more than 90°
    off its heading (a truck reversing out of a pause bay, in this model)."""
    speed = float(np.hypot(*v_ref))
    target = ref + v_ref * TRACK_LOOKAHEAD_S
    d = target - p
    dist = float(np.hypot(*d))
    if speed < 1e-6 and dist < TRACK_STOP_M:
        return 0.0, 0.0
    err = wrap_angle(math.atan2(d[1], d[0]) - yaw)
    uw = float(np.clip(2.0 * err, -1.5, 1.5))
    if abs(err) > math.pi / 2:
        return 0.0, uw
    heading = np.array([math.cos(yaw), math.sin(yaw)])
    lag = float((ref - p) @ heading)
    uv = (speed + TRACK_GAIN * lag) * math.cos(err)
    if speed < 1e-6:  # standing reference: approach it, slowing down
        uv = min(uv, 0.8 * dist)
    return float(np.clip(uv, 0.0, v_max)), uw


def ground_obstacle_points(
    points: ArrayLike, position: ArrayLike, yaw: float, others: Sequence[ArrayLike] = ()
) -> FloatArray:
    """A ground robot's LiDAR points (yaw frame, relative to its base at ``position``) as world
    x-y obstacle points for its NMPC's safe corridor: only those between the heights of
    :data:`GROUND_OBSTACLE_BAND_M` (no floor; what the body can touch), less those within
    :data:`SHARED_BODY_M` of an ``others`` position (robots that share their predictions: eq. 12
    keeps clear of them), rounded to the millimetre and de-duplicated."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    lo, hi = GROUND_OBSTACLE_BAND_M
    pts = pts[(pts[:, 2] > lo) & (pts[:, 2] < hi)]
    if len(pts) == 0:
        return np.zeros((0, 2))
    world = yaw_frame_to_world(pts, yaw)[:, :2] + np.asarray(position, dtype=float)[:2]
    for other in others:
        o = np.asarray(other, dtype=float)[:2]
        world = world[np.hypot(world[:, 0] - o[0], world[:, 1] - o[1]) >= SHARED_BODY_M]
    return np.unique(np.round(world, 3), axis=0)
