"""Reactive artificial potential field on a raw point cloud (seed 002 §3.2.3, eq. 3 and Alg. 1).

Repulsive force from the LiDAR points ρ (body frame, metres) inside the radius of influence r_F,
plus a static potential from the points inside the safety-critical radius r_c (seed 002 eq. 3)::

    F^r = Σ_{‖ρ_i‖ ≤ r_F} L ∘ (1 − ‖ρ_i‖/r_F)² · (−ρ_i/‖ρ_i‖)  +  Σ_{‖ρ_i‖ ≤ r_c} L_c · (−ρ_i/‖ρ_i‖)

where L = [L_x, L_y, L_z] is the largest force per point and L_c the static potential. The r_c term
is zero when N_c ≤ n points lie inside r_c (the *dust rule*: a few dust particles must not trigger
the large static force, while a real obstacle still does). Points at the origin (‖ρ‖ = 0, no
direction) are ignored.

Alg. 1 then shapes the force, with k the current and k−1 the previous scan:

    if ‖F^r_k‖ > F_max:                 F^r_k ← sgn(F^r_k) F_max
    if ‖F^r_k − F^r_{k−1}‖ > ΔF_max:     F^r_k ← F^r_{k−1} + sgn(F^r_k − F^r_{k−1}) ΔF_max
    if ‖F^a‖ > 1:                       F^a ← F^a / ‖F^a‖
    F ← F^r_k + F^a;  if ‖F‖ > 1:        F ← F / ‖F‖

with F^a = wp^B − p̂^B (the vector to the next waypoint). The shifted reference handed to the NMPC
is p_ref^B = F + p̂^B. ``sgn`` of a vector is read as its direction v/‖v‖: the tests right before
each assignment are on norms, and only this reading makes the assignments meet them
(‖F^r‖ = F_max, ‖F^r_k − F^r_{k−1}‖ = ΔF_max); an element-wise sign would turn a force along x into
a diagonal of norm √3·F_max and break the very rate limit it is meant to impose.

The sums and Alg. 1 run as compiled loops (:mod:`btmission.control._apf_kernels`): a scan holds a
few to a few hundred points, and every vehicle evaluates the field every control period, so numpy's
per-call overhead outweighed the arithmetic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike

from btmission.types import FloatArray, Vec3

__all__ = [
    "ApfConfig",
    "ApfResult",
    "PotentialField",
    "SeparationConfig",
    "braking_distance",
    "influence_radius_for_speed",
    "limit_approach_speed",
    "repulsive_force",
    "separation_bound",
    "shape_force",
    "stopping_speed",
]


@dataclass(frozen=True)
class ApfConfig:
    """APF parameters (seed 002 §3.2.3). The paper gives no values; these suit a ~1 m MAV in
    2-4 m wide tunnels with a VLP-16-class scan (tens to hundreds of points inside r_F)."""

    r_influence_m: float = 1.6
    """r_F: radius of influence."""
    r_critical_m: float = 0.6
    """r_c: safety-critical radius with the static potential."""
    gain: Vec3 = (0.001, 0.001, 0.001)
    """L = [L_x, L_y, L_z]: largest force per point inside r_F."""
    gain_critical: float = 0.2
    """L_c: static force per point inside r_c."""
    dust_points: int = 3
    """n: the r_c term is ignored when at most this many points lie inside r_c."""
    force_max: float = 1.5
    """F_max: saturation of ‖F^r‖. Above 1, so a saturated repulsion outweighs any attraction."""
    force_rate_max: float = 0.3
    """ΔF_max: largest change of F^r from one scan to the next."""

    def __post_init__(self) -> None:
        if not 0 < self.r_critical_m < self.r_influence_m:
            raise ValueError(
                f"need 0 < r_critical_m < r_influence_m, got {self.r_critical_m} and "
                f"{self.r_influence_m}"
            )
        if len(self.gain) != 3 or any(g < 0 for g in self.gain) or self.gain_critical < 0:
            raise ValueError("gain must be three non-negative numbers and gain_critical >= 0")
        if self.dust_points < 0:
            raise ValueError(f"dust_points must be >= 0, got {self.dust_points}")
        if self.force_max <= 0 or self.force_rate_max <= 0:
            raise ValueError("force_max and force_rate_max must be positive")

    @cached_property
    def packed(self) -> FloatArray:
        """(r_F, r_c, L_x, L_y, L_z, L_c, n, F_max, ΔF_max): the parameters as the compiled
        kernels take them."""
        return np.array(
            [self.r_influence_m, self.r_critical_m, *self.gain, self.gain_critical,
             self.dust_points, self.force_max, self.force_rate_max],
            dtype=float,
        )  # fmt: skip


@dataclass(frozen=True)
class ApfResult:
    """One APF step. Forces are body-frame vectors; ``reference`` = F + p̂ (p_ref^B)."""

    force: FloatArray
    """F: the normalised total force (‖F‖ ≤ 1)."""
    reference: FloatArray
    """p_ref^B = F + p̂^B: the obstacle-free position reference for the NMPC."""
    repulsive: FloatArray
    """F^r_k after saturation and rate saturation (the value remembered for the next scan)."""
    repulsive_raw: FloatArray
    """F^r of eq. 3 before Alg. 1 (its norm feeds the adaptive weights of eq. 4)."""
    attractive: FloatArray
    """F^a after normalisation."""
    n_influence: int
    """N_ρr: points inside r_F."""
    n_critical: int
    """N_ρc: points inside r_c."""
    critical_ignored: bool
    """True when 0 < N_ρc ≤ n and the static r_c term was dropped as dust."""


def braking_distance(speed_m_s: float, decel_m_s2: float, reaction_s: float) -> float:
    """Distance to stop from ``speed_m_s``: d = v·t_r + v² / (2 a) (reaction, then full braking).

    ``reaction_s`` covers what passes before the full deceleration ``decel_m_s2`` acts: the APF's
    rate saturation ΔF_max ramping the repulsion up, the NMPC's input-rate limit (eq. 2) tilting
    the MAV back and the attitude loop's lag.
    """
    if speed_m_s < 0 or decel_m_s2 <= 0 or reaction_s < 0:
        raise ValueError("need speed >= 0, decel > 0 and reaction time >= 0")
    return speed_m_s * reaction_s + speed_m_s**2 / (2.0 * decel_m_s2)


def stopping_speed(distance_m: float, decel_m_s2: float, reaction_s: float) -> float:
    """The largest speed that can still stop within ``distance_m``: the root v ≥ 0 of
    v·t_r + v² / (2 a) = d (0 when d ≤ 0)."""
    if decel_m_s2 <= 0 or reaction_s < 0:
        raise ValueError("need decel > 0 and reaction time >= 0")
    if distance_m <= 0:
        return 0.0
    at = decel_m_s2 * reaction_s
    return float(-at + np.sqrt(at * at + 2.0 * decel_m_s2 * distance_m))


def limit_approach_speed(
    velocity: ArrayLike,
    points: ArrayLike,
    stand_off_m: float,
    decel_m_s2: float,
    reaction_s: float,
    passes: int = 6,
    corridor_m: float = np.inf,
    heading: ArrayLike | None = None,
) -> FloatArray:
    """``velocity`` with its component towards every point of ``points`` (same frame, relative
    to the MAV) bounded by the speed that can still stop before coming within ``stand_off_m`` of
    it (:func:`stopping_speed` of ‖ρ‖ − stand-off). Components along the rock (sliding past a
    wall) and away from it are kept: only the approach is limited.

    Each pass removes the largest excess (the most constraining point); ``passes`` bounds the
    work, enough for a wall ahead, one beside it and the floor or roof at a corner.

    Only points within ``corridor_m`` of the line along ``velocity`` — or along ``heading``, the
    way the MAV actually moves — count: a straight path passes farther ones by, and the floor
    ahead of a MAV flying level over it is not something it approaches.
    """
    v = np.asarray(velocity, dtype=float).copy()
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    d = np.sqrt(np.einsum("ij,ij->i", pts, pts)) if len(pts) else np.zeros(0)
    ok = d > 0
    if not ok.any() or not np.any(v):
        return v
    if np.isfinite(corridor_m):
        near = np.zeros(len(pts), dtype=bool)
        for line in (v, heading):
            if line is None or not np.any(line):
                continue
            u = np.asarray(line, dtype=float) / vector_norm(line)
            along = pts @ u
            lateral2 = d * d - along * along
            near |= (along > 0) & (lateral2 <= corridor_m * corridor_m)
        ok &= near
        if not ok.any():
            return v
    units = pts[ok] / d[ok, None]
    at = decel_m_s2 * reaction_s
    room = np.maximum(d[ok] - stand_off_m, 0.0)
    allowed = -at + np.sqrt(at * at + 2.0 * decel_m_s2 * room)  # stopping_speed, vectorised
    for _ in range(passes):
        excess = units @ v - allowed
        i = int(np.argmax(excess))
        if excess[i] <= 1e-12:
            break
        v -= excess[i] * units[i]
    return v


@dataclass(frozen=True)
class SeparationConfig:
    """The agents' separation rule (:func:`separation_bound`). ``stand_off_m`` = 0 turns it
    off."""

    stand_off_m: float = 1.0
    """s: the distance two agents keep at the least (centre to centre)."""
    decel_m_s2: float = 1.5
    """a: the deceleration this agent's own stop counts on."""
    reaction_s: float = 0.6
    """t_r: the time before that deceleration acts (the autopilot's velocity loop lag)."""
    share: float = 0.5
    """σ: this agent's share of the gap (½: each of two agents keeps to its half)."""
    lead_decel_m_s2: float = 3.6
    """a_j: the hardest a neighbour moving away brakes (default: the tilt limit, g·tan 0.35):
    the distance it still travels, w²/(2·a_j), is room this agent may use."""
    passes: int = 4
    """The most constraining neighbours bounded per step."""

    def __post_init__(self) -> None:
        if self.stand_off_m < 0 or self.decel_m_s2 <= 0 or self.reaction_s < 0:
            raise ValueError("need stand_off_m >= 0, decel_m_s2 > 0 and reaction_s >= 0")
        if not 0 < self.share <= 1 or self.lead_decel_m_s2 <= 0 or self.passes < 1:
            raise ValueError("need 0 < share <= 1, lead_decel_m_s2 > 0 and passes >= 1")

    @cached_property
    def packed(self) -> FloatArray:
        """(s, a, t_r, σ, a_j, passes): the parameters as the compiled kernels take them."""
        return np.array(
            [self.stand_off_m, self.decel_m_s2, self.reaction_s, self.share,
             self.lead_decel_m_s2, self.passes],
            dtype=float,
        )  # fmt: skip


def separation_bound(
    velocity: ArrayLike,
    others: ArrayLike,
    config: SeparationConfig,
    others_velocity: ArrayLike | None = None,
    current: ArrayLike | None = None,
) -> FloatArray:
    """``velocity`` with its approach to every other agent bounded so that this agent can still
    stop before its share of the gap is used up (``others``: their positions relative to it,
    (k, 3); ``others_velocity``: their velocities, (k, 3), NaN or None where not shared;
    ``current``: this agent's velocity now, None: not known, no correction; all in the
    velocity's frame)::

        v·u_i ≤ A_i − max(0, c·u_i − A_i),
        A_i = v_stop(σ·(‖ρ_i‖ − s) + w_i²/(2·a_j)),   u_i = ρ_i/‖ρ_i‖,  w_i = max(0, v_i·u_i),
        v_stop(x) = −a·t_r + √((a·t_r)² + 2·a·x)   (the root of v·t_r + v²/(2a) = x, 0 for x ≤ 0)

    It is seed 003's set-exclusion constraint (eq. 12, C = [r_obs² − ‖p − p_obs‖²]_+ = 0 at
    every step of the prediction horizon) for a vehicle without a predictive controller: its
    prediction is the stop it can still make (:func:`braking_distance`: reaction t_r, then
    deceleration a), and the constraint holds along it while the approach speed is at most
    v_stop of its room. With σ = ½ each of two agents keeps to its half of the gap, so two
    agents that both apply the rule stop s apart at the least however they meet, and one
    alone stops at s from one that does not move (a drone climbing from its pad, holding at
    its task). A neighbour that moves away from this agent at w_i (its velocity, shared on the
    link with its position: seed 003's agents share their predictions) adds the distance it
    still travels if it brakes as hard as it can (a_j), so a drone following another along a
    drift keeps a shorter gap than behind a standing drone, and is still safe when the leader
    stops dead; one that moves towards it adds nothing (it keeps to its own half). Only the approach is bounded: moving along another
    agent (passing it) or away from it is kept, so the APF's sidestep still lets two drones
    meeting head-on pass. The autopilot's velocity loop lags a command lowered step by step
    (two drones meeting head-on at 1.5 m/s each came within 0.12 m with the bound on the
    command alone), so while the current velocity c still approaches faster than A_i the
    command is lowered by that excess again: with a first-order loop the approach then falls
    onto A_i twice as fast. Each pass removes the largest excess (the most constraining
    neighbour), at most ``config.passes`` of them.
    """
    from btmission.control._apf_kernels import separation_bound as compiled

    v = _vec3(velocity, "velocity")
    rel = np.ascontiguousarray(others, dtype=float).reshape(-1, 3)
    if others_velocity is None:
        vel = np.full(rel.shape, np.nan)
    else:
        vel = np.ascontiguousarray(others_velocity, dtype=float).reshape(-1, 3)
    if len(vel) != len(rel):
        raise ValueError(f"{len(rel)} positions but {len(vel)} velocities of other agents")
    now = np.full(3, np.nan) if current is None else _vec3(current, "current velocity")
    out = np.empty(3)
    c = config
    compiled(
        float(v[0]), float(v[1]), float(v[2]), float(now[0]), float(now[1]), float(now[2]),
        rel, vel, c.stand_off_m, c.decel_m_s2, c.reaction_s, c.share, c.lead_decel_m_s2,
        c.passes, out,
    )  # fmt: skip
    return out


def influence_radius_for_speed(
    speed_m_s: float, config: ApfConfig, decel_m_s2: float, reaction_s: float
) -> float:
    """r_F for a cruise speed: at least the configured r_F, and wide enough that a wall entering
    it can still be stopped for before it reaches the safety-critical radius r_c::

        r_F(v) = max(r_F, r_c + v·t_r + v² / (2 a))

    Seed 002 gives no r_F; its tuning flew 0.9-1 m/s, and §4.5 names safety distances that adapt
    to the manoeuvre as the next step. With a fixed r_F the repulsion of eq. 3 starts too late at
    2.3 m/s: the MAV needs ~2 m to stop, more than the whole 1.6 m field (the clearance loss the
    speed runs showed). At 1 m/s the configured r_F is kept unchanged.
    """
    need = config.r_critical_m + braking_distance(speed_m_s, decel_m_s2, reaction_s)
    return max(config.r_influence_m, need)


def vector_norm(v: ArrayLike) -> float:
    """‖v‖ of one vector: ``np.linalg.norm``'s √(v·v), to the bit, without its per-call cost
    (the control step takes several norms of 3-vectors per vehicle)."""
    a = np.asarray(v, dtype=float)
    return math.sqrt(float(a @ a))


def repulsive_force(points: ArrayLike, config: ApfConfig) -> tuple[FloatArray, int, int, bool]:
    """F^r of seed 002 eq. 3 for an (M, 3) body-frame point cloud.

    Returns (F^r, N_ρr, N_ρc, critical_ignored). Non-finite points (NaN returns of a LiDAR) are
    dropped.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be an (M, 3) array, got shape {pts.shape}")
    from btmission.control._apf_kernels import repulsive

    force = np.zeros(3)
    if len(pts) == 0:
        return force, 0, 0, False
    c = config
    g = c.gain
    n, n_crit = repulsive(
        np.ascontiguousarray(pts), c.r_influence_m, c.r_critical_m, float(g[0]), float(g[1]),
        float(g[2]), c.gain_critical, c.dust_points, force,
    )  # fmt: skip
    if n == 0:
        return np.zeros(3), 0, 0, False
    return force, int(n), int(n_crit), bool(0 < n_crit <= c.dust_points)


def shape_force(
    repulsive: ArrayLike, previous: ArrayLike, attractive: ArrayLike, config: ApfConfig
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Seed 002 Alg. 1: saturation, rate saturation and normalisation.

    Returns (F, F^r_k, F^a) with F the total force (‖F‖ ≤ 1), F^r_k the shaped repulsive force
    (‖F^r_k‖ ≤ F_max and ‖F^r_k − F^r_{k−1}‖ ≤ ΔF_max, given a previous force within F_max) and F^a
    the normalised attraction.
    """
    from btmission.control._apf_kernels import shape

    out = np.empty(9)
    shape(
        _vec(repulsive), _vec(previous), _vec(attractive), config.force_max,
        config.force_rate_max, out,
    )  # fmt: skip
    return out[0:3], out[3:6], out[6:9]


def _vec(v: ArrayLike) -> FloatArray:
    a: FloatArray = np.ascontiguousarray(v, dtype=float).reshape(3)
    return a


class PotentialField:
    """Stateful APF: remembers F^r_{k−1} between scans. Call :meth:`step` once per scan."""

    def __init__(self, config: ApfConfig | None = None) -> None:
        self.config = config or ApfConfig()
        self._previous = np.zeros(3)

    @property
    def previous_repulsive(self) -> FloatArray:
        """F^r_{k−1}: the shaped repulsive force of the previous scan."""
        return self._previous.copy()

    def reset(self) -> None:
        """Forget the previous repulsive force (start from zero)."""
        self._previous = np.zeros(3)

    def step(
        self, points: ArrayLike, waypoint: ArrayLike, position: ArrayLike = (0.0, 0.0, 0.0)
    ) -> ApfResult:
        """Shift the waypoint ``wp^B`` away from obstacles in ``points`` (all body frame).

        ``position`` is p̂^B (zero when the body frame is centred on the MAV). Returns the
        reference p_ref^B = F + p̂^B with the intermediate forces.
        """
        p = _vec3(position, "position")
        wp = _vec3(waypoint, "waypoint")
        raw, n_rf, n_rc, ignored = repulsive_force(points, self.config)
        total, fr, fa = shape_force(raw, self._previous, wp - p, self.config)
        self._previous = fr
        return ApfResult(
            force=total,
            reference=total + p,
            repulsive=fr,
            repulsive_raw=raw,
            attractive=fa,
            n_influence=n_rf,
            n_critical=n_rc,
            critical_ignored=ignored,
        )


def _vec3(values: ArrayLike, what: str) -> FloatArray:
    arr = np.asarray(values, dtype=float).ravel()
    if arr.size != 3 or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be three finite numbers, got {arr.tolist()}")
    return arr
