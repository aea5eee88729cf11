"""Geometry of a voxel map for the 3D viewer: the rock surface as triangles, the risk layer as points.

Pure geometry (numpy, one numba kernel; no I/O, no viewer import), so the viewer only encodes
arrays and the tests can check the geometry itself.

:func:`surface_mesh` draws the boundary between rock and open space of a
:class:`~btmission.world.voxel.VoxelMap`:

* **Open space** is every voxel that is not OCCUPIED: FREE *and* UNKNOWN. An unmapped patch of a
  tunnel is then drawn as part of the tunnel, not as a block of rock in it (the planner treats
  unknown voxels as enterable at a price, not as walls, :mod:`btmission.planning.risk`).
* **Only rock/open faces**: a face is drawn where an occupied voxel touches an open one across a
  shared face. The map's outer boundary is never drawn (the box of solid rock around a mine would
  hide it).
* **Orientation**: every triangle's normal points from the rock into the open space, with
  counter-clockwise winding seen from the open side (three.js front faces). With back-face culling
  a camera outside the mine sees through the rock — roof, walls, floor — into the tunnels (the
  classic cut-away), and a camera inside a tunnel sees its walls.
* **Decimation**: coplanar adjacent faces of the same orientation are merged into rectangles
  (greedy meshing, :mod:`btmission.viz._mesh_kernel`), two triangles each. If that is still over
  the triangle budget, the grid is coarsened by 2 per axis (then 4, 8 ...) and meshed again; see
  :func:`coarse_rock` for why a coarse cell is rock only when *all* its voxels are.
* **Colours** by height over the map's vertical extent (dark umber at the bottom through ochre and
  sandstone to pale limestone at the top, so the levels of a mine read apart), darkened on walls
  and more on ceilings (so floor, wall and roof read apart as well).

Each rectangle has its own four vertices (a vertex is not shared between rectangles: greedy
rectangles meet in T-junctions anyway, and per-rectangle vertices keep flat shading exact).

:func:`risk_points` gives the D*+ risk layer (:mod:`btmission.planning.risk`, eq. 3) as a point
cloud: the free voxels near rock, with their risk cost scaled to [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from btmission.planning.risk import CostMap, RiskParams
from btmission.world.voxel import FREE, OCCUPIED, MapError, VoxelMap

DEFAULT_MAX_TRIANGLES = 150_000
DEFAULT_MAX_POINTS = 100_000

_PERMUTATIONS: tuple[tuple[int, int, int], ...] = ((0, 1, 2), (1, 2, 0), (2, 0, 1))
"""Per face axis, the grid axes as (normal, u, v): right-handed, ``e_normal = e_u × e_v``."""

_HEIGHT_STOPS = np.array([0.0, 0.3, 0.6, 0.85, 1.0])
_HEIGHT_COLOURS = np.array(
    [
        [0.40, 0.33, 0.28],  # dark umber (the lowest floors)
        [0.56, 0.45, 0.35],  # brown
        [0.73, 0.61, 0.44],  # ochre
        [0.83, 0.76, 0.62],  # sandstone
        [0.91, 0.89, 0.84],  # pale limestone (the highest roofs)
    ]
)
_SHADE_FLOOR, _SHADE_WALL, _SHADE_CEILING = 1.0, 0.82, 0.62
"""Brightness of faces looking up (floors), sideways (walls) and down (ceilings)."""

_QUAD_TRIANGLES = {
    0: np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),  # normal +axis: CCW seen from +axis
    1: np.array([[0, 2, 1], [0, 3, 2]], dtype=np.uint32),  # normal -axis: the reverse
}
"""Triangles of a rectangle with corners (u0,v0), (u1,v0), (u1,v1), (u0,v1), by normal sign."""


@dataclass(frozen=True, eq=False)
class SurfaceMesh:
    """A triangle mesh of a map's rock surface (:func:`surface_mesh`); arrays are read-only."""

    vertices: npt.NDArray[np.float32]
    """(N, 3) world positions (m)."""
    faces: npt.NDArray[np.uint32]
    """(M, 3) vertex indices, counter-clockwise seen from the open side."""
    colors: npt.NDArray[np.float32]
    """(N, 3) RGB in [0, 1] per vertex."""
    cell_m: float
    """Edge of the cells meshed (m): the map's resolution times the coarsening factor (1, 2, 4 ...)."""
    unit_faces: int
    """How many rock/open cell faces (of ``cell_m``) the triangles cover (before merging)."""

    @property
    def triangles(self) -> int:
        """Number of triangles."""
        return len(self.faces)

    @property
    def nbytes(self) -> int:
        """Bytes of the vertex, face and colour arrays (what the viewer sends)."""
        return int(self.vertices.nbytes + self.faces.nbytes + self.colors.nbytes)


def coarse_rock(vmap: VoxelMap, factor: int) -> npt.NDArray[np.uint8]:
    """The rock mask (1 rock, 0 open) of ``vmap`` on cells of ``factor`` voxels per axis.

    A coarse cell is rock only if **every** voxel of the map in it is rock; one open (free or
    unknown) voxel makes the whole cell open. So coarsening never closes a passage — the centre of
    every open voxel lies in an open coarse cell, and a 1-voxel gap in a wall stays a gap — at the
    price of thin walls (thinner than a coarse cell) between tunnels thinning out or vanishing.
    For a viewer that is the right way to err: a drone seen flying through drawn rock would be
    wrong, a slightly wide tunnel is not. Where the map's size is not a multiple of ``factor``, the
    last cells are partly outside the map; only their voxels inside it count.
    """
    rock = vmap.state == OCCUPIED
    out: npt.NDArray[np.uint8]
    if factor == 1:
        out = rock.view(np.uint8)
        return out
    shape = np.asarray(rock.shape)
    pad = -shape % factor
    rock = np.pad(rock, [(0, int(p)) for p in pad], constant_values=True)
    nc = (shape + pad) // factor
    blocks = rock.reshape(nc[0], factor, nc[1], factor, nc[2], factor)
    out = np.ascontiguousarray(blocks.all(axis=(1, 3, 5))).view(np.uint8)
    return out


def _quads(rock: npt.NDArray[np.uint8]) -> list[tuple[int, npt.NDArray[np.int32]]]:
    """Greedy rectangles of each face axis: ``(axis, rows (down, p, u0, v0, u1, v1))``."""
    from btmission.viz._mesh_kernel import greedy_quads

    return [
        (axis, greedy_quads(np.ascontiguousarray(rock.transpose(perm))))
        for axis, perm in enumerate(_PERMUTATIONS)
    ]


def _height_colours(z: npt.NDArray[np.float64], lo: float, hi: float) -> npt.NDArray[np.float64]:
    """The rock colour map (module docstring) at heights ``z`` between ``lo`` and ``hi``."""
    t = np.clip((z - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    return np.stack([np.interp(t, _HEIGHT_STOPS, _HEIGHT_COLOURS[:, c]) for c in range(3)], axis=-1)


def _assemble(
    vmap: VoxelMap, quads: list[tuple[int, npt.NDArray[np.int32]]], factor: int
) -> SurfaceMesh:
    """Vertices, triangles and colours of the rectangles ``quads`` on cells of ``factor`` voxels."""
    cell = vmap.resolution * factor
    origin = np.asarray(vmap.origin)
    lo, hi = vmap.bounds
    corners: list[npt.NDArray[np.float64]] = []
    shades: list[npt.NDArray[np.float64]] = []
    tris: list[npt.NDArray[np.uint32]] = []
    unit_faces = 0
    base = 0
    for axis, rows in quads:
        perm = _PERMUTATIONS[axis]
        down, p, u0, v0, u1, v1 = (rows[:, k].astype(np.int64) for k in range(6))
        unit_faces += int(np.sum((u1 - u0) * (v1 - v0)))
        # corner k of every rectangle, in (normal, u, v) cell coordinates: (u0,v0) (u1,v0) (u1,v1) (u0,v1)
        uv = np.stack(
            [np.stack([u0, v0], -1), np.stack([u1, v0], -1), np.stack([u1, v1], -1),
             np.stack([u0, v1], -1)], axis=1,
        )  # fmt: skip
        idx = np.empty((len(rows), 4, 3), dtype=np.float64)
        idx[:, :, perm[0]] = p[:, None]
        idx[:, :, perm[1]] = uv[:, :, 0]
        idx[:, :, perm[2]] = uv[:, :, 1]
        # cells partly outside the map (coarse grids) end at the map's edge
        corners.append(np.minimum(origin + idx.reshape(-1, 3) * cell, hi))
        if axis == 2:
            shade = np.where(down == 0, _SHADE_FLOOR, _SHADE_CEILING)
        else:
            shade = np.full(len(rows), _SHADE_WALL)
        shades.append(np.repeat(shade, 4))
        for sign, local in _QUAD_TRIANGLES.items():
            first = base + 4 * np.flatnonzero(down == sign).astype(np.uint32)
            tris.append((first[:, None, None] + local[None]).reshape(-1, 3))
        base += 4 * len(rows)
    vertices = np.concatenate(corners) if corners else np.zeros((0, 3))
    shade_all = np.concatenate(shades) if shades else np.zeros(0)
    colours = _height_colours(vertices[:, 2], lo[2], hi[2]) * shade_all[:, None]
    faces = np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.uint32)
    mesh = SurfaceMesh(
        vertices=vertices.astype(np.float32),
        faces=faces.astype(np.uint32),
        colors=np.clip(colours, 0.0, 1.0).astype(np.float32),
        cell_m=cell,
        unit_faces=unit_faces,
    )
    for arr in (mesh.vertices, mesh.faces, mesh.colors):
        arr.flags.writeable = False
    return mesh


def surface_mesh(vmap: VoxelMap, *, max_triangles: int = DEFAULT_MAX_TRIANGLES) -> SurfaceMesh:
    """The rock surface of ``vmap`` as at most ``max_triangles`` triangles (module docstring).

    Meshes the full-resolution grid with greedy rectangles; while that gives more than
    ``max_triangles`` triangles, coarsens the grid by 2 per axis (:func:`coarse_rock`) and meshes
    again. A grid coarsened to a single cell has no rock/open faces left, so this always ends.
    The mine of ``missions/mine_inspection.yaml`` (400 × 240 × 24 voxels) fits the default budget
    at full resolution.
    """
    if max_triangles < 0:
        raise MapError(f"max_triangles must be ≥ 0, got {max_triangles}")
    factor = 1
    while True:
        quads = _quads(coarse_rock(vmap, factor))
        if 2 * sum(len(rows) for _, rows in quads) <= max_triangles:
            return _assemble(vmap, quads, factor)
        factor *= 2


def risk_points(
    vmap: VoxelMap, params: RiskParams | None = None, *, max_points: int = DEFAULT_MAX_POINTS
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """The risk layer as points: centres ``(N, 3)`` of the free voxels whose risk cost is > 0 and
    that cost scaled to [0, 1] ``(N,)``.

    The cost is the planner's own (:class:`~btmission.planning.risk.CostMap`, eq. 3:
    ``c_u / (d + 1)`` within ``r`` of rock). It is divided by the highest cost a free voxel can
    have, ``c_u / (resolution + 1)`` (a free voxel sharing a face with rock), so 1 means "touching
    rock" and the scale does not change as the map does (the lowest value is
    ``(resolution + 1) / (r + 1)``, just inside the radius). Unknown voxels are left out (their
    cost also holds ``c_u`` for being unknown). Over ``max_points`` points, a seeded random subset
    of ``max_points`` is kept (deterministic, in map order, without the stripes a stride gives).
    """
    if max_points < 0:
        raise MapError(f"max_points must be ≥ 0, got {max_points}")
    costs = CostMap(vmap, params)
    cost = costs.voxel_cost
    keep = (vmap.state == FREE) & (cost > 0)
    index = np.argwhere(keep)
    value = cost[keep]
    if len(index) > max_points:
        chosen = np.sort(np.random.default_rng(0).choice(len(index), max_points, replace=False))
        index, value = index[chosen], value[chosen]
    top = costs.params.unknown_cost / (vmap.resolution + 1.0)
    scaled = np.clip(value / top, 0.0, 1.0) if top > 0 else np.zeros_like(value)
    return vmap.index_to_world(index).astype(np.float32), scaled.astype(np.float32)
