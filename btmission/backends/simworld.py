"""The embedded simulator's static world: the rock, the ground and what the cameras look for.

:class:`SimWorld` holds the mission's :class:`~btmission.world.voxel.VoxelMap` with its rock
faces (the centres of the faces between rock voxels and open voxels) sorted into cells for ball
queries (the short-range LiDAR's points, a vehicle's clearance to the nearest wall or roof face),
a per-column ground table for ``ground_z``, and ray casting through the voxels (the depth
camera). :class:`Artifact` is an object the mission places in the world for the cameras. The
world is static: built once per run, shared by the simulator
(:class:`~btmission.backends.sim.Simulator`) and by the map sensors of any provider
(:class:`~btmission.backends.mapsensors.MapSensors`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from btmission.backends.mapsensors import Bodies
from btmission.types import FloatArray
from btmission.world.voxel import OCCUPIED, VoxelMap

WALL_QUERY_M = 5.0
"""Clearances beyond this are reported as inf (nothing near enough to matter)."""
GROUND_TABLE_MAX_VOXELS = 64_000_000
"""Maps up to this size keep a per-voxel ground table (2 bytes a voxel) for fast ground_z."""
SURFACE_CELLS_MAX = 4_000_000
"""Most cells of the grid the rock-face points are sorted into (its start table: 8 bytes each)."""


@dataclass(frozen=True)
class Artifact:
    label: str
    position: tuple[float, float, float]
    size_m: float = 0.5


class _SurfaceCells:
    """The rock-face points sorted into cubic cells, for ball queries
    (:mod:`btmission.world._surface_kernels`). Cells of 1 m (at least two voxels), larger
    where a huge map would need more than :data:`SURFACE_CELLS_MAX` of them."""

    def __init__(self, points: FloatArray, resolution: float) -> None:
        pts = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
        lo = pts.min(axis=0) if len(pts) else np.zeros(3)
        span = (pts.max(axis=0) - lo) if len(pts) else np.zeros(3)
        cell = max(1.0, 2.0 * resolution)
        while float(np.prod(np.floor(span / cell) + 1)) > SURFACE_CELLS_MAX:
            cell *= 2.0
        dims = (np.floor(span / cell) + 1).astype(np.int64)
        ijk = np.minimum(np.floor((pts - lo) / cell).astype(np.int64), dims - 1)
        flat = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        order = np.argsort(flat, kind="stable")
        self.points = np.ascontiguousarray(pts[order])
        self.starts = np.searchsorted(flat[order], np.arange(int(np.prod(dims)) + 1)).astype(
            np.int64
        )
        self.lo = lo
        self.cell = cell
        self.dims = dims

    def nearest(self, queries: FloatArray, max_d: float) -> FloatArray:
        """Distance from each query point to the nearest point (inf beyond ``max_d``)."""
        if len(self.points) == 0:
            return np.full(len(queries), math.inf)
        from btmission.world._surface_kernels import nearest_distances

        out: FloatArray = nearest_distances(
            self.points, self.starts, self.lo, self.cell, self.dims,
            np.ascontiguousarray(queries, dtype=float), float(max_d),
        )  # fmt: skip
        return out

    def ball(self, p: FloatArray, radius: float) -> FloatArray:
        from btmission.world._surface_kernels import ball_points

        out: FloatArray = ball_points(
            self.points, self.starts, self.lo, self.cell, self.dims, p, radius
        )
        return out

    def scan(
        self, p: FloatArray, radius: float, yaw: float, bodies: Bodies, sphere: FloatArray
    ) -> FloatArray:
        from btmission.world._surface_kernels import scan_points

        centres, radii, skip = bodies
        out: FloatArray = scan_points(
            self.points, self.starts, self.lo, self.cell, self.dims, p, radius, float(yaw),
            np.ascontiguousarray(centres, dtype=float).reshape(-1, 3),
            np.ascontiguousarray(radii, dtype=float), int(skip), sphere,
        )  # fmt: skip
        return out


class SimWorld:
    """The static world: voxel map, rock surfaces (face points sorted into cells), ground
    heights, ray casting."""

    def __init__(self, voxel_map: VoxelMap, artifacts: Sequence[Artifact] = ()) -> None:
        self.map = voxel_map
        self.artifacts = tuple(artifacts)
        st = voxel_map.state
        occ = st == OCCUPIED
        res = voxel_map.resolution
        pts: list[FloatArray] = []
        normals: list[int] = []
        for axis in range(3):
            for d in (-1, 1):
                # faces of rock voxels whose neighbour along (axis, d) is inside the map and open
                src = [slice(None)] * 3
                dst = [slice(None)] * 3
                src[axis] = slice(0, -1) if d == 1 else slice(1, None)
                dst[axis] = slice(1, None) if d == 1 else slice(0, -1)
                face = occ[tuple(src)] & ~occ[tuple(dst)]
                idx = np.argwhere(face)
                if d == -1:
                    idx[:, axis] += 1
                centres = voxel_map.index_to_world(idx)
                centres[:, axis] += d * res / 2
                pts.append(centres)
                normals.append(len(idx) * (1 if (axis == 2 and d == 1) else 0))
        self.surface = np.vstack(pts) if pts else np.zeros((0, 3))
        up = np.zeros(len(self.surface), dtype=bool)
        start = 0
        for block, is_floor in zip(pts, normals):
            if is_floor:
                up[start : start + len(block)] = True
            start += len(block)
        self.walls = self.surface[~up]
        self._cells = _SurfaceCells(self.surface, float(res))
        self._wall_cells = _SurfaceCells(self.walls, float(res))
        self._occ = occ
        self._origin = tuple(float(o) for o in voxel_map.origin)
        self._res = float(res)
        self._grid = np.array([*self._origin, self._res], dtype=float)
        """Origin and resolution, for the compiled multirotor step."""
        self._shape = tuple(int(n) for n in occ.shape)
        # the highest rock voxel at or below each voxel of its column (-1: none): ground_z in
        # O(1) per query instead of a column scan (the world is static)
        nz = occ.shape[2]
        self._below: npt.NDArray[np.int16] | None = None
        if nz < 2**15 and occ.size <= GROUND_TABLE_MAX_VOXELS:
            levels = np.where(occ, np.arange(nz, dtype=np.int16), np.int16(-1))
            self._below = np.maximum.accumulate(levels, axis=2)

    # ------------------------------------------------------------------ queries
    def _voxel(self, p: Sequence[float] | FloatArray) -> tuple[int, int, int] | None:
        """The voxel index of ``p``, not bounds-checked (None for a non-finite point), with the
        arithmetic of :meth:`VoxelMap.world_to_index` done on scalars (the hot path of every
        simulator step)."""
        o, r = self._origin, self._res
        fx, fy, fz = (p[0] - o[0]) / r, (p[1] - o[1]) / r, (p[2] - o[2]) / r
        if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
            return None
        return math.floor(fx), math.floor(fy), math.floor(fz)

    def occupied(self, p: Sequence[float] | FloatArray) -> bool:
        idx = self._voxel(p)
        if idx is None:
            return False
        i, j, k = idx
        nx, ny, nz = self._shape
        return 0 <= i < nx and 0 <= j < ny and 0 <= k < nz and bool(self._occ[i, j, k])

    def occupied_rows(self, points: FloatArray) -> list[bool]:
        """:meth:`occupied` of each of ``points`` (n, 3), with its arithmetic, in one compiled
        pass (:func:`~btmission.backends._multirotor_kernels.rock_rows`)."""
        from btmission.backends._multirotor_kernels import rock_rows

        pts = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
        return rock_rows(self._occ, self._grid, pts).tolist()  # type: ignore[no-any-return]

    def ground_z(self, p: Sequence[float] | FloatArray) -> float:
        """:meth:`VoxelMap.ground_z <btmission.world.voxel.VoxelMap.ground_z>`, from the
        precomputed column table."""
        below = self._below
        if below is None:
            return self.map.ground_z(p)
        idx = self._voxel(p)
        if idx is None:
            return self.map.ground_z(p)  # (its own handling of the odd cases)
        i, j, k = idx
        o, r = self._origin, self._res
        nx, ny, nz = self._shape
        if not (0 <= i < nx and 0 <= j < ny) or k < 0:
            return o[2]
        top = int(below[i, j, min(k, nz - 1)])
        return o[2] if top < 0 else o[2] + (top + 1) * r

    def wall_distance(self, p: FloatArray) -> float:
        """Distance from ``p`` to the nearest wall or roof face (inf if there is none within
        :data:`WALL_QUERY_M`)."""
        return float(self.wall_distances(np.asarray(p, dtype=float).reshape(1, 3))[0])

    def wall_distances(self, points: FloatArray) -> FloatArray:
        """:meth:`wall_distance` of each of ``points`` (n, 3), in one call."""
        return self._wall_cells.nearest(
            np.asarray(points, dtype=float).reshape(-1, 3), WALL_QUERY_M
        )

    @property
    def cells(self) -> _SurfaceCells:
        """The rock-face points sorted into cells (what the compiled scans take)."""
        return self._cells

    def surface_points(self, p: FloatArray, radius: float) -> FloatArray:
        """The rock-face points (world) within ``radius`` of ``p``."""
        return self._cells.ball(np.asarray(p, dtype=float), float(radius))

    def scan_points(
        self, p: FloatArray, radius: float, yaw: float, bodies: Bodies, sphere: FloatArray
    ) -> FloatArray:
        """What the short-range LiDAR at ``p`` sees within ``radius``, relative to ``p`` in the
        yaw frame of ``yaw``: the rock-face points, then ``sphere`` (unit points) scaled onto
        each of ``bodies`` whose reference point (the bottom of its sphere) is in range."""
        return self._cells.scan(np.asarray(p, dtype=float), float(radius), yaw, bodies, sphere)

    def raycast(self, origin: FloatArray, dirs: FloatArray, max_range: float) -> FloatArray:
        """Distance along each unit direction to the first rock voxel (inf beyond ``max_range``).

        Marches every ray in steps of a quarter voxel (a compiled loop that stops at the first
        hit): a ray can skip at most the corner of a voxel, which the sub-voxel step keeps below
        the depth camera's noise."""
        from btmission.backends._raycast import march

        vm = self.map
        return march(  # type: ignore[no-any-return]
            self._occ,
            np.asarray(origin, dtype=np.float64),
            np.ascontiguousarray(dirs, dtype=np.float64),
            np.asarray(vm.origin, dtype=np.float64),
            vm.resolution,
            vm.resolution / 4,
            float(max_range),
        )
