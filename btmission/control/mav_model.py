"""The MAV prediction model of the COMPRA NMPC (seed 002 §3.2.2), as numpy and as CasADi.

Eight states in the yaw-compensated frame (world axes rotated by the current yaw ψ about z, so
roll and pitch act along the frame's y and x axes), three inputs::

    x = [p_x, p_y, p_z, v_x, v_y, v_z, φ, θ]        u = [T, φ_ref, θ_ref]

    ṗ = v
    v̇ = R_{x,y}(θ, φ) [0, 0, T]ᵀ + [0, 0, −g]ᵀ − diag(A_x, A_y, A_z) v
      = [T cos φ sin θ,  −T sin φ,  T cos φ cos θ − g]ᵀ − A v
    φ̇ = (K_φ φ_ref − φ) / τ_φ
    θ̇ = (K_θ θ_ref − θ) / τ_θ

T is the mass-less total thrust (m/s², hover T = g); φ_ref, θ_ref go to the low-level attitude
controller, whose closed loop is the first-order lag (τ, K). This is the model of the NMPC papers
seed 002 cites for its controller ([31], [32]: Lindqvist et al.); seed 002 itself only states the
state and input vectors. The yaw ψ is not a state: it is regulated by a decoupled PD
(:func:`yaw_rate_pd`), and positions/velocities are rotated into the yaw frame with
:func:`world_to_yaw_frame` before a solve.

The same right-hand side is written once per backend: :func:`mav_dynamics` (numpy, used by the
closed-loop simulations in tests and benchmarks) and :func:`mav_dynamics_casadi` (symbolic, used by
the NMPC); a test checks they agree. :func:`rk4_step` integrates either one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from btmission.types import FloatArray

__all__ = [
    "NU",
    "NX",
    "MavParams",
    "mav_dynamics",
    "mav_dynamics_casadi",
    "rk4_step",
    "simulate",
    "world_to_yaw_frame",
    "wrap_angle",
    "yaw_frame_to_world",
    "yaw_rate_pd",
]

NX = 8
"""Number of model states ``[p(3), v(3), φ, θ]``."""
NU = 3
"""Number of model inputs ``[T, φ_ref, θ_ref]``."""

_S = TypeVar("_S")


@dataclass(frozen=True)
class MavParams:
    """Physical parameters of the MAV model (module docstring).

    The defaults are the values the cited NMPC papers use for their ~1-3 kg quadrotors
    (gravity, linear drag A = (0.1, 0.1, 0.2) 1/s, attitude time constants 0.5 s with unit gains).
    """

    g: float = 9.81
    drag: tuple[float, float, float] = (0.1, 0.1, 0.2)
    tau_roll_s: float = 0.5
    tau_pitch_s: float = 0.5
    gain_roll: float = 1.0
    gain_pitch: float = 1.0

    def __post_init__(self) -> None:
        if self.g <= 0 or self.tau_roll_s <= 0 or self.tau_pitch_s <= 0:
            raise ValueError("g and the attitude time constants must be positive")
        if len(self.drag) != 3 or any(a < 0 for a in self.drag):
            raise ValueError(f"drag must be three non-negative numbers, got {self.drag}")


def _rhs(
    x: Any, u: Any, params: MavParams, cos: Callable[[Any], Any], sin: Callable[[Any], Any]
) -> list[Any]:
    """The eight right-hand sides, written once for numpy scalars and CasADi symbols alike."""
    vx, vy, vz, phi, theta = x[3], x[4], x[5], x[6], x[7]
    thrust, phi_ref, theta_ref = u[0], u[1], u[2]
    ax, ay, az = params.drag
    return [
        vx,
        vy,
        vz,
        thrust * cos(phi) * sin(theta) - ax * vx,
        -thrust * sin(phi) - ay * vy,
        thrust * cos(phi) * cos(theta) - params.g - az * vz,
        (params.gain_roll * phi_ref - phi) / params.tau_roll_s,
        (params.gain_pitch * theta_ref - theta) / params.tau_pitch_s,
    ]


def mav_dynamics(x: ArrayLike, u: ArrayLike, params: MavParams = MavParams()) -> FloatArray:
    """ẋ = f(x, u) of the module docstring, for one state (8,) and input (3,)."""
    xs = np.asarray(x, dtype=float)
    us = np.asarray(u, dtype=float)
    return np.array(_rhs(xs, us, params, math.cos, math.sin), dtype=float)


def mav_dynamics_casadi(x: Any, u: Any, params: MavParams = MavParams()) -> Any:
    """ẋ = f(x, u) as a CasADi expression (``x``: 8×1 and ``u``: 3×1 SX/MX symbols)."""
    import casadi as ca

    return ca.vertcat(*_rhs(x, u, params, ca.cos, ca.sin))


def rk4_step(f: Callable[[_S, Any], _S], x: _S, u: Any, dt: float, substeps: int = 1) -> _S:
    """Classic RK4 of ``ẋ = f(x, u)`` over ``dt`` in ``substeps`` equal steps (zero-order-hold u).

    Works on numpy arrays and on CasADi expressions alike (only +, * and calls to ``f``).
    """
    if substeps < 1:
        raise ValueError("substeps must be at least 1")
    h = dt / substeps
    for _ in range(substeps):
        k1: Any = f(x, u)
        k2: Any = f(x + (h / 2) * k1, u)  # type: ignore[operator]
        k3: Any = f(x + (h / 2) * k2, u)  # type: ignore[operator]
        k4: Any = f(x + h * k3, u)  # type: ignore[operator]
        x = x + (h / 6) * (k1 + 2 * k2 + 2 * k3 + k4)  # type: ignore[operator]
    return x


def simulate(
    x: ArrayLike, u: ArrayLike, dt: float, params: MavParams = MavParams(), substeps: int = 10
) -> FloatArray:
    """Advance the numpy model by ``dt`` under a constant input (RK4, ``substeps`` sub-steps).

    This is the "plant" of the closed-loop tests and benchmarks: integrated finer than the NMPC's
    own one-step RK4 prediction, so the controller sees a (small) model mismatch.
    """
    return rk4_step(
        lambda s, v: mav_dynamics(s, v, params), np.asarray(x, dtype=float), u, dt, substeps
    )


def wrap_angle(a: float) -> float:
    """``a`` wrapped to (−π, π]."""
    w = math.remainder(a, 2 * math.pi)
    return math.pi if w == -math.pi else w


def _rot_z(vec: ArrayLike, psi: float) -> FloatArray:
    v = np.asarray(vec, dtype=float)
    c, s = math.cos(psi), math.sin(psi)
    if v.shape == (3,):  # one vector (most calls): the same products, without the fancy indexing
        x, y = float(v[0]), float(v[1])
        return np.array([c * x - s * y, s * x + c * y, float(v[2])])
    out = v.copy()
    out[..., 0] = c * v[..., 0] - s * v[..., 1]
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    return out


def world_to_yaw_frame(vec: ArrayLike, psi: float) -> FloatArray:
    """Rotate world-frame vector(s) (…, 3) into the yaw-compensated frame of heading ``psi``."""
    return _rot_z(vec, -psi)


def yaw_frame_to_world(vec: ArrayLike, psi: float) -> FloatArray:
    """Inverse of :func:`world_to_yaw_frame`."""
    return _rot_z(vec, psi)


def yaw_rate_pd(
    psi: float,
    psi_ref: float,
    yaw_rate: float,
    kp: float = 1.5,
    kd: float = 0.2,
    max_rate: float = 1.0,
    yaw_rate_ref: float = 0.0,
) -> float:
    """Decoupled yaw PD of seed 002 §3.2.2: ψ̇_cmd = ψ̇_ref + K_p·wrap(ψ_ref − ψ) + K_d·(ψ̇_ref − ψ̇).

    Returns the yaw-rate command for the attitude controller, clipped to ±``max_rate`` (rad/s).
    The angle error is wrapped so the MAV always turns the short way round.
    """
    cmd = yaw_rate_ref + kp * wrap_angle(psi_ref - psi) + kd * (yaw_rate_ref - yaw_rate)
    return float(np.clip(cmd, -max_rate, max_rate))
