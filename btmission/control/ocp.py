"""A stage-wise multiple-shooting OCP for NMPC, solved by fatrop (default) or ipopt via CasADi.

Both NMPCs of this package (:mod:`~btmission.control.nmpc` for the MAV, seed 002 eq. 1-2, and
:mod:`~btmission.control.unicycle_nmpc` for ground robots, seed 003 eq. 11-12) share one shape::

    min  Σ_{j=0}^{N-1} ℓ_j(x_j, u_j, u_{j-1}; p) + ℓ_N(x_N; p)
    s.t. x_0 = x̂,  u_{-1} = u_prev                           (measured state, last applied input)
         x_{j+1} = ζ(x_j, u_j)                                (discretised model, RK4)
         u_min ≤ u_j ≤ u_max                                  (input bounds)
         |u_{j,i} − u_{j-1,i}| ≤ Δu_max,i  for rate-limited i  (seed 002 eq. 2a, 2b)

fatrop exploits the optimal-control structure only if the NLP is laid out stage by stage and every
constraint couples at most one stage to the next (DESIGN §8). The input-rate constraint couples
u_j with u_{j-1}, so the previous input is carried as extra state: z_j = [x_j; u_{j-1}] with
z_{j+1} = [ζ(x_j, u_j); u_j]. Variables are ordered z_0, u_0, z_1, u_1, …, z_N and each stage's
constraints (dynamics gap, then the initial condition at j = 0, then the rate bounds) follow in
stage order, so ``structure_detection="auto"`` finds the structure. The same NLP is handed to ipopt
(``expand=True``), which makes the two solvers directly comparable.

The NLP is built once into a CasADi ``nlpsol`` function (no per-call symbolic work); weights,
references and obstacle data enter as parameters so they can change every step without rebuilding.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from btmission.types import FloatArray

__all__ = ["SOLVERS", "OcpSolution", "StagewiseOcp", "check_solver"]

SOLVERS = ("fatrop", "ipopt")
"""NLP solvers the OCP can use (both ship in CasADi's PyPI wheel)."""


def check_solver(name: str) -> None:
    """Raise ``ValueError`` unless ``name`` is one of :data:`SOLVERS`."""
    if name not in SOLVERS:
        raise ValueError(f"unknown solver '{name}' (choose one of {', '.join(SOLVERS)})")


StageCost = Callable[[int, Any, Any, Any, Any], Any]
"""ℓ_j(j, x_j, u_j, u_{j-1}, p) → scalar CasADi expression."""
TerminalCost = Callable[[Any, Any], Any]
"""ℓ_N(x_N, p) → scalar CasADi expression."""


@dataclass
class OcpSolution:
    """One solve: the optimal (or last) trajectories and what the solver said about them."""

    states: FloatArray
    """Predicted states x_0 … x_N, shape (N+1, nx)."""
    inputs: FloatArray
    """Planned inputs u_0 … u_{N-1}, shape (N, nu)."""
    success: bool
    status: str
    iterations: int
    wall_time_s: float
    cost: float
    primal: FloatArray = field(repr=False)
    """The raw decision vector (for warm starts)."""


class StagewiseOcp:
    """The OCP of the module docstring, built once; :meth:`solve` is called every control step.

    Args:
        step: discretised model ``ζ(x, u) → x⁺`` as a CasADi ``Function`` (SX inside).
        nx, nu: state and input sizes.
        horizon: N.
        n_params: number of user parameters ``p`` passed to the costs.
        stage_cost, terminal_cost: the cost terms (CasADi expressions of MX symbols).
        u_lower, u_upper: input bounds (length ``nu``; ±inf allowed).
        rate_limits: per-input max change per step (length ``nu``; ``inf`` = not rate-limited).
        solver: ``"fatrop"`` or ``"ipopt"``.
        max_iter, tol: solver iteration cap and tolerance.
    """

    def __init__(
        self,
        *,
        step: Any,
        nx: int,
        nu: int,
        horizon: int,
        n_params: int,
        stage_cost: StageCost,
        terminal_cost: TerminalCost,
        u_lower: Sequence[float],
        u_upper: Sequence[float],
        rate_limits: Sequence[float],
        solver: str = "fatrop",
        max_iter: int = 100,
        tol: float = 1e-6,
        name: str = "nmpc",
    ) -> None:
        import casadi as ca

        check_solver(solver)
        if not ca.has_nlpsol(solver):
            raise RuntimeError(f"this CasADi build has no '{solver}' plugin")
        if horizon < 1:
            raise ValueError(f"horizon must be at least 1, got {horizon}")
        if not (len(u_lower) == len(u_upper) == len(rate_limits) == nu):
            raise ValueError(f"u_lower, u_upper and rate_limits must each have {nu} entries")
        if any(lo > hi for lo, hi in zip(u_lower, u_upper)):
            raise ValueError(
                f"input bounds are empty: lower {list(u_lower)} > upper {list(u_upper)}"
            )
        if any(not r > 0 for r in rate_limits):
            raise ValueError(
                f"rate limits must be positive (inf for none), got {list(rate_limits)}"
            )
        self.nx, self.nu, self.horizon, self.n_params = nx, nu, horizon, n_params
        self.solver_name = solver
        self.u_lower = np.asarray(u_lower, dtype=float)
        self.u_upper = np.asarray(u_upper, dtype=float)
        self.rate_limits = np.asarray(rate_limits, dtype=float)
        nz = nx + nu
        self._nz = nz
        rated = [i for i in range(nu) if math.isfinite(rate_limits[i])]

        x0 = ca.MX.sym("x0", nx)
        u_prev = ca.MX.sym("u_prev", nu)
        p_user = ca.MX.sym("p", n_params)
        w: list[Any] = []
        lbw: list[float] = []
        ubw: list[float] = []
        g: list[Any] = []
        lbg: list[float] = []
        ubg: list[float] = []
        equality: list[bool] = []
        zs = [ca.MX.sym(f"z{j}", nz) for j in range(horizon + 1)]
        us = [ca.MX.sym(f"u{j}", nu) for j in range(horizon)]
        for j in range(horizon + 1):
            w.append(zs[j])
            lbw += [-math.inf] * nz
            ubw += [math.inf] * nz
            if j < horizon:
                w.append(us[j])
                lbw += list(map(float, u_lower))
                ubw += list(map(float, u_upper))
        cost: Any = 0
        for j in range(horizon):
            z, u = zs[j], us[j]
            xj, uprev_j = z[:nx], z[nx:]
            g.append(zs[j + 1] - ca.vertcat(step(xj, u), u))
            lbg += [0.0] * nz
            ubg += [0.0] * nz
            equality += [True] * nz
            if j == 0:
                g.append(z - ca.vertcat(x0, u_prev))
                lbg += [0.0] * nz
                ubg += [0.0] * nz
                equality += [True] * nz
            for i in rated:
                g.append(u[i] - uprev_j[i])
                lbg.append(-float(rate_limits[i]))
                ubg.append(float(rate_limits[i]))
                equality.append(False)
            cost = cost + stage_cost(j, xj, u, uprev_j, p_user)
        cost = cost + terminal_cost(zs[horizon][:nx], p_user)

        nlp = {
            "x": ca.vertcat(*w),
            "f": cost,
            "g": ca.vertcat(*g),
            "p": ca.vertcat(x0, u_prev, p_user),
        }
        opts: dict[str, Any] = {"expand": True, "print_time": False, "error_on_fail": False}
        if solver == "fatrop":
            opts["structure_detection"] = "auto"
            opts["equality"] = equality
            opts["fatrop"] = {"print_level": 0, "max_iter": max_iter, "tol": tol, "mu_init": 0.1}
        else:
            opts["ipopt"] = {"print_level": 0, "sb": "yes", "max_iter": max_iter, "tol": tol}
        self._solver = ca.nlpsol(name, solver, nlp, opts)
        self._lbw = np.asarray(lbw)
        self._ubw = np.asarray(ubw)
        self._lbg = np.asarray(lbg)
        self._ubg = np.asarray(ubg)
        self.n_variables = len(lbw)
        self.last_stats: dict[str, Any] = {}
        """The solver's statistics of the last :meth:`solve` (fatrop adds the detected
        structure: ``N`` and per-stage ``nx``, ``nu``, ``ng``)."""

    # ------------------------------------------------------------------------------------------
    def initial_guess(self, x0: ArrayLike, u: ArrayLike) -> FloatArray:
        """A guess that holds state ``x0`` and input ``u`` over the whole horizon."""
        z = np.concatenate([np.asarray(x0, dtype=float), np.asarray(u, dtype=float)])
        stage = np.concatenate([z, np.asarray(u, dtype=float)])
        return np.concatenate([np.tile(stage, self.horizon), z])

    def shifted(self, primal: FloatArray) -> FloatArray:
        """Warm start for the next step: the last solution moved one stage earlier.

        ``z_1, u_1, …, z_N`` followed by a copy of the last input and the last state.
        """
        nz, nu = self._nz, self.nu
        head = primal[nz + nu :]
        last_u = primal[-nz - nu : -nz]
        return np.concatenate([head, last_u, primal[-nz:]])

    def solve(
        self, x0: ArrayLike, u_prev: ArrayLike, params: ArrayLike, guess: ArrayLike | None = None
    ) -> OcpSolution:
        """Solve from state ``x0`` with last applied input ``u_prev`` (clipped into the bounds).

        Never raises on a solver failure: a CasADi exception or a non-finite result comes back as
        ``success=False`` with the reason in ``status`` (the caller decides on a fallback).
        """
        x0 = np.asarray(x0, dtype=float).ravel()
        u_prev_arr = np.clip(np.asarray(u_prev, dtype=float).ravel(), self.u_lower, self.u_upper)
        p = np.concatenate([x0, u_prev_arr, np.asarray(params, dtype=float).ravel()])
        w0 = self.initial_guess(x0, u_prev_arr) if guess is None else np.asarray(guess, float)
        t0 = time.perf_counter()
        try:
            res = self._solver(
                x0=w0, p=p, lbx=self._lbw, ubx=self._ubw, lbg=self._lbg, ubg=self._ubg
            )
            wall = time.perf_counter() - t0
            stats = self._solver.stats()
            self.last_stats = dict(stats)
            primal = np.asarray(res["x"], dtype=float).ravel()
            cost = float(res["f"])
            success = bool(stats.get("success", False))
            status = str(stats.get("return_status", "unknown"))
            iterations = int(stats.get("iter_count", -1))
        except RuntimeError as exc:  # CasADi reports evaluation errors (NaN, …) this way
            wall = time.perf_counter() - t0
            primal = np.full(self.n_variables, np.nan)
            cost, success, iterations = math.nan, False, -1
            status = f"exception: {str(exc).strip().splitlines()[-1]}"
        if success and not np.all(np.isfinite(primal)):
            success, status = False, "non-finite solution"
        if self.solver_name == "fatrop" and status == "0":
            status = "Solve_Succeeded"  # fatrop reports 0; use ipopt's wording for both
        states, inputs = self._unpack(primal)
        return OcpSolution(states, inputs, success, status, iterations, wall, cost, primal)

    def _unpack(self, primal: FloatArray) -> tuple[FloatArray, FloatArray]:
        nz, nu, n = self._nz, self.nu, self.horizon
        body = primal[: n * (nz + nu)].reshape(n, nz + nu)
        states = np.vstack([body[:, : self.nx], primal[n * (nz + nu) :][None, : self.nx]])
        return states, body[:, nz:].copy()
