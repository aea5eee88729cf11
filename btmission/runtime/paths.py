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
    row: int
    """Its row of :attr:`PathCosts._rows`: the path length (m) from every padded voxel to the
    goal (inf where unreachable)."""


_NO_PATH = 0
"""The row of :attr:`PathCosts._rows` that is inf everywhere: a goal with no field."""

_GOAL_SETS = 8
"""Goal tuples :meth:`PathCosts.path_costs` keeps resolved to rows (the bidders' current ones)."""

INITIAL_ROWS = 32
"""Rows of cost fields :class:`PathCosts` makes room for at once (more are made by doubling, a
copy of the rows in use: 0.2 s for 8 fields of the 2 M-voxel mine, a stall in the middle of a
run)."""


START_ESCAPE_M = 5.0
"""How far from a start in rock (deeper than ``snap_m``) or outside the map a path may begin:
the nearest voxel the planner may enter within it (:meth:`PathCosts._escape`)."""


def _fmt_point(p: Sequence[float]) -> str:
    return "[" + ", ".join(f"{float(v):.2f}" for v in p[:3]) + "]"


def field_bytes(shape: Sequence[int]) -> int:
    """Memory of one cost-to-goal field of :class:`PathCosts` on a map of ``shape`` voxels:
    float32 over the map padded by a voxel on every side."""
    return 4 * math.prod(int(n) + 2 for n in shape)


@dataclass(frozen=True)
class Route:
    """A path to a goal: waypoints from the agent's voxel to the goal's (the D*+ voxel path
    thinned by :func:`~btmission.planning.paths.thin_path`), and its length."""

    goal: Point
    waypoints: npt.NDArray[np.float64]
    length_m: float


def _cell(u: float, n: int) -> int:
    """The index along one axis of a map ``n`` voxels long for ``u`` voxels from its origin (less
    than half a voxel outside counts as the edge voxel: :meth:`PathCosts._flat`)."""
    if -0.5 <= u < 0:
        return 0
    if n <= u < n + 0.5:
        return n - 1
    return math.floor(u)


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
        reserve: int = 0,
    ) -> None:
        self.clearance_m = clearance_m
        self.snap_m = snap_m
        self.risk = risk
        self.max_bytes = max_bytes
        self.reserve = reserve
        """Fields to make room for at once (besides :data:`INITIAL_ROWS`): the goals the
        caller expects, so that their fields need no copy of the others to fit."""
        self.searches = 0
        """Backward searches run so far (one per distinct goal voxel, plus re-runs)."""
        self.version = -1
        """Counts the maps this service has planned on (:meth:`set_map`): costs are equal for
        equal :meth:`start_key` only within one version."""
        self.set_map(voxel_map)

    def set_map(self, voxel_map: VoxelMap) -> None:
        """Plan on ``voxel_map`` from now on (rock appeared or went): every field is dropped
        (searched again when next asked for) and :attr:`version` moves on."""
        self.map = voxel_map
        self._grid = (*(float(o) for o in voxel_map.origin), float(voxel_map.resolution))
        self._shape = tuple(int(n) for n in voxel_map.shape)
        self.cost_map = CostMap(inflate(voxel_map, self.clearance_m), self.risk)
        self._cost_flat = self.cost_map.flat_padded()
        """The cost map's padded costs as one flat view (:meth:`_start` reads them)."""
        self.planner = Planner(self.cost_map)
        self._fields: OrderedDict[int, _GoalField | None] = OrderedDict()
        self._field_bytes = field_bytes(voxel_map.shape)
        self._most_rows = max(1, self.max_bytes // self._field_bytes) + 2  # one over: evicting
        rows = min(self._most_rows, max(INITIAL_ROWS, self.reserve + 1))
        self._rows = np.empty((rows, self.cost_map.padded.size), np.float32)
        """Every field's lengths, one row each (row 0: no path), so that the costs to many
        goals are one gather (:meth:`path_costs`). Room for :data:`INITIAL_ROWS` from the start:
        rows not in use are never touched, so the memory behind them is not taken (it is
        reserved, not written), and the first fields of a run need no copy of the others."""
        self._rows[0] = np.inf
        self._free_rows: list[int] = []
        self._in_use = 1
        self._layout = 0
        """Moves on whenever a field's row is freed (eviction): resolved goal sets are stale."""
        self._sets: OrderedDict[int, tuple[tuple[Point, ...], int, npt.NDArray[np.intp]]] = (
            OrderedDict()
        )
        self._snapped: dict[int, int] = {}
        self._escaped: dict[tuple[int, int], int] = {}
        self._goal_voxel: dict[Point, int] = {}
        self._last_start: tuple[Point, int] | None = None
        self.version += 1

    # ---------------------------------------------------------------- indices
    def _flat(self, point: Sequence[float]) -> int:
        """Padded flat index of the voxel holding ``point`` (-1 outside the map). A point less
        than half a voxel outside counts as in the edge voxel: a real vehicle resting on a map
        whose floor is its edge reports z a few millimetres below it (estimator noise)."""
        ox, oy, oz, res = self._grid
        nx, ny, nz = self._shape
        i = _cell((point[0] - ox) / res, nx)
        j = _cell((point[1] - oy) / res, ny)
        k = _cell((point[2] - oz) / res, nz)
        if not (0 <= i < nx and 0 <= j < ny and 0 <= k < nz):
            return -1
        return ((i + 1) * (ny + 2) + (j + 1)) * (nz + 2) + (k + 1)  # padded C-order index

    def _open(self, flat: int) -> int:
        """``flat``, or the nearest voxel within ``snap_m`` the planner may enter (-1: none)."""
        if flat < 0:
            return -1
        cost = self.cost_map.flat_padded()
        if math.isfinite(cost[flat]):  # (a scalar: math's test, not a numpy ufunc call)
            return flat
        hit = self._snapped.get(flat)
        if hit is not None:
            return hit
        idx = self.cost_map.unpad_index(np.array([flat]))[0]
        best = self._nearest_open(idx, self.snap_m)
        self._snapped[flat] = best
        return best

    def _nearest_open(self, idx: npt.NDArray[np.intp], radius_m: float) -> int:
        """The padded index of the voxel the planner may enter nearest to voxel ``idx``, within
        ``radius_m`` (-1: none). Searches the cube around it only: bounded."""
        vm = self.map
        k = math.ceil(radius_m / vm.resolution)
        lo = np.maximum(idx - k, 0)
        hi = np.minimum(idx + k + 1, vm.shape)
        window = self.cost_map.voxel_cost[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        cand = np.argwhere(np.isfinite(window))
        if len(cand):
            d2 = np.sum((cand + lo - idx) ** 2, axis=1)
            j = int(np.argmin(d2))
            if math.sqrt(float(d2[j])) * vm.resolution <= radius_m:
                return int(self.cost_map.padded_index(cand[j] + lo))
        return -1

    def _escape(self, start: Sequence[float]) -> int:
        """Where a vehicle the map puts in rock (or just outside the map) plans from: the
        nearest voxel the planner may enter within :data:`START_ESCAPE_M` (-1: none). A failsafe
        descent on a real autopilot left a drone where the map has rock (the autopilot's ground
        is not the map's); planning from nowhere failed on every tick, 1,471 times in one run."""
        ox, oy, oz, res = self._grid
        u = np.array([(float(c) - o) / res for c, o in zip(start[:3], (ox, oy, oz), strict=True)])
        idx = np.clip(np.floor(u), 0, np.array(self._shape) - 1).astype(np.intp)
        outside_m = float(np.linalg.norm(u - np.clip(u, 0, self._shape))) * res
        radius = START_ESCAPE_M - outside_m  # from the start itself, not the map's edge
        if radius < 0:
            return -1
        key = (int(self.cost_map.padded_index(idx)), round(radius / res))
        hit = self._escaped.get(key)
        if hit is None:
            hit = self._escaped[key] = self._nearest_open(idx, radius)
        return hit

    def start_key(self, start: Point) -> tuple[int, int]:
        """What :meth:`path_costs` from ``start`` depends on: the open voxel it starts from and
        the map :attr:`version`. Starts with equal keys have equal costs to every goal (a bidder
        that has not moved to another voxel may send its previous costs again)."""
        return (self.version, self._start(start))

    def _start(self, start: Sequence[float]) -> int:
        """The open voxel a path from ``start`` begins at: :meth:`_open` of :meth:`_flat`, with
        their common case — a start inside the map, in a voxel the planner may enter — in line
        (every bidder asks every round, from a position it has not stood at before)."""
        key = (x, y, z) = (float(start[0]), float(start[1]), float(start[2]))
        last = self._last_start
        if last is not None and last[0] == key:
            return last[1]
        ox, oy, oz, res = self._grid
        nx, ny, nz = self._shape
        u, v, w = (x - ox) / res, (y - oy) / res, (z - oz) / res  # (as _flat computes them)
        if 0.0 <= u < nx and 0.0 <= v < ny and 0.0 <= w < nz:  # int() is floor() here
            flat = ((int(u) + 1) * (ny + 2) + (int(v) + 1)) * (nz + 2) + (int(w) + 1)
            f = flat if math.isfinite(self._cost_flat[flat]) else self._open(flat)
        else:
            f = self._open(self._flat(key))
        if f < 0:  # deep in rock, or outside the map: out to the nearest free voxel
            f = self._escape(key)
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
            row = self._new_row()
            pad = self._rows[row].reshape(self.cost_map.padded.shape)
            pad[...] = np.inf
            pad[1:-1, 1:-1, 1:-1] = field.length_m
            entry = _GoalField(field, row)
            field.drop_dense()  # keep the float32 copy only
        self._fields[f] = entry
        self._evict()
        return entry

    def _new_row(self) -> int:
        """A free row of :attr:`_rows` (grown by doubling, within ``max_bytes``)."""
        if self._free_rows:
            return self._free_rows.pop()
        n, size = self._rows.shape
        if self._in_use == n:
            grown = np.empty((max(n + 1, min(2 * n, self._most_rows)), size), dtype=np.float32)
            grown[:n] = self._rows
            self._rows = grown
        self._in_use += 1
        return self._in_use - 1

    def _evict(self) -> None:
        per = self._field_bytes
        while len(self._fields) > 1 and len(self._fields) * per > self.max_bytes:
            _, old = self._fields.popitem(last=False)
            if old is not None:
                self._free_rows.append(old.row)
                self._layout += 1

    def _row_of(self, goal: Point) -> int:
        entry = self._goal(goal)
        return _NO_PATH if entry is None else entry.row

    def _goal_rows(self, goals: Sequence[Point]) -> npt.NDArray[np.intp] | None:
        """Each goal's row of :attr:`_rows` (None: its fields do not all fit in ``max_bytes``
        at once). A tuple of goals is remembered by identity (a bidder passes the same one
        every round until the announced tasks change)."""
        key = id(goals)
        hit = self._sets.get(key)
        if hit is not None and hit[0] is goals and hit[1] == self._layout:
            return hit[2]
        layout = self._layout
        rows = np.fromiter((self._row_of(g) for g in goals), dtype=np.intp, count=len(goals))
        if self._layout != layout:  # a field was evicted while others were searched
            return None
        if isinstance(goals, tuple):
            self._sets[key] = (goals, layout, rows)
            self._sets.move_to_end(key)
            if len(self._sets) > _GOAL_SETS:
                self._sets.popitem(last=False)
        return rows

    # ---------------------------------------------------------------- queries
    def path_cost(self, start: Point, goal: Point) -> float:
        """Length (m) of the D*+ path from ``start`` to ``goal`` (inf if there is none)."""
        s = self._start(start)
        if s < 0:
            return math.inf
        entry = self._goal(goal)
        if entry is None:
            return math.inf
        return float(self._rows[entry.row, s])

    def path_costs(self, start: Point, goals: Sequence[Point]) -> npt.NDArray[np.float64]:
        """:meth:`path_cost` to each of ``goals``: the start's voxel is found once and the
        lengths are one gather from the stacked fields."""
        s = self._start(start)
        if s < 0:
            return np.full(len(goals), np.inf)
        rows = self._goal_rows(goals)
        if rows is not None:
            out: npt.NDArray[np.float64] = (
                self._rows[: self._in_use, s].take(rows).astype(np.float64)
            )
            return out
        out = np.full(len(goals), np.inf)  # more fields than max_bytes holds: one at a time
        for i, g in enumerate(goals):
            entry = self._goal(g)
            if entry is not None:
                out[i] = self._rows[entry.row, s]
        return out

    def route(self, start: Point, goal: Point) -> Route | None:
        """The D*+ path from ``start`` to ``goal`` (None if there is none)."""
        entry = self._goal(goal)
        if entry is None:
            return None
        s = self._start(start)
        length = float(self._rows[entry.row, s]) if s >= 0 else math.inf
        if not math.isfinite(length):
            return None
        centre = self.map.index_to_world(self.cost_map.unpad_index(np.array([s]))[0])
        pts = entry.field.path_to(centre)
        if len(pts) == 0:
            return None
        pts = thin_path(self.cost_map, pts)  # waypoints where a straight line would be worse
        return Route((float(goal[0]), float(goal[1]), float(goal[2])), pts, length)

    def start_problem(self, start: Sequence[float]) -> str | None:
        """Why no path can begin at ``start`` (in rock or outside the map with no voxel the
        planner may enter within :data:`START_ESCAPE_M`), or None."""
        if self._start(start) >= 0:
            return None
        where = self.problem(start) or "in the clearance margin of rock"
        return (
            f"the vehicle is {where} at {_fmt_point(start)} and no free voxel is within "
            f"{START_ESCAPE_M:g} m to plan from"
        )

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
