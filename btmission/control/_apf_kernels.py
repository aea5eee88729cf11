# mypy: allow-untyped-defs
"""Compiled APF of seed 002 (§3.2.3, eq. 3 and Alg. 1), for :mod:`btmission.control.apf` and the
navigator's control step.

Every vehicle evaluates the field on its LiDAR points every control period; a scan holds a few to a
few hundred points, so numpy's per-call overhead, not the arithmetic, was the cost. These loops
do the same sums point by point (eq. 3)::

    F^r = Σ_{0 < ‖ρ_i‖ ≤ r_F} L ∘ (1 − ‖ρ_i‖/r_F)² · (−ρ_i/‖ρ_i‖)  +  [N_c > n] Σ_{‖ρ_i‖ ≤ r_c} L_c · (−ρ_i/‖ρ_i‖)

and Alg. 1's saturation, rate saturation and normalisation, with ``sgn`` of a vector read as its
direction (see :mod:`btmission.control.apf`).

numba in nopython mode (typed by numba, not annotated, like the planner's kernels); ``cache=True``
stores the machine code next to this file.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _norm3(x, y, z):  # pragma: no cover - jit
    return math.sqrt(x * x + y * y + z * z)


@njit(cache=True)
def repulsive(pts, rf, rc, gx, gy, gz, gc, dust, out):  # pragma: no cover - jit
    """Eq. 3 on the (M, 3) body-frame ``pts`` into ``out[0:3]``; returns (N_ρr, N_ρc). Points at
    the origin and non-finite ones are skipped (a NaN distance compares false)."""
    sx = sy = sz = 0.0
    cx = cy = cz = 0.0
    n = 0
    nc = 0
    rf2 = rf * rf
    for i in range(pts.shape[0]):
        x = pts[i, 0]
        y = pts[i, 1]
        z = pts[i, 2]
        d2 = x * x + y * y + z * z
        if d2 <= rf2 and d2 > 0.0:
            d = math.sqrt(d2)
            a = 1.0 - d / rf
            w = a * a / d
            sx += w * x
            sy += w * y
            sz += w * z
            n += 1
            if d <= rc:
                nc += 1
                inv = 1.0 / d
                cx += inv * x
                cy += inv * y
                cz += inv * z
    fx = -sx * gx
    fy = -sy * gy
    fz = -sz * gz
    if nc > dust:
        fx -= gc * cx
        fy -= gc * cy
        fz -= gc * cz
    out[0] = fx
    out[1] = fy
    out[2] = fz
    return n, nc


@njit(cache=True)
def shape(raw, prev, att, fmax, frate, out):  # pragma: no cover - jit
    """Alg. 1 on F^r (``raw``), F^r_{k−1} (``prev``) and F^a (``att``): ``out[0:3]`` = F,
    ``out[3:6]`` = the shaped F^r_k, ``out[6:9]`` = the normalised F^a."""
    rx, ry, rz = raw[0], raw[1], raw[2]
    n = _norm3(rx, ry, rz)
    if n > fmax:
        rx, ry, rz = rx / n * fmax, ry / n * fmax, rz / n * fmax
    dx, dy, dz = rx - prev[0], ry - prev[1], rz - prev[2]
    n = _norm3(dx, dy, dz)
    if n > frate:
        rx = prev[0] + dx / n * frate
        ry = prev[1] + dy / n * frate
        rz = prev[2] + dz / n * frate
    ax, ay, az = att[0], att[1], att[2]
    n = _norm3(ax, ay, az)
    if n > 1.0:
        ax, ay, az = ax / n, ay / n, az / n
    tx, ty, tz = rx + ax, ry + ay, rz + az
    n = _norm3(tx, ty, tz)
    if n > 1.0:
        tx, ty, tz = tx / n, ty / n, tz / n
    out[0], out[1], out[2] = tx, ty, tz
    out[3], out[4], out[5] = rx, ry, rz
    out[6], out[7], out[8] = ax, ay, az


@njit(cache=True)
def separation_bound(
    vx, vy, vz, cx, cy, cz, rel, vel, stand_off, decel, reaction, share, lead_decel, passes, out
):  # fmt: skip  # pragma: no cover - jit
    """The velocity (vx, vy, vz) with its approach to each other agent at ``rel[i]`` (relative
    positions, the velocity's frame), moving at ``vel[i]`` (NaN: unknown), bounded
    (:func:`btmission.control.apf.separation_bound`)::

        v·u_i ≤ A_i − max(0, c·u_i − A_i),
        A_i = v_stop(max(0, share·(‖ρ_i‖ − s) + max(0, v_i·u_i)² / (2·a_j))),
        v_stop(x) = −a·t_r + √((a·t_r)² + 2·a·x)

    with (cx, cy, cz) = c the vehicle's current velocity: while it approaches faster than A_i
    (its velocity loop lags the lowered command), the command is lowered by the excess again.

    each pass removing the largest excess along its u_i, at most ``passes`` times (the most
    constraining neighbours first); into ``out[0:3]``. Returns the passes that changed it."""
    at = decel * reaction
    k = rel.shape[0]
    changed = 0
    for _ in range(passes):
        worst = 1e-12
        best = -1
        bx = by = bz = 0.0
        for i in range(k):
            x, y, z = rel[i, 0], rel[i, 1], rel[i, 2]
            d = _norm3(x, y, z)
            if not d > 0.0:  # (NaN or on top of it: no direction)
                continue
            ux, uy, uz = x / d, y / d, z / d
            room = share * (d - stand_off)
            away = ux * vel[i, 0] + uy * vel[i, 1] + uz * vel[i, 2]
            if away > 0.0:  # (NaN: not shared, no credit)
                room += away * away / (2.0 * lead_decel)
            if room < 0.0:
                room = 0.0
            allowed = -at + math.sqrt(at * at + 2.0 * decel * room)
            late = ux * cx + uy * cy + uz * cz - allowed
            if late > 0.0:
                allowed -= late
            excess = ux * vx + uy * vy + uz * vz - allowed
            if excess > worst:
                worst, best = excess, i
                bx, by, bz = ux, uy, uz
        if best < 0:
            break
        vx -= worst * bx
        vy -= worst * by
        vz -= worst * bz
        changed += 1
    out[0], out[1], out[2] = vx, vy, vz
    return changed


@njit(cache=True)
def navigator_force(
    points, others, px, py, pz, vx, vy, vz, goal, yaw, prev, flat, speed, position_gain, field,
    agents, separation, others_vel,
):  # fmt: skip  # pragma: no cover - jit
    """One APF control step of the navigator (its ``_apf_reference``), everything in one call:

    - F^r (eq. 3) on the LiDAR ``points`` (yaw frame) with ``field`` = (r_F, r_c, L_x, L_y, L_z,
      L_c, n), plus the other agents' repulsion: eq. 3 on their positions ``others`` (world,
      rotated here into the yaw frame, z dropped when ``flat``) with ``agents``' parameters and,
      when that push opposes the way ahead, a sidestep to the right of half its size; the
      vehicle is at (px, py, pz), moving at (vx, vy, vz);
    - Alg. 1 against ``prev`` = F^r_{k−1}, with F^a = the goal in the yaw frame;
    - the world-frame force F, its velocity F·speed with the approach to every neighbour bounded
      (:func:`separation_bound`, with their velocities ``others_vel`` (k, 3) and ``separation``
      = (s, a, t_r, share, a_j, passes); none when s ≤ 0), then the reference p + F·max(1, speed·‖F‖/K_p) and the velocity F·speed.

    Returns a (10,) array: reference (0:3), velocity (3:6), the shaped F^r_k (6:9) and ‖F^r‖
    before shaping (9), for eq. 4."""
    c = math.cos(-yaw)
    s = math.sin(-yaw)
    wx = goal[0] - px
    wy = goal[1] - py
    wbx = c * wx - s * wy
    wby = s * wx + c * wy
    wbz = goal[2] - pz
    raw = np.empty(3)
    repulsive(
        points, field[0], field[1], field[2], field[3], field[4], field[5], int(field[6]), raw
    )
    k = others.shape[0]
    if k:
        rel = np.empty((k, 3))
        for i in range(k):
            ox = others[i, 0] - px
            oy = others[i, 1] - py
            rel[i, 0] = c * ox - s * oy
            rel[i, 1] = s * ox + c * oy
            rel[i, 2] = 0.0 if flat else others[i, 2] - pz
        push = np.empty(3)
        n, _ = repulsive(
            rel, agents[0], agents[1], agents[2], agents[3], agents[4], agents[5],
            int(agents[6]), push,
        )  # fmt: skip
        if n:
            wn = max(_norm3(wbx, wby, wbz), 1e-9)
            hx, hy, hz = wbx / wn, wby / wn, wbz / wn
            fn = _norm3(push[0], push[1], push[2])
            if push[0] * hx + push[1] * hy + push[2] * hz < -0.7 * fn:
                push[0] += 0.5 * fn * hy
                push[1] += 0.5 * fn * -hx
        raw[0] += push[0]
        raw[1] += push[1]
        raw[2] += push[2]
    att = np.empty(3)
    att[0], att[1], att[2] = wbx, wby, wbz
    shaped = np.empty(9)
    shape(raw, prev, att, field[7], field[8], shaped)
    cw = math.cos(yaw)
    sw = math.sin(yaw)
    fx = cw * shaped[0] - sw * shaped[1]
    fy = sw * shaped[0] + cw * shaped[1]
    fz = shaped[2]
    if k and separation[0] > 0.0 and speed > 0.0:  # the approach to every neighbour bounded
        wrel = np.empty((k, 3))
        for i in range(k):
            wrel[i, 0] = others[i, 0] - px
            wrel[i, 1] = others[i, 1] - py
            wrel[i, 2] = 0.0 if flat else others[i, 2] - pz
        v = np.empty(3)
        if separation_bound(
            fx * speed, fy * speed, fz * speed, vx, vy, vz, wrel, others_vel, separation[0], separation[1],
            separation[2], separation[3], separation[4], int(separation[5]), v,
        ):  # fmt: skip
            fx, fy, fz = v[0] / speed, v[1] / speed, v[2] / speed
    norm = math.sqrt(fx * fx + fy * fy + fz * fz)
    stretch = max(1.0, speed * norm / position_gain)
    out = np.empty(10)
    out[0] = px + fx * stretch
    out[1] = py + fy * stretch
    out[2] = pz + fz * stretch
    out[3] = fx * speed
    out[4] = fy * speed
    out[5] = fz * speed
    out[6], out[7], out[8] = shaped[3], shaped[4], shaped[5]
    out[9] = _norm3(raw[0], raw[1], raw[2])
    return out
