"""MAV reference-tracking NMPC of COMPRA (seed 002 §3.2.2, eq. 1-2) with adaptive weights (eq. 4).

Model: :mod:`~btmission.control.mav_model` (8 states, inputs [T, φ_ref, θ_ref]), discretised by
one RK4 step per sampling time. Cost (seed 002 eq. 1), for a constant set-point over the horizon::

    J = Σ_{j=0}^{N} ‖x_ref − x_{k+j|k}‖²_{Q_x} + Σ_{j=0}^{N-1} ‖u_ref − u_{k+j|k}‖²_{Q_u}
                                              + ‖u_{k+j|k} − u_{k+j-1|k}‖²_{Q_Δu}

with diagonal weights, subject to u_min ≤ u ≤ u_max and the input-rate constraints (eq. 2a, 2b)
|φ_ref,j−1 − φ_ref,j| ≤ Δφ_max, |θ_ref,j−1 − θ_ref,j| ≤ Δθ_max, where u_{k−1|k} is the input
applied at the previous step. 20 Hz and N = 20 (a one-second prediction) as in the paper.

Differences from the paper, on purpose: the paper solves with OpEn (PANOC + a penalty method for the
rate constraints); here the rate constraints are hard constraints of an interior-point solve by
fatrop (default) or ipopt, through CasADi (:mod:`~btmission.control.ocp`). The position weight is a
parameter, so the adaptive scheme of eq. 4,

    Q_p = Q_p,min + (Q_p,max − Q_p,min) / (1 + c ‖F_r‖),

(:func:`adaptive_position_weight`, fed by the APF's repulsive force) changes it every step without
rebuilding the solver.

Safety: every solve is warm-started from the previous solution shifted by one stage. If the solver
fails (not converged, exception, non-finite output), :meth:`MavNmpc.solve` returns a *hold-position*
command instead (:func:`hold_position_command`: a PD law towards the position where the failure
began, within the same input bounds and rate limits) and flags ``fallback=True``; the warm start
is dropped so the next solve starts afresh.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, TypedDict, Unpack

import numpy as np
from numpy.typing import ArrayLike

from btmission.control.mav_model import NU, NX, MavParams, mav_dynamics_casadi, rk4_step
from btmission.control.ocp import OcpSolution, StagewiseOcp, check_solver
from btmission.types import FloatArray, Vec3

__all__ = [
    "MavNmpc",
    "NmpcConfig",
    "NmpcResult",
    "PendingSolve",
    "SolveOptions",
    "adaptive_position_weight",
    "hold_position_command",
    "nmpc_pool",
]


@dataclass(frozen=True)
class NmpcConfig:
    """Tuning of the MAV NMPC. Rate and horizon are the paper's; weights/bounds are ours.

    Weights are the diagonals of Q_x (position, velocity, attitude), Q_u and Q_Δu (order
    [T, φ_ref, θ_ref]). ``q_position`` is Q_p,max of eq. 4; ``q_position_min`` and
    ``force_gain`` (c) complete it. Angles in rad, thrust in m/s² (mass-less), rates per step.
    """

    dt_s: float = 0.05
    horizon: int = 20
    q_position: Vec3 = (4.0, 4.0, 4.0)
    q_position_min: Vec3 = (1.0, 1.0, 1.0)
    force_gain: float = 2.0
    q_velocity: Vec3 = (1.5, 1.5, 1.5)
    q_attitude: tuple[float, float] = (1.0, 1.0)
    q_input: Vec3 = (0.5, 2.0, 2.0)
    q_rate: Vec3 = (0.5, 20.0, 20.0)
    thrust_min: float = 5.0
    thrust_max: float = 15.0
    tilt_max_rad: float = 0.35
    rate_max_rad: float = 0.05
    """Δφ_max = Δθ_max per step (0.05 rad at 20 Hz = 1 rad/s)."""
    solver: str = "fatrop"
    max_iter: int = 100
    tol: float = 1e-6
    compiled: bool = False
    """Call gcc-compiled NLP functions (built once, cached; see :mod:`~btmission.control.ocp`)."""
    warm_mu_init: float | None = None
    """fatrop's initial barrier parameter for warm-started solves (``None``: 0.1, as cold)."""
    model: MavParams = field(default_factory=MavParams)
    hold_kp: float = 1.0
    hold_kd: float = 1.6

    def __post_init__(self) -> None:
        if self.dt_s <= 0:
            raise ValueError(f"dt_s must be positive, got {self.dt_s}")
        if self.horizon < 1:
            raise ValueError(f"horizon must be at least 1, got {self.horizon}")
        check_solver(self.solver)
        if not 0 <= self.thrust_min < self.thrust_max:
            raise ValueError("need 0 <= thrust_min < thrust_max")
        if not self.thrust_min <= self.model.g <= self.thrust_max:
            raise ValueError("the hover thrust g must lie within [thrust_min, thrust_max]")
        if self.tilt_max_rad <= 0 or self.rate_max_rad <= 0:
            raise ValueError("tilt_max_rad and rate_max_rad must be positive")
        weights = (
            *self.q_position,
            *self.q_position_min,
            *self.q_velocity,
            *self.q_attitude,
            *self.q_input,
            *self.q_rate,
        )
        if any(q < 0 for q in weights):
            raise ValueError("weights must be non-negative")
        if any(lo > hi for lo, hi in zip(self.q_position_min, self.q_position)):
            raise ValueError("q_position_min must not exceed q_position (Q_p,max)")
        if self.force_gain < 0:
            raise ValueError("force_gain (c of eq. 4) must be non-negative")

    @property
    def u_lower(self) -> FloatArray:
        return np.array([self.thrust_min, -self.tilt_max_rad, -self.tilt_max_rad])

    @property
    def u_upper(self) -> FloatArray:
        return np.array([self.thrust_max, self.tilt_max_rad, self.tilt_max_rad])

    @property
    def rate_limits(self) -> FloatArray:
        """Per-step input-change limits [T, φ_ref, θ_ref]; thrust is not rate-limited (eq. 2)."""
        return np.array([math.inf, self.rate_max_rad, self.rate_max_rad])

    @property
    def hover_input(self) -> FloatArray:
        return np.array([self.model.g, 0.0, 0.0])


def adaptive_position_weight(
    force_norm: float | ArrayLike, q_min: float | ArrayLike, q_max: float | ArrayLike, c: float
) -> FloatArray:
    """Seed 002 eq. 4: Q_p = Q_p,min + (Q_p,max − Q_p,min) / (1 + c‖F_r‖).

    Equals Q_p,max with no repulsive force and decreases monotonically towards Q_p,min as the
    force grows, so the MAV tracks its waypoint less aggressively near obstacles.
    """
    f = np.asarray(force_norm, dtype=float)
    if np.any(f < 0) or c < 0:
        raise ValueError("the force norm and c must be non-negative")
    lo = np.asarray(q_min, dtype=float)
    hi = np.asarray(q_max, dtype=float)
    return np.asarray(lo + (hi - lo) / (1.0 + c * f), dtype=float)


def hold_position_command(
    x: ArrayLike, hold: ArrayLike, u_prev: ArrayLike, config: NmpcConfig
) -> FloatArray:
    """Safe fallback: a PD law that holds position ``hold``, within the NMPC's bounds and rates.

    Desired acceleration a = K_p (p_hold − p) − K_d v + [0, 0, g]; inverting the model's
    thrust direction gives T = ‖a‖, φ = asin(−a_y / T), θ = atan2(a_x, a_z). The command is clipped
    to the input bounds and moved from ``u_prev`` by at most the rate limits (eq. 2).
    """
    xs = np.asarray(x, dtype=float)
    acc = config.hold_kp * (np.asarray(hold, float)[:3] - xs[:3]) - config.hold_kd * xs[3:6]
    acc[2] += config.model.g
    thrust = float(np.linalg.norm(acc))
    phi = math.asin(float(np.clip(-acc[1] / thrust, -1.0, 1.0))) if thrust > 0 else 0.0
    theta = math.atan2(acc[0], acc[2])
    return _project(np.array([thrust, phi, theta]), u_prev, config)


def _project(u: ArrayLike, u_prev: ArrayLike, config: NmpcConfig) -> FloatArray:
    """Clip ``u`` into the input bounds and to within the rate limits of ``u_prev``.

    A converged interior-point solution already satisfies both up to the solver tolerance; the
    projection makes the applied command satisfy them exactly.
    """
    up = np.clip(np.asarray(u_prev, dtype=float), config.u_lower, config.u_upper)
    step = np.minimum(config.rate_limits, 1e9)
    lo = np.maximum(config.u_lower, up - step)
    hi = np.minimum(config.u_upper, up + step)
    return np.asarray(np.clip(np.asarray(u, dtype=float), lo, hi), dtype=float)


class SolveOptions(TypedDict, total=False):
    """The keyword options of :meth:`MavNmpc.solve` and :meth:`MavNmpc.solve_async`."""

    u_ref: ArrayLike | None
    u_prev: ArrayLike | None
    q_position: ArrayLike | None
    repulsive_force: float | None


@dataclass
class NmpcResult:
    """What :meth:`MavNmpc.solve` returns each control step."""

    u: FloatArray
    """The command to apply now: [T, φ_ref, θ_ref]."""
    success: bool
    """The solver converged (False ⇒ ``u`` is the hold-position fallback)."""
    status: str
    fallback: bool
    solve_time_s: float
    iterations: int
    predicted_states: FloatArray
    """x_{k|k} … x_{k+N|k} (NaN on failure)."""
    predicted_inputs: FloatArray
    q_position: FloatArray
    """The position weight used for this solve (eq. 4)."""
    solve_cpu_s: float = 0.0
    """CPU time of the solver call (:attr:`~btmission.control.ocp.OcpSolution.cpu_time_s`)."""


class MavNmpc:
    """The seed 002 NMPC; call :meth:`solve` once per control period (``config.dt_s``).

    States and references are in the yaw-compensated frame (see
    :func:`~btmission.control.mav_model.world_to_yaw_frame`). The controller remembers the last
    applied input (for the rate constraint and cost) and the last solution (warm start);
    :meth:`reset` forgets both.
    """

    def __init__(self, config: NmpcConfig | None = None) -> None:
        import casadi as ca

        self.config = cfg = config or NmpcConfig()
        xs = ca.SX.sym("x", NX)
        us = ca.SX.sym("u", NU)
        step = ca.Function(
            "mav_rk4",
            [xs, us],
            [rk4_step(lambda a, b: mav_dynamics_casadi(a, b, cfg.model), xs, us, cfg.dt_s)],
        )
        # parameters: x_ref (8), u_ref (3), q_p (3); the other weights are constants
        q_rest = np.concatenate([cfg.q_velocity, cfg.q_attitude])
        q_u = np.asarray(cfg.q_input)
        q_du = np.asarray(cfg.q_rate)

        def state_cost(x: Any, p: Any) -> Any:
            err = p[0:NX] - x
            qx = ca.vertcat(p[NX + NU : NX + NU + 3], ca.DM(q_rest))
            return ca.sum1(qx * err**2)

        def stage_cost(j: int, x: Any, u: Any, u_prev: Any, p: Any) -> Any:
            du = u - u_prev
            return (
                state_cost(x, p)
                + ca.sum1(ca.DM(q_u) * (p[NX : NX + NU] - u) ** 2)
                + ca.sum1(ca.DM(q_du) * du**2)
            )

        self.ocp = StagewiseOcp(
            step=step,
            nx=NX,
            nu=NU,
            horizon=cfg.horizon,
            n_params=NX + NU + 3,
            stage_cost=stage_cost,
            terminal_cost=state_cost,
            u_lower=cfg.u_lower.tolist(),
            u_upper=cfg.u_upper.tolist(),
            rate_limits=cfg.rate_limits.tolist(),
            solver=cfg.solver,
            max_iter=cfg.max_iter,
            tol=cfg.tol,
            name=f"mav_nmpc_{cfg.solver}",
            compiled=cfg.compiled,
            warm_mu_init=cfg.warm_mu_init,
        )
        self._u_last = cfg.hover_input
        self._guess: FloatArray | None = None
        self._hold: FloatArray | None = None
        self._pending = False

    @property
    def last_input(self) -> FloatArray:
        """u_{k−1}: the input applied at the previous step (hover before the first solve)."""
        return self._u_last.copy()

    def reset(self, u_prev: ArrayLike | None = None) -> None:
        """Forget the warm start and the fallback hold point; set the previous input."""
        self._u_last = self.config.hover_input if u_prev is None else _vector(u_prev, NU, "u_prev")
        self._guess = None
        self._hold = None

    def solve(self, x: ArrayLike, x_ref: ArrayLike, **options: Unpack[SolveOptions]) -> NmpcResult:
        """One control step from state ``x`` towards set-point ``x_ref`` (both 8 values).

        ``x_ref`` may also be a 3-vector (a position; zero velocity and attitude). ``u_ref``
        defaults to hover. ``u_prev`` overrides the remembered previous input. The position weight
        is ``q_position`` if given, else eq. 4 of ``‖F_r‖ = repulsive_force`` if given, else
        Q_p,max. Raises ``ValueError`` for a malformed or non-finite state/reference.
        """
        xs, params, qp = self._prepare(x, x_ref, options)
        return self._finish(xs, qp, self.ocp.solve(xs, self._u_last, params, self._guess))

    def solve_async(
        self, x: ArrayLike, x_ref: ArrayLike, **options: Unpack[SolveOptions]
    ) -> PendingSolve:
        """:meth:`solve`, with the CasADi call on the NMPC thread pool (:func:`nmpc_pool`).

        The arguments are checked and the problem set up now, in the caller's thread; the
        solver runs in a worker (CasADi releases the GIL while it solves), and
        :meth:`PendingSolve.result` — called in the caller's thread — updates the warm start,
        the previous input and the fallback exactly as :meth:`solve` does, so the result is the
        same, whichever thread solved it. Several controllers' solves can run at once; one
        controller must collect its result before it solves again.
        """
        xs, params, qp = self._prepare(x, x_ref, options)
        collect = self.ocp.solve_on(nmpc_pool(), xs, self._u_last, params, self._guess)
        self._pending = True
        return PendingSolve(self, xs, qp, collect)

    def _prepare(
        self, x: ArrayLike, x_ref: ArrayLike, options: SolveOptions
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Check the inputs; (state, solver parameters, position weight). Sets u_prev if given."""
        if self._pending:
            raise RuntimeError("this NMPC has a solve in flight: collect its result() first")
        cfg = self.config
        u_ref, u_prev = options.get("u_ref"), options.get("u_prev")
        q_position, repulsive_force = options.get("q_position"), options.get("repulsive_force")
        xs = _vector(x, NX, "state x")
        ref_in = np.asarray(x_ref, dtype=float).ravel()
        if ref_in.size == 3:
            ref_in = np.concatenate([ref_in, np.zeros(NX - 3)])
        ref = _vector(ref_in, NX, "reference x_ref")
        uref = cfg.hover_input if u_ref is None else _vector(u_ref, NU, "u_ref")
        if u_prev is not None:
            self._u_last = _vector(u_prev, NU, "u_prev")
        if q_position is not None:
            qp = np.broadcast_to(np.asarray(q_position, dtype=float), (3,)).copy()
            if np.any(qp < 0) or not np.all(np.isfinite(qp)):
                raise ValueError(f"q_position must be finite and non-negative, got {qp}")
        elif repulsive_force is not None:
            qp = adaptive_position_weight(
                repulsive_force, cfg.q_position_min, cfg.q_position, cfg.force_gain
            )
        else:
            qp = np.asarray(cfg.q_position, dtype=float)
        return xs, np.concatenate([ref, uref, qp]), qp

    def _finish(self, xs: FloatArray, qp: FloatArray, sol: OcpSolution) -> NmpcResult:
        """The command from a solution (or the fallback); updates warm start and u_{k−1}."""
        cfg = self.config
        self._pending = False
        if sol.success:
            u = _project(sol.inputs[0], self._u_last, cfg)
            self._guess = self.ocp.shifted(sol.primal)
            self._hold = None
            fallback = False
        else:
            if self._hold is None:
                self._hold = xs[:3].copy()
            u = hold_position_command(xs, self._hold, self._u_last, cfg)
            self._guess = None
            fallback = True
        self._u_last = u
        return NmpcResult(
            u=u.copy(),
            success=sol.success,
            status=sol.status,
            fallback=fallback,
            solve_time_s=sol.wall_time_s,
            iterations=sol.iterations,
            predicted_states=sol.states,
            predicted_inputs=sol.inputs,
            q_position=qp,
            solve_cpu_s=sol.cpu_time_s,
        )


class PendingSolve:
    """A :meth:`MavNmpc.solve_async` in flight; :meth:`result` waits for it and finishes it."""

    def __init__(
        self, nmpc: MavNmpc, xs: FloatArray, qp: FloatArray, collect: Callable[[], OcpSolution]
    ) -> None:
        self._nmpc, self._xs, self._qp, self._collect = nmpc, xs, qp, collect
        self._result: NmpcResult | None = None

    def result(self) -> NmpcResult:
        """The :class:`NmpcResult` :meth:`MavNmpc.solve` would have returned (idempotent)."""
        if self._result is None:
            self._result = self._nmpc._finish(self._xs, self._qp, self._collect())
        return self._result


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def nmpc_pool() -> ThreadPoolExecutor:
    """The threads :meth:`MavNmpc.solve_async` solves on: one per CPU, at most two (the
    development machine's cores), created on first use and shared by every controller."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            workers = max(1, min(2, os.cpu_count() or 1))
            _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="nmpc")
        return _POOL


def _vector(values: ArrayLike | Sequence[float], n: int, what: str) -> FloatArray:
    arr = np.asarray(values, dtype=float).ravel()
    if arr.size != n:
        raise ValueError(f"{what} must have {n} values, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be finite, got {arr.tolist()}")
    return arr
