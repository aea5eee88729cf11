"""The D*+ planner: optimal risk-aware paths on the 26-connected voxel grid.

D*+ (Karlsson et al., seed 000 [35]) plans the cheapest path P between two voxels, minimising the
sum of the traversal costs of the voxels it enters, ``Σ_{c_i ∈ P} c_i`` with ``c`` from eq. 3-4
(:mod:`btmission.planning.risk`). Here that is:

* :meth:`Planner.plan` — one query, A* with the octile-distance heuristic (admissible: every step
  costs at least its length), returning the path, its cost and its length;
* :meth:`Planner.one_to_all` — Dijkstra from one start to every voxel: what an agent needs to bid on
  many tasks with a single search (seed 000 §IV-B2: the bid is the length of the risk-aware path);
  :meth:`Planner.costs_to` stops as soon as the given goals are settled;
* :class:`IncrementalPlanner` — replanning toward one goal after local map changes
  (:meth:`CostMap.set_states`) with D* Lite semantics: the same result as planning from scratch,
  far less work. It keeps the cost-to-goal field of its last fresh search and repairs from it
  (``method="field"``, the default) or runs D* Lite itself (Koenig & Likhachev 2002, the algorithm
  D*+ builds on; ``method="dstar-lite"``); a large change falls back to a fresh search.

Start and goal are world points. A point outside the map or inside rock is an error
(:class:`PlanningError`) unless ``snap=True``, which moves it to the nearest free voxel (within
``snap_radius_m``) and says so in :attr:`PlanResult.warnings`. Occupied voxels are never entered.

The searches run as numba kernels (:mod:`._kernels`) on the flat padded cost array; a pure-Python
reference lives in :mod:`.reference` for the tests.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from btmission.planning.risk import CostMap
from btmission.world.voxel import MapError

Point = npt.ArrayLike
_NO_FIELD = np.zeros(0)
_NO_INT = np.zeros(0, dtype=np.int32)
_NO_TREE = (_NO_INT, _NO_INT, 0, _NO_INT, _NO_INT)


class PlanningError(MapError):
    """A start or goal cannot be used (outside the map, in rock), or no path exists."""


@dataclass(frozen=True)
class PlanResult:
    """A planned path: voxel centres from start to goal, its cost (eq. 4 summed) and length (m)."""

    path: npt.NDArray[np.float64]
    """(N, 3) world coordinates of the voxel centres, start first."""
    voxels: npt.NDArray[np.int64]
    """(N, 3) voxel indices of the same."""
    cost: float
    length_m: float
    expanded: int
    """Voxels the search expanded (a measure of work)."""
    start: tuple[float, float, float]
    goal: tuple[float, float, float]
    warnings: tuple[str, ...] = ()

    @property
    def found(self) -> bool:
        return bool(np.isfinite(self.cost))


class CostField:
    """One-to-all result: optimal cost and path length (m) from the start to every voxel.

    A *reverse* field (``Planner.one_to_all(goal, reverse=True)``) holds the cost and length of
    the optimal path from every voxel *to* its root instead: the cost-to-goal field D* keeps.
    :meth:`at` then answers "how far from here to the goal" and :meth:`path_to` gives the path
    from the point to the goal.

    :meth:`at` and :meth:`path_to` answer single voxels; :attr:`cost` and :attr:`length_m` build
    full arrays of the map's shape on first use (``inf`` where unreachable and in rock).

    The field reads the planner's work arrays directly, so creating it copies nothing. Before the
    planner searches again it copies the reached voxels out (in voxel order, about 1.5 ms for
    a 2 M-voxel mine) so that the field stays valid however long it is kept.
    """

    def __init__(
        self,
        planner: Planner,
        start: tuple[float, float, float],
        reached: int,
        expanded: int,
        reverse: bool = False,
    ):
        self._planner = planner
        self.start = start
        self.reverse = reverse
        """True when the field holds costs *to* ``start`` (see the class docstring)."""
        self.reached = reached
        """Number of voxels with a finite cost."""
        self.expanded = expanded
        self._ids: npt.NDArray[np.int64] | None = None  # set when detached
        self._g = self._length = np.zeros(0)
        self._parent = np.zeros(0, dtype=np.int64)
        self._full: dict[str, npt.NDArray[np.float64]] = {}

    def _detach(self) -> None:
        """Copy the reached voxels out of the planner's work arrays (before they are reused)."""
        if self._ids is not None:
            return
        self._ids, self._g, self._length, self._parent = self._planner._last_tree()

    def _dense(self, name: str) -> npt.NDArray[np.float64]:
        if name not in self._full:
            cm = self._planner.cost_map
            if self._ids is None:  # g is inf wherever the last search did not reach
                g, _, length = self._planner._work()[:3]
                full = g.copy() if name == "cost" else np.where(g < np.inf, length, np.inf)
            else:
                full = np.full(cm.padded.size, np.inf)
                full[self._ids] = self._g if name == "cost" else self._length
            self._full[name] = full.reshape(cm.padded.shape)[1:-1, 1:-1, 1:-1]
        return self._full[name]

    def drop_dense(self) -> None:
        """Forget the full arrays built by :attr:`cost` / :attr:`length_m` (memory)."""
        self._full.clear()

    @property
    def cost(self) -> npt.NDArray[np.float64]:
        """Optimal cost from the start to each voxel (map-shaped)."""
        return self._dense("cost")

    @property
    def length_m(self) -> npt.NDArray[np.float64]:
        """Length (m) of the optimal path to each voxel (map-shaped)."""
        return self._dense("length")

    def _flat(self, point: Point) -> int | None:
        cm = self._planner.cost_map
        idx = cm.map.world_to_index(point)
        return int(cm.padded_index(idx)) if bool(cm.map.in_bounds(idx)) else None

    def _slot(self, flat: int) -> int | None:
        assert self._ids is not None
        k = int(np.searchsorted(self._ids, flat))
        return k if k < len(self._ids) and self._ids[k] == flat else None

    def at(self, point: Point) -> tuple[float, float]:
        """(cost, length in m) of the optimal path to the voxel containing ``point`` (inf, inf if
        unreachable, in rock or outside the map)."""
        f = self._flat(point)
        if f is None:
            return np.inf, np.inf
        if self._ids is None:
            g, _, length = self._planner._work()[:3]
            if g[f] == np.inf:
                return np.inf, np.inf
            return float(g[f]), float(length[f])
        k = self._slot(f)
        return (np.inf, np.inf) if k is None else (float(self._g[k]), float(self._length[k]))

    def path_to(self, point: Point) -> npt.NDArray[np.float64]:
        """World path (voxel centres) from the start to ``point`` ((0, 3) if unreachable); for a
        reverse field, from ``point`` to the root."""
        from btmission.planning import _kernels as K

        cm = self._planner.cost_map
        f = self._flat(point)
        if f is None or not np.isfinite(self.at(point)[0]):
            return np.zeros((0, 3))
        if self._ids is None:
            parent = self._planner._work()[1]
            flat = K.trace(parent, f, parent.size)
        else:
            chain: list[int] = []
            k = self._slot(f)
            while k is not None:
                chain.append(int(self._ids[k]))
                p = int(self._parent[k])
                k = self._slot(p) if p >= 0 else None
            flat = np.asarray(chain[::-1], dtype=np.int64)
        if self.reverse:  # parents point toward the root: the chain runs point → root
            flat = flat[::-1]
        return cm.map.index_to_world(cm.unpad_index(flat))


def neighbour_table(
    padded_shape: tuple[int, int, int], resolution: float
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Flat offsets and step lengths (m) of the 26 neighbours in a C-order padded grid."""
    _, py, pz = padded_shape
    offs: list[int] = []
    steps: list[float] = []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                if dx == dy == dz == 0:
                    continue
                offs.append((dx * py + dy) * pz + dz)
                steps.append(resolution * float(np.sqrt(dx * dx + dy * dy + dz * dz)))
    return np.asarray(offs, dtype=np.int64), np.asarray(steps, dtype=np.float64)


class Planner:
    """Single queries and one-to-all searches on a :class:`CostMap` (see the module docstring)."""

    def __init__(self, cost_map: CostMap):
        if cost_map.padded.size >= 2**31 - 1:
            raise MapError(
                f"a map of {cost_map.map.size:,} voxels is too large to plan on (the search "
                "indexes voxels with 32-bit integers): use a coarser resolution or a smaller map"
            )
        self.cost_map = cost_map
        self._off, self._step = neighbour_table(cost_map.padded.shape, cost_map.resolution)
        _, py, pz = cost_map.padded.shape
        self._sx, self._sy = py * pz, pz
        # Bucket queue (see _kernels.search): width = shortest step; enough buckets for the
        # largest key increase of one step (step + c_u + c_r, twice that with the heuristic).
        res = cost_map.resolution
        c_u = cost_map.params.unknown_cost
        worst = float(self._step.max()) + c_u + c_u / (1.0 + res)
        self._delta = float(self._step.min())
        need = int(np.ceil(2.0 * worst / self._delta)) + 3
        self._n_buckets = 1 << max(4, (need - 1).bit_length())  # a power of two: bucket & mask
        self._w: tuple[npt.NDArray[Any], ...] | None = None
        self._pool: tuple[npt.NDArray[np.int32], npt.NDArray[np.float64]] | None = None
        self._run = 0
        self._n_reached = 0  # voxels the last search reached (touched[:n]): reset by the next
        self._live: weakref.ref[CostField] | None = None
        self._best_node = -1

    # -------------------------------------------------------------- endpoints
    def resolve(
        self, point: Point, what: str, *, snap: bool = False, snap_radius_m: float = 5.0
    ) -> tuple[int, tuple[float, float, float], str | None]:
        """Padded flat voxel of ``point`` and the point used; a warning when it was snapped.

        Raises :class:`PlanningError` when the point is outside the map or in rock (unless
        ``snap``, and then only when no free voxel lies within ``snap_radius_m``).
        """
        p = np.asarray(point, dtype=np.float64).ravel()
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise PlanningError(f"{what} must be three finite numbers x, y, z, got {list(p)}")
        vm = self.cost_map.map
        idx = vm.world_to_index(p)
        inside = bool(vm.in_bounds(idx))
        problem = None
        if not inside:
            problem = f"{what} ({_fmt(p)}) is outside the map ({vm.bounds_text()})"
        elif not np.isfinite(self.cost_map.voxel_cost[tuple(idx)]):
            problem = f"{what} ({_fmt(p)}) is inside rock (an occupied voxel)"
        if problem is None:
            return (
                int(self.cost_map.padded_index(idx)),
                (float(p[0]), float(p[1]), float(p[2])),
                None,
            )
        if not snap:
            raise PlanningError(problem + "; use snap to move it to the nearest free voxel")
        q = vm.nearest_free(p, snap_radius_m)
        if q is None:
            raise PlanningError(problem + f" and no free voxel lies within {snap_radius_m:g} m")
        qi = vm.world_to_index(q)
        moved = float(np.linalg.norm(q - p))
        msg = f"{problem}: snapped to the nearest free voxel ({_fmt(q)}), {moved:.2f} m away"
        return int(self.cost_map.padded_index(qi)), (float(q[0]), float(q[1]), float(q[2])), msg

    # -------------------------------------------------------------- searches
    def _work(self) -> tuple[npt.NDArray[Any], ...]:
        """The search's work arrays, allocated once per planner (see :func:`_kernels.search`):
        g (inf where the last search did not reach), parent, length, done (run numbers), touched
        (the voxels the last search reached, in the order reached)."""
        n = self.cost_map.padded.size
        if self._w is None or len(self._w[0]) != n or self._run > 2**30:
            i32 = np.int32
            self._w = (
                np.full(n, np.inf),  # g
                np.empty(n, dtype=i32),  # parent
                np.empty(n),  # length
                np.zeros(n, dtype=i32),  # done (run number)
                np.empty(n, dtype=i32),  # touched
            )
            self._run = 0
            self._n_reached = 0
            cap = n // 4 + 64  # bucket entries: a mine takes ~1.4 per voxel reached
            self._pool = (np.empty((cap, 2), dtype=i32), np.empty(cap))
        return self._w

    def _grow_pool(self, reached: int) -> None:
        """More bucket entries after a search ran out of them having reached ``reached`` voxels:
        enough for the whole free map at the rate seen so far, at least twice as many."""
        assert self._pool is not None
        cap = len(self._pool[1])
        n_free = int(np.count_nonzero(np.isfinite(self.cost_map.flat_padded())))
        new = max(2 * cap, int(1.25 * cap / max(reached, 1) * n_free))
        self._pool = (np.empty((new, 2), dtype=np.int32), np.empty(new))

    def _search(
        self,
        sources: Sequence[int],
        targets: Sequence[int],
        heuristic: bool,
        reverse: bool = False,
        hfield: npt.NDArray[np.float64] | None = None,
        hshift: float = 0.0,
        tree: tuple[Any, ...] | None = None,
    ) -> tuple[int, int]:
        """Run the compiled search; returns (expansions, voxels reached). Results stay in the
        work arrays until the next search: g/parent/length where ``g`` is finite."""
        from btmission.planning import _kernels as K

        live = self._live() if self._live is not None else None
        if live is not None:
            live._detach()  # a CostField still reads the work arrays: give it its own copy
        self._live = None
        w = self._work()
        src = np.asarray(sources, dtype=np.int64)
        tgt = np.asarray(targets, dtype=np.int64)
        assert self._pool is not None
        while True:
            self._run += 1
            expanded, reached, best = K.search(
                self.cost_map.flat_padded(),
                self._off,
                self._step,
                src,
                tgt,
                heuristic,
                reverse,
                self._sx,
                self._sy,
                self.cost_map.resolution,
                self._delta,
                self._n_buckets,
                w,
                self._run,
                _NO_FIELD if hfield is None else hfield,
                float(hshift),
                _NO_TREE if tree is None else tree,
                self._n_reached,
                self._pool,
            )
            self._n_reached = int(reached)
            if expanded >= 0:
                break
            self._grow_pool(int(reached))  # out of bucket entries: again, from the start
        self._best_node = int(best)
        return int(expanded), int(reached)

    def _reached(self, flat: npt.NDArray[np.int64]) -> npt.NDArray[np.bool_]:
        """Whether voxels ``flat`` were reached by the last search."""
        out: npt.NDArray[np.bool_] = self._work()[0][flat] < np.inf
        return out

    def _last_tree(
        self,
    ) -> tuple[
        npt.NDArray[np.int64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.int64],
    ]:
        """(voxels in increasing order, g, length, parent) of every voxel the last search reached
        (copies; one pass over the map, about 1.5 ms for 2 M voxels, instead of sorting them)."""
        from btmission.planning import _kernels as K

        g, parent, length = self._work()[:3]
        ids, gs, lengths, parents = K.reached_tree(g, length, parent, self._n_reached)
        return ids, gs, lengths, parents

    def plan(
        self, start: Point, goal: Point, *, snap: bool = False, snap_radius_m: float = 5.0
    ) -> PlanResult:
        """The optimal path from ``start`` to ``goal`` (A*). ``cost`` is inf when none exists."""
        from btmission.planning import _kernels as K

        s, sp, w1 = self.resolve(start, "start", snap=snap, snap_radius_m=snap_radius_m)
        t, tp, w2 = self.resolve(goal, "goal", snap=snap, snap_radius_m=snap_radius_m)
        expanded, _ = self._search([s], [t], True)
        warnings = tuple(w for w in (w1, w2) if w)
        if not self._reached(np.array([t]))[0]:
            return self._result(
                np.zeros(0, dtype=np.int64), np.inf, np.inf, expanded, sp, tp, warnings
            )
        g, parent, length = self._work()[:3]
        flat = K.trace(parent, t, parent.size)
        return self._result(flat, float(g[t]), float(length[t]), expanded, sp, tp, warnings)

    def _result(
        self,
        flat: npt.NDArray[np.int64],
        cost: float,
        length: float,
        expanded: int,
        sp: tuple[float, float, float],
        tp: tuple[float, float, float],
        warnings: tuple[str, ...],
    ) -> PlanResult:
        vox = self.cost_map.unpad_index(flat) if len(flat) else np.zeros((0, 3), dtype=np.int64)
        path = self.cost_map.map.index_to_world(vox) if len(flat) else np.zeros((0, 3))
        return PlanResult(path, vox, cost, length, expanded, sp, tp, warnings)

    def one_to_all(
        self, start: Point | Sequence[Point], *, snap: bool = False, reverse: bool = False
    ) -> CostField:
        """Optimal cost and path length from ``start`` to every voxel (Dijkstra over the grid).

        ``start`` may also be a list of points: the field is then the cost from the nearest of them
        (used to check that tasks are reachable from any agent). With ``reverse`` the edges are
        walked backwards: the field holds the cost of the optimal path from every voxel *to*
        ``start`` (eq. 4 charges the voxels a path enters, so the two directions differ) — one
        search gives every agent's cost to one goal, wherever the agents are.
        """
        pts = np.asarray(start, dtype=np.float64)
        many = pts.ndim == 2
        srcs = [self.resolve(p, "start", snap=snap)[0] for p in (pts if many else [pts])]
        expanded, reached = self._search(srcs, [], False, reverse=reverse)
        sp = tuple(float(v) for v in (pts[0] if many else pts))
        field = CostField(self, (sp[0], sp[1], sp[2]), reached, expanded, reverse)
        self._live = weakref.ref(field)
        return field

    def costs_to(
        self, start: Point, goals: Sequence[Point], *, snap: bool = False
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(costs, lengths in m) of the optimal paths from ``start`` to each goal, from one search
        that stops once every goal is settled. Goals outside the map or in rock give inf."""
        s = self.resolve(start, "start", snap=snap)[0]
        vm = self.cost_map.map
        gi = vm.world_to_index(np.asarray(goals, dtype=np.float64).reshape(-1, 3))
        ok = vm.in_bounds(gi)
        flat = np.full(len(gi), -1, dtype=np.int64)
        flat[ok] = self.cost_map.padded_index(gi[ok])
        valid = [int(f) for f in flat if f >= 0 and np.isfinite(self.cost_map.flat_padded()[f])]
        targets = sorted(set(valid))
        if not targets:
            return np.full(len(gi), np.inf), np.full(len(gi), np.inf)
        self._search([s], targets, False)
        g, _, length = self._work()[:3]
        safe = np.maximum(flat, 0)
        hit = (flat >= 0) & self._reached(safe)
        costs = np.where(hit, g[safe], np.inf)
        lengths = np.where(hit, length[safe], np.inf)
        return costs, lengths


class _Query(NamedTuple):
    """One IncrementalPlanner.plan call: start voxel and point, warnings, whether to start afresh
    and why, and how many voxels changed since the last call."""

    start: int
    point: tuple[float, float, float]
    warnings: tuple[str, ...]
    fresh: bool
    reason: str
    n_changed: int


@dataclass
class ReplanStats:
    """What the last :meth:`IncrementalPlanner.plan` did."""

    expanded: int = 0
    changed_voxels: int = 0
    fresh: bool = True
    """True when the search started from scratch (first call, goal change or fallback)."""
    reason: str = "first search"


class IncrementalPlanner:
    """Replanning toward a fixed goal after local map changes, with the same result as a fresh
    search and far less work.

    >>> # planner = IncrementalPlanner(cost_map, goal); planner.plan(start)
    >>> # planner.notify(*cost_map.set_box(lo, hi, OCCUPIED))   # a 2 m rock appears
    >>> # planner.plan(new_start)   # same cost as Planner.plan, a fraction of the expansions

    Both methods start from the full backward tree from the goal (the cost-to-goal of every voxel,
    one bucket-queue Dijkstra on reversed edges: what a fresh search costs).

    ``method="field"`` (default) keeps that cost-to-goal field ``G`` and answers each query with
    A* from the start using ``max(octile, G - Δ)`` as heuristic, ``Δ`` being the sum of every cost
    decrease since ``G`` was computed. Costs that rose leave ``G`` a lower bound; decreases are
    covered by ``Δ`` (a path's cost fell by at most the sum of the decreases), so the heuristic stays
    admissible and the result exact (Adaptive A*, Koenig & Likhachev 2005, with the shift for
    decreases). While costs have only risen, the field's own tree (each voxel's next voxel toward
    the goal) also ends the search early: a voxel whose old path avoids every changed voxel keeps
    exactly that cost-to-goal, so reaching it completes a candidate path and the search stops once
    no open voxel can beat the best candidate. A* then expands little more than the detour around
    the change. Rock that becomes passable, or repairs that grow too large, renew ``G``.

    ``method="dstar-lite"`` is D* Lite (Koenig & Likhachev 2002, Fig. 4) with ``km`` for the moving
    start: changed edges make voxels inconsistent and only those whose keys are below the start's
    are repaired. Same results; on the 26-connected grid each of its expansions costs several times
    a bucket-queue expansion, so it is the slower of the two here (see ``btmission bench planner``).

    A batch of more than ``max_changed`` changed voxels, or (D* Lite) a repair over
    ``max_expansions_factor`` × the map's voxels, triggers a fresh search; :attr:`stats` says what
    happened on the last call.
    """

    METHODS = ("field", "dstar-lite")

    def __init__(
        self,
        cost_map: CostMap,
        goal: Point,
        *,
        method: str = "field",
        snap: bool = False,
        max_changed: int = 50_000,
        max_expansions_factor: float = 1.0,
    ):
        if method not in self.METHODS:
            raise ValueError(
                f"unknown method '{method}' (expected one of: {', '.join(self.METHODS)})"
            )
        self.method = method
        self.cost_map = cost_map
        self._planner = Planner(cost_map)
        self.goal_flat, self.goal, w = self._planner.resolve(goal, "goal", snap=snap)
        self.warnings: list[str] = [w] if w else []
        self.max_changed = max_changed
        self.max_expansions = max(1000, int(max_expansions_factor * cost_map.padded.size))
        self.stats = ReplanStats()
        self._pending: list[tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]] = []
        self._last_start: int | None = None
        self._reset_needed = True
        self._hshift = 0.0
        self._field_reached = 0
        self._chg: npt.NDArray[np.int32] | None = None
        self._memo = self._stack = self._gnext = np.zeros(0, dtype=np.int32)
        self._fid = 0

    def notify(self, changed: npt.NDArray[np.int64], old_cost: npt.NDArray[np.float64]) -> None:
        """Tell the planner which voxels changed cost (the return value of
        :meth:`CostMap.set_states` / :meth:`CostMap.set_box`)."""
        if len(changed):
            self._pending.append((np.asarray(changed, np.int64), np.asarray(old_cost, np.float64)))

    def _initialise(self, start: int) -> int:
        """A fresh search: the full backward tree from the goal, which leaves every voxel
        consistent (``g = rhs``) and the open list empty."""
        p = self._planner
        expanded, reached = p._search([self.goal_flat], [], False, reverse=True)
        ids, g_reached, _, parent = p._last_tree()
        n = self.cost_map.padded.size
        g = np.full(n, np.inf)
        g[ids] = g_reached
        self.g = g
        self._field_reached = reached
        self._hshift = 0.0
        if self.method == "field":
            # the tree of the field: each voxel's next voxel toward the goal, and which voxels
            # changed since (stamped with the field's number), for the early stop of the search
            if self._chg is None or len(self._chg) != n:
                self._chg = np.zeros(n, dtype=np.int32)
                self._memo = np.zeros(n, dtype=np.int32)
                self._stack = np.empty(n, dtype=np.int32)
            self._gnext = np.full(n, -1, dtype=np.int32)
            self._gnext[ids] = parent
            self._fid += 1
        if self.method == "dstar-lite":
            self.rhs = g.copy()
            self.inq = np.zeros(n, dtype=np.uint8)
            self.qk1 = np.empty(n)  # read only where inq is set
            self.qk2 = np.empty(n)
            cap = 1 << 16
            self.hk1 = np.empty(cap)
            self.hk2 = np.empty(cap)
            self.hv = np.empty(cap, dtype=np.int64)
            self.km = 0.0
            self.n_heap = 0
        self._last_start = start
        self._pending.clear()
        self._reset_needed = False
        return expanded

    def plan(self, start: Point, *, snap: bool = False) -> PlanResult:
        """The optimal path from ``start`` to the goal under the current costs."""
        p = self._planner
        s, sp, w = p.resolve(start, "start", snap=snap)
        warnings = tuple(self.warnings + ([w] if w else []))
        if not np.isfinite(self.cost_map.flat_padded()[self.goal_flat]):
            raise PlanningError(f"goal ({_fmt(self.goal)}) is now inside rock")
        n_changed = sum(len(c) for c, _ in self._pending)
        fresh, reason = False, "repaired"
        if self._reset_needed:
            fresh, reason = True, "first search"
        elif n_changed > self.max_changed:
            fresh, reason = True, f"{n_changed} changed voxels > max_changed={self.max_changed}"
        q = _Query(s, sp, warnings, fresh, reason, n_changed)
        return self._plan_field(q) if self.method == "field" else self._plan_dstar(q)

    def _plan_field(self, q: _Query) -> PlanResult:
        from btmission.planning import _kernels as K

        s, sp, warnings, fresh, reason, n_changed = q
        p = self._planner
        cost = self.cost_map.flat_padded()
        for changed, old in self._pending:
            new = cost[changed]
            if not fresh and np.any(~np.isfinite(old) & np.isfinite(new)):
                fresh, reason = True, "rock became passable: the cost-to-goal field is renewed"
            both = np.isfinite(old) & np.isfinite(new)
            drop = old[both] - new[both]
            self._hshift += float(drop[drop > 0].sum())
            if self._chg is not None:
                self._chg[changed] = self._fid
        self._pending.clear()
        initial = self._initialise(s) if fresh else 0
        # With only rises since the field was made, its tree gives exact costs wherever the old
        # path avoids the changes: the search may stop there (see _kernels.search).
        tree = None
        if self._hshift == 0.0 and self._chg is not None:
            tree = (self._gnext, self._chg, self._fid, self._memo, self._stack)
        expanded, _ = p._search(
            [s], [self.goal_flat], True, hfield=self.g, hshift=self._hshift, tree=tree
        )
        if not fresh and expanded > self._field_reached // 2:
            self._reset_needed = True  # the field no longer pays: renew it on the next call
            reason = "repaired; the field is renewed on the next call"
        self.stats = ReplanStats(expanded + initial, n_changed, fresh, reason)
        g, parent = p._work()[:2]
        t = p._best_node if tree is not None else self.goal_flat
        if t < 0 or not p._reached(np.array([t]))[0]:
            return p._result(
                np.zeros(0, dtype=np.int64), np.inf, np.inf, expanded, sp, self.goal, warnings
            )
        head = K.trace(parent, t, parent.size)
        cost_t = float(g[t]) + (float(self.g[t]) if t != self.goal_flat else 0.0)
        tail: list[int] = []
        x = t
        while x != self.goal_flat:  # the rest of the way along the field's old tree
            x = int(self._gnext[x])
            tail.append(x)
        flat = np.concatenate([head, np.asarray(tail, dtype=np.int64)])
        length_m = float(self._steps(flat).sum())
        return p._result(flat, cost_t, length_m, expanded + initial, sp, self.goal, warnings)

    def _plan_dstar(self, q: _Query) -> PlanResult:
        from btmission.planning import _kernels as K

        s, sp, warnings, fresh, reason, n_changed = q
        p = self._planner
        initial = 0
        if fresh:
            initial = self._initialise(s)
        else:
            assert self._last_start is not None
            if s != self._last_start:
                self.km += float(
                    K._octile(self._last_start, s, p._sx, p._sy, self.cost_map.resolution)
                )
                self._last_start = s
            cost = self.cost_map.flat_padded()
            for changed, old in self._pending:
                self.hk1, self.hk2, self.hv, self.n_heap = K.dstar_edges_changed(
                    changed,
                    old,
                    self.g,
                    self.rhs,
                    cost,
                    p._off,
                    p._step,
                    self.goal_flat,
                    s,
                    self.km,
                    p._sx,
                    p._sy,
                    self.cost_map.resolution,
                    self.hk1,
                    self.hk2,
                    self.hv,
                    self.n_heap,
                    self.inq,
                    self.qk1,
                    self.qk2,
                )
            self._pending.clear()
        expanded, ok = self._compute(s)
        expanded += initial
        if not ok:
            fresh, reason = True, f"repair exceeded {self.max_expansions:,} expansions"
            expanded += self._initialise(s)
            more, ok = self._compute(s)
            expanded += more
        self.stats = ReplanStats(expanded, n_changed, fresh, reason)
        cost_map = self.cost_map
        total = float(self.g[s]) if self.g[s] == self.rhs[s] else float(self.rhs[s])
        if not np.isfinite(total):
            return p._result(
                np.zeros(0, dtype=np.int64), np.inf, np.inf, expanded, sp, self.goal, warnings
            )
        flat = K.descend(
            self.g, cost_map.flat_padded(), p._off, p._step, s, self.goal_flat, cost_map.padded.size
        )
        steps = self._steps(flat)
        return p._result(flat, total, float(steps.sum()), expanded, sp, self.goal, warnings)

    def _compute(self, start: int) -> tuple[int, bool]:
        from btmission.planning import _kernels as K

        p = self._planner
        self.hk1, self.hk2, self.hv, n, expanded, ok = K.dstar_compute(
            self.n_heap,
            self.km,
            self.goal_flat,
            self.g,
            self.rhs,
            self.cost_map.flat_padded(),
            p._off,
            p._step,
            start,
            p._sx,
            p._sy,
            self.cost_map.resolution,
            self.hk1,
            self.hk2,
            self.hv,
            self.inq,
            self.qk1,
            self.qk2,
            self.max_expansions,
        )
        self.n_heap = int(n)
        return int(expanded), bool(ok)

    def _steps(self, flat: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
        if len(flat) < 2:
            return np.zeros(0)
        idx = self.cost_map.unpad_index(flat)
        out: npt.NDArray[np.float64] = np.linalg.norm(np.diff(idx, axis=0), axis=1)
        return out * self.cost_map.resolution


def _fmt(p: npt.ArrayLike) -> str:
    return ", ".join(f"{v:g}" for v in np.asarray(p, dtype=np.float64).ravel())
