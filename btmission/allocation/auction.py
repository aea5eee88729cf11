"""The auctioneer: one auction round as a pure step function (seed 003 §IV, seed 000 §IV-B).

A round has the paper's three stages (seed 003 Fig. 3):

1. **Announcement** — :func:`announce`: the tasks that have arrived and are not finished, in
   (arrival, id) order. The announcement keeps its serial number while that set is unchanged,
   so bids computed against it stay aligned with it.
2. **Bidding** — agents answer with a :class:`Bid`: one cost per announced task, ``c_kj =
   f_cost(task, state) · k_bt`` (eq. 8-10; see :mod:`btmission.allocation.bidder`), NaN for a
   task it does not bid on (participation) and ``inf`` for one it cannot reach. The auctioneer
   keeps each agent's latest bid on a board; a bid older than ``agent_timeout_s`` is stale and
   its agent is dropped (it wins nothing new). The task it holds is leased to it: it stays
   with it until ``lease_s`` after its last bid, so an agent cut off for less than that keeps
   its task (and its late report of it counts); then the task returns to the pool.
3. **Allocation** — :func:`auction_round`: the board becomes a cost matrix, priorities become
   profit bonuses, and an exact solver (:mod:`btmission.allocation.solvers`) finds the matching
   that assigns the most tasks, then maximizes ``Σ (priority_scale · priority_j − c_kj)``
   (eq. 4-7), keeping current holders on exact ties. Tasks whose agent has passed the commit
   point (k_bt = 0) stay with that agent whatever the other bids. An agent that gave a task up
   does not get it again for ``cooldown_s`` (its bid on it is left out), so the others are
   offered it first. Every task left without an agent gets the reason.

:func:`auction_round` is pure: ``(state, bids, now) → (assignments, new_state, report)``, with no
clock, I/O or randomness, so a round can be replayed and tested exactly. The fixed-rate loop
that calls it is :class:`btmission.allocation.loop.AuctionLoop`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from operator import is_
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from btmission.allocation.solvers import (
    MAX_COST,
    MISSION_SOLVERS,
    AssignmentProblem,
    solve,
)
from btmission.allocation.tasks import HELD, PoolTask, TaskInfo, TaskPool, TaskState
from btmission.types import FloatArray, recorder

_T = TypeVar("_T")

SOLVERS: tuple[str, ...] = ("assignment", "ilp-scip", "dense", "sparse", "pruned")
"""``AuctionConfig.solver``: a mission's ``assignment`` (the solver chosen automatically) or
``ilp-scip`` (the paper's ILP), or one of the assignment solvers forced (benchmarks): ``dense``,
``sparse`` or ``pruned`` (:mod:`btmission.allocation.solvers`)."""


@dataclass(frozen=True)
class AuctionConfig:
    """The mission's ``coordination`` settings the auctioneer uses."""

    participation: float = 1.0
    """Fraction of the announced tasks each agent bids on: its ``ceil(p · n)`` cheapest."""
    priority_scale: float = 1000.0
    """Profit bonus per unit of task priority (seed 003 scenario 3)."""
    solver: str = "assignment"
    agent_timeout_s: float = 3.0
    """A bid older than this is stale: its agent is dropped from the auction (it wins nothing
    new); the task it holds stays with it for the lease (``lease_s``)."""
    lease_s: float = 30.0
    """How long after an agent's last bid the task it holds stays with it: past this (and at
    least ``agent_timeout_s``) the task returns to the pool. A dead agent's task waits this
    long; a partition shorter than this costs nothing (the cut-off agent keeps its task)."""
    rate_hz: float = 10.0
    """Rounds per second of the fixed-rate loop (the paper ran at 9 Hz)."""
    cooldown_s: float = 30.0
    """An agent that gave a task up takes no part in its allocation for this long."""
    exclude_after: int = 3
    """Different tasks an agent may give up in a row (none done between) before it is taken
    out of the auction (0: never)."""

    def __post_init__(self) -> None:
        if not 0 < self.participation <= 1:
            raise ValueError(f"participation must be in (0, 1], got {self.participation}")
        if not (self.priority_scale >= 0 and math.isfinite(self.priority_scale)):
            raise ValueError(f"priority_scale must be ≥ 0, got {self.priority_scale}")
        if self.solver not in SOLVERS:
            raise ValueError(
                f"unknown solver '{self.solver}' (expected one of: {', '.join(SOLVERS)})"
            )
        if not self.agent_timeout_s > 0:
            raise ValueError(f"agent_timeout_s must be > 0, got {self.agent_timeout_s}")
        if not self.lease_s > 0:
            raise ValueError(f"lease_s must be > 0, got {self.lease_s}")
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")
        if not (self.cooldown_s >= 0 and math.isfinite(self.cooldown_s)):
            raise ValueError(f"cooldown_s must be ≥ 0, got {self.cooldown_s}")
        if not self.exclude_after >= 0:
            raise ValueError(f"exclude_after must be ≥ 0, got {self.exclude_after}")

    @property
    def method(self) -> str:
        """The solver method (:func:`btmission.allocation.solvers.solve`)."""
        return MISSION_SOLVERS.get(self.solver, self.solver)

    @classmethod
    def from_spec(cls, spec: Any) -> AuctionConfig:
        """From a mission's :class:`~btmission.spec.mission.CoordinationSpec`."""
        return cls(
            participation=spec.participation,
            priority_scale=spec.priority_scale,
            solver=spec.solver,
            agent_timeout_s=spec.agent_timeout_s,
            lease_s=spec.lease_s,
            rate_hz=spec.auction_rate_hz,
            cooldown_s=spec.cooldown_s,
            exclude_after=spec.exclude_after,
        )


def participation_k(participation: float, n_tasks: int) -> int:
    """How many tasks an agent bids on: ``ceil(participation · n_tasks)`` (at least 1 if any)."""
    if n_tasks <= 0:
        return 0
    return max(1, min(n_tasks, math.ceil(participation * n_tasks - 1e-9)))


def cheapest(costs: FloatArray, k: int, keep: int = -1) -> NDArray[np.bool_]:
    """Mask of the ``k`` cheapest finite entries of ``costs`` (ties: lower index first), plus
    ``keep`` (an agent always bids on its current task). Unreachable (inf) entries are kept too:
    they say "cannot", which is information, not a bid."""
    finite = np.isfinite(costs)
    mask = np.isinf(costs)
    idx = np.nonzero(finite)[0]
    if len(idx) <= k:
        mask |= finite
    else:
        order = np.argsort(costs[idx], kind="stable")[:k]
        mask[idx[order]] = True
    if 0 <= keep < len(costs) and finite[keep]:
        mask[keep] = True
    return mask


# --------------------------------------------------------------------------------------------
# Messages
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Announcement:
    """The announced tasks (stage 1). ``serial`` changes only when the set of tasks does.

    ``epoch`` names the coordinator that announced it (its incarnation: chosen when it starts,
    a restarted coordinator has another and counts serials and rounds from the start again;
    0: unknown, e.g. made by hand or received from a sender of wire format 1). Within one
    epoch, serials and rounds only grow, so an agent can tell an old message delivered late
    from a new one (:class:`btmission.runtime.agent.Freshness`)."""

    serial: int = 0
    time_s: float = 0.0
    tasks: tuple[TaskInfo, ...] = ()
    epoch: int = 0

    @property
    def ids(self) -> tuple[str, ...]:
        cached = self.__dict__.get("_ids")
        if cached is None:
            cached = tuple(t.id for t in self.tasks)
            object.__setattr__(self, "_ids", cached)
        return cached  # type: ignore[no-any-return]

    @property
    def index(self) -> Mapping[str, int]:
        """Task id → position in the announcement."""
        cached = self.__dict__.get("_index")
        if cached is None:
            cached = {tid: j for j, tid in enumerate(self.ids)}
            object.__setattr__(self, "_index", cached)
        return cached  # type: ignore[no-any-return]

    @property
    def priorities(self) -> FloatArray:
        """Task priorities in announcement order."""
        cached = self.__dict__.get("_prio")
        if cached is None:
            cached = np.array([t.priority for t in self.tasks], dtype=np.float64)
            object.__setattr__(self, "_prio", cached)
        return cached  # type: ignore[no-any-return]

    def __len__(self) -> int:
        return len(self.tasks)

    def memo(self, key: Hashable, make: Callable[[], _T]) -> _T:
        """``make()``, computed once per ``key`` for this announcement and kept with it: what
        every agent derives from the same announced tasks (a bidder's plan)."""
        memo = self.__dict__.get("_memo")
        if memo is None:
            memo = {}
            object.__setattr__(self, "_memo", memo)
        if key in memo:
            return memo[key]  # type: ignore[no-any-return]
        value = memo[key] = make()
        return value


@dataclass(frozen=True, eq=False)
class Bid:
    """An agent's bid (stage 2): costs for ``tasks`` (usually the announced ids, in order).

    ``costs[i]`` is the cost for ``tasks[i]``: finite ≥ 0 = a bid, NaN = no bid (the agent does
    not take part for that task), ``inf`` = it cannot reach it. ``committed_to`` is the task the
    agent has passed the commit point of (its behaviour tree's k_bt = 0), if any. A bid is also
    the agent's heartbeat: ``time_s`` is when it was made. ``serial`` is the serial of the
    announcement it answers (None: unknown, e.g. a bid made by hand); a round ignores bids that
    answer an older announcement than the one it collected bids for
    (:meth:`btmission.allocation.loop.AuctionLoop.close_round`).
    """

    agent: str
    time_s: float
    tasks: tuple[str, ...]
    costs: FloatArray
    committed_to: str | None = None
    serial: int | None = None

    @classmethod
    def of(
        cls,
        agent: str,
        time_s: float,
        costs: Mapping[str, float],
        committed_to: str | None = None,
        serial: int | None = None,
    ) -> Bid:
        """From a task id → cost mapping (tasks left out are not bid on)."""
        return cls(
            agent,
            time_s,
            tuple(costs),
            np.fromiter(costs.values(), dtype=np.float64, count=len(costs)),
            committed_to,
            serial,
        )

    @classmethod
    def aligned(
        cls,
        agent: str,
        time_s: float,
        announcement: Announcement,
        costs: FloatArray | Sequence[float],
        committed_to: str | None = None,
    ) -> Bid:
        """Costs in announcement order (the fast path: no id lookups in the auctioneer); the
        bid answers the announcement's serial."""
        return recorder(cls)(
            agent=agent,
            time_s=time_s,
            tasks=announcement.ids,
            costs=np.asarray(costs, dtype=np.float64),
            committed_to=committed_to,
            serial=announcement.serial,
        )  # (every agent, every round: without the frozen dataclass's per-field assignment)

    def cost_of(self, task_id: str) -> float:
        """This bid's cost for ``task_id`` (NaN if it does not bid on it)."""
        for i, t in enumerate(self.tasks):
            if t == task_id:
                return float(self.costs[i])
        return math.nan

    def problem(self) -> str | None:
        """What makes this bid unusable, or None."""
        return self._form_problem() or self._cost_problem()

    def _form_problem(self) -> str | None:
        """:meth:`problem` but for the range of the costs."""
        if not self.agent:
            return "bid without an agent id"
        if not math.isfinite(self.time_s):
            return f"bid from {self.agent}: time is not finite"
        if self.costs.shape != (len(self.tasks),):
            return f"bid from {self.agent}: {self.costs.shape} costs for {len(self.tasks)} task(s)"
        return None

    def _cost_problem(self) -> str | None:
        """A cost out of range (:meth:`problem`, once the form is right), or None."""
        costs = self.costs
        if costs.dtype == np.float64 and costs.flags.c_contiguous:  # a bid's own array
            i = int(_first_bad_cost()(costs, MAX_COST))
        else:
            bad = (costs < 0) | ((costs > MAX_COST) & np.isfinite(costs))
            i = int(np.nonzero(bad)[0][0]) if np.logical_or.reduce(bad) else -1
        if i >= 0:
            return (
                f"bid from {self.agent}: cost {costs[i]:g} for task '{self.tasks[i]}' is "
                f"out of range (expected 0 … {MAX_COST:g}, NaN for no bid, inf for unreachable)"
            )
        return None


_F64 = np.dtype(np.float64)


def _first_bad_cost() -> Callable[[FloatArray, float], int]:
    """The compiled range check (:mod:`btmission.allocation._bid_kernels`), imported when first
    needed (it brings numba in)."""
    from btmission.allocation._bid_kernels import first_bad_cost

    return first_bad_cost  # type: ignore[no-any-return]


def costs_in_range(bids: Sequence[Bid]) -> bool:
    """Whether no bid has a cost out of range, so that each bid's :meth:`Bid.problem` is its
    form check alone: one compiled pass over every bid's costs at once instead of one call per
    bid. False when some bid's costs are not a 1-D float64 array (then check each bid)."""
    arrays = [b.costs for b in bids]
    for a in arrays:
        if a.dtype is not _F64 or a.ndim != 1:
            return False
    if not arrays:
        return True
    return int(_first_bad_cost()(np.concatenate(arrays), MAX_COST)) < 0


@dataclass(frozen=True)
class Change:
    """A task that changed hands this round (``None`` = no agent)."""

    task: str
    before: str | None
    after: str | None
    reason: str

    def __str__(self) -> str:
        return f"{self.task}: {self.before or '—'} → {self.after or '—'} ({self.reason})"


@dataclass(frozen=True)
class RoundReport:
    """What one round did and why (the event log records it)."""

    round: int
    time_s: float
    serial: int
    """Serial of the announcement the round allocated."""
    announced: int
    agents: tuple[str, ...]
    """Agents whose bids took part (live, sorted by id)."""
    dropped: tuple[str, ...]
    """Agents dropped this round because their latest bid was stale."""
    assignments: Mapping[str, str]
    """Agent → task for every held task after the round (committed ones included)."""
    committed: tuple[str, ...]
    """Agents kept on their task because they passed its commit point."""
    unassigned: Mapping[str, str]
    """Announced task without an agent → why."""
    changes: tuple[Change, ...]
    ignored: tuple[str, ...]
    """Bids (or parts of bids) the round could not use, and why."""
    method: str
    """The solver that ran (dense, sparse, ilp-scip, or "none" when nothing was to solve)."""
    bids: int
    """(agent, task) bids considered by the solver."""
    total_cost: float
    """Σ bid costs of the pairs the solver assigned (pinned committed pairs excluded)."""
    late_bids: int = 0
    """Bids that arrived while no round was collecting (after the last one closed): ignored."""
    stale_bids: int = 0
    """Bids that answered an older announcement than this round's: ignored."""


@dataclass(frozen=True)
class AuctionState:
    """Everything the auctioneer remembers between rounds (immutable)."""

    config: AuctionConfig = AuctionConfig()
    pool: TaskPool = TaskPool()
    round: int = 0
    announcement: Announcement = Announcement()
    board: Mapping[str, Bid] = field(default_factory=dict)
    """Each live agent's latest bid."""
    paused: bool = False
    """Allocation paused by the operator: every holder keeps its task, nothing else is
    assigned (the rounds still run, so bids keep agents alive and progress is taken)."""
    excluded: frozenset[str] = frozenset()
    """Agents the operator took out of the auction: each keeps the task it holds (until it is
    done or released) and wins nothing else. An agent that gave up ``config.exclude_after``
    different tasks in a row is taken out the same way
    (:func:`~btmission.allocation.loop.apply_progress`)."""
    cooldown: Mapping[tuple[str, str], float] = field(default_factory=dict)
    """(agent, task) → until when the agent, which gave the task up, takes no part in its
    allocation (``config.cooldown_s`` after the give-up; expired entries are dropped by the
    next round)."""
    streaks: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    """Agent → the different tasks it gave up since it last finished one (or was taken out
    of the auction for it)."""
    silent: Mapping[str, float] = field(default_factory=dict)
    """Agents dropped for silence that still hold a task → the time of their last bid: each
    keeps its task until ``config.lease_s`` after it (its lease), then the task is re-offered."""

    # -- progress reported by the agents (between rounds) ----------------------------------
    def add_task(self, info: TaskInfo, now: float | None = None) -> AuctionState:
        """An operator adds a task (announced from the next round at or after its arrival)."""
        return replace(self, pool=self.pool.add(info, now))

    def commit(self, task_id: str, agent: str, now: float) -> AuctionState:
        """``agent`` passed the commit point of ``task_id`` (also inferred from bids)."""
        return replace(self, pool=self.pool.commit(task_id, agent, now))

    def complete(self, task_id: str, agent: str, now: float) -> AuctionState:
        return replace(self, pool=self.pool.complete(task_id, agent, now))

    def fail(self, task_id: str, agent: str, now: float, reason: str = "") -> AuctionState:
        return replace(self, pool=self.pool.fail(task_id, agent, now, reason))

    def give_up(self, task_id: str, agent: str, now: float, reason: str = "") -> AuctionState:
        """``agent`` hands ``task_id`` back (:meth:`TaskPool.give_up`): unless that was the
        task's last attempt, the agent is cooled down for it (``config.cooldown_s``); the task
        joins the agent's streak of give-ups."""
        pool = self.pool.give_up(task_id, agent, now, reason)
        cooldown = self.cooldown
        if pool[task_id].state is TaskState.OPEN and self.config.cooldown_s > 0:
            cooldown = {**cooldown, (agent, task_id): now + self.config.cooldown_s}
        streak = self.streaks.get(agent, ())
        if task_id not in streak:
            streak = (*streak, task_id)
        streaks = {**self.streaks, agent: streak}
        return replace(self, pool=pool, cooldown=cooldown, streaks=streaks)

    def finished(self, agent: str) -> AuctionState:
        """``agent`` finished a task: its streak of give-ups ends."""
        if agent not in self.streaks:
            return self
        return replace(self, streaks={a: s for a, s in self.streaks.items() if a != agent})

    def holders(self) -> dict[str, str]:
        """Agent → the task it holds (assigned or committed)."""
        return self.pool.holders()


# --------------------------------------------------------------------------------------------
# Stage 1: announcement
# --------------------------------------------------------------------------------------------
def announce(state: AuctionState, now: float) -> AuctionState:
    """The state with the announcement for ``now`` (same serial if the task set is unchanged)."""
    infos = state.pool.announced_infos(now)
    ann = state.announcement
    if infos is ann.tasks or (
        len(infos) == len(ann.tasks) and all(map(is_, ann.tasks, infos))
    ):  # (the pool hands the same tuple on while the announced tasks are the same ones)
        return state
    new = Announcement(ann.serial + 1, now, infos, ann.epoch)
    return replace(state, announcement=new)


# --------------------------------------------------------------------------------------------
# Stage 3: allocation
# --------------------------------------------------------------------------------------------
def _ingest(board: Mapping[str, Bid], bids: Iterable[Bid], ignored: list[str]) -> dict[str, Bid]:
    new = dict(board)
    bids = bids if isinstance(bids, list) else list(bids)
    check = Bid._form_problem if costs_in_range(bids) else Bid.problem
    for b in bids:
        problem = check(b)
        if problem:
            ignored.append(problem)
            continue
        old = new.get(b.agent)
        if old is not None and old.time_s > b.time_s:
            ignored.append(f"bid from {b.agent} at t={b.time_s:.3f}s is older than its last one")
            continue
        new[b.agent] = b
    return new


def _matrix(
    ann: Announcement, agents: Sequence[str], board: Mapping[str, Bid]
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Bids as an agents × tasks matrix (NaN = none) and which pairs a bid covered at all."""
    na, nt = len(agents), len(ann)
    ids = ann.ids
    rows = [board[a] for a in agents]
    if na and all(b.tasks is ids for b in rows):  # every bid answers this announcement
        costs = np.array([b.costs for b in rows], dtype=np.float64)
        return costs, np.ones((na, nt), dtype=bool)
    costs = np.full((na, nt), np.nan)
    covered = np.zeros((na, nt), dtype=bool)
    index = ann.index
    remap: dict[int, tuple[NDArray[np.intp], NDArray[np.intp]]] = {}
    for i, b in enumerate(rows):
        if b.tasks is ids or b.tasks == ids:
            costs[i] = b.costs
            covered[i] = True
            continue
        key = id(b.tasks)
        if key not in remap:
            pos = np.fromiter((index.get(t, -1) for t in b.tasks), dtype=np.intp)
            src = np.nonzero(pos >= 0)[0]
            remap[key] = (src, pos[src])
        src, dst = remap[key]
        costs[i, dst] = b.costs[src]
        covered[i, dst] = True
    return costs, covered


_OUTBID: dict[int, str] = {}
"""The "outbid" reason by number of bidders (the reason of most open tasks, every round)."""


def _outbid(n: int) -> str:
    text = _OUTBID[n] = f"outbid: its {n} bidder(s) won other tasks"
    return text


_SHOWN = 3
"""Agents a reason names (the others are counted)."""


def _names(shown: Sequence[str], total: int) -> str:
    """``shown`` (the first :data:`_SHOWN` of ``total`` agents) and how many more there are."""
    return ", ".join(shown) + (f" and {total - len(shown)} more" if total > len(shown) else "")


def auction_round(
    state: AuctionState, bids: Iterable[Bid], now: float
) -> tuple[dict[str, str | None], AuctionState, RoundReport]:
    """One auction round at time ``now`` (module docstring).

    ``bids`` are the bids received since the last round (they may answer this round's or an
    earlier announcement). Returns ``(assignments, new_state, report)``: ``assignments`` maps every
    live agent to the task it should execute, or None (no task: its default behaviour).
    """
    cfg = state.config
    state = announce(state, now)
    ann = state.announcement
    ignored: list[str] = []
    board = _ingest(state.board, bids, ignored)
    pool = state.pool
    changed: dict[str, PoolTask] = {}
    changes: list[Change] = []

    def move(t: PoolTask, st: TaskState, agent: str | None, reason: str) -> None:
        changed[t.id] = t.moved(now, st, agent, reason)
        if agent != t.agent:
            changes.append(Change(t.id, t.agent, agent, reason))

    # stale agents: dropped from the auction (they win nothing new); a silent holder keeps its
    # task until its lease (lease_s after its last bid) runs out, then the task is re-offered
    stale = sorted(a for a, b in board.items() if now - b.time_s > cfg.agent_timeout_s)
    holders = state.holders()
    silent = state.silent
    if stale or silent:
        silent = {a: t for a, t in silent.items() if a not in board}  # (heard again: renewed)
        for a in stale:
            silent[a] = board.pop(a).time_s
    leased: dict[int, str] = {}
    """Announced task → the silent agent holding it within its lease (out of the matching)."""
    leasing: set[str] = set()
    for a in sorted(set(holders) - set(board)):  # silent, or holds a task but never bid
        tid = holders.pop(a)
        last = silent.get(a)
        if last is None:
            move(pool[tid], TaskState.OPEN, None, f"agent {a} is not bidding")
        elif now - last <= max(cfg.lease_s, cfg.agent_timeout_s):
            leasing.add(a)
            if tid in ann.index:
                leased[ann.index[tid]] = a
        else:
            move(
                pool[tid],
                TaskState.OPEN,
                None,
                f"lease of {a} ran out (no word for {now - last:.1f} s)",
            )
    if silent:
        silent = {a: t for a, t in silent.items() if a in leasing}
    agents = sorted(board)
    rows = [board[a] for a in agents]
    row_of = {a: i for i, a in enumerate(agents)}
    index = ann.index
    ids = ann.ids
    tasks = pool.tasks  # (every task looked up below is announced, so in the pool)

    # commit points reported with the bids (k_bt = 0)
    for a, b in zip(agents, rows):
        target = b.committed_to
        if target is None:
            continue
        t = changed.get(target) or pool.get(target)
        if t is None or t.agent != a or t.state.terminal:
            ignored.append(f"{a} reports a commit point on '{target}', which it does not hold")
        elif t.state is TaskState.ASSIGNED:
            if t.info.multi_stage:
                changed[target] = t.moved(now, TaskState.COMMITTED, a, "commit point (k_bt = 0)")
            else:
                ignored.append(f"{a} reports a commit point on '{target}', which has none")

    def current(tid: str) -> PoolTask:
        return changed.get(tid) or tasks[tid]

    # pinned pairs: a committed task stays with its agent whatever the bids; while allocation
    # is paused every holder is pinned, and an excluded agent keeps only what it holds
    paused, excluded = state.paused, state.excluded
    pinned = {
        a: tid
        for a, tid in holders.items()
        if tid in index
        and (
            paused
            or a in excluded
            or (changed.get(tid) or tasks[tid]).state is TaskState.COMMITTED  # current(tid)
        )
    }
    costs, covered = _matrix(ann, agents, board)
    na, nt = costs.shape
    if paused:  # nothing but the pinned pairs below
        costs[:] = np.nan
    elif excluded:
        for a in excluded:
            if a in row_of:
                costs[row_of[a]] = np.nan
                covered[row_of[a]] = False
    cooldown = state.cooldown
    cooling: dict[int, list[tuple[str, float]]] = {}
    """Announced task → the agents cooling down for it (they gave it up), until when."""
    if cooldown:  # (rare: only after a give-up) drop the expired, leave the others' bids out
        cooldown = {k: until for k, until in cooldown.items() if until > now}
        for (a, tid), until in sorted(cooldown.items()):
            i, j = row_of.get(a), index.get(tid)
            if i is not None and j is not None:
                costs[i, j] = np.nan
                cooling.setdefault(j, []).append((a, until))
    for a, tid in pinned.items():  # a committed agent takes part in nothing else
        i = row_of[a]
        costs[i] = np.nan
        costs[i, index[tid]] = 0.0
    held_col = [-1] * na
    for a, tid in holders.items():
        if tid in index and a not in pinned:
            held_col[row_of[a]] = index[tid]
    incumbent = np.array(held_col, dtype=np.intp)

    # participation guard: an agent bidding on more than its k cheapest is trimmed to them
    k = participation_k(cfg.participation, nt)
    if k < nt:
        for row in np.nonzero(np.count_nonzero(np.isfinite(costs), axis=1) > k)[0]:
            costs[row, ~cheapest(costs[row], k, int(incumbent[row]))] = np.nan
    unreachable = np.isinf(costs)
    n_inf = unreachable.sum(axis=0)
    costs[unreachable] = np.nan
    n_fin = np.isfinite(costs).sum(axis=0)

    # solve without the pinned agents and tasks
    winner: dict[int, str] = {index[t]: a for a, t in pinned.items()}
    if pinned or leased:
        free_rows = np.array([i for i, a in enumerate(agents) if a not in pinned], dtype=np.intp)
        free_cols = np.array(
            [j for j in range(nt) if j not in winner and j not in leased], dtype=np.intp
        )
        sub = costs[np.ix_(free_rows, free_cols)]
        col_pos = np.full(nt + 1, -1, dtype=np.intp)
        col_pos[free_cols] = np.arange(len(free_cols))
        inc_sub = col_pos[incumbent[free_rows]]  # -1 stays -1 (last slot)
        bonus = cfg.priority_scale * ann.priorities[free_cols]
    else:  # (the same, without the identity maps)
        free_rows = np.arange(na, dtype=np.intp)
        free_cols = np.arange(nt, dtype=np.intp)
        sub, inc_sub = costs, incumbent
        bonus = cfg.priority_scale * ann.priorities
    problem = AssignmentProblem.dense(sub, bonus=bonus, incumbent=inc_sub)
    method = "none"
    total = 0.0
    if problem.n_bids:
        match = solve(problem, cfg.method)
        method = match.method
        mr, mc = match.rows, match.cols
        for j, i, cost in zip(free_cols[mc].tolist(), free_rows[mr].tolist(), sub[mr, mc].tolist()):
            winner[j] = agents[i]
            total += cost  # (in the matching's order, as before)

    assignments: dict[str, str | None] = dict.fromkeys(agents)
    won_by: list[str | None] = [None] * nt
    for j, a in winner.items():
        assignments[a] = ids[j]
        won_by[j] = a

    # why no task got an agent this round, whatever the task (None: it depends on the task)
    overall: str | None = None
    if not agents:
        overall = "no agents are bidding"
    elif paused:
        overall = "allocation paused by the operator"
    elif all(a in excluded for a in agents):
        overall = "every agent is out of the auction (excluded by the operator)"

    def why(j: int) -> tuple[str, TaskState]:
        """Why announced task ``j`` got no agent, and the state that goes with it, when no
        bidder of it won another task (the publication below handles that, the common case)."""
        covering = np.flatnonzero(covered[:, j])  # the agents whose bids covered it
        who = [agents[i] for i in covering[:_SHOWN].tolist()]  # (those its reason names)
        if n_inf[j]:
            return f"unreachable: no path from {_names(who, len(covering))}", TaskState.UNREACHABLE
        if j in cooling:
            gave = cooling[j]
            names = _names([f"{a} (until t={u:.1f}s)" for a, u in gave[:_SHOWN]], len(gave))
            return f"cooling down: given up by {names}", TaskState.OPEN
        if who:
            busy = [f"{a} (committed to {pinned[a]})" if a in pinned else a for a in who]
            part = (
                f"; each agent bids on its {k} cheapest of {nt} (participation "
                f"{cfg.participation:g})"
                if k < nt
                else ""
            )
            return f"no bids: declined by {_names(busy, len(covering))}{part}", TaskState.OPEN
        return "awaiting bids (newly announced)", TaskState.OPEN

    # publish: update the pool, with reasons
    cur = list(map(tasks.__getitem__, ids))
    for tid, t in changed.items():  # (a change below is to the task at hand only)
        j = index.get(tid)
        if j is not None:
            cur[j] = t
    bidders = n_fin.tolist()
    note = recorder(PoolTask)
    unassigned: dict[str, str] = {}
    for j, t in enumerate(cur):
        who = won_by[j]
        if who is None and j in leased:  # its silent holder keeps it (within the lease)
            continue
        if who is not None:
            if t.agent == who and t.state in HELD:
                continue
            c = float(costs[row_of[who], j])
            won = f"reassigned from {t.agent}" if t.agent else "won"
            move(t, TaskState.ASSIGNED, who, f"{won} at cost {c:.4g}")
            continue
        st = TaskState.OPEN
        if overall is not None:
            reason = overall
        elif bidders[j]:
            reason = _OUTBID.get(bidders[j]) or _outbid(bidders[j])
        else:
            reason, st = why(j)
        tid = t.id
        unassigned[tid] = reason
        if t.agent is not None:
            moved_to = assignments.get(t.agent)
            lost = (
                f"{t.agent} reassigned to {moved_to}"
                if moved_to
                else f"{t.agent} lost it: {reason}"
            )
            move(t, st, None, lost)
        elif t.state is not st:
            move(t, st, None, reason)
        elif t.note != reason:  # (replace(t, note=reason) without its field checks)
            changed[tid] = note(
                info=t.info, state=t.state, agent=t.agent, note=reason, history=t.history
            )

    new_pool = pool.with_tasks(changed)
    new_state = replace(state, pool=new_pool, round=state.round + 1, board=board)
    if cooldown is not state.cooldown:
        new_state = replace(new_state, cooldown=cooldown)
    if silent is not state.silent:
        new_state = replace(new_state, silent=silent)
    report = RoundReport(
        round=new_state.round,
        time_s=now,
        serial=ann.serial,
        announced=nt,
        agents=tuple(agents),
        dropped=tuple(stale),
        assignments={a: t for a, t in assignments.items() if t is not None},
        committed=tuple(
            sorted(a for a, t in pinned.items() if current(t).state is TaskState.COMMITTED)
        ),
        unassigned=unassigned,
        changes=tuple(changes),
        ignored=tuple(ignored),
        method=method,
        bids=problem.n_bids,
        total_cost=total,
    )
    return assignments, new_state, report
