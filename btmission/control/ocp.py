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

``compiled=True`` makes the solver call machine code instead of CasADi's SX virtual machine for
the NLP's functions (objective, constraints, their derivatives and the Lagrangian's Hessian):
:func:`compiled_nlp` writes them out as C once, compiles them with gcc (``-O1``) into a shared
library under :func:`cache_dir` named by a hash of the functions, and the solver loads that
library (``nlpsol(name, solver, "….so")``). Same functions, same numbers: on 945 recorded mine
mission states the commands were bit for bit those of the SX solver. The first build compiles
(about 20 s on the 2-core machine); later builds, in any process, load the cached library in
milliseconds. Without gcc (or if compiling fails) the SX solver is used and a ``RuntimeWarning``
says why. ``warm_mu_init`` starts warm-started fatrop solves from a smaller barrier parameter:
the guess is the previous optimum shifted, so the interior-point method need not start far
from the bounds (seed 002's MAV NMPC: 4.35 → 3.09 iterations a solve).
"""

from __future__ import annotations

import hashlib
import math
import os
import shutil
import subprocess
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from btmission.types import FloatArray

__all__ = [
    "COMPILE_FLAGS",
    "SOLVERS",
    "OcpSolution",
    "StagewiseOcp",
    "cache_dir",
    "check_solver",
    "compiled_nlp",
]

SOLVERS = ("fatrop", "ipopt")
"""NLP solvers the OCP can use (both ship in CasADi's PyPI wheel)."""


def check_solver(name: str) -> None:
    """Raise ``ValueError`` unless ``name`` is one of :data:`SOLVERS`."""
    if name not in SOLVERS:
        raise ValueError(f"unknown solver '{name}' (choose one of {', '.join(SOLVERS)})")


COMPILE_FLAGS = ("-O1", "-fPIC", "-shared")
"""gcc flags for the compiled NLP. ``-O2`` compiled twice as long (43 s against 16-25 s on the
loaded 2-core machine) for no measurable gain in the solve."""
COMPILE_TIMEOUT_S = 600.0
"""A compile that takes longer is abandoned (the SX solver is used, with a warning)."""


Solved = tuple[tuple[FloatArray, float, dict[str, Any]] | RuntimeError, float, float]
"""A solver call's outcome: ((primal, cost, the solver's statistics) or its ``RuntimeError``,
wall time s, CPU time s of the thread that solved)."""


def _timed(
    evaluate: Callable[[], Any], read: Callable[[Any], tuple[FloatArray, float, dict[str, Any]]]
) -> Solved:
    """``evaluate()`` (one solver call), timed, then ``read(its return)`` for (primal, cost,
    statistics) — or the ``RuntimeError`` CasADi raised (:data:`Solved`)."""
    t0, c0 = time.perf_counter(), time.thread_time()
    try:
        res = evaluate()
    except RuntimeError as exc:
        return exc, time.perf_counter() - t0, time.thread_time() - c0
    wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
    return read(res), wall, cpu


def _timed_call(nlpsol: Any, args: dict[str, Any]) -> Solved:
    """One call of the solver (:data:`Solved`). Everything that touches CasADi happens here, in
    the thread that solves: each CasADi call releases and retakes the GIL, which costs the
    caller's thread a wait on every call while another thread holds it (the deferred solves of
    a fleet)."""
    return _timed(
        lambda: nlpsol(**args),
        lambda res: (
            np.asarray(res["x"], dtype=float).ravel(),
            float(res["f"]),
            nlpsol.stats(),
        ),
    )


class _Buffered:
    """One ``nlpsol`` called through CasADi's function buffer (``Function.buffer()``, CasADi ≥
    3.6): the inputs and outputs are numpy arrays the solver reads and writes in place.

    ``nlpsol(**args)`` converts every numpy argument into a ``DM`` and every result into a
    ``DM`` (then into numpy) while it holds the GIL — ~0.25 ms of a ~1 ms warm solve of the
    MAV NMPC on the 2-core machine, and time the thread that waits for the solve cannot use.
    Here the bounds are written once, the guess and the parameters are copied in before each
    call, and the call itself (:meth:`__call__`, on the worker) touches no Python object but
    the results it copies out. Same solver, same inputs, same numbers.

    One solve at a time: :meth:`StagewiseOcp.solve_on` uses the buffer only while no other
    buffered solve of the same OCP is in flight (the NMPCs collect each solve before the next).
    """

    def __init__(self, nlpsol: Any, bounds: dict[str, FloatArray]) -> None:
        self.buffer, self.evaluate = nlpsol.buffer()
        self.names_in = list(nlpsol.name_in())
        self.inputs = {name: np.zeros(nlpsol.nnz_in(i)) for i, name in enumerate(self.names_in)}
        for name, values in bounds.items():
            self.inputs[name][:] = values
        for i, name in enumerate(self.names_in):
            self.buffer.set_arg(i, self.inputs[name].data)
        self.outputs = {
            name: np.zeros(nlpsol.nnz_out(i)) for i, name in enumerate(nlpsol.name_out())
        }
        for i, values in enumerate(self.outputs.values()):
            self.buffer.set_res(i, values.data)
        self.busy = False

    def load(self, w0: FloatArray, p: FloatArray) -> None:
        """Copy this solve's guess and parameters in (in the caller's thread)."""
        self.busy = True
        self.inputs["x0"][:] = w0
        self.inputs["p"][:] = p

    def __call__(self) -> Solved:
        """The solve, as :func:`_timed_call` returns it."""
        return _timed(self.evaluate, self._read)

    def _read(self, _: object) -> tuple[FloatArray, float, dict[str, Any]]:
        out = self.outputs
        return out["x"].copy(), float(out["f"][0]), self.buffer.stats()


def cache_dir() -> Path:
    """Where compiled NLPs are kept: ``$BTMISSION_CACHE_DIR``, else ``$XDG_CACHE_HOME/btmission``,
    else ``~/.cache/btmission``; the libraries go in its ``casadi`` folder."""
    root = os.environ.get("BTMISSION_CACHE_DIR")
    if not root:
        xdg = os.environ.get("XDG_CACHE_HOME")
        root = str(Path(xdg) / "btmission") if xdg else str(Path.home() / ".cache" / "btmission")
    return Path(root) / "casadi"


def compiled_nlp(solver: Any, compiler: str = "gcc") -> Path | None:
    """The shared library of ``solver``'s NLP functions, compiled once and cached (module doc).

    The file name is a hash of the generated C source, the flags and the CasADi version, so a
    changed problem never loads a stale library. Returns ``None`` (after a ``RuntimeWarning``)
    if ``compiler`` is missing, fails or times out; the caller then keeps the SX solver.
    """
    import casadi as ca

    gcc = shutil.which(compiler)
    if gcc is None:
        warnings.warn(
            f"no C compiler '{compiler}' found: the NMPC runs on CasADi's SX virtual machine "
            "(correct, about twice as slow); install gcc for the compiled solver",
            RuntimeWarning,
            stacklevel=3,
        )
        return None
    # what ``solver.generate_dependencies`` writes, but as a string (that one writes to the cwd)
    gen = ca.CodeGenerator("nlp", {})
    gen.add(solver.oracle())
    for fn in solver.get_function():
        gen.add(solver.get_function(fn))
    code = gen.dump().encode()
    key = hashlib.sha256(code + " ".join(COMPILE_FLAGS).encode() + ca.CasadiMeta.version().encode())
    folder = cache_dir()
    target = folder / f"nlp_{key.hexdigest()[:24]}.so"
    if target.exists():
        return target
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="btmission-nlp-", dir=folder) as tmp:
        source = Path(tmp) / "nlp.c"
        source.write_bytes(code)
        built = Path(tmp) / target.name
        try:
            subprocess.run(
                [gcc, *COMPILE_FLAGS, str(source), "-o", str(built)],
                check=True,
                capture_output=True,
                timeout=COMPILE_TIMEOUT_S,
            )
        except (OSError, subprocess.SubprocessError) as exc:
            detail = getattr(exc, "stderr", b"") or b""
            warnings.warn(
                f"compiling the NMPC's NLP failed ({type(exc).__name__}: "
                f"{detail.decode(errors='replace').strip()[:200] or exc}); "
                "using CasADi's SX virtual machine",
                RuntimeWarning,
                stacklevel=3,
            )
            return None
        os.replace(built, target)  # atomic: a concurrent build writes the same bytes
    return target


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
    cpu_time_s: float = 0.0
    """CPU time of the thread that ran the solver call (what the solve costs a core, whatever
    else shares the machine; ``wall_time_s`` also counts waiting for a core or the GIL)."""


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
        compiled: call gcc-compiled NLP functions (module docstring; cached).
        warm_mu_init: fatrop's initial barrier parameter for warm-started solves (``None``: the
            cold-start value 0.1 for every solve). Ignored by ipopt.
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
        compiled: bool = False,
        warm_mu_init: float | None = None,
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
        if warm_mu_init is not None and not warm_mu_init > 0:
            raise ValueError(f"warm_mu_init must be positive, got {warm_mu_init}")

        def options(mu_init: float) -> dict[str, Any]:
            opts: dict[str, Any] = {"print_time": False, "error_on_fail": False}
            if solver == "fatrop":
                opts["structure_detection"] = "auto"
                opts["equality"] = equality
                opts["fatrop"] = {
                    "print_level": 0,
                    "max_iter": max_iter,
                    "tol": tol,
                    "mu_init": mu_init,
                }
            else:
                opts["ipopt"] = {"print_level": 0, "sb": "yes", "max_iter": max_iter, "tol": tol}
            return opts

        self._solver = ca.nlpsol(name, solver, nlp, {"expand": True, **options(0.1)})
        self.compiled = False
        """True when the solver calls the gcc-compiled NLP (``compiled=True`` and gcc worked)."""
        library: Path | None = None
        if compiled:
            library = compiled_nlp(self._solver)
            if library is not None:
                self._solver = ca.nlpsol(name, solver, str(library), options(0.1))
                self.compiled = True
        self._solver_warm = self._solver
        if warm_mu_init is not None and solver == "fatrop":
            source = str(library) if library is not None else nlp
            extra = {} if library is not None else {"expand": True}
            self._solver_warm = ca.nlpsol(name, solver, source, {**extra, **options(warm_mu_init)})
        self._bounds = {
            name: np.array(values, dtype=float)
            for name, values in (("lbx", lbw), ("ubx", ubw), ("lbg", lbg), ("ubg", ubg))
        }
        """The bounds as the solver buffers take them (:class:`_Buffered`)."""
        self._buffers: dict[int, _Buffered | None] = {}
        """Each solver's :class:`_Buffered` (None: it has none), by ``id`` of the solver."""
        self._lbw = ca.DM(lbw)  # DM once: converting numpy bounds on every call cost ~0.1 ms
        self._ubw = ca.DM(ubw)
        self._lbg = ca.DM(lbg)
        self._ubg = ca.DM(ubg)
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
        return self.solve_on(None, x0, u_prev, params, guess)()

    def solve_on(
        self,
        executor: Executor | None,
        x0: ArrayLike,
        u_prev: ArrayLike,
        params: ArrayLike,
        guess: ArrayLike | None = None,
    ) -> Callable[[], OcpSolution]:
        """:meth:`solve` with only the solver call on ``executor`` (``None``: now, here).

        Returns a function that waits for the call and builds the :class:`OcpSolution` in the
        thread that calls it: the worker runs nothing but the CasADi call (which releases the
        GIL), the Python around it stays in the caller's thread.
        """
        x0 = np.asarray(x0, dtype=float).ravel()
        u_prev_arr = np.clip(np.asarray(u_prev, dtype=float).ravel(), self.u_lower, self.u_upper)
        p = np.concatenate([x0, u_prev_arr, np.asarray(params, dtype=float).ravel()])
        if guess is None:
            w0, nlpsol = self.initial_guess(x0, u_prev_arr), self._solver
        else:
            w0, nlpsol = np.asarray(guess, dtype=float), self._solver_warm
        buffered = self._buffered(nlpsol)
        if buffered is not None and not buffered.busy:
            buffered.load(w0, p)
            call: Callable[[], Solved] = buffered
        else:  # (no buffer, or its solve is still in flight: the plain call)
            buffered = None
            args = {"x0": w0, "p": p, "lbx": self._lbw, "ubx": self._ubw}
            args.update(lbg=self._lbg, ubg=self._ubg)
            call = partial(_timed_call, nlpsol, args)

        def collect(result: Callable[[], Solved]) -> OcpSolution:
            try:
                done = result()
            finally:  # (whatever the call raised: the buffer serves the next solve)
                if buffered is not None:
                    buffered.busy = False
            return self._solution(*done)

        if executor is None:
            solution = collect(call)
            return lambda: solution
        future = executor.submit(call)
        return lambda: collect(future.result)

    def _buffered(self, nlpsol: Any) -> _Buffered | None:
        """The buffer of ``nlpsol`` (made on first use), or None where CasADi has none."""
        key = id(nlpsol)
        if key not in self._buffers:
            try:
                made: _Buffered | None = _Buffered(nlpsol, self._bounds)
            except (AttributeError, NotImplementedError, RuntimeError, KeyError):
                made = None
            self._buffers[key] = made
        return self._buffers[key]

    def _solution(
        self,
        res: tuple[FloatArray, float, dict[str, Any]] | RuntimeError,
        wall: float,
        cpu: float,
    ) -> OcpSolution:
        if isinstance(res, tuple):
            primal, cost, stats = res
            self.last_stats = stats
            success = bool(stats.get("success", False))
            status = str(stats.get("return_status", "unknown"))
            iterations = int(stats.get("iter_count", -1))
        else:  # CasADi reports evaluation errors (NaN, …) as a RuntimeError
            primal = np.full(self.n_variables, np.nan)
            cost, success, iterations = math.nan, False, -1
            status = f"exception: {str(res).strip().splitlines()[-1]}"
        if success and not np.all(np.isfinite(primal)):
            success, status = False, "non-finite solution"
        if self.solver_name == "fatrop" and status == "0":
            status = "Solve_Succeeded"  # fatrop reports 0; use ipopt's wording for both
        states, inputs = self._unpack(primal)
        return OcpSolution(states, inputs, success, status, iterations, wall, cost, primal, cpu)

    def _unpack(self, primal: FloatArray) -> tuple[FloatArray, FloatArray]:
        nz, nu, n = self._nz, self.nu, self.horizon
        body = primal[: n * (nz + nu)].reshape(n, nz + nu)
        states = np.vstack([body[:, : self.nx], primal[n * (nz + nu) :][None, : self.nx]])
        return states, body[:, nz:].copy()
