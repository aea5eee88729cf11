"""Immutable snapshots of a running mission, for readers on other threads.

The run loop owns every mutable object (agents, coordinator, vehicles); a viewer, an operator
console or a progress display on another thread must not read them while a step changes them.
Instead, after each step the loop publishes a :class:`RunSnapshot` — frozen dataclasses and
tuples, built from plain values — by replacing one reference (atomic in CPython). A reader takes
:attr:`~btmission.runtime.runner.MissionRun.snapshot` and may keep it as long as it likes: it
never changes.

The task pool is immutable already (:class:`~btmission.allocation.tasks.TaskPool`), so a
snapshot's tasks are read from the pool it was taken with, only when asked for
(:attr:`RunSnapshot.tasks`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from btmission.allocation.tasks import TaskPool
from btmission.vehicles.base import Vec3

if TYPE_CHECKING:
    from btmission.runtime.agent import Agent
    from btmission.runtime.runner import MissionRun


@dataclass(frozen=True)
class TaskSnapshot:
    """One task as it stands: state, holder, priority, and why (the pool's note)."""

    id: str
    type: str
    state: str
    agent: str | None
    priority: float
    arrival_s: float
    note: str


@dataclass(frozen=True)
class AgentSnapshot:
    """One agent as it stands."""

    id: str
    position: Vec3
    yaw: float
    mode: str
    armed: bool
    alive: bool
    link_up: bool
    task: str | None
    action: str
    """The action its tree started last (``stage`` event)."""
    tree: Mapping[int, str] = field(default_factory=lambda: MappingProxyType({}))
    """Node uid (pre-order index, as in ``tree`` events) → status (``SUCCESS``, ``FAILURE``,
    ``RUNNING``, ``INVALID``) after its last tick."""
    tree_nodes: tuple[tuple[str, int, str], ...] = ()
    """``(name, parent uid, kind)`` by uid (the root's parent is -1): what names the statuses of
    :attr:`tree`, for a reader that did not see the agent's first ``tree`` event."""
    recalled: bool = False
    """The operator recalled it (it bids no more; its default behaviour runs)."""
    vehicle: str = "multirotor"
    """Its vehicle's kind (:class:`~btmission.vehicles.base.VehicleKind`: ``multirotor`` or
    ``ground``)."""


@dataclass(frozen=True)
class RunSnapshot:
    """The whole run after one step (module docstring)."""

    time_s: float
    steps: int
    agents: tuple[AgentSnapshot, ...]
    pool: TaskPool = field(repr=False, compare=False)
    ended: str | None = None
    """Why the run ended (None while it runs)."""
    paused: bool = False
    """Allocation paused by the operator."""
    excluded: frozenset[str] = frozenset()
    """Agents the operator took out of the auction."""

    @cached_property
    def tasks(self) -> tuple[TaskSnapshot, ...]:
        """The tasks that have arrived, in the pool's order."""
        return tuple(
            TaskSnapshot(
                t.id,
                t.info.type,
                t.state.value,
                t.agent,
                t.info.priority,
                t.info.arrival_s,
                t.note,
            )
            for t in self.pool
            if t.info.arrival_s <= self.time_s + 1e-9
        )

    def agent(self, agent_id: str) -> AgentSnapshot:
        for a in self.agents:
            if a.id == agent_id:
                return a
        raise KeyError(agent_id)

    def task(self, task_id: str) -> TaskSnapshot:
        for t in self.tasks:
            if t.id == task_id:
                return t
        raise KeyError(task_id)

    def counts(self) -> dict[str, int]:
        """Arrived tasks per state (what a progress line shows)."""
        out: dict[str, int] = {}
        for t in self.tasks:
            out[t.state] = out.get(t.state, 0) + 1
        return out


class SnapshotTaker:
    """Takes a run's snapshots, keeping what never changes between two (each agent's tree
    nodes) or changes only when the agent ticks (its tree's statuses)."""

    def __init__(self) -> None:
        self._trees: dict[str, tuple[tuple[int, Any], Mapping[int, str]]] = {}
        self._nodes: dict[str, tuple[tuple[str, int, str], ...]] = {}

    def _tree_nodes(self, agent: Agent) -> tuple[tuple[str, int, str], ...]:
        """The agent's tree nodes as immutable tuples (built once: the tree never changes)."""
        nodes = self._nodes.get(agent.id)
        if nodes is None:
            nodes = self._nodes[agent.id] = tuple(
                (str(n[0]), int(n[1]), str(n[2])) for n in agent.tree_nodes
            )
        return nodes

    def take(self, run: MissionRun, ended: str | None = None) -> RunSnapshot:
        """The run as it stands now (``ended``: why it ended, if it has)."""
        agents = []
        for aid, a in run.agents.items():
            tel = a.ctx.telemetry()
            p = tel.position
            key = (a.ticks, a.task)  # a tree changes when it ticks, or stops for a new task
            cached = self._trees.get(aid)
            if cached is None or cached[0] != key:
                cached = self._trees[aid] = (key, a.tree_status)
            tree = cached[1]
            agents.append(
                AgentSnapshot(
                    aid,
                    (float(p[0]), float(p[1]), float(p[2])),
                    float(tel.yaw),
                    tel.mode.value,
                    bool(tel.armed),
                    a.alive,
                    run.link_up(aid),
                    a.task.id if a.task is not None else None,
                    a.action,
                    tree,
                    self._tree_nodes(a),
                    a.recalled,
                    run.vehicles[aid].kind.value,
                )
            )
        state = run.coordinator.state
        return RunSnapshot(
            run.now(),
            run.steps,
            tuple(agents),
            state.pool,
            ended,
            state.paused,
            state.excluded,
        )
