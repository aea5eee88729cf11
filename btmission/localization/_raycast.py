# mypy: allow-untyped-defs
"""numba kernel: cast rays through an occupancy grid (Amanatides & Woo's voxel traversal, 1987).

Kept free of Python objects so numba compiles it in nopython mode; ``cache=True`` stores the
machine code next to this file, so only the first run on a machine pays the compile time (~1 s).
"""

from __future__ import annotations

import numpy as np
from numba import njit

INF = np.inf


@njit(cache=True, inline="always")
def _axis(i, g, d):  # pragma: no cover - compiled
    """Step (±1 or 0), distance to the first voxel boundary and between boundaries along one
    axis, for a ray at coordinate ``g`` (in voxel ``i``) with direction component ``d``."""
    if d > 0:
        return 1, (i + 1 - g) / d, 1.0 / d
    if d < 0:
        return -1, (i - g) / d, -1.0 / d
    return 0, INF, INF


@njit(cache=True)
def cast_rays(blocked, start, dirs, max_t):  # pragma: no cover - compiled
    """Distance along each ray to the first blocked voxel, in voxel units (``inf``: none).

    ``blocked`` is a ``bool`` grid ``(nx, ny, nz)``; ``start`` the rays' common origin in voxel
    coordinates (voxel ``(i, j, k)`` spans ``[i, i+1) × [j, j+1) × [k, k+1)``); ``dirs`` ``(n, 3)``
    unit directions; ``max_t`` ``(n,)`` the longest distance to look along each ray. A ray ends
    without a hit when it leaves the grid or passes ``max_t``; one starting in a blocked voxel hits
    at 0. The returned distance is where the ray *enters* the blocked voxel, i.e. the wall's face.
    """
    nx, ny, nz = blocked.shape
    n = dirs.shape[0]
    out = np.full(n, INF)
    gx, gy, gz = start[0], start[1], start[2]
    ix0, iy0, iz0 = int(np.floor(gx)), int(np.floor(gy)), int(np.floor(gz))
    if ix0 < 0 or iy0 < 0 or iz0 < 0 or ix0 >= nx or iy0 >= ny or iz0 >= nz:
        return out
    if blocked[ix0, iy0, iz0]:
        out[:] = 0.0
        return out
    for r in range(n):
        ix, iy, iz = ix0, iy0, iz0
        sx, tmx, tdx = _axis(ix, gx, dirs[r, 0])
        sy, tmy, tdy = _axis(iy, gy, dirs[r, 1])
        sz, tmz, tdz = _axis(iz, gz, dirs[r, 2])
        lim = max_t[r]
        while True:
            # step every axis whose boundary comes first; ties (the ray passing exactly through
            # an edge or a corner, e.g. from a sensor on a voxel corner) move diagonally, since
            # the voxels that only touch that edge or corner are not entered
            t = min(tmx, tmy, tmz)
            if t > lim:
                break
            tie = t + 1e-12 * (1.0 + abs(t))
            leaves = False
            if tmx <= tie:
                ix += sx
                tmx += tdx
                leaves = leaves or ix < 0 or ix >= nx
            if tmy <= tie:
                iy += sy
                tmy += tdy
                leaves = leaves or iy < 0 or iy >= ny
            if tmz <= tie:
                iz += sz
                tmz += tdz
                leaves = leaves or iz < 0 or iz >= nz
            if leaves:
                break
            if blocked[ix, iy, iz]:
                out[r] = abs(t)
                break
    return out
