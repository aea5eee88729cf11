"""The agent side of the auction: bids from task-type cost expressions (seed 003 §V-B, eq. 8-10).

For every announced task ``T_j`` an agent ``R_k`` bids

    c_kj = f_cost(T_j, state) · k_bt                                   (eq. 8)

where ``f_cost`` is the task type's ``cost`` expression from the mission — e.g.
``path_cost(location)`` (Γ1, eq. 9) or ``path_cost(pickup) + path_cost(pickup, dropoff)`` (Γ2,
eq. 10) — evaluated with path costs from a pluggable :class:`CostProvider` (straight lines by
default; the D*+ planner provides risk-aware path costs through the same interface), and
``k_bt`` comes from the agent's behaviour tree: 1 normally, 0 for its current task once the
task's commit condition holds (e.g. ``holding(pickup)``). An agent past a commit point bids
only on that task: it keeps it (the auctioneer also pins it) and takes part in nothing else.

**Switch cost** (``coordination.switch_cost``, 0 by default as in the paper): an agent that is
executing a task adds it to its bids on every other task, so two agents whose bids differ by
less than that no longer trade tasks back and forth as they move.

**Participation** (seed 003 §IV-B): an agent bids only on its ``ceil(participation · n)``
cheapest announced tasks — plus the task it is executing, so it never drops its own task just
because others look cheaper. Tasks it cannot do (its library lacks the goal) or cannot reach
(``inf`` from the provider) are reported as such, not bid on.

**Repeated bids.** An announcement is repeated every round while its tasks are unchanged. When
every task the agent bids on costs ``path_cost(field)`` and the provider says what its costs
from a start depend on (``start_key(start)``: the D*+ service's start voxel and map version), a
bidder whose key, current task and settings are those of its previous bid on the same
announcement sends that bid's costs again instead of recomputing them: the same numbers,
computed once.
"""

from __future__ import annotations

import ast
import math
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from btmission.allocation.auction import Announcement, Bid, cheapest, participation_k
from btmission.allocation.tasks import TaskInfo
from btmission.errors import BtmissionError
from btmission.types import FloatArray

Point = tuple[float, float, float]


class CostFunction(Protocol):
    """A task type's cost expression, as the bidder uses it (a mission's are
    :class:`btmission.spec.costexpr.CostExpr`)."""

    @property
    def text(self) -> str:
        """The expression as written, e.g. ``path_cost(location)``."""
        ...

    @property
    def tree(self) -> ast.Expression:
        """The parsed expression (the bidder recognises a lone ``path_cost(field)``)."""
        ...

    def evaluate(
        self, call: Callable[[str, tuple[object, ...]], float], fields: Mapping[str, object]
    ) -> float:
        """The cost with ``call(function_name, argument_values)`` supplying the path costs."""
        ...


class BidType(Protocol):
    """What the bidder reads of a task type: its cost (a mission's task types are
    :class:`btmission.spec.mission.TaskType`)."""

    @property
    def cost(self) -> CostFunction: ...


@runtime_checkable
class CostProvider(Protocol):
    """Path costs for bids. Implemented by :class:`StraightLine` and by the D*+ planner.

    A provider may also offer ``path_costs(start, goals) -> array``, the costs from one start to
    many goals in one call (the runtime's D*+ fields answer it with one gather); the bidder then
    uses it for every task type whose cost is exactly ``path_cost(field)``. It passes the same
    ``goals`` tuple every round while the announcement is unchanged (a provider may remember
    what it resolved them to, by identity). A provider with ``path_costs`` may also offer
    ``start_key(start) -> hashable``: starts with equal keys have equal ``path_costs`` to any
    goals (the bidder then repeats a bid instead of recomputing it; module docstring)."""

    def path_cost(self, start: Point, goal: Point) -> float:
        """Cost of the best path from ``start`` to ``goal``; ``math.inf`` if there is none."""
        ...


@dataclass(frozen=True)
class StraightLine:
    """Euclidean distance: the cost provider until a planner is plugged in."""

    def path_cost(self, start: Point, goal: Point) -> float:
        return math.dist(start, goal)


@dataclass(frozen=True)
class AgentState:
    """What the bid depends on: where the agent is and what its behaviour tree is doing."""

    id: str
    position: Point
    task: str | None = None
    """The task it is executing, if any."""
    committed: bool = False
    """Its tree has passed ``task``'s commit condition (k_bt = 0 for it)."""


def k_bt(agent: AgentState, task_id: str) -> float:
    """The behaviour-tree factor of eq. 8-10: 0 for the current task after its commit point,
    else 1."""
    return 0.0 if agent.committed and task_id == agent.task else 1.0


def _single_path_cost(tt: BidType) -> str | None:
    """The task field ``X`` when the type's cost is exactly ``path_cost(X)`` (eq. 9's Γ1): such
    bids can be computed for all tasks of the type at once by a provider's ``path_costs``."""
    cached = _SINGLE.get(tt.cost.text, _MISSING)
    if cached is not _MISSING:
        return cached  # type: ignore[return-value]
    body = tt.cost.tree.body
    field = None
    if (
        isinstance(body, ast.Call)
        and isinstance(body.func, ast.Name)
        and body.func.id == "path_cost"
        and len(body.args) == 1
        and isinstance(body.args[0], ast.Name)
    ):
        field = body.args[0].id
    _SINGLE[tt.cost.text] = field
    return field


_MISSING = object()
_SINGLE: dict[str, object] = {}


class _Plan:
    """How a bidder computes its costs on one announcement; the same for every agent whose
    bidder has the same task types and places, so it is kept with the announcement
    (:meth:`Announcement.memo`): the tasks whose cost is ``path_cost(field)`` by type (one
    :meth:`path_costs` call each, with the same goals tuple every round) and those evaluated
    task by task (:meth:`Bidder.f_cost`). Tasks of types the bidder cannot do get no bid."""

    def __init__(
        self,
        tasks: Sequence[TaskInfo],
        fields: Mapping[str, str | None],
        places: Mapping[str, Point],
    ) -> None:
        self.single: list[int] = []
        rows: dict[str, list[int]] = {}
        for j, t in enumerate(tasks):
            if t.type not in fields:
                continue  # f_cost is NaN: no bid
            if fields[t.type] is None:
                self.single.append(j)
            else:
                rows.setdefault(t.type, []).append(j)
        self._tasks = tasks
        self._fields = fields
        self._places = places
        self._rows = rows
        self._batches: list[tuple[npt.NDArray[np.intp], tuple[Point, ...]]] | None = None
        self._k: dict[float, int] = {}

    def participation_k(self, participation: float) -> int:
        """:func:`~btmission.allocation.auction.participation_k` for these tasks (kept)."""
        k = self._k.get(participation)
        if k is None:
            k = self._k[participation] = participation_k(participation, len(self._tasks))
        return k

    def whole(self) -> bool:
        """Whether one batch holds every task, in order (its costs are the whole bid row)."""
        batches = self.batches()
        return len(batches) == 1 and len(batches[0][0]) == len(self._tasks)

    def batches(self) -> list[tuple[npt.NDArray[np.intp], tuple[Point, ...]]]:
        """(rows, goals) per batched type; raises :class:`BidError` for a bad position."""
        if self._batches is None:
            out = []
            for ttype, rows in self._rows.items():
                name = self._fields[ttype]
                assert name is not None
                tasks = [self._tasks[j] for j in rows]
                goals = tuple(_point(t, t.fields.get(name), self._places) for t in tasks)
                out.append((np.array(rows, dtype=np.intp), goals))
            self._batches = out
        return self._batches


class BidError(BtmissionError, ValueError):
    """A task's fields do not fit its type's cost expression (e.g. a position is not [x, y, z])."""


def _point(task: TaskInfo, value: object, places: Mapping[str, Point] | None = None) -> Point:
    """A task field as a position: ``[x, y, z]``, or the name of a place (a node of the
    mission's topological map)."""
    if isinstance(value, str) and places:
        hit = places.get(value)
        if hit is not None:
            return hit
        raise BidError(
            f"task '{task.id}' ({task.type}): '{value}' is not a place of the mission's "
            f"topological map (known: {', '.join(sorted(places))})"
        )
    if (
        isinstance(value, (list, tuple))
        and len(value) == 3
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
    ):
        return (float(value[0]), float(value[1]), float(value[2]))
    raise BidError(
        f"task '{task.id}' ({task.type}): cost functions need positions [x, y, z], got {value!r}"
    )


class Bidder:
    """Computes one agent's bids on announcements.

    ``task_types`` are the types this agent can do (others get no bid). Path costs between two
    task fields (``path_cost(pickup, dropoff)``) do not depend on the agent and are cached
    (least recently used, ``cache_size`` entries). The bidder of a mission's agent is built by
    :func:`btmission.runtime.mission_auction.bidder_for_agent`.
    """

    def __init__(
        self,
        task_types: Mapping[str, BidType],
        provider: CostProvider | None = None,
        participation: float = 1.0,
        *,
        cache_size: int = 4096,
        switch_cost: float = 0.0,
        places: Mapping[str, Point] | None = None,
    ):
        if not 0 < participation <= 1:
            raise ValueError(f"participation must be in (0, 1], got {participation}")
        if not (switch_cost >= 0 and math.isfinite(switch_cost)):
            raise ValueError(f"switch_cost must be ≥ 0, got {switch_cost}")
        self.switch_cost = switch_cost
        self.task_types = dict(task_types)
        self.provider: CostProvider = provider if provider is not None else StraightLine()
        self.participation = participation
        self.places: Mapping[str, Point] = dict(places or {})
        """Named places task fields may refer to (nodes of the mission's topological map)."""
        self._cache: OrderedDict[tuple[Point, Point], float] = OrderedDict()
        self._cache_size = cache_size
        self._places_key = tuple(sorted((k, tuple(v)) for k, v in self.places.items()))
        self._last: tuple[object, Announcement, FloatArray] | None = None
        """The previous bid's key, announcement and costs (a repeated bid sends them again)."""
        self._fields: dict[bool, tuple[tuple[str, str | None], ...]] = {}
        """Per task type, the single path cost its cost is (or None), sorted: the bid plan's
        key, with and without a batch-capable provider (:meth:`costs`)."""
        self._hot: tuple[Announcement, object, _Plan, Any, Any] | None = None
        """The last announcement's plan and provider functions (:meth:`_plan_of`)."""
        self.repeated = 0
        """Bids that repeated the previous one's costs (module docstring) instead of computing
        them."""

    def _static_cost(self, a: Point, b: Point) -> float:
        key = (a, b)
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        value = float(self.provider.path_cost(a, b))
        self._cache[key] = value
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return value

    def f_cost(self, task: TaskInfo, agent: AgentState) -> float:
        """``f_cost(task, state)`` of eq. 8: the task type's cost expression for this agent
        (NaN if the agent cannot do the type, ``inf`` if a path does not exist)."""
        tt = self.task_types.get(task.type)
        if tt is None:
            return math.nan

        def call(name: str, args: tuple[object, ...]) -> float:
            pts = [_point(task, v, self.places) for v in args]
            if name == "distance":
                start, goal = (agent.position, pts[0]) if len(pts) == 1 else (pts[0], pts[1])
                return math.dist(start, goal)
            if len(pts) == 1:
                return float(self.provider.path_cost(agent.position, pts[0]))
            return self._static_cost(pts[0], pts[1])

        try:
            value = tt.cost.evaluate(call, task.fields)
        except KeyError as exc:
            raise BidError(f"task '{task.id}' ({task.type}) has no field {exc}") from None
        if math.isnan(value) or value < 0:
            raise BidError(
                f"task '{task.id}' ({task.type}): cost '{tt.cost.text}' is {value:g}; bids must "
                "be ≥ 0"
            )
        return value

    def costs(self, announcement: Announcement, agent: AgentState) -> FloatArray:
        """``c_kj`` for every announced task, in announcement order (eq. 8), participation
        applied: NaN = no bid, ``inf`` = unreachable."""
        tasks = announcement.tasks
        if agent.committed:
            out = np.full(len(tasks), np.nan)
            if agent.task is not None and agent.task in announcement.index:
                out[announcement.index[agent.task]] = 0.0  # f_cost · k_bt with k_bt = 0
            return out
        plan, batch, start_key = self._plan_of(announcement)
        key = None
        if start_key is not None and not plan.single:
            key = (
                self.provider,
                start_key(agent.position),
                agent.task,
                self.switch_cost,
                self.participation,
            )
            last = self._last
            if last is not None and last[1] is announcement and last[0] == key:
                self.repeated += 1  # not moved to another voxel: the same costs
                return last[2].copy()
        row: FloatArray | None = None
        if not plan.single and plan.whole():  # one batch, every task: its costs are the row
            assert batch is not None
            row = np.array(batch(agent.position, plan.batches()[0][1]), dtype=np.float64)
        if row is not None and row.shape == (len(tasks),):  # (else numpy's rules, as for several)
            out = row
        else:
            out = np.full(len(tasks), np.nan)
            for j in plan.single:
                t = tasks[j]
                out[j] = self.f_cost(t, agent) * k_bt(agent, t.id)
            for rows, goals in plan.batches():
                assert batch is not None
                out[rows] = np.asarray(batch(agent.position, goals), dtype=np.float64)
        # k_bt = 1 on every task here: an agent past its commit point returned above (eq. 8)
        if self.switch_cost and agent.task is not None:
            mine = announcement.index.get(agent.task)
            held = out[mine] if mine is not None else None
            out += self.switch_cost
            if mine is not None:
                out[mine] = held  # (every other task's cost + the switch cost)
        k = plan.participation_k(self.participation)
        if k < len(tasks):
            keep = announcement.index.get(agent.task, -1) if agent.task is not None else -1
            out[~cheapest(out, k, keep)] = np.nan
        if key is not None:
            self._last = (key, announcement, out.copy())
        return out

    def _plan_of(
        self, announcement: Announcement
    ) -> tuple[_Plan, Callable[..., Any] | None, Callable[[Point], object] | None]:
        """The bid plan for ``announcement`` (kept with it: the same for every bidder with these
        task types and places), and the provider's batch and start-key functions (None where it
        has none). Looked up once per announcement (every agent bids on every one)."""
        hot = self._hot
        if hot is not None and hot[0] is announcement and hot[1] is self.provider:
            return hot[2], hot[3], hot[4]
        provider = self.provider
        batch = getattr(provider, "path_costs", None)
        fields = self._fields.get(batch is not None)
        if fields is None:  # (the task types and the provider do not change)
            fields = self._fields[batch is not None] = tuple(
                sorted(
                    (name, _single_path_cost(tt) if batch is not None else None)
                    for name, tt in self.task_types.items()
                )
            )
        tasks = announcement.tasks
        plan = announcement.memo(
            ("bid-plan", fields, self._places_key),
            lambda: _Plan(tasks, dict(fields), self.places),
        )
        start_key = getattr(provider, "start_key", None)
        self._hot = (announcement, provider, plan, batch, start_key)
        return plan, batch, start_key

    def bid(self, announcement: Announcement, agent: AgentState, now: float) -> Bid:
        """The bid message for ``announcement`` (aligned with it)."""
        return Bid.aligned(
            agent.id,
            now,
            announcement,
            self.costs(announcement, agent),
            agent.task if agent.committed else None,
        )


def bids_for(
    bidders: Mapping[str, Bidder],
    agents: Sequence[AgentState],
    announcement: Announcement,
    now: float,
) -> list[Bid]:
    """Every agent's bid on ``announcement`` (in-process simulation of the bidding stage)."""
    return [bidders[a.id].bid(announcement, a, now) for a in agents]
