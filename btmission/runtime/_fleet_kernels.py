# mypy: allow-untyped-defs
"""Compiled control step of a whole fleet's route-following drones, for
:class:`btmission.runtime.fleetstep.FleetFollow`.

At 30 drones the per-drone control step was ~25 µs, most of it Python between four compiled
calls (the carrot, the LiDAR scan, the neighbour query, the APF). :func:`fleet_follow` makes those
same four calls — the very kernels the per-drone path uses, so every number is the same to the
bit — for every drone in one call. It runs on one core: spread over two with ``prange`` (each
drone's result depends on its own inputs only) it saved 30 µs of a 1.5 ms step at 30 drones,
not worth a thread pool in every process (GNU OpenMP's, numba's first choice here, hangs a
forked child).

The neighbours each drone sees are what the per-drone path would show it: the agents share where
they are during the control loop, in its order, so those before the drone are where they are
now (``cur``) and those after it where they were one step ago (``prev``) — row ``r`` is taken
from ``cur`` when its rank in the loop is below the drone's; so are the velocities they share
with it (``vcur``, ``vprev``: the separation rule's).

numba in nopython mode (typed by numba, not annotated, like the planner's kernels); ``cache=True``
stores the machine code next to this file, keyed on this file and the files of the kernels it
calls (:func:`btmission.kernelcache.key_on_callees`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from btmission.control import _apf_kernels
from btmission.control._apf_kernels import navigator_force
from btmission.kernelcache import key_on_callees
from btmission.links import _neighbour_kernels
from btmission.links._neighbour_kernels import near_rows
from btmission.runtime import _route_kernels
from btmission.runtime._route_kernels import carrots
from btmission.world import _surface_kernels
from btmission.world._surface_kernels import scan_points

OUT = 15
"""Columns of :func:`fleet_follow`'s result: code (0 go, 1 the per-drone path must decide),
segment, arc length, reference (3:6), velocity (6:9), shaped F^r_k (9:12), ‖F^r‖ (12), and the
point twice the lookahead along (13:15, x and y)."""


@njit(cache=True)
def fleet_follow(
    routes, route_off, seg0, tel, pose, body, target, ground_goal, apf_prev,
    spts, sstarts, slo, scell, sdims, radius, centres, radii, sphere,
    prev, cur, vprev, vcur, rank, own_row, own_rank, within,
    window, look, tol, settled, speed, gain, field, agents, separation,
):  # fmt: skip  # pragma: no cover - jit
    """One control step of ``m`` drones following routes (rows of the per-drone arrays):

    - ``routes[route_off[i]:route_off[i + 1]]`` is drone i's route table (``Polyline``), ``seg0``
      where its projection starts; ``tel`` (m, 7) its estimated x, y, z, vx, vy, vz, yaw;
      ``pose`` (m, 4) its true x, y, z, yaw (where the LiDAR is); ``body`` its row of the body
      table (``centres``, ``radii``); ``target`` (m, 3) the route's target, ``ground_goal`` whether
      it lies on the ground; ``apf_prev`` (m, 3) F^r_{k−1};
    - the rock surface cells (``spts`` … ``sdims``), the LiDAR ``radius`` and unit ``sphere``;
    - the bus's start rows ``prev`` / ``cur`` and shared velocities ``vprev`` / ``vcur`` with
      each row's ``rank`` in the control loop, and each drone's ``own_row`` and ``own_rank``
      (module docstring); ``within`` the neighbour range.

    A drone that may have arrived (within ``tol`` of its target horizontally and about settled),
    or whose carrot is the raised target of a ground goal, gets code 1: the per-drone path,
    which asks the agent's map, decides those."""
    m = tel.shape[0]
    n = prev.shape[0]
    out = np.zeros((m, OUT))
    for i in range(m):
        table = routes[route_off[i] : route_off[i + 1]]
        px, py, pz = tel[i, 0], tel[i, 1], tel[i, 2]
        c = carrots(table, px, py, pz, seg0[i], window, look, 2 * look)
        out[i, 1], out[i, 2] = c[0], c[1]
        out[i, 13], out[i, 14] = c[5], c[6]
        dx, dy = px - target[i, 0], py - target[i, 1]
        vx, vy, vz = tel[i, 3], tel[i, 4], tel[i, 5]
        near = math.sqrt(dx * dx + dy * dy) <= tol * (1 + 1e-9) + 1e-12
        if near and math.sqrt(vx * vx + vy * vy + vz * vz) <= settled * (1 + 1e-9) + 1e-12:
            out[i, 0] = 1.0
            continue
        left = table[table.shape[0] - 1, 8] - c[1]
        if ground_goal[i] and left < look:
            out[i, 0] = 1.0
            continue
        p = np.empty(3)
        p[0], p[1], p[2] = pose[i, 0], pose[i, 1], pose[i, 2]
        scan = scan_points(
            spts, sstarts, slo, scell, sdims, p, radius, pose[i, 3], centres, radii, body[i],
            sphere,
        )  # fmt: skip
        seen = np.empty((n, 3))
        for r in range(n):
            src = cur if rank[r] < own_rank[i] else prev
            seen[r, 0], seen[r, 1], seen[r, 2] = src[r, 0], src[r, 1], src[r, 2]
        rows = near_rows(seen, n, px, py, within, own_row[i])
        others = np.empty((len(rows), 3))
        others_vel = np.empty((len(rows), 3))
        for k in range(len(rows)):
            r = rows[k]
            vsrc = vcur if rank[r] < own_rank[i] else vprev
            for col in range(3):
                others[k, col] = seen[r, col]
                others_vel[k, col] = vsrc[r, col]
            if others[k, 2] != others[k, 2]:  # a 2D share: at this drone's height
                others[k, 2] = pz
        goal = np.empty(3)
        goal[0], goal[1], goal[2] = c[2], c[3], c[4]
        f = navigator_force(
            scan, others, px, py, pz, vx, vy, vz, goal, tel[i, 6], apf_prev[i], False, speed,
            gain, field, agents, separation, others_vel,
        )  # fmt: skip
        out[i, 3:13] = f
    return out


key_on_callees([fleet_follow], _surface_kernels, _apf_kernels, _neighbour_kernels, _route_kernels)
