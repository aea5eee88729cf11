"""numba kernel of :mod:`btmission.viz.mesh`: greedy meshing of the rock/open boundary.

The grid is given with the faces' normal axis first: ``solid[p, u, v]`` is 1 for rock, 0 for open
space, and ``(axis, u, v)`` is a right-handed frame (``e_axis = e_u × e_v``). Every plane ``p`` in
``1 .. n-1`` lies between cells ``p-1`` and ``p``; a face there has its normal along ``+axis`` when
rock is below (``p-1``) and open space above (``p``), along ``-axis`` the other way round. Planes
0 and n (the map's outer boundary) never carry faces.

Greedy meshing (per plane and normal sign): scan the 2D mask of faces row by row; at each face not
yet covered, grow a rectangle along v as far as the mask goes, then along u while the whole next
row of that width is a mask face not yet covered; mark it covered and emit it. Every face is
covered by exactly one rectangle and no rectangle covers a non-face.

Kept free of Python objects so numba compiles it in nopython mode; ``cache=True`` stores the
machine code next to this file (``python -m btmission.warmup`` compiles it at install time).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from numba import njit


@njit(cache=True, inline="always")
def _is_face(solid: npt.NDArray[np.uint8], p: int, u: int, v: int, down: int) -> bool:
    """Whether plane p carries a face at (u, v) with normal ``+axis`` (down=0) or ``-axis`` (1)."""
    below = solid[p - 1, u, v]
    above = solid[p, u, v]
    if down == 0:
        return bool(below == 1 and above == 0)
    return bool(below == 0 and above == 1)


@njit(cache=True)
def greedy_quads(solid: npt.NDArray[np.uint8]) -> npt.NDArray[np.int32]:
    """Rectangles covering the faces between rock and open cells of ``solid`` (module docstring).

    Returns ``(Q, 6)`` int32 rows ``(down, p, u0, v0, u1, v1)``: a rectangle on plane ``p`` over
    ``[u0, u1) × [v0, v1)``, normal ``+axis`` when ``down`` is 0 and ``-axis`` when it is 1.
    """
    n, nu, nv = solid.shape
    count = 0  # unit faces: an upper bound on the rectangles
    for p in range(1, n):
        for u in range(nu):
            for v in range(nv):
                if solid[p - 1, u, v] != solid[p, u, v]:
                    count += 1
    out = np.empty((count, 6), dtype=np.int32)
    used = np.zeros((nu, nv), dtype=np.uint8)
    q = 0
    for p in range(1, n):
        for down in range(2):
            used[:, :] = 0
            for u in range(nu):
                for v in range(nv):
                    if used[u, v] or not _is_face(solid, p, u, v, down):
                        continue
                    v1 = v + 1
                    while v1 < nv and not used[u, v1] and _is_face(solid, p, u, v1, down):
                        v1 += 1
                    u1 = u + 1
                    while u1 < nu:
                        whole = True
                        for w in range(v, v1):
                            if used[u1, w] or not _is_face(solid, p, u1, w, down):
                                whole = False
                                break
                        if not whole:
                            break
                        u1 += 1
                    used[u:u1, v:v1] = 1
                    out[q, 0] = down
                    out[q, 1] = p
                    out[q, 2] = u
                    out[q, 3] = v
                    out[q, 4] = u1
                    out[q, 5] = v1
                    q += 1
    return out[:q]
