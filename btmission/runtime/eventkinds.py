"""The kinds of event a run publishes: one frozen dataclass each, registered by its kind name.

:mod:`btmission.runtime.events` has what they build on (:class:`~btmission.runtime.events.
TypedEvent`, the stream, the log) and its docstring the table of kinds and fields; a kind's
class here declares exactly the fields its producers write (``tests/unit/runtime/test_events_typed.py`` holds
the two in step). :mod:`btmission.runtime.events` imports this module, so every kind is
registered as soon as events are.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from btmission.runtime.events import (
    AgentEntry,
    Placed,
    Point,
    StatusChange,
    TreeNode,
    TypedEvent,
    optional,
    register_event,
)

if TYPE_CHECKING:
    from btmission.vehicles.provider import Vehicle


@register_event
@dataclass(frozen=True, kw_only=True)
class HeaderEvent(TypedEvent):
    """The first event of a log, from the mission alone (nothing is built yet)."""

    KIND = "header"
    format: str
    """``btmission-log``."""
    version: int
    """The log format version (:data:`LOG_VERSION`; 1: no ``world_ref``, no ``tree`` /
    ``route`` events)."""
    mission: str
    description: str | None
    file: str | None
    """The mission file, as given on the command line."""
    seed: int
    controller: str
    world: dict[str, Any] | None
    """The mission's ``world`` spec (map generator or file, resolution, topomap)."""
    world_ref: dict[str, Any] | None = optional()
    """Where to find the world from the log alone (:func:`world_reference`; version 2)."""
    map: dict[str, Any] | None = optional()
    """Early version 1 logs: the voxel map's shape, resolution, origin (now in ``built``)."""
    step_s: float | None = optional()
    part: str | None = optional()
    """A distributed run's process: ``coordinator`` or ``agents <id>, ...``
    (:meth:`~btmission.runtime.distribution.Part.describe`); absent in a one-process run."""
    auction_rate_hz: float | None = optional()
    agents: list[AgentEntry]
    """``[{id, library, vehicle, start}]``."""
    tasks: list[dict[str, Any]] | None
    """``[{id, type, at, fields}]``: the mission file's tasks."""
    artifacts: list[Placed] | None = optional()
    """``[{label, p, size_m}]``: objects placed in the simulator."""


@register_event
@dataclass(frozen=True, kw_only=True)
class BuiltEvent(TypedEvent):
    KIND = "built"
    map: dict[str, Any]
    """``{shape, resolution, origin}`` of the voxel map."""
    build_s: float
    started_unix: float | None = optional()
    """A distributed run's coordinator process: when its mission clock was zero (Unix time)."""


@register_event
@dataclass(frozen=True, kw_only=True)
class TaskAddedEvent(TypedEvent):
    KIND = "task_added"
    task: str
    type: str
    fields: dict[str, Any]
    priority: float | None = optional()
    by: str | None = optional()
    """``mission`` or ``api``."""
    problems: list[str] = field(default_factory=list)
    at: float | None = optional()
    """When it is to arrive, if later than it was added (an operator's task with ``at``): it is
    announced from then on (a restarted coordinator reads it back)."""


@register_event
@dataclass(frozen=True, kw_only=True)
class TaskStateEvent(TypedEvent):
    """A task changed state or agent (the auction pool's history)."""

    KIND = "task"
    task: str
    state: str
    """open, assigned, committed, done, failed, unreachable."""
    agent: str | None
    reason: str


@register_event
@dataclass(frozen=True, kw_only=True)
class RoundEvent(TypedEvent):
    KIND = "round"
    round: int
    announced: int
    agents: int
    method: str
    bids: int
    step_ms: float
    assignments: dict[str, str | None] | None = optional()
    """Agent → task, when they changed."""
    dropped: list[str] | None = optional()
    """Agents that stopped bidding, when there are any."""
    late_bids: int | None = optional()
    """Bids that came after their round closed, when there are any."""
    stale_bids: int | None = optional()
    """Bids for an announcement older than the round's, when there are any."""


@register_event
@dataclass(frozen=True, kw_only=True)
class AgentTaskEvent(TypedEvent):
    KIND = "agent_task"
    agent: str
    task: str | None


@register_event
@dataclass(frozen=True, kw_only=True)
class StageEvent(TypedEvent):
    KIND = "stage"
    agent: str
    task: str | None
    action: str


@register_event
@dataclass(frozen=True, kw_only=True)
class CommittedEvent(TypedEvent):
    KIND = "committed"
    agent: str
    task: str


@register_event
@dataclass(frozen=True, kw_only=True)
class ProgressEvent(TypedEvent):
    KIND = "progress"
    agent: str
    task: str
    event: str
    """done, failed, committed or gave_up (the agent hands the task back: its vehicle kept
    refusing a command)."""
    reason: str


@register_event
@dataclass(frozen=True, kw_only=True)
class RetryEvent(TypedEvent):
    """An action asks its vehicle again, after a back-off, for a command the vehicle refused
    transiently (arming refused, OFFBOARD denied, no answer): the leaf keeps running."""

    KIND = "retry"
    agent: str
    task: str | None
    """The agent's task (null: its default behaviour)."""
    action: str
    retry: int
    """This retry's number, 1 … ``retries``."""
    retries: int
    """How many the action makes before it gives up (the ``refusal_retries`` setting)."""
    reason: str
    """The vehicle's refusal."""
    wait_s: float
    """The back-off before it asks again (mission time)."""


@register_event
@dataclass(frozen=True, kw_only=True)
class AttemptEvent(TypedEvent):
    """An agent's attempt at a task ended without success, as the coordinator took it: the
    agent gave the task up (back to the pool, or failed for good at ``max_attempts``) or
    reported it failed. Logged before the ``task`` event of the change it made."""

    KIND = "attempt"
    task: str
    agent: str
    attempt: int
    """Its number (1 for the task's first)."""
    max_attempts: int
    reason: str
    """The agent's reason."""
    gave_up: bool
    """True: handed back (its vehicle kept refusing); false: the task failed."""
    state: str
    """The task's state after it: open (offered to the others) or failed."""
    cooldown_until: float | None = optional()
    """Until when the agent takes no part in the task's allocation (a give-up that left the
    task open, with ``coordination.cooldown_s`` > 0)."""


@register_event
@dataclass(frozen=True, kw_only=True)
class AgentExcludedEvent(TypedEvent):
    """The coordinator took an agent out of the auction, as the operator's exclude does: it
    gave up ``coordination.exclude_after`` different tasks in a row (IncludeAgent brings it
    back)."""

    KIND = "agent_excluded"
    agent: str
    tasks: list[str]
    """The tasks it gave up, in order."""
    reason: str


@register_event
@dataclass(frozen=True, kw_only=True)
class PoseEvent(TypedEvent):
    KIND = "pose"
    agent: str
    p: Point
    v: Point | None
    yaw: float | None
    mode: str | None
    armed: bool | None
    flying: bool | None
    odometer_m: float | None
    """The distance travelled (null: not measured: a real vehicle)."""
    clearance_m: float | None
    """The smallest distance to rock since the previous pose (null: not measured)."""

    @classmethod
    def of(cls, agent: str, vehicle: Vehicle) -> PoseEvent:
        """Agent ``agent``'s pose now: its vehicle's telemetry, and the provider's ground truth
        (the simulator's odometer and clearance; null on real vehicles)."""
        tel = vehicle.backend.telemetry()
        return cls(
            agent=agent,
            p=[float(c) for c in tel.position],
            v=[float(c) for c in tel.velocity],
            yaw=tel.yaw,
            mode=tel.mode.value,
            armed=tel.armed,
            flying=not tel.landed,
            odometer_m=vehicle.odometer_m() if vehicle.odometer_m else None,
            clearance_m=vehicle.clearance_m() if vehicle.clearance_m else None,
        )


@register_event
@dataclass(frozen=True, kw_only=True)
class CollisionEvent(TypedEvent):
    KIND = "collision"
    agent: str
    other: str
    """``rock`` or another agent's id."""
    p: Point


@register_event
@dataclass(frozen=True, kw_only=True)
class AgentLostEvent(TypedEvent):
    KIND = "agent_lost"
    agent: str
    reason: str


@register_event
@dataclass(frozen=True, kw_only=True)
class SignalEvent(TypedEvent):
    KIND = "signal"
    agent: str
    name: str
    value: Any


@register_event
@dataclass(frozen=True, kw_only=True)
class LinkEvent(TypedEvent):
    KIND = "link"
    agent: str
    up: bool


@register_event
@dataclass(frozen=True, kw_only=True)
class VehicleLinkEvent(TypedEvent):
    """The agent lost (``up`` false) or heard again its vehicle's autopilot."""

    KIND = "vehicle_link"
    agent: str
    up: bool
    mode: str | None = optional()
    """The vehicle's mode when its link came back (the failsafe it took meanwhile)."""


@register_event
@dataclass(frozen=True, kw_only=True)
class CoordinatorLinkEvent(TypedEvent):
    """The agent lost (``up`` false: nothing heard from it for ``coordination.agent_timeout_s``)
    or heard again its coordinator. While it is lost the agent keeps its task within its lease
    (``coordination.lease_s``) and stops it ``agent_timeout_s`` before the lease ends."""

    KIND = "coordinator_link"
    agent: str
    up: bool
    silent_s: float
    """How long nothing had been heard from the coordinator."""


@register_event
@dataclass(frozen=True, kw_only=True)
class TakenOverEvent(TypedEvent):
    """The vehicle's autopilot (a failsafe) or its pilot took it over: it left the flight the
    tree was flying for a mode nobody in the mission asked for. The agent stands down — its
    task goes back to the pool, it bids no more and sends no setpoints or commands — until
    the operator includes it again (``include_agent``)."""

    KIND = "taken_over"
    agent: str
    mode: str
    """The mode the vehicle is in (``MANUAL`` for a mode of the pilot's: RTL, ALTCTL ...)."""
    failsafe: bool
    """The autopilot reports a failsafe (HEARTBEAT's system status CRITICAL/EMERGENCY)."""
    final: bool
    """The agent stood down (``runtime.settings.takeover_is_final``, the default); false: its
    tree flies on."""
    task: str | None = optional()
    """The task handed back to the pool (when ``final``)."""


@register_event
@dataclass(frozen=True, kw_only=True)
class ObjectsEvent(TypedEvent):
    KIND = "objects"
    agent: str
    objects: list[Placed]
    """``[{label, p, observations}]``."""
    rejected: dict[str, Any] | None = optional()


@register_event
@dataclass(frozen=True, kw_only=True)
class JunctionEvent(TypedEvent):
    """DPHR saw several deep regions (a junction) and chose one to follow (library ``compra``)."""

    KIND = "junction"
    agent: str
    offsets: list[float]
    """Each branch's normalised centroid column s̄_x ∈ [−1, 1] (negative = left)."""
    chosen: int
    """Index of the followed branch in ``offsets``."""


@register_event
@dataclass(frozen=True, kw_only=True)
class JunctionSwitchEvent(TypedEvent):
    """Within one junction DPHR left the branch it followed for another (s̄_x ``was`` → the
    chosen one's), because the other grew more than ``switch_ratio`` times larger."""

    KIND = "junction_switch"
    agent: str
    offsets: list[float]
    chosen: int
    was: float


@register_event
@dataclass(frozen=True, kw_only=True)
class RelocalizedEvent(TypedEvent):
    """An agent localised itself in the map from one LiDAR scan (library ``aerial_mine``)."""

    KIND = "relocalized"
    agent: str
    task: str | None
    localized: bool
    confidence: float | None
    fitness: float | None
    reason: str
    points: int
    sensor: str | None
    time_ms: float | None
    truth: dict[str, Any]
    """The telemetry pose ``{x, y, z, yaw_deg}`` (the true pose in the simulator)."""
    estimate: dict[str, Any] | None = optional()
    error_m: float | None = optional()
    error_deg: float | None = optional()


@register_event
@dataclass(frozen=True, kw_only=True)
class LeafErrorEvent(TypedEvent):
    KIND = "leaf_error"
    agent: str | None = optional()
    """The agent whose leaf raised (absent: a run-wide service)."""
    task: str | None = optional(written_with="agent")
    """The agent's task then (null: none)."""
    leaf: str
    """The leaf (e.g. ``scan(location)``) or ``service <library>.<name>``."""
    phase: str
    error: str
    message: str
    where: str
    traceback: str


@register_event
@dataclass(frozen=True, kw_only=True)
class WarningEvent(TypedEvent):
    KIND = "warning"
    agent: str | None = optional()
    variable: str | None = optional()
    leaf: str | None = optional()
    message: str


@register_event
@dataclass(frozen=True, kw_only=True)
class InternalErrorEvent(TypedEvent):
    KIND = "internal_error"
    type: str
    message: str
    traceback: str


@register_event
@dataclass(frozen=True, kw_only=True)
class EndEvent(TypedEvent):
    KIND = "end"
    reason: str
    wall_s: float | None
    steps: int | None = optional()
    done: list[str] = field(default_factory=list)
    open: dict[str, str] = field(default_factory=dict)
    pending: list[str] = field(default_factory=list)
    cancelled: list[str] | None = optional()
    """Tasks the operator cancelled (only when there are any)."""


@register_event
@dataclass(frozen=True, kw_only=True)
class DispatchEvent(TypedEvent):
    """What the fleet dispatcher (seed 004) did for a truck."""

    KIND = "dispatch"
    truck: str
    event: str
    """requested, withdrawn, failed, deferred, adopted."""
    goal: str | None
    reason: str | None = optional()
    to: str | None = optional()
    items: int | None = optional()
    depart: float | None = optional(written_with="arrive")
    """When the truck leaves (null: a mission of no items)."""
    arrive: float | None = optional()
    mission: dict[str, Any] | None = optional()


@register_event
@dataclass(frozen=True, kw_only=True)
class RouteEvent(TypedEvent):
    """An agent adopted a new planned path (D*+), decimated to at most
    :data:`~btmission.runtime.navconfig.ROUTE_EVENT_POINTS` points."""

    KIND = "route"
    agent: str
    task: str | None
    points: list[Point]
    length_m: float
    """The whole path's length (before decimation)."""


@register_event
@dataclass(frozen=True, kw_only=True)
class TreeEvent(TypedEvent):
    """Behaviour-tree nodes of an agent whose status changed (the net change since the agent's
    previous ``tree`` event; BehaviorTree.CPP's StatusChangeLogger)."""

    KIND = "tree"
    agent: str
    changes: list[StatusChange]
    """``[[uid, old, new], ...]``: uid is the node's pre-order index (the root is 0), statuses
    are py_trees' (``INVALID``, ``RUNNING``, ``SUCCESS``, ``FAILURE``)."""
    nodes: list[TreeNode] | None = optional()
    """In an agent's first ``tree`` event only: the tree, ``[[name, parent uid, kind], ...]`` in
    uid order (the root's parent is -1; kind: fallback, sequence, condition, action)."""
    blackboard: dict[str, Any] | None = optional()
    """The agent's blackboard keys that changed since its previous ``tree`` event: key → value
    as shown (:func:`~btmission.runtime.treestatus.blackboard_value`)."""
    unset: list[str] | None = optional()
    """Blackboard keys removed since the previous ``tree`` event."""


@register_event
@dataclass(frozen=True, kw_only=True)
class CommandEvent(TypedEvent):
    """An operator's command, applied between two steps (:mod:`btmission.runtime.commands`):
    who sent it, what it was, and whether it was refused (``error``). Its arguments follow as
    fields of their own (``task``, ``agent``, ``priority``, ``up``, ``reason`` ...)."""

    KIND = "command"
    EXTRA_AFTER = "by"
    command: str
    by: str
    ok: bool
    error: str | None = optional()

    @property
    def args(self) -> Mapping[str, Any]:
        """The command's arguments (written between ``by`` and ``ok``)."""
        return self.extra


@register_event
@dataclass(frozen=True, kw_only=True)
class WithdrawnEvent(TypedEvent):
    """An agent's assignment was withdrawn: another agent's earlier completion (or commit
    point) of the same task reached the coordinator late (a link that was down)."""

    KIND = "withdrawn"
    agent: str
    task: str
    by: str
    """The agent whose report took the task."""
    reason: str


@register_event
@dataclass(frozen=True, kw_only=True)
class ClockEvent(TypedEvent):
    """An agent process set its mission clock to its coordinator's (docs/distributed.md)."""

    KIND = "clock"
    agent: str
    was_s: float
    """What its clock said."""
    now_s: float
    """The coordinator's time it took."""


@register_event
@dataclass(frozen=True, kw_only=True)
class ResumedEvent(TypedEvent):
    """A coordinator restarted from its log goes on writing it (docs/distributed.md): what it
    logs next continues the run this log began."""

    KIND = "resumed"
    log: str
    """The log it rebuilt its state from (this one)."""
    last_s: float
    """The mission time of the last event it found there."""
