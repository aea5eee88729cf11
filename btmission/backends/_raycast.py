# mypy: allow-untyped-defs
"""Compiled ray marching through a voxel grid, for the simulated depth camera.

numba in nopython mode (typed by numba, not annotated: like the planner's kernels); ``cache=True``
stores the machine code next to this file, so only the first run on a machine compiles it.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def march(occ, origin, dirs, grid_origin, resolution, step, max_range):  # pragma: no cover - jit
    """Distance along each unit direction to the first occupied voxel, sampled every ``step``
    metres (inf when none is met within ``max_range``)."""
    n = dirs.shape[0]
    nx, ny, nz = occ.shape
    out = np.full(n, np.inf)
    steps = int(np.ceil(max_range / step))
    for r in range(n):
        for k in range(1, steps + 1):
            t = k * step
            i = int(np.floor((origin[0] + dirs[r, 0] * t - grid_origin[0]) / resolution))
            j = int(np.floor((origin[1] + dirs[r, 1] * t - grid_origin[1]) / resolution))
            m = int(np.floor((origin[2] + dirs[r, 2] * t - grid_origin[2]) / resolution))
            if 0 <= i < nx and 0 <= j < ny and 0 <= m < nz and occ[i, j, m]:
                out[r] = t
                break
    return out
