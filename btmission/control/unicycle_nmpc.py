"""Ground-robot NMPC with inter-agent collision avoidance (seed 003 §VI, eq. 11-12).

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
        # params: x_ref (3), rho (1), obstacles m × (N+1) × 2 (stage-major)
        n_params = NX + 1 + m * (n + 1) * 2
        q_state = ca.DM([cfg.q_position, cfg.q_position, cfg.q_heading])
        q_u, q_du = ca.DM(list(cfg.q_input)), ca.DM(list(cfg.q_rate))
        r2 = (cfg.r_obs_m + cfg.margin_m) ** 2

        def exclusion(j: int, x: Any, p: Any) -> Any:
            total: Any = 0
            for i in range(m):
                k = NX + 1 + (j * m + i) * 2
                d2 = (x[0] - p[k]) ** 2 + (x[1] - p[k + 1]) ** 2
                total = total + ca.fmax(r2 - d2, 0) ** 2  # C_circle² of eq. 12
            return p[NX] * total

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

    def reset(self) -> None:
        """Forget the warm start and the previous input."""
        self._u_last = np.zeros(NU)
        self._guess = None

    def solve(
        self,
        x: ArrayLike,
        x_ref: ArrayLike,
        others: Sequence[ArrayLike] = (),
    ) -> UnicycleResult:
        """One step from state ``x`` = [p_x, p_y, ψ] towards ``x_ref`` (2 or 3 values).

        ``others``: the other agents' predicted positions, each (N+1, 2) (or (N+1, ≥2)) over this
        agent's horizon. A failed solve returns u = 0 (stop) with ``success=False``.
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
        obstacles = np.full((n + 1, cfg.max_agents, 2), FAR)
        tracks: list[FloatArray] = []
        for i, traj in enumerate(others):
            arr = np.asarray(traj, dtype=float)
            if arr.ndim != 2 or arr.shape[0] != n + 1 or arr.shape[1] < 2:
                raise ValueError(
                    f"other agent {i}: expected an ({n + 1}, 2) predicted trajectory, "
                    f"got shape {arr.shape}"
                )
            obstacles[:, i, :] = arr[:, :2]
            tracks.append(arr[:, :2])
        rho = cfg.penalty
        guess = self._guess
        total_time = 0.0
        solves = 0
        sol: OcpSolution | None = None
        violation = 0.0
        for _ in range(cfg.penalty_updates + 1):
            params = np.concatenate([ref, [rho], obstacles.ravel()])
            sol = self.ocp.solve(xs, self._u_last, params, guess)
            total_time += sol.wall_time_s
            solves += 1
            if not sol.success:
                break
            violation = max(
                (exclusion_violation(sol.states, t, cfg.r_obs_m + cfg.margin_m) for t in tracks),
                default=0.0,
            )
            if violation <= cfg.violation_tol_m:
                break
            guess = sol.primal
            rho *= cfg.penalty_growth
        assert sol is not None
        if sol.success:
            u = np.clip(sol.inputs[0], [cfg.v_min, -cfg.omega_max], [cfg.v_max, cfg.omega_max])
            self._guess = self.ocp.shifted(sol.primal)
            states = sol.states
        else:
            u = np.zeros(NU)
            self._guess = None
            states = np.tile(xs, (n + 1, 1))  # stopped: predict standing still
        self._u_last = u
        return UnicycleResult(
            u=u,
            success=sol.success,
            status=sol.status,
            predicted_states=states,
            violation_m=violation,
            penalty=rho,
            solves=solves,
            solve_time_s=total_time,
        )
