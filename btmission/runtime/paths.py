"""Risk-aware path costs and paths for bids and path following, from D*+ cost-to-goal fields.

Seed 000 §IV-B2: an agent bids the length of the D*+ path from where it is to the task; seed 003
eq. 8-10 builds every bid from such path costs. Goals are fixed (a task's location, its pick-up and
drop-off) while agents move, so instead of one search from each agent every round the service keeps,
for each goal, **one backward one-to-all search** — the cost-to-goal field that D* itself maintains
(:meth:`~btmission.planning.dstar.Planner.one_to_all` with ``reverse=True``). Then

* a bid is a lookup: the path length from any voxel to that goal;
* a path is a walk down the same field's tree from the agent's voxel (the optimal D*+ path under
  eq. 3-4, identical to what :meth:`Planner.plan` would return in cost);

and one field serves every agent and every round until the map changes. Fields are kept per goal
voxel, least recently used first out, within ``max_bytes``.

:class:`PathCosts` implements the allocation's
:class:`~btmission.allocation.bidder.CostProvider` protocol (``path_cost(start, goal)``).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from btmission.planning.dstar import CostField, Planner
from btmission.planning.paths import thin_path
from btmission.planning.risk import CostMap, RiskParams, distance_to_rock
from btmission.world.voxel import OCCUPIED, VoxelMap

Point = tuple[float, float, float]


@dataclass
class _GoalField:
    field: CostField
    length: npt.NDArray[np.float32]
    """Path length (m) from every padded voxel to the goal (inf where unreachable)."""


@dataclass(frozen=True)
class Route:
    """A path to a goal: waypoints from the agent's voxel to the goal's (the D*+ voxel path
    thinned by :func:`~btmission.planning.paths.thin_path`), and its length."""

    goal: Point
    waypoints: npt.NDArray[np.float64]
    length_m: float


class PathCosts:
    """D*+ path lengths and paths to goals, one backward search per goal (module docstring).

    Plans on the map *inflated* by ``clearance_m`` (voxels whose centre lies closer than that to
    rock are treated as rock), so that a path is safe for a vehicle of that radius — seed 003
    §V-B's "robot-safe path, where the size of the robotic platform is taken into account". A
    start or goal in the inflated margin (a drone standing on the floor) is moved to the nearest
    open voxel within ``snap_m``; a goal in real rock or outside the map has no path.
    """

    def __init__(
        self,
        voxel_map: VoxelMap,
        risk: RiskParams | None = None,
        *,
        clearance_m: float = 0.0,
        snap_m: float = 1.5,
        max_bytes: int = 1 << 30,
    ) -> None:
        self.map = voxel_map
        self.clearance_m = clearance_m
        self.snap_m = snap_m
        self.cost_map = CostMap(inflate(voxel_map, clearance_m), risk)
        self.planner = Planner(self.cost_map)
        self.max_bytes = max_bytes
        self._fields: OrderedDict[int, _GoalField | None] = OrderedDict()
        self._snapped: dict[int, int] = {}
        self._goal_voxel: dict[Point, int] = {}
        self._last_start: tuple[Point, int] | None = None
        self.searches = 0
        """Backward searches run so far (one per distinct goal voxel, plus re-runs)."""

    # ---------------------------------------------------------------- indices
    def _flat(self, point: Sequence[float]) -> int:
        """Padded flat index of the voxel holding ``point`` (-1 outside the map). A point less
        than half a voxel outside counts as in the edge voxel: a real vehicle resting on a map
        whose floor is its edge reports z a few millimetres below it (estimator noise)."""
        vm = self.map
        res = vm.resolution
        nx, ny, nz = vm.shape
        idx = []
        for axis, n in enumerate((nx, ny, nz)):
            u = (point[axis] - vm.origin[axis]) / res
            if -0.5 <= u < 0:
                u = 0.0
            elif n <= u < n + 0.5:
                u = n - 1.0
            idx.append(math.floor(u))
        i, j, k = idx
        if not (0 <= i < nx and 0 <= j < ny and 0 <= k < nz):
            return -1
        return ((i + 1) * (ny + 2) + (j + 1)) * (nz + 2) + (k + 1)  # padded C-order index

    def _open(self, flat: int) -> int:
        """``flat``, or the nearest voxel within ``snap_m`` the planner may enter (-1: none)."""
        if flat < 0:
            return -1
        cost = self.cost_map.flat_padded()
        if np.isfinite(cost[flat]):
            return flat
        hit = self._snapped.get(flat)
        if hit is not None:
            return hit
        vm = self.map
        idx = self.cost_map.unpad_index(np.array([flat]))[0]
        k = math.ceil(self.snap_m / vm.resolution)
        lo = np.maximum(idx - k, 0)
        hi = np.minimum(idx + k + 1, vm.shape)
        window = self.cost_map.voxel_cost[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        cand = np.argwhere(np.isfinite(window))
        best = -1
        if len(cand):
            d2 = np.sum((cand + lo - idx) ** 2, axis=1)
            j = int(np.argmin(d2))
            if math.sqrt(float(d2[j])) * vm.resolution <= self.snap_m:
                best = int(self.cost_map.padded_index(cand[j] + lo))
        self._snapped[flat] = best
        return best

    def _start(self, start: Sequence[float]) -> int:
        key = (float(start[0]), float(start[1]), float(start[2]))
        if self._last_start is not None and self._last_start[0] == key:
            return self._last_start[1]
        f = self._open(self._flat(key))
        self._last_start = (key, f)
        return f

    def _goal(self, goal: Sequence[float]) -> _GoalField | None:
        """The cost-to-goal field of ``goal``'s voxel (None: outside the map or in rock)."""
        key = (float(goal[0]), float(goal[1]), float(goal[2]))
        f = self._goal_voxel.get(key)
        if f is None:
            f = self._goal_voxel[key] = self._flat(goal)
        if f in self._fields:
            self._fields.move_to_end(f)
            return self._fields[f]
        entry: _GoalField | None = None
        root = self._open(f) if self.problem(goal) is None else -1
        if root >= 0:
            centre = self.map.index_to_world(self.cost_map.unpad_index(np.array([root]))[0])
            field = self.planner.one_to_all(centre, reverse=True)
            self.searches += 1
            pad = np.full(self.cost_map.padded.shape, np.inf, dtype=np.float32)
            pad[1:-1, 1:-1, 1:-1] = field.length_m
            entry = _GoalField(field, pad.ravel())
            field.drop_dense()  # keep the float32 copy only
        self._fields[f] = entry
        self._evict()
        return entry

    def _evict(self) -> None:
        per = self.cost_map.padded.size * 4
        while len(self._fields) > 1 and len(self._fields) * per > self.max_bytes:
            self._fields.popitem(last=False)

    # ---------------------------------------------------------------- queries
    def path_cost(self, start: Point, goal: Point) -> float:
        """Length (m) of the D*+ path from ``start`` to ``goal`` (inf if there is none)."""
        s = self._start(start)
        if s < 0:
            return math.inf
        entry = self._goal(goal)
        if entry is None:
            return math.inf
        return float(entry.length[s])

    def path_costs(self, start: Point, goals: Sequence[Point]) -> npt.NDArray[np.float64]:
        """:meth:`path_cost` to each of ``goals`` (the start's voxel is found once)."""
        out = np.full(len(goals), np.inf)
        s = self._start(start)
        if s < 0:
            return out
        for i, g in enumerate(goals):
            entry = self._goal(g)
            if entry is not None:
                out[i] = entry.length[s]
        return out

    def route(self, start: Point, goal: Point) -> Route | None:
        """The D*+ path from ``start`` to ``goal`` (None if there is none)."""
        entry = self._goal(goal)
        if entry is None:
            return None
        s = self._start(start)
        if s < 0 or not math.isfinite(float(entry.length[s])):
            return None
        centre = self.map.index_to_world(self.cost_map.unpad_index(np.array([s]))[0])
        pts = entry.field.path_to(centre)
        if len(pts) == 0:
            return None
        pts = thin_path(self.cost_map, pts)  # waypoints where a straight line would be worse
        return Route((float(goal[0]), float(goal[1]), float(goal[2])), pts, float(entry.length[s]))

    def problem(self, point: Sequence[float]) -> str | None:
        """Why ``point`` cannot be a goal (outside the map, inside rock), or None."""
        vm = self.map
        p = np.asarray(point, dtype=np.float64)
        if not bool(vm.contains(p[None, :])[0]):
            return f"outside the map ({vm.bounds_text()})"
        if vm.state_at(p) == OCCUPIED:
            return "inside rock"
        return None


def inflate(voxel_map: VoxelMap, clearance_m: float) -> VoxelMap:
    """``voxel_map`` with every voxel whose centre is closer than ``clearance_m`` to the rock
    surface made rock (the surface lies half a voxel from a rock voxel's centre). The
    configuration space of a vehicle of that radius."""
    if clearance_m <= 0:
        return voxel_map
    res = voxel_map.resolution
    d = distance_to_rock(voxel_map.state, res, clearance_m + res)
    state = voxel_map.state.copy()
    state[(d - res / 2 < clearance_m) & (state != OCCUPIED)] = OCCUPIED
    return VoxelMap(state, res, voxel_map.origin, dict(voxel_map.meta, inflated_m=clearance_m))
