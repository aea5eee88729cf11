"""The D*+ risk layer: the cost of entering each voxel (seed 000 §IV-C2, eq. 3-4).

For every voxel, with ``d`` its distance (m) to the nearest occupied voxel and ``r`` the radius in
which risk is evaluated::

    c_r = c_u / (d + 1)   if d < r,   else 0                                   (eq. 3)
    c   = c_r + c_d               if the voxel is free
    c   = c_u + c_r + c_d         if the voxel is unknown                      (eq. 4)

``c_d`` is the length of the step into the voxel (resolution × 1, √2 or √3 on the 26-connected
grid), so a path's cost is its length plus the risk of every voxel it enters. This module stores the
per-voxel part ``c_r + c_u·[unknown]`` (:attr:`CostMap.voxel_cost`); the planner adds ``c_d`` per
step. Occupied voxels are never entered: their cost is ``inf`` (they are not in the graph, unlike
the "huge cost" walls of the D*+ reference code, DESIGN §8), and so is the one-voxel border around
the grid (the planner's array is padded so its inner loop needs no bounds checks).

``d`` is the Euclidean distance between voxel centres in metres (``scipy.ndimage
.distance_transform_edt``), so a free voxel touching rock has ``d`` = resolution. Voxels outside the
map do not count as rock: for a mine the rock is in the map; an ``empty`` world has no walls.

Defaults: ``r = 1.5 m`` (in a 4-5 m drift the middle metre or two is risk-free, so a drone keeps to
the centre line and pays more the closer it gets to a wall, floor or roof) and ``c_u = 10`` (metres
of travel per voxel entered: an unknown voxel is worth a 10 m detour, a free voxel touching rock
``10 / 1.5 ≈ 6.7 m`` at 0.5 m resolution). The paper gives no values; the D*+ reference code uses a
2-voxel risk band. Because the costs are per voxel entered (eq. 4 sums them over the voxels of the
path), their weight against distance grows as the resolution gets finer.

Local updates: when voxels change state, only distances within ``r`` of the change can change, and
those depend only on rock within ``2r`` of it, so :meth:`CostMap.set_states` recomputes the distance
transform on that window alone and reports which voxel costs changed (for incremental replanning).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from btmission.world.voxel import OCCUPIED, UNKNOWN, MapError, VoxelMap

DEFAULT_RADIUS_M = 1.5
DEFAULT_UNKNOWN_COST = 10.0
MAX_UNKNOWN_COST = 1e5


@dataclass(frozen=True)
class RiskParams:
    """The two parameters of eq. 3-4, with the paper's meaning."""

    radius_m: float = DEFAULT_RADIUS_M
    """r: voxels closer than this to an occupied voxel carry the risk cost c_r."""
    unknown_cost: float = DEFAULT_UNKNOWN_COST
    """c_u: extra cost of entering an unknown voxel, and the scale of c_r = c_u / (d + 1)."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius_m) and self.radius_m >= 0):
            raise MapError(f"risk radius r must be a finite number ≥ 0 m, got {self.radius_m}")
        if not (np.isfinite(self.unknown_cost) and 0 <= self.unknown_cost <= MAX_UNKNOWN_COST):
            raise MapError(
                f"unknown cost c_u must be a number in [0, {MAX_UNKNOWN_COST:g}], got "
                f"{self.unknown_cost} (beyond that paths no longer change, searches only slow down)"
            )


def risk_cost(distance: npt.ArrayLike, params: RiskParams) -> npt.NDArray[np.float64]:
    """Eq. 3: ``c_r = c_u / (d + 1)`` where ``d < r``, else 0 (``d`` in metres)."""
    d = np.asarray(distance, dtype=np.float64)
    return np.where(d < params.radius_m, params.unknown_cost / (d + 1.0), 0.0)


def voxel_costs(
    state: npt.NDArray[np.uint8], distance: npt.ArrayLike, params: RiskParams
) -> npt.NDArray[np.float64]:
    """Eq. 4 without the step length: ``c_r (+ c_u if unknown)``; ``inf`` for occupied voxels."""
    c = risk_cost(distance, params)
    c = c + np.where(state == UNKNOWN, params.unknown_cost, 0.0)
    return np.where(state == OCCUPIED, np.inf, c)


def distance_to_rock(
    state: npt.NDArray[np.uint8], resolution: float, cap: float
) -> npt.NDArray[np.float32]:
    """Distance (m) from each voxel centre to the nearest occupied voxel centre, capped at ``cap``
    (0 inside rock, ``cap`` where no rock is nearer than ``cap`` or the array holds no rock)."""
    from scipy import ndimage

    occ = state == OCCUPIED
    if not occ.any():
        return np.full(state.shape, cap, dtype=np.float32)
    d = ndimage.distance_transform_edt(~occ, sampling=resolution)
    out: npt.NDArray[np.float32] = np.minimum(d, cap).astype(np.float32)
    return out


class CostMap:
    """A voxel map with its risk layer, kept in the padded flat layout the planner searches.

    ``padded`` is ``(nx+2, ny+2, nz+2)`` float64: ``inf`` on the border and in rock, else
    ``c_r + c_u·[unknown]``. ``voxel_cost`` is its inner view (same shape as the map), ``distance``
    the capped distance to rock (m). ``version`` counts the changes made with :meth:`set_states`.
    """

    def __init__(self, voxel_map: VoxelMap, params: RiskParams | None = None):
        self.map = voxel_map
        self.params = params or RiskParams()
        nx, ny, nz = voxel_map.shape
        self.padded = np.full((nx + 2, ny + 2, nz + 2), np.inf, dtype=np.float64)
        self.voxel_cost = self.padded[1:-1, 1:-1, 1:-1]
        self.distance = np.zeros(voxel_map.shape, dtype=np.float32)
        self.version = 0
        self.rebuild()

    @property
    def resolution(self) -> float:
        return self.map.resolution

    @property
    def _cap(self) -> float:
        # Distances ≥ r all give c_r = 0; keep one voxel beyond r so "d < r" stays exact.
        return float(self.params.radius_m + self.map.resolution)

    def rebuild(self) -> None:
        """Recompute the whole layer from the map (distance transform over the full grid)."""
        if self.params.radius_m == 0 or self.params.unknown_cost == 0:
            self.distance[...] = self._cap  # c_r is 0 everywhere: no distances needed
        else:
            self.distance[...] = distance_to_rock(self.map.state, self.map.resolution, self._cap)
        self.voxel_cost[...] = voxel_costs(self.map.state, self.distance, self.params)
        self.version += 1

    def flat_padded(self) -> npt.NDArray[np.float64]:
        """The padded cost array as one flat view (what the numba kernels index)."""
        return self.padded.reshape(-1)

    def padded_index(self, index: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """Flat padded numbers of voxel indices ``(..., 3)`` of the map."""
        i = np.asarray(index, dtype=np.int64) + 1
        _, py, pz = self.padded.shape
        return np.asarray((i[..., 0] * py + i[..., 1]) * pz + i[..., 2], dtype=np.int64)

    def unpad_index(self, flat: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """Map voxel indices ``(..., 3)`` of flat padded numbers."""
        f = np.asarray(flat, dtype=np.int64)
        return np.stack(np.unravel_index(f, self.padded.shape), axis=-1).astype(np.int64) - 1

    def set_states(
        self, index: npt.ArrayLike, new_state: int | npt.ArrayLike
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
        """Change the state of voxels ``index`` (``(N, 3)``) and update the layer around them.

        Returns the flat padded numbers of the voxels whose cost changed and their *old* costs
        (what :class:`~btmission.planning.dstar.IncrementalPlanner` needs to repair its search).
        """
        idx = np.asarray(index, dtype=np.int64).reshape(-1, 3)
        if len(idx) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        if not np.all(self.map.in_bounds(idx)):
            raise MapError("set_states: voxel index outside the map")
        new = np.broadcast_to(np.asarray(new_state, dtype=np.uint8), (len(idx),))
        if np.any(new > UNKNOWN):
            raise MapError("set_states: states are 0 (free), 1 (occupied) or 2 (unknown)")
        st = self.map.state
        st[idx[:, 0], idx[:, 1], idx[:, 2]] = new
        # Window: the change's bounding box ± cap (the only capped distances that can change)
        # ± cap again (the rock those voxels can see within cap).
        reach = int(np.ceil(self._cap / self.map.resolution - 1e-9))
        shape = np.asarray(self.map.shape)
        lo_in = np.maximum(idx.min(axis=0) - reach, 0)
        hi_in = np.minimum(idx.max(axis=0) + reach + 1, shape)
        lo_out = np.maximum(lo_in - reach, 0)
        hi_out = np.minimum(hi_in + reach, shape)
        outer = tuple(slice(int(a), int(b)) for a, b in zip(lo_out, hi_out))
        inner = tuple(slice(int(a - o), int(b - o)) for a, b, o in zip(lo_in, hi_in, lo_out))
        dist = distance_to_rock(st[outer], self.map.resolution, self._cap)[inner]
        region = tuple(slice(int(a), int(b)) for a, b in zip(lo_in, hi_in))
        self.distance[region] = dist
        new_cost = voxel_costs(st[region], dist, self.params)
        old_cost = self.voxel_cost[region]
        changed = np.argwhere(~((new_cost == old_cost) | (np.isinf(new_cost) & np.isinf(old_cost))))
        old_vals = old_cost[changed[:, 0], changed[:, 1], changed[:, 2]].copy()
        self.voxel_cost[region] = new_cost
        self.version += 1
        return self.padded_index(changed + lo_in), old_vals

    def set_box(
        self, lo: npt.ArrayLike, hi: npt.ArrayLike, new_state: int
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
        """:meth:`set_states` on every voxel whose centre lies in the world box ``[lo, hi]``."""
        vm = self.map
        i0 = np.maximum(np.ceil((np.asarray(lo) - vm.origin) / vm.resolution - 0.5), 0).astype(int)
        i1 = np.minimum(
            np.floor((np.asarray(hi) - vm.origin) / vm.resolution - 0.5), np.asarray(vm.shape) - 1
        ).astype(int)
        if np.any(i1 < i0):
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        grid = np.mgrid[i0[0] : i1[0] + 1, i0[1] : i1[1] + 1, i0[2] : i1[2] + 1]
        return self.set_states(grid.reshape(3, -1).T, new_state)
