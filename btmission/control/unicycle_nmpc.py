"""Ground-robot NMPC with inter-agent and static-obstacle avoidance (seed 003 §VI, eq. 11-12).

Unicycle model (eq. 11), x = [p_x, p_y, ψ], u = [u_v, u_ω]::

    ṗ_x = cos ψ · u_v,   ṗ_y = sin ψ · u_v,   ψ̇ = u_ω

discretised by RK4 with T_s = 0.1 s, horizon N = 50 (a 5 s prediction), as in the paper. The cost
(seed 003 refers to its eq. 1 predecessor) penalises the state's deviation from the reference
way-point, the inputs, the input changes and the terminal state. Inputs are bounded,
u_min ≤ u ≤ u_max.

Collision avoidance is the set-exclusion constraint of eq. 12 for every other agent i and every
predicted step j = 0 … N::

    C_circle(p_j, p_obs,j^i, r_obs) = [r_obs² − ‖p_j − p_obs,j^i‖²]_+ = 0

where p_obs^i is agent i's *shared* predicted trajectory. As in the paper (which follows Hermans
et al.'s quadratic penalty method for set-exclusion constraints), the constraint enters the cost
as ρ · C_circle², and the solve is repeated with ρ ×= ``penalty_growth`` (warm-started) while the
largest violation exceeds ``violation_tol``, up to ``penalty_updates`` times. Keeping the
constraint in the cost keeps the NLP stage-wise, so fatrop can solve it (:mod:`~.ocp`).

Static obstacles (shelves, walls; seed 003 §VI leaves them to its lab's free floor) are kept at
``r_static_m`` by a *safe corridor*: for every predicted step j a convex polygon of half-spaces
around the linearisation point p̄_j (the previous solution shifted by a step, or the current
position), built from the obstacle points o (e.g. the LiDAR's, projected on the floor) by
:func:`safe_halfspaces`. The closest point o_1 to p̄_j gives the half-space::

    n_1ᵀ p_j ≤ n_1ᵀ o_1 − r_static,      n_1 = (o_1 − p̄_j) / ‖o_1 − p̄_j‖

every point o with n_1ᵀ o ≥ n_1ᵀ o_1 (behind that plane) then satisfies ‖p_j − o‖ ≥ r_static
whenever p_j does, so it is dropped; the closest remaining point gives the next half-space, up to
``max_halfspaces`` per step (the greedy separating-plane construction of safe-flight-corridor
planners). Each half-space is a conservative linearisation of the non-convex distance constraint
‖p_j − o‖ ≥ r_static, so the set it leaves is convex and stage-local. It enters the cost like
eq. 12, as ρ_s · Σ_k [n_kᵀ p_j − b_k]_+² (b_k = n_kᵀ o_k − r_static), and within the same update
loop the corridor is rebuilt around the new solution (a sequential-convex step) and ρ_s ×=
``penalty_growth`` while the predicted positions come closer than r_static + margin − tol to any
obstacle point (the *true* distance, not the half-spaces).

:class:`UnicycleNmpc` is one agent's controller; :meth:`UnicycleNmpc.solve` takes the other agents'
predicted trajectories (``(N+1, 2)`` arrays, e.g. the ``predicted_positions`` other agents
published at their last step, shifted by :func:`shift_prediction`) and returns its own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from btmission.control.mav_model import rk4_step, wrap_angle
from btmission.control.ocp import OcpSolution, StagewiseOcp, check_solver
from btmission.types import FloatArray

__all__ = [
    "UnicycleConfig",
    "UnicycleNmpc",
    "UnicycleResult",
    "exclusion_violation",
    "obstacle_violation",
    "safe_halfspaces",
    "shift_prediction",
    "unicycle_dynamics",
    "unicycle_step",
]

NX = 3
NU = 2
FAR = 1e4
"""Where unused obstacle slots are parked (far outside any r_obs)."""


def unicycle_dynamics(x: Any, u: Any) -> Any:
    """Seed 003 eq. 11 for numpy arrays or CasADi expressions."""
    if isinstance(x, np.ndarray):
        return np.array([math.cos(x[2]) * u[0], math.sin(x[2]) * u[0], u[1]])
    import casadi as ca

    return ca.vertcat(ca.cos(x[2]) * u[0], ca.sin(x[2]) * u[0], u[1])


def unicycle_step(x: ArrayLike, u: ArrayLike, dt: float, substeps: int = 4) -> FloatArray:
    """Advance the numpy unicycle by ``dt`` (RK4 in ``substeps``); the simulation plant."""
    return rk4_step(
        unicycle_dynamics, np.asarray(x, dtype=float), np.asarray(u, float), dt, substeps
    )


def exclusion_violation(positions: ArrayLike, obstacles: ArrayLike, r_obs: float) -> float:
    """max over j of [r_obs − ‖p_j − p_obs,j‖]_+ (metres inside the exclusion circle; 0 = safe)."""
    p = np.asarray(positions, dtype=float)[:, :2]
    o = np.asarray(obstacles, dtype=float)[: len(p), :2]
    d = np.linalg.norm(p[: len(o)] - o, axis=1)
    return float(max(0.0, float(np.max(r_obs - d)))) if len(d) else 0.0


def obstacle_violation(positions: ArrayLike, points: ArrayLike, r_static: float) -> float:
    """max over j of [r_static − min_o ‖p_j − o‖]_+ against obstacle points ``points`` (P, 2)."""
    p = np.asarray(positions, dtype=float)[:, :2]
    o = np.asarray(points, dtype=float).reshape(-1, 2) if np.size(points) else np.zeros((0, 2))
    if len(p) == 0 or len(o) == 0:
        return 0.0
    d2 = ((p[:, None, :] - o[None, :, :]) ** 2).sum(axis=2).min(axis=1)
    return float(max(0.0, r_static - float(np.sqrt(d2.min()))))


def safe_halfspaces(
    centres: ArrayLike,
    points: ArrayLike,
    r_static: float,
    max_halfspaces: int,
    query_radius: float = 1.5,
) -> FloatArray:
    """Per-step safe corridor (module docstring): (M, max_halfspaces, 3) rows [n_x, n_y, b] with
    n_kᵀ p ≤ b_k, b_k = n_kᵀ o_k − r_static, around each of the M ``centres`` (the linearisation
    points p̄_j). Only points within ``query_radius`` of p̄_j count; unused rows are [0, 0, 1]
    (always satisfied)."""
    c = np.asarray(centres, dtype=float).reshape(-1, 2)
    o = np.asarray(points, dtype=float).reshape(-1, 2) if np.size(points) else np.zeros((0, 2))
    out = np.zeros((len(c), max_halfspaces, 3))
    out[:, :, 2] = 1.0
    if len(o) == 0 or max_halfspaces == 0:
        return out
    rel = o[None, :, :] - c[:, None, :]  # (M, P, 2)
    dist = np.sqrt((rel**2).sum(axis=2))
    used = dist.min(axis=0) <= query_radius  # near some step: the rest never count
    o, rel, dist = o[used], rel[:, used], dist[:, used]
    if len(o) == 0:
        return out
    dist[(dist > query_radius) | (dist <= 1e-9)] = np.inf  # not candidates
    rows = np.arange(len(c))
    for k in range(max_halfspaces):  # every step's greedy construction at once
        idx = np.argmin(dist, axis=1)
        d = dist[rows, idx]
        live = np.isfinite(d)
        if not live.any():
            break
        n = rel[rows, idx] / np.where(live, d, 1.0)[:, None]
        edge = (n * o[idx]).sum(axis=1)  # n_kᵀ o_k
        out[live, k, :2] = n[live]
        out[live, k, 2] = edge[live] - r_static
        behind = (o @ n.T).T >= edge[:, None] - 1e-9  # covered by this plane (o_k included)
        dist[behind & live[:, None]] = np.inf
    return out


def shift_prediction(prediction: ArrayLike) -> FloatArray:
    """A trajectory published one step ago, advanced one step: drop the first, repeat the last."""
    arr = np.asarray(prediction, dtype=float)
    return np.vstack([arr[1:], arr[-1:]])


@dataclass(frozen=True)
class UnicycleConfig:
    """Seed 003's T_s = 0.1 s, N = 50 and r_obs = 0.3 m (TurtleBots); the weights are ours."""

    dt_s: float = 0.1
    horizon: int = 50
    r_obs_m: float = 0.3
    margin_m: float = 0.02
    """Added to r_obs inside the optimiser, so the penalty method's small residual violation
    (and the one-step-old shared predictions) stays outside r_obs itself."""
    max_agents: int = 4
    """Obstacle slots compiled into the solver (other agents beyond this are an error)."""
    r_static_m: float = 0.3
    """Safety distance from static obstacle points (shelves, walls) to the robot's centre."""
    static_margin_m: float = 0.03
    """Added to r_static inside the optimiser (the penalty's residual, points between samples)."""
    max_halfspaces: int = 6
    """Half-spaces of the safe corridor per predicted step (0: no static-obstacle constraints)."""
    corridor_radius_m: float = 1.5
    """Obstacle points farther than this from a step's linearisation point are ignored."""
    static_penalty: float = 1e4
    """ρ_s₀ of the safe-corridor penalty."""
    q_position: float = 2.0
    q_heading: float = 0.0
    q_terminal: float = 10.0
    q_input: tuple[float, float] = (0.1, 0.05)
    q_rate: tuple[float, float] = (2.0, 1.0)
    v_max: float = 0.4
    v_min: float = -0.1
    omega_max: float = 1.5
    penalty: float = 100.0
    penalty_growth: float = 10.0
    penalty_updates: int = 3
    violation_tol_m: float = 0.005
    solver: str = "fatrop"
    max_iter: int = 100

    def __post_init__(self) -> None:
        if self.dt_s <= 0 or self.horizon < 1:
            raise ValueError("dt_s must be positive and horizon at least 1")
        if self.r_obs_m <= 0 or self.margin_m < 0 or self.max_agents < 0:
            raise ValueError("r_obs_m must be positive, margin_m and max_agents >= 0")
        if self.r_static_m <= 0 or self.static_margin_m < 0 or self.max_halfspaces < 0:
            raise ValueError("r_static_m must be positive, static_margin_m, max_halfspaces >= 0")
        if self.corridor_radius_m <= self.r_static_m or self.static_penalty <= 0:
            raise ValueError("need corridor_radius_m > r_static_m and static_penalty > 0")
        if not self.v_min <= 0 <= self.v_max or self.omega_max <= 0:
            raise ValueError("need v_min <= 0 <= v_max and omega_max > 0")
        if self.penalty <= 0 or self.penalty_growth <= 1 or self.penalty_updates < 0:
            raise ValueError("need penalty > 0, penalty_growth > 1, penalty_updates >= 0")
        check_solver(self.solver)


@dataclass
class UnicycleResult:
    """One control step of a ground robot."""

    u: FloatArray
    """[u_v, u_ω] to apply now (zero on failure: stop, the safe fallback)."""
    success: bool
    status: str
    predicted_states: FloatArray
    """(N+1, 3) prediction: share ``predicted_states[:, :2]`` with the other agents."""
    violation_m: float
    """Largest predicted intrusion into another agent's r_obs circle (after the last update)."""
    penalty: float
    """ρ of the last solve."""
    solves: int
    solve_time_s: float
    static_violation_m: float = 0.0
    """Largest predicted intrusion into r_static + margin of an obstacle point (steps 1 … N)."""
    static_penalty: float = 0.0
    """ρ_s of the last solve."""
    solve_cpu_s: float = 0.0
    """CPU time of the solver calls (:attr:`~btmission.control.ocp.OcpSolution.cpu_time_s`)."""

    @property
    def predicted_positions(self) -> FloatArray:
        return self.predicted_states[:, :2].copy()


class UnicycleNmpc:
    """One agent's distributed NMPC (seed 003 §VI). Call :meth:`solve` every ``dt_s``."""

    def __init__(self, config: UnicycleConfig | None = None) -> None:
        import casadi as ca

        self.config = cfg = config or UnicycleConfig()
        n, m = cfg.horizon, cfg.max_agents
        xs = ca.SX.sym("x", NX)
        us = ca.SX.sym("u", NU)
        step = ca.Function(
            "unicycle_rk4", [xs, us], [rk4_step(unicycle_dynamics, xs, us, cfg.dt_s)]
        )
        kh = cfg.max_halfspaces
        # params: x_ref (3), rho (1), rho_s (1), obstacles m × (N+1) × 2 (stage-major), then the
        # safe corridor (N+1) × kh × [n_x, n_y, b] (stage-major)
        agents0 = NX + 2
        corridor0 = agents0 + m * (n + 1) * 2
        n_params = corridor0 + (n + 1) * kh * 3
        q_state = ca.DM([cfg.q_position, cfg.q_position, cfg.q_heading])
        q_u, q_du = ca.DM(list(cfg.q_input)), ca.DM(list(cfg.q_rate))
        r2 = (cfg.r_obs_m + cfg.margin_m) ** 2

        def exclusion(j: int, x: Any, p: Any) -> Any:
            total: Any = 0
            for i in range(m):
                k = agents0 + (j * m + i) * 2
                d2 = (x[0] - p[k]) ** 2 + (x[1] - p[k + 1]) ** 2
                total = total + ca.fmax(r2 - d2, 0) ** 2  # C_circle² of eq. 12
            corridor: Any = 0
            for h in range(kh):
                k = corridor0 + (j * kh + h) * 3
                # [n_kᵀ p_j − b_k]_+² of the safe corridor (module docstring)
                corridor = corridor + ca.fmax(p[k] * x[0] + p[k + 1] * x[1] - p[k + 2], 0) ** 2
            return p[NX] * total + p[NX + 1] * corridor

        def tracking(x: Any, p: Any, weight: Any) -> Any:
            err = ca.vertcat(p[0] - x[0], p[1] - x[1], ca.sin((p[2] - x[2]) / 2) * 2)
            return ca.sum1(weight * err**2)

        def stage_cost(j: int, x: Any, u: Any, u_prev: Any, p: Any) -> Any:
            return (
                tracking(x, p, q_state)
                + ca.sum1(q_u * u**2)
                + ca.sum1(q_du * (u - u_prev) ** 2)
                + exclusion(j, x, p)
            )

        def terminal_cost(x: Any, p: Any) -> Any:
            return tracking(
                x, p, q_state * (cfg.q_terminal / max(cfg.q_position, 1e-9))
            ) + exclusion(n, x, p)

        self.ocp = StagewiseOcp(
            step=step,
            nx=NX,
            nu=NU,
            horizon=n,
            n_params=n_params,
            stage_cost=stage_cost,
            terminal_cost=terminal_cost,
            u_lower=[cfg.v_min, -cfg.omega_max],
            u_upper=[cfg.v_max, cfg.omega_max],
            rate_limits=[math.inf, math.inf],
            solver=cfg.solver,
            max_iter=cfg.max_iter,
            name=f"unicycle_nmpc_{cfg.solver}",
        )
        self._u_last = np.zeros(NU)
        self._guess: FloatArray | None = None
        self._centres: FloatArray | None = None
        """Linearisation points of the safe corridor: the last prediction, shifted."""

    def reset(self) -> None:
        """Forget the warm start and the previous input."""
        self._u_last = np.zeros(NU)
        self._guess = None
        self._centres = None

    def solve(
        self,
        x: ArrayLike,
        x_ref: ArrayLike,
        others: Sequence[ArrayLike] = (),
        obstacles: ArrayLike | None = None,
    ) -> UnicycleResult:
        """One step from state ``x`` = [p_x, p_y, ψ] towards ``x_ref`` (2 or 3 values).

        ``others``: the other agents' predicted positions, each (N+1, 2) (or (N+1, ≥2)) over this
        agent's horizon. ``obstacles``: static obstacle points (P, ≥2) in the same frame (only x
        and y are used), kept at ``r_static_m`` through the safe corridor. A failed solve returns
        u = 0 (stop) with ``success=False``.
        """
        cfg = self.config
        n = cfg.horizon
        xs = np.asarray(x, dtype=float).ravel()
        if xs.size != NX or not np.all(np.isfinite(xs)):
            raise ValueError(f"state x must be three finite numbers, got {xs.tolist()}")
        ref = np.asarray(x_ref, dtype=float).ravel()
        if ref.size == 2:
            ref = np.append(ref, xs[2])
        if ref.size != NX or not np.all(np.isfinite(ref)):
            raise ValueError(f"x_ref must be two or three finite numbers, got {ref.tolist()}")
        ref[2] = xs[2] + wrap_angle(ref[2] - xs[2])
        if len(others) > cfg.max_agents:
            raise ValueError(
                f"{len(others)} other agents but the solver was built for max_agents={cfg.max_agents}"
            )
        obstacles_xy = np.full((n + 1, cfg.max_agents, 2), FAR)
        tracks: list[FloatArray] = []
        for i, traj in enumerate(others):
            arr = np.asarray(traj, dtype=float)
            if arr.ndim != 2 or arr.shape[0] != n + 1 or arr.shape[1] < 2:
                raise ValueError(
                    f"other agent {i}: expected an ({n + 1}, 2) predicted trajectory, "
                    f"got shape {arr.shape}"
                )
            obstacles_xy[:, i, :] = arr[:, :2]
            tracks.append(arr[:, :2])
        points = np.zeros((0, 2))
        if obstacles is not None and np.size(obstacles) and cfg.max_halfspaces:
            pts = np.asarray(obstacles, dtype=float)
            if pts.ndim != 2 or pts.shape[1] < 2 or not np.all(np.isfinite(pts[:, :2])):
                raise ValueError(f"obstacles must be finite (P, 2) points, got shape {pts.shape}")
            near = np.hypot(pts[:, 0] - xs[0], pts[:, 1] - xs[1])
            # beyond a horizon's travel plus the corridor radius nothing can matter
            reach = cfg.v_max * cfg.dt_s * n + cfg.corridor_radius_m
            points = pts[near <= reach, :2]
        r_static = cfg.r_static_m + cfg.static_margin_m
        rho = cfg.penalty
        rho_s = cfg.static_penalty
        guess = self._guess
        centres = np.tile(xs[:2], (n + 1, 1)) if self._centres is None else self._centres.copy()
        centres[0] = xs[:2]
        total_time = 0.0
        total_cpu = 0.0
        solves = 0
        sol: OcpSolution | None = None
        violation = 0.0
        static_violation = 0.0
        for _ in range(cfg.penalty_updates + 1):
            corridor = safe_halfspaces(
                centres, points, r_static, cfg.max_halfspaces, cfg.corridor_radius_m
            )
            params = np.concatenate([ref, [rho, rho_s], obstacles_xy.ravel(), corridor.ravel()])
            sol = self.ocp.solve(xs, self._u_last, params, guess)
            total_time += sol.wall_time_s
            total_cpu += sol.cpu_time_s
            solves += 1
            if not sol.success:
                break
            violation = max(
                (exclusion_violation(sol.states, t, cfg.r_obs_m + cfg.margin_m) for t in tracks),
                default=0.0,
            )
            # step 0 is the measured state: nothing the solve can change
            static_violation = obstacle_violation(sol.states[1:], points, r_static)
            if violation <= cfg.violation_tol_m and static_violation <= cfg.violation_tol_m:
                break
            guess = sol.primal
            if violation > cfg.violation_tol_m:
                rho *= cfg.penalty_growth
            if static_violation > cfg.violation_tol_m:
                rho_s *= cfg.penalty_growth
                centres = sol.states[:, :2].copy()  # re-linearise around the new solution
        assert sol is not None
        if sol.success:
            u = np.clip(sol.inputs[0], [cfg.v_min, -cfg.omega_max], [cfg.v_max, cfg.omega_max])
            self._guess = self.ocp.shifted(sol.primal)
            states = sol.states
            self._centres = shift_prediction(states[:, :2])
        else:
            u = np.zeros(NU)
            self._guess = None
            self._centres = None
            states = np.tile(xs, (n + 1, 1))  # stopped: predict standing still
        self._u_last = u
        return UnicycleResult(
            u=u,
            success=sol.success,
            status=sol.status,
            predicted_states=states,
            violation_m=violation,
            penalty=rho,
            static_violation_m=static_violation,
            static_penalty=rho_s,
            solves=solves,
            solve_time_s=total_time,
            solve_cpu_s=total_cpu,
        )
