# mypy: allow-untyped-defs
"""Compiled multirotor step of the embedded simulator (:class:`btmission.backends.sim.Simulator`).

One call per multirotor per simulation step does what a step of seed 002's model asks: the
autopilot's attitude command from the active mode and setpoint, the tilt limit, the yaw loop,
one RK4 step of the eight-state model in the yaw frame (seed 002 §3.2.2, eq. 1)

    ṗ = v
    v̇_x = T cos φ sin θ − A_x v_x
    v̇_y = −T sin φ − A_y v_y
    v̇_z = T cos φ cos θ − g − A_z v_z
    φ̇ = (K_φ φ_ref − φ) / τ_φ
    θ̇ = (K_θ θ_ref − θ) / τ_θ

rotated back to the world, then rock and ground contact. It is the arithmetic of
:func:`btmission.control.mav_model.mav_dynamics` (the same operations in the same order, so the
same bits: a test compares them), without Python's per-call cost on a dozen floats, which was
most of the simulator's time at fleet scale. What a step changes in the vehicle's mode, battery
and contact records stays in :meth:`Simulator._step_multirotor`.

numba in nopython mode (typed by numba, not annotated, like the planner's kernels); ``cache=True``
stores the machine code next to this file.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# the packed parameters (:func:`pack_params`)
P_G, P_AX, P_AY, P_AZ, P_GAIN_ROLL, P_TAU_ROLL, P_GAIN_PITCH, P_TAU_PITCH = range(8)
P_MAX_SPEED, P_MAX_CLIMB, P_BODY_RADIUS, P_TILT_MAX, P_HEADING_P, P_YAW_RATE_MAX = range(8, 14)
P_LAND_SPEED, P_IMPACT_SPEED, P_POSITION_GAIN, P_VELOCITY_GAIN = range(14, 18)

# what the attitude command follows (:func:`step`'s ``command``)
CMD_NONE, CMD_POSITION, CMD_VELOCITY, CMD_ATTITUDE, CMD_HOLD, CMD_LAND = range(6)
# what the yaw follows (``yaw_mode``)
YAW_NONE, YAW_RATE, YAW_HEADING = range(3)

# the result (``out``)
OUT_YAW, OUT_YAW_RATE, OUT_THRUST, OUT_GROUND, OUT_ROCK, OUT_IMPACT, OUT_LANDED = range(8, 15)
OUT_ODOMETER = 15
N_OUT = 16


def pack_params(
    g: float,
    drag: tuple[float, float, float],
    gain_roll: float,
    tau_roll: float,
    gain_pitch: float,
    tau_pitch: float,
    max_speed: float,
    max_climb: float,
    body_radius: float,
    tilt_max: float,
    heading_p: float,
    yaw_rate_max: float,
    land_speed: float,
    impact_speed: float,
    position_gain: float,
    velocity_gain: float,
) -> np.ndarray:
    """The model's, the autopilot's and the simulator's parameters as one array for :func:`step`."""
    return np.array(
        [
            g,
            drag[0],
            drag[1],
            drag[2],
            gain_roll,
            tau_roll,
            gain_pitch,
            tau_pitch,
            max_speed,
            max_climb,
            body_radius,
            tilt_max,
            heading_p,
            yaw_rate_max,
            land_speed,
            impact_speed,
            position_gain,
            velocity_gain,
        ],
        dtype=np.float64,
    )


@njit(cache=True, inline="always")
def _rhs(vx, vy, vz, phi, theta, thrust, phi_ref, theta_ref, p):  # pragma: no cover - jit
    """The derivatives of (v, φ, θ) (module docstring; ṗ = v is the caller's)."""
    return (
        thrust * math.cos(phi) * math.sin(theta) - p[P_AX] * vx,
        -thrust * math.sin(phi) - p[P_AY] * vy,
        thrust * math.cos(phi) * math.cos(theta) - p[P_G] - p[P_AZ] * vz,
        (p[P_GAIN_ROLL] * phi_ref - phi) / p[P_TAU_ROLL],
        (p[P_GAIN_PITCH] * theta_ref - theta) / p[P_TAU_PITCH],
    )


@njit(cache=True, inline="always")
def _derivative(s, u, p, k):  # pragma: no cover - jit
    """k = f(s, u): ṗ = v, then :func:`_rhs`."""
    k[0], k[1], k[2] = s[3], s[4], s[5]
    k[3], k[4], k[5], k[6], k[7] = _rhs(s[3], s[4], s[5], s[6], s[7], u[0], u[1], u[2], p)


@njit(cache=True, inline="always")
def _advance(x, h, k, s):  # pragma: no cover - jit
    """s = x + h·k."""
    for i in range(8):
        s[i] = x[i] + h * k[i]


@njit(cache=True)
def rk4(x, u, dt, p):  # pragma: no cover - jit
    """One RK4 step of the model (8 states, zero-order-hold input ``u`` = [T, φ_ref, θ_ref]):
    ``rk4_step(mav_dynamics, x, u, dt)``, the same operations in the same order."""
    k1, k2, k3, k4, s = np.empty(8), np.empty(8), np.empty(8), np.empty(8), np.empty(8)
    _derivative(x, u, p, k1)
    _advance(x, dt / 2, k1, s)
    _derivative(s, u, p, k2)
    _advance(x, dt / 2, k2, s)
    _derivative(s, u, p, k3)
    _advance(x, dt, k3, s)
    _derivative(s, u, p, k4)
    h6 = dt / 6
    out = np.empty(8)
    for i in range(8):
        out[i] = x[i] + h6 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i])
    return out


@njit(cache=True)
def _wrap(a):  # pragma: no cover - jit
    return (a + math.pi) % (2 * math.pi) - math.pi


@njit(cache=True)
def thrust_attitude(ax, ay, az, yaw, g, tilt_max):  # pragma: no cover - jit
    """[T, φ_ref, θ_ref] for a world-frame acceleration command (``thrust_attitude`` of the
    autopilot: R_z(−ψ) into the yaw frame, the tilt limited to ``tilt_max``)."""
    tz = max(az + g, 0.2 * g)
    c, s = math.cos(-yaw), math.sin(-yaw)
    tx, ty = c * ax - s * ay, s * ax + c * ay
    horiz = math.hypot(tx, ty)
    limit = tz * math.tan(tilt_max)
    if horiz > limit:
        tx, ty = tx * limit / horiz, ty * limit / horiz
    thrust = math.sqrt(tx * tx + ty * ty + tz * tz)
    phi = math.asin(max(-1.0, min(1.0, -ty / thrust)))
    theta = math.atan2(tx, tz)
    return thrust, phi, theta


@njit(cache=True, inline="always")
def _voxel(grid, x, y, z):  # pragma: no cover - jit
    """(finite, i, j, k): the voxel index of (x, y, z), not bounds-checked (``grid`` = origin
    x, y, z and resolution)."""
    fx = (x - grid[0]) / grid[3]
    fy = (y - grid[1]) / grid[3]
    fz = (z - grid[2]) / grid[3]
    if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
        return False, 0, 0, 0
    return True, math.floor(fx), math.floor(fy), math.floor(fz)


@njit(cache=True)
def occupied(occ, grid, x, y, z):  # pragma: no cover - jit
    """Whether (x, y, z) is in a rock voxel."""
    finite, i, j, k = _voxel(grid, x, y, z)
    nx, ny, nz = occ.shape
    return finite and 0 <= i < nx and 0 <= j < ny and 0 <= k < nz and occ[i, j, k]


@njit(cache=True)
def ground_z(occ, grid, x, y, z):  # pragma: no cover - jit
    """``VoxelMap.ground_z``: the top of the highest rock voxel at or below (x, y, z) in its
    column, or the map's bottom where there is none."""
    finite, i, j, k = _voxel(grid, x, y, z)
    nx, ny, nz = occ.shape
    if not finite or not (0 <= i < nx and 0 <= j < ny) or k < 0:
        return grid[2]
    for level in range(min(k, nz - 1), -1, -1):
        if occ[i, j, level]:
            return grid[2] + (level + 1) * grid[3]
    return grid[2]


@njit(cache=True)
def step(
    x,
    yaw,
    command,
    target,
    velocity,
    attitude,
    clamp,
    yaw_mode,
    yaw_sp,
    landed,
    dt,
    p,
    occ,
    grid,
    out,
):  # pragma: no cover - jit
    """One step of one multirotor (module docstring) from state ``x`` (p, v, φ, θ) and heading
    ``yaw``. ``command``: what the attitude command follows (CMD_*) — ``target`` is the position
    setpoint (CMD_POSITION) or the hold point (CMD_HOLD, CMD_LAND), ``velocity`` the velocity
    setpoint (feed-forward for CMD_POSITION), ``attitude`` [T, φ, θ] (CMD_ATTITUDE); ``clamp``:
    limit the commanded tilt; ``yaw_mode``/``yaw_sp``: a yaw rate or a heading to hold (YAW_*).
    Writes the new state (out[0:8]), heading, yaw rate, thrust, the ground height under it, rock
    contact, ground impact, landed (1.0/0.0) and the distance flown."""
    g = p[P_G]
    if command == CMD_NONE:
        thrust, phi_ref, theta_ref = 0.0, 0.0, 0.0
    elif command == CMD_ATTITUDE:
        thrust, phi_ref, theta_ref = attitude[0], attitude[1], attitude[2]
    else:
        kp = p[P_POSITION_GAIN]
        if command == CMD_POSITION:
            dx = velocity[0] + kp * (target[0] - x[0])
            dy = velocity[1] + kp * (target[1] - x[1])
            dz = velocity[2] + kp * (target[2] - x[2])
        elif command == CMD_VELOCITY:
            dx, dy, dz = velocity[0], velocity[1], velocity[2]
        elif command == CMD_HOLD:
            dx = kp * (target[0] - x[0])
            dy = kp * (target[1] - x[1])
            dz = kp * (target[2] - x[2])
        else:  # CMD_LAND
            dx = kp * (target[0] - x[0])
            dy = kp * (target[1] - x[1])
            dz = -p[P_LAND_SPEED]
        h = np.hypot(dx, dy)
        if h > p[P_MAX_SPEED]:
            scale = p[P_MAX_SPEED] / h
            dx, dy = dx * scale, dy * scale
        dz = min(max(dz, -p[P_MAX_CLIMB]), p[P_MAX_CLIMB])
        kv = p[P_VELOCITY_GAIN]
        thrust, phi_ref, theta_ref = thrust_attitude(
            kv * (dx - x[3]) + p[P_AX] * x[3],
            kv * (dy - x[4]) + p[P_AY] * x[4],
            kv * (dz - x[5]) + p[P_AZ] * x[5],
            yaw,
            g,
            p[P_TILT_MAX],
        )
    if clamp:
        tilt = p[P_TILT_MAX]
        phi_ref = min(max(phi_ref, -tilt), tilt)
        theta_ref = min(max(theta_ref, -tilt), tilt)
    if yaw_mode == YAW_RATE:
        rate = yaw_sp
    elif yaw_mode == YAW_HEADING:
        most = p[P_YAW_RATE_MAX]
        rate = min(max(p[P_HEADING_P] * _wrap(yaw_sp - yaw), -most), most)
    else:
        rate = 0.0
    if landed and thrust < g * 1.01:
        rate = 0.0
    for i in range(8):
        out[i] = x[i]
    rock = False
    if landed and thrust <= g:
        for i in range(3, 8):
            out[i] = 0.0  # resting on the ground
    else:
        # integrate in the yaw frame from p = 0 and rotate the displacement back (ṗ = v only)
        c, sn = math.cos(yaw), math.sin(yaw)
        xy = np.empty(8)
        xy[0], xy[1], xy[2] = 0.0, 0.0, 0.0
        xy[3] = c * x[3] + sn * x[4]
        xy[4] = -sn * x[3] + c * x[4]
        xy[5], xy[6], xy[7] = x[5], x[6], x[7]
        u = np.empty(3)
        u[0], u[1], u[2] = thrust, phi_ref, theta_ref
        xy = rk4(xy, u, dt, p)
        out[0] = x[0] + c * xy[0] - sn * xy[1]
        out[1] = x[1] + sn * xy[0] + c * xy[1]
        out[2] = x[2] + xy[2]
        out[3] = c * xy[3] - sn * xy[4]
        out[4] = sn * xy[3] + c * xy[4]
        out[5], out[6], out[7] = xy[5], xy[6], xy[7]
        if occupied(occ, grid, out[0], out[1], out[2] + p[P_BODY_RADIUS]):
            rock = True  # bumped into rock: stopped at the last free position
            out[0], out[1], out[2] = x[0], x[1], x[2]
            out[3], out[4], out[5] = 0.0, 0.0, 0.0
    ground = ground_z(occ, grid, out[0], out[1], out[2] + 0.05)
    impact = False
    if out[2] <= ground:
        if out[5] < -p[P_IMPACT_SPEED]:
            impact = True
        out[2] = ground
        for i in range(3, 8):
            out[i] = 0.0
    out[OUT_YAW] = _wrap(yaw + rate * dt)
    out[OUT_YAW_RATE] = rate
    out[OUT_THRUST] = thrust
    out[OUT_GROUND] = ground
    out[OUT_ROCK] = 1.0 if rock else 0.0
    out[OUT_IMPACT] = 1.0 if impact else 0.0
    now_landed = out[2] - ground < 0.05 and out[5] <= 0.3 and thrust <= g * 1.05
    out[OUT_LANDED] = 1.0 if now_landed else 0.0
    d0, d1, d2 = out[0] - x[0], out[1] - x[1], out[2] - x[2]
    out[OUT_ODOMETER] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@njit(cache=True)
def step_all(
    xs, yaws, commands, targets, velocities, attitudes, clamps, yaw_modes, yaw_sps, landed, dt,
    p, occ, grid,
):  # fmt: skip  # pragma: no cover - jit
    """:func:`step` for every row (a drone each): its (m, N_OUT) results."""
    out = np.empty((xs.shape[0], N_OUT))
    for i in range(xs.shape[0]):
        step(
            xs[i], yaws[i], commands[i], targets[i], velocities[i], attitudes[i], clamps[i],
            yaw_modes[i], yaw_sps[i], landed[i], dt, p, occ, grid, out[i],
        )  # fmt: skip
    return out


# ---- the contact test (every body, every step)
@njit(cache=True)
def rock_rows(occ, grid, centres):  # pragma: no cover - jit
    """:func:`occupied` of each row of ``centres`` (n, 3)."""
    out = np.zeros(centres.shape[0], dtype=np.bool_)
    for i in range(centres.shape[0]):
        out[i] = occupied(occ, grid, centres[i, 0], centres[i, 1], centres[i, 2])
    return out


@njit(cache=True)
def near_pairs(centres, radii, margin):  # pragma: no cover - jit
    """The pairs (i < j, row-major order) whose spheres come within ``margin`` of touching:
    ‖c_i − c_j‖² < (r_i + r_j + margin)² — the candidates for the exact test."""
    n = centres.shape[0]
    out = np.empty((n * (n - 1) // 2, 2), dtype=np.int64)
    k = 0
    for i in range(n):
        for j in range(i + 1, n):
            dx = centres[i, 0] - centres[j, 0]
            dy = centres[i, 1] - centres[j, 1]
            dz = centres[i, 2] - centres[j, 2]
            reach = radii[i] + radii[j] + margin
            if dx * dx + dy * dy + dz * dz < reach * reach:
                out[k, 0] = i
                out[k, 1] = j
                k += 1
    return out[:k]
