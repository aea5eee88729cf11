"""Small closed-loop scenarios of the reactive-navigation modules, returned as plain data.

Each function runs one scenario from the issue's test list against the numpy models and the
synthetic sensors of :mod:`~btmission.control.scenes`, and returns a log dataclass that tests assert
on and :mod:`~btmission.control.plots` draws. No I/O.

* :func:`waypoint_flight` — the MAV NMPC flies to a set-point (seed 002 eq. 1-2).
* :func:`corridor_flight` — NMPC + APF down a corridor with the carrot pulled into a wall and dust
  near the MAV (eq. 3, Alg. 1, eq. 4).
* :func:`head_on` — two unicycles with the distributed set-exclusion NMPC (seed 003 eq. 11-12).
* :func:`explore_tunnel` — COMPRA in a bending tunnel: carrot + DPHR + APF out for the time
  budget, then back along the breadcrumbs (seed 002 Alg. 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from btmission.types import FloatArray

__all__ = [
    "CorridorLog",
    "ExplorationLog",
    "FlightLog",
    "HeadOnLog",
    "corridor_flight",
    "explore_tunnel",
    "head_on",
    "waypoint_flight",
]


@dataclass(frozen=True)
class FlightLog:
    """A closed-loop MAV flight at the NMPC rate."""

    dt_s: float
    states: FloatArray
    """(K+1, 8) states, starting with the initial one."""
    inputs: FloatArray
    """(K, 3) applied [T, φ_ref, θ_ref]."""
    solve_times_s: FloatArray
    success: NDArray[np.bool_]
    goal: FloatArray


def waypoint_flight(
    goal: ArrayLike = (2.0, -1.5, 2.5),
    start: ArrayLike = (0.0, 0.0, 1.0),
    steps: int = 100,
    solver: str = "fatrop",
) -> FlightLog:
    """Hover at ``start``, then fly to ``goal`` for ``steps`` NMPC periods."""
    from btmission.control.mav_model import simulate
    from btmission.control.nmpc import MavNmpc, NmpcConfig

    cfg = NmpcConfig(solver=solver)
    nmpc = MavNmpc(cfg)
    x = np.zeros(8)
    x[:3] = np.asarray(start, dtype=float)
    target = np.asarray(goal, dtype=float)
    states, inputs, times, ok = [x], [], [], []
    for _ in range(steps):
        res = nmpc.solve(x, target)
        x = simulate(x, res.u, cfg.dt_s, cfg.model)
        states.append(x)
        inputs.append(res.u)
        times.append(res.solve_time_s)
        ok.append(res.success)
    return FlightLog(
        cfg.dt_s, np.array(states), np.array(inputs), np.array(times), np.array(ok), target
    )


@dataclass(frozen=True)
class CorridorLog:
    """NMPC + APF in a straight corridor (y ∈ ±width/2, z ∈ [0, height])."""

    width_m: float
    height_m: float
    flight: FlightLog
    forces: FloatArray
    """(K, 3) total force F per step (‖F‖ ≤ 1)."""
    repulsive: FloatArray
    """(K, 3) shaped F^r_k per step."""
    repulsive_raw_norm: FloatArray
    q_position: FloatArray
    """(K,) the eq. 4 position weight used (x component)."""
    dust_ignored: NDArray[np.bool_]
    clearance: FloatArray
    """(K+1,) distance to the nearest wall, floor or ceiling."""


def corridor_flight(
    steps: int = 140,
    width_m: float = 2.4,
    height_m: float = 3.0,
    pull: ArrayLike = (1.0, 1.0, 0.0),
    initial_velocity: ArrayLike = (0.0, 0.5, 0.0),
    dust: bool = True,
    apf_config: object | None = None,
) -> CorridorLog:
    """Fly down a corridor with the body-frame waypoint ``pull`` (default: ahead and into the left
    wall) shifted by the APF; two dust points near the MAV on every other scan if ``dust``."""
    from btmission.control.apf import ApfConfig, PotentialField
    from btmission.control.mav_model import simulate
    from btmission.control.nmpc import MavNmpc, NmpcConfig
    from btmission.control.scenes import lidar_scan, straight_corridor

    tunnel = straight_corridor(width_m, height_m)
    apf = PotentialField(apf_config if isinstance(apf_config, ApfConfig) else None)
    cfg = NmpcConfig()
    nmpc = MavNmpc(cfg)
    x = np.zeros(8)
    x[2] = height_m / 2
    x[3:6] = np.asarray(initial_velocity, dtype=float)
    waypoint = np.asarray(pull, dtype=float)
    dust_points = np.array([[0.3, 0.1, 0.0], [0.2, -0.15, 0.1]])

    def clearance(s: FloatArray) -> float:
        return float(min(width_m / 2 - s[1], width_m / 2 + s[1], s[2], height_m - s[2]))

    states, inputs, times, ok = [x], [], [], []
    forces, reps, raws, qps, ignored, clear = [], [], [], [], [], [clearance(x)]
    for k in range(steps):
        points = lidar_scan(tunnel, x[:3])
        if dust and k % 2:
            points = np.vstack([points, dust_points])
        res = apf.step(points, waypoint)
        raw = float(np.linalg.norm(res.repulsive_raw))
        step = nmpc.solve(x, x[:3] + res.reference, repulsive_force=raw)
        x = simulate(x, step.u, cfg.dt_s, cfg.model)
        states.append(x)
        inputs.append(step.u)
        times.append(step.solve_time_s)
        ok.append(step.success)
        forces.append(res.force)
        reps.append(res.repulsive)
        raws.append(raw)
        qps.append(step.q_position[0])
        ignored.append(res.critical_ignored)
        clear.append(clearance(x))
    flight = FlightLog(
        cfg.dt_s, np.array(states), np.array(inputs), np.array(times), np.array(ok), waypoint
    )
    return CorridorLog(
        width_m,
        height_m,
        flight,
        np.array(forces),
        np.array(reps),
        np.array(raws),
        np.array(qps),
        np.array(ignored),
        np.array(clear),
    )


@dataclass(frozen=True)
class HeadOnLog:
    """Two unicycles driving at each other."""

    dt_s: float
    a: FloatArray
    """(K+1, 3) states of robot A."""
    b: FloatArray
    goals: FloatArray
    """(2, 2) goals of A and B."""
    inputs_a: FloatArray
    inputs_b: FloatArray
    success: NDArray[np.bool_]
    distance: FloatArray
    """(K+1,) distance between the robots."""
    r_obs_m: float


def head_on(
    steps: int = 110, offset: float = 0.05, gap_m: float = 4.0, avoid: bool = True
) -> HeadOnLog:
    """A at (0, offset) heading +x to (gap, offset); B at (gap, 0) heading −x to the origin.

    With ``avoid`` each robot gets the other's last predicted trajectory (shifted one step), the
    distributed scheme of seed 003 §VI; without it they ignore each other.
    """
    from btmission.control.unicycle_nmpc import (
        UnicycleNmpc,
        shift_prediction,
        unicycle_step,
    )

    a, b = UnicycleNmpc(), UnicycleNmpc()
    cfg = a.config
    n = cfg.horizon
    xa, xb = np.array([0.0, offset, 0.0]), np.array([gap_m, 0.0, math.pi])
    ga, gb = np.array([gap_m, offset]), np.array([0.0, 0.0])
    pa, pb = np.tile(xa[:2], (n + 1, 1)), np.tile(xb[:2], (n + 1, 1))
    sa, sb, ua, ub, ok = [xa], [xb], [], [], []
    for _ in range(steps):
        ra = a.solve(xa, ga, [shift_prediction(pb)] if avoid else [])
        rb = b.solve(xb, gb, [shift_prediction(pa)] if avoid else [])
        pa, pb = ra.predicted_positions, rb.predicted_positions
        xa, xb = unicycle_step(xa, ra.u, cfg.dt_s), unicycle_step(xb, rb.u, cfg.dt_s)
        sa.append(xa)
        sb.append(xb)
        ua.append(ra.u)
        ub.append(rb.u)
        ok.append(ra.success and rb.success)
    a_arr, b_arr = np.array(sa), np.array(sb)
    return HeadOnLog(
        cfg.dt_s,
        a_arr,
        b_arr,
        np.array([ga, gb]),
        np.array(ua),
        np.array(ub),
        np.array(ok),
        np.linalg.norm(a_arr[:, :2] - b_arr[:, :2], axis=1),
        cfg.r_obs_m,
    )


@dataclass(frozen=True)
class ExplorationLog:
    """A COMPRA exploration run in a tunnel (2-D top view plus the mode per step)."""

    tunnel_left: FloatArray
    tunnel_right: FloatArray
    positions: FloatArray
    """(K+1, 3) MAV positions."""
    yaws: FloatArray
    modes: list[str]
    breadcrumbs: FloatArray
    """(B, 3) the crumbs recorded on the way out."""
    yaw_rates: FloatArray
    """(K,) DPHR yaw-rate references (0 outside exploration)."""
    dt_s: float
    clearance: FloatArray
    """(K+1,) horizontal distance to the nearest wall."""


def explore_tunnel(
    bend: str = "left",
    mission_time_s: float = 14.0,
    dt_s: float = 0.2,
    speed_m_s: float = 0.8,
    max_time_s: float = 60.0,
) -> ExplorationLog:
    """COMPRA in a bending tunnel with a kinematic MAV (moves towards the APF reference at up to
    ``speed_m_s``; yaw integrates the DPHR rate while exploring, holds ψ_ref on the way back).

    Sensors each step, kept small so the whole run takes a few seconds: a 96×72 depth image for
    DPHR and a 16 × 375 LiDAR scan for the APF (whose per-point gain L is scaled up ×5 from the
    default, tuned for 1,875 azimuths, so the force per metre of wall stays the same).
    """
    from btmission.control.apf import ApfConfig, PotentialField
    from btmission.control.compra import CompraConfig, CompraExplorer, Mode
    from btmission.control.dphr import DphrConfig, deepest_point_heading
    from btmission.control.mav_model import world_to_yaw_frame, wrap_angle
    from btmission.control.scenes import DepthCamera, bending_tunnel, depth_image, lidar_scan

    tunnel = bending_tunnel(bend, straight_m=4.0, radius_m=6.0, exit_m=30.0)
    explorer = CompraExplorer(CompraConfig(mission_time_s=mission_time_s, breadcrumb_rate_hz=1.0))
    azimuths = 375
    scale = 1875 / azimuths
    default_gain = ApfConfig().gain
    apf = PotentialField(
        ApfConfig(gain=(default_gain[0] * scale, default_gain[1] * scale, default_gain[2] * scale))
    )
    camera = DepthCamera(width=96, height=72)
    dphr_cfg = DphrConfig(stride=1)
    p = np.array([0.0, 0.0, 1.5])
    yaw = 0.0
    positions, yaws, modes, rates = [p.copy()], [yaw], [], []
    starts, edges = tunnel.segments()

    def wall_clearance(q: FloatArray) -> float:
        rel = q[:2] - starts
        s = np.clip(np.einsum("ij,ij->i", rel, edges) / np.einsum("ij,ij->i", edges, edges), 0, 1)
        return float(np.min(np.linalg.norm(rel - s[:, None] * edges, axis=1)))

    clear = [wall_clearance(p)]
    t = 0.0
    while t < max_time_s:
        rate = 0.0
        if explorer.mode is Mode.EXPLORE:
            rate = deepest_point_heading(depth_image(tunnel, p, yaw, camera), dphr_cfg).yaw_rate
        cmd = explorer.step(t, p, yaw, altitude_m=p[2], dphr_yaw_rate=rate)
        modes.append(cmd.mode.value)
        rates.append(cmd.yaw_rate_ref)
        if cmd.mode is Mode.LAND:
            break
        if cmd.yaw_ref is None:
            yaw = wrap_angle(yaw + cmd.yaw_rate_ref * dt_s)
        else:
            yaw = cmd.yaw_ref
        # APF in the body frame: rotate the scan's world geometry by the current yaw
        points = lidar_scan(tunnel, p, yaw, azimuth_steps=azimuths)
        body_wp = world_to_yaw_frame(cmd.waypoint - p, yaw)
        ref_body = apf.step(points, body_wp).reference
        step = world_to_yaw_frame(ref_body, -yaw)  # back to the world frame
        norm = float(np.linalg.norm(step))
        if norm > speed_m_s * dt_s:
            step = step * (speed_m_s * dt_s / norm)
        p = p + step
        t += dt_s
        positions.append(p.copy())
        yaws.append(yaw)
        clear.append(wall_clearance(p))
    crumbs = np.array([c.position for c in explorer.trail.recorded]).reshape(-1, 3)
    return ExplorationLog(
        tunnel.left,
        tunnel.right,
        np.array(positions),
        np.array(yaws),
        modes,
        crumbs,
        np.array(rates),
        dt_s,
        np.array(clear),
    )
