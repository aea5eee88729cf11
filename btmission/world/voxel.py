"""Voxel maps: a uniform 3D grid of free / occupied / unknown voxels (the D*+ planner's world).

A :class:`VoxelMap` is a ``uint8`` array ``state[ix, iy, iz]`` (C order, so the flat index of
``(ix, iy, iz)`` is ``(ix * ny + iy) * nz + iz``), a voxel edge length ``resolution`` in metres and
the world position ``origin`` of the *corner* of voxel ``(0, 0, 0)``. Voxel ``(i, j, k)`` covers
``origin + [i, i+1) × resolution`` along each axis; its centre is ``origin + (i + 0.5) ×
resolution``. z is height (metres); x, y are horizontal.

The three states follow OctoMap's, which D*+ plans on (seed 000 §IV-C2): *occupied* voxels are never
entered, *free* ones cost the step length plus the risk near rock, *unknown* ones cost ``c_u`` on
top (eq. 4, :mod:`btmission.planning.risk`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from btmission.errors import BtmissionError
from btmission.types import FloatArray

FREE: int = 0
OCCUPIED: int = 1
UNKNOWN: int = 2
STATE_NAMES: dict[int, str] = {FREE: "free", OCCUPIED: "occupied", UNKNOWN: "unknown"}

IntArray = npt.NDArray[np.int64]

_FAR_INDEX = float(2**62)
"""Voxel index given to points too far away for an int64 index (never inside a grid)."""


class MapError(BtmissionError, ValueError):
    """A map or a position on it cannot be used (bad file, point outside the map, ...)."""


def checked_shape(size: Sequence[float], resolution: float) -> tuple[int, int, int]:
    """The grid shape of ``size`` metres at ``resolution`` m, within the voxel budget
    (:func:`btmission.limits.grid_shape`); :class:`MapError` otherwise, before any allocation."""
    from btmission.limits import grid_shape

    try:
        return grid_shape(size, resolution)
    except (TypeError, ValueError) as exc:
        raise MapError(str(exc)) from None


def check_grid(shape: Sequence[int], what: str) -> None:
    """:class:`MapError` when a grid of ``shape`` would exceed the voxel budget."""
    from btmission.limits import check_voxels

    try:
        check_voxels(shape, what)
    except ValueError as exc:
        raise MapError(str(exc)) from None


@dataclass(eq=False)
class VoxelMap:
    """Occupancy voxel grid with its resolution (m) and origin (world corner of voxel 0,0,0)."""

    state: npt.NDArray[np.uint8]
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    meta: dict[str, Any] = field(default_factory=dict)
    """Free-form provenance (generator, seed, source file...); saved with ``.npz`` maps."""

    def __post_init__(self) -> None:
        st = np.asarray(self.state)
        if st.ndim != 3 or min(st.shape) < 1:
            raise MapError(f"a voxel map needs a non-empty 3D state array, got shape {st.shape}")
        if not np.issubdtype(st.dtype, np.integer) and st.dtype != np.bool_:
            raise MapError(
                f"voxel states must be integers (0 free, 1 occupied, 2 unknown), got {st.dtype}"
            )
        st = np.ascontiguousarray(st, dtype=np.uint8)
        if st.size and int(st.max()) > UNKNOWN:
            raise MapError(
                f"voxel state {int(st.max())} is not one of 0 (free), 1 (occupied), 2 (unknown)"
            )
        self.state = st
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise MapError(f"resolution must be a positive number of metres, got {self.resolution}")
        self.resolution = float(self.resolution)
        if len(self.origin) != 3 or not all(np.isfinite(self.origin)):
            shown = ", ".join(f"{float(v):g}" for v in self.origin)
            raise MapError(f"origin must be three finite numbers, got ({shown})")
        self.origin = (float(self.origin[0]), float(self.origin[1]), float(self.origin[2]))

    # ---------------------------------------------------------------- construction
    @classmethod
    def empty(
        cls,
        size: Sequence[float],
        resolution: float,
        origin: Sequence[float] = (0.0, 0.0, 0.0),
        fill: int = FREE,
    ) -> VoxelMap:
        """A map of ``size`` metres (rounded up to whole voxels), every voxel ``fill``."""
        shape = checked_shape(size, resolution)
        ox, oy, oz = (float(v) for v in origin)
        return cls(np.full(shape, fill, dtype=np.uint8), resolution, (ox, oy, oz))

    def copy(self) -> VoxelMap:
        return VoxelMap(self.state.copy(), self.resolution, self.origin, dict(self.meta))

    # ---------------------------------------------------------------- geometry
    @property
    def shape(self) -> tuple[int, int, int]:
        nx, ny, nz = self.state.shape
        return int(nx), int(ny), int(nz)

    @property
    def size(self) -> int:
        """Number of voxels."""
        return int(self.state.size)

    @property
    def extent(self) -> tuple[float, float, float]:
        """Size in metres along x, y, z."""
        nx, ny, nz = self.shape
        r = self.resolution
        return nx * r, ny * r, nz * r

    @property
    def bounds(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(min corner, max corner) in world coordinates."""
        ex = self.extent
        lo = self.origin
        return lo, (lo[0] + ex[0], lo[1] + ex[1], lo[2] + ex[2])

    def bounds_text(self) -> str:
        """The map's extent for messages, as half-open intervals: a point exactly on an upper
        edge is outside (``x [0, 12), y [0, 8), z [0, 2)``)."""
        lo, hi = self.bounds
        return ", ".join(f"{a} [{lo[i]:g}, {hi[i]:g})" for i, a in enumerate("xyz"))

    def world_to_index(self, points: npt.ArrayLike) -> IntArray:
        """Voxel indices ``(..., 3)`` containing ``points`` (no bounds check; see :meth:`contains`)."""
        p = np.asarray(points, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):  # 1e300 / 0.1: inf, clamped below
            f = np.floor((p - np.asarray(self.origin)) / self.resolution)
        # far-away, infinite or NaN points get an index far outside the grid instead of an
        # undefined (and warned about) float → int64 cast; fmin/fmax also replace NaN
        np.fmin(f, _FAR_INDEX, out=f)
        np.fmax(f, -_FAR_INDEX, out=f)
        out: IntArray = f.astype(np.int64)
        return out

    def index_to_world(self, index: npt.ArrayLike) -> FloatArray:
        """Centres of voxels ``index`` (``(..., 3)``) in world coordinates."""
        i = np.asarray(index, dtype=np.float64)
        return np.asarray(self.origin) + (i + 0.5) * self.resolution

    def in_bounds(self, index: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Whether voxel indices ``(..., 3)`` lie inside the grid."""
        i = np.asarray(index)
        out: npt.NDArray[np.bool_] = np.all((i >= 0) & (i < np.asarray(self.shape)), axis=-1)
        return out

    def contains(self, points: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Whether world ``points`` (``(..., 3)``) lie inside the map."""
        return self.in_bounds(self.world_to_index(points))

    def flat(self, index: npt.ArrayLike) -> IntArray:
        """Flat (C-order) voxel numbers of indices ``(..., 3)``."""
        i = np.asarray(index, dtype=np.int64)
        _, ny, nz = self.shape
        return np.asarray((i[..., 0] * ny + i[..., 1]) * nz + i[..., 2], dtype=np.int64)

    def unflat(self, flat: npt.ArrayLike) -> IntArray:
        """Voxel indices ``(..., 3)`` of flat voxel numbers."""
        f = np.asarray(flat, dtype=np.int64)
        return np.stack(np.unravel_index(f, self.shape), axis=-1).astype(np.int64)

    def state_at(self, point: npt.ArrayLike) -> int | None:
        """The state of the voxel containing ``point``, or None outside the map."""
        idx = self.world_to_index(point)
        if not bool(self.in_bounds(idx)):
            return None
        return int(self.state[tuple(idx)])

    # ---------------------------------------------------------------- summaries
    def counts(self) -> dict[str, int]:
        """Number of free, occupied and unknown voxels."""
        bc = np.bincount(self.state.ravel(), minlength=3)
        return {STATE_NAMES[s]: int(bc[s]) for s in (FREE, OCCUPIED, UNKNOWN)}

    def describe(self) -> str:
        """One line: shape, resolution, extent, origin and state counts."""
        nx, ny, nz = self.shape
        ex = self.extent
        c = self.counts()
        o = ", ".join(f"{v:g}" for v in self.origin)
        return (
            f"{nx}×{ny}×{nz} voxels ({self.size:,}) at {self.resolution:g} m = "
            f"{ex[0]:g} × {ex[1]:g} × {ex[2]:g} m, origin ({o}); "
            f"free {c['free']:,}, occupied {c['occupied']:,}, unknown {c['unknown']:,}"
        )

    def ground_z(self, point: npt.ArrayLike) -> float:
        """Height of the ground under ``point``: the top of the highest occupied voxel at or
        below it in its column, or the map's bottom (``origin`` z) where there is none — a map
        without a floor (a room, a warehouse) stands on z = origin."""
        p = np.asarray(point, dtype=np.float64).ravel()
        res = self.resolution
        ix = int(np.floor((p[0] - self.origin[0]) / res))
        iy = int(np.floor((p[1] - self.origin[1]) / res))
        iz = int(np.floor((p[2] - self.origin[2]) / res))
        nx, ny, nz = self.shape
        if not (0 <= ix < nx and 0 <= iy < ny) or iz < 0:
            return self.origin[2]
        hits = np.flatnonzero(self.state[ix, iy, : min(iz, nz - 1) + 1] == OCCUPIED)
        if len(hits) == 0:
            return self.origin[2]
        return self.origin[2] + (int(hits[-1]) + 1) * res

    def nearest_free(self, point: npt.ArrayLike, max_distance: float = np.inf) -> FloatArray | None:
        """Centre of the free voxel nearest to ``point`` (None if none within ``max_distance`` m).

        Used to snap a start or goal that lies in rock or just outside the map. Only free voxels
        count (never unknown ones): a snapped position must be known to be safe.
        """
        p = np.asarray(point, dtype=np.float64)
        lo = np.zeros(3, dtype=np.intp)
        grid = self.state
        if np.isfinite(max_distance):  # only the box around the point can hold the answer
            o, r = np.asarray(self.origin), self.resolution
            lo = np.clip(np.floor((p - max_distance - o) / r).astype(np.intp), 0, self.shape)
            hi = np.clip(np.floor((p + max_distance - o) / r).astype(np.intp) + 1, 0, self.shape)
            grid = grid[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        free = np.argwhere(grid == FREE) + lo
        if free.size == 0:
            return None
        centres = self.index_to_world(free)
        d2 = np.sum((centres - p) ** 2, axis=1)
        k = int(np.argmin(d2))
        if np.sqrt(d2[k]) > max_distance:
            return None
        return np.asarray(centres[k], dtype=np.float64)

    def __repr__(self) -> str:
        return f"VoxelMap({self.describe()})"
