"""The agent runtime: one robot's mission tree, ticked at a fixed rate, bidding in the auction.

An :class:`Agent` holds (seed 000 §IV-C, Fig. 3-4, Fig. 7; seed 003 §V):

* its **mission tree** — :func:`~btmission.synthesis.mission_tree.build_mission_tree` turned into
  py_trees with every leaf bound to the library's implementations through an
  :class:`~btmission.runtime.leaves.AgentContext` — ticked every ``1 / tick_hz`` seconds;
* its **blackboard**, where the current task's fields are written when a task is assigned;
* a **bidder** (:class:`~btmission.allocation.bidder.Bidder`) whose path costs come from D*+
  (:class:`~btmission.runtime.paths.PathCosts`): on every announcement it answers with
  ``c_kj = f_cost(T_j, state) · k_bt`` (eq. 8-10);
* **k_bt from the tree**: a task type with ``commit_after`` (e.g. ``holding(pickup)``) puts that
  condition in its branch; once a tick leaves it SUCCESS the agent is committed (k_bt = 0 for its
  task, no bids on anything else) and says so to the coordinator;
* its :class:`~btmission.runtime.navigation.Navigator`, stepped every control period.

The tree is ticked through a py_trees ``BehaviourTree``
(:class:`~btmission.runtime.treestatus.LeanBehaviourTree`) whose
:class:`~btmission.runtime.treestatus.TreeStatusLogger` publishes the nodes whose status changed
(``tree`` events, throttled by the ``tree_event_s`` setting; :attr:`Agent.tree_status` is the
current status of every node); every new path the navigator adopts is a ``route`` event.

When the task branch's goal holds (the branch returns SUCCESS) the agent reports the task done;
when the branch fails it reports it failed, with the reason of the action that failed — unless
that action failed because the vehicle refused it (:attr:`StatefulAction.refused
<btmission.runtime.leaves.StatefulAction.refused>`: arming refused after its retries, a mode the
vehicle will not take): then the task is not the problem, so the agent *gives it up* (progress
``gave_up``) and the coordinator offers it to the others. Until the coordinator has
acknowledged that, the agent does not follow an assignment of the task it gave up (one sent
before the coordinator knew). Without a task, the idle timer runs and the default branch (e.g.
return home and land) takes over after ``idle_timeout_s``. Progress reports are kept until the
coordinator acknowledges them, so one made while the agent's link is down is delivered when the
link returns.

Over a network an older message can arrive after a newer one. The agent follows an assignment
only if it is newer than the last one it followed, and bids on an announcement only if it is
not older than the last one it bid on (:class:`Freshness`: the coordinator's epoch, then the
round or the serial).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import py_trees
from py_trees.common import Status

from btmission.allocation.auction import Announcement
from btmission.allocation.bidder import AgentState, CostProvider
from btmission.allocation.loop import Progress
from btmission.allocation.tasks import TaskInfo
from btmission.diagnostics import Diagnostic, Severity, SpecError
from btmission.fastpaths.ticks import FAILURE as _FAILURE
from btmission.fastpaths.ticks import SUCCESS as _SUCCESS
from btmission.links.bus import (
    AgentLink,
    AgentStatus,
    Assignment,
    ProgressAck,
    ProgressKey,
    progress_key,
)
from btmission.plugins import Implementations
from btmission.recursion import main_thread_limit, recursion_for_depth, recursion_limit
from btmission.runtime.actions import CommandRetrySettings
from btmission.runtime.eventkinds import (
    AgentTaskEvent,
    CommittedEvent,
    CoordinatorLinkEvent,
    LeafErrorEvent,
    ProgressEvent,
    RouteEvent,
    StageEvent,
    TakenOverEvent,
    TreeEvent,
    VehicleLinkEvent,
    WarningEvent,
)
from btmission.runtime.events import (
    EmitEvent,
    GenericEvent,
    TypedEvent,
)
from btmission.runtime.leaves import (
    BUILTIN_ACTIONS,
    BUILTIN_CONDITIONS,
    AgentContext,
    AgentView,
    Blackboard,
    ConditionLeaf,
    ErrorReporter,
    StatefulAction,
    describe,
    setup_failed,
)
from btmission.runtime.mission_auction import bidder_for_agent
from btmission.runtime.navconfig import route_points
from btmission.runtime.navigation import Navigator
from btmission.runtime.paths import PathCosts
from btmission.runtime.substitution import Substitutions
from btmission.runtime.treestatus import (
    LeanBehaviourTree,
    TreeEventSettings,
    TreeStatusLogger,
    blackboard_value,
)
from btmission.settings import settings_of
from btmission.spec.mission import Mission
from btmission.spec.source import format_path
from btmission.synthesis.mission_tree import build_mission_tree
from btmission.synthesis.pytrees import behaviour_depth, build_behaviour_tree
from btmission.synthesis.tree import Kind, Node, Role
from btmission.types import recorder
from btmission.vehicles.base import Backend, Mode, Sensors, VehicleKind

PROGRESS_RESEND_S = 1.0
"""A progress report the coordinator has not acknowledged after this long is sent again (the
coordinator ignores copies it has seen)."""


class Freshness:
    """Which of the coordinator's messages are new enough to act on (pure bookkeeping).

    Every announcement and assignment carries the coordinator's epoch (its incarnation,
    :class:`~btmission.allocation.auction.Announcement`), and within an epoch a count that only
    grows: an assignment's round, an announcement's serial. :meth:`accept` says whether a
    message is to be acted on:

    * within the epoch last seen, a count lower than the last accepted one of its ``stream`` is
      old (delivered late); with ``strict``, so is an equal one (an assignment already
      followed; an announcement is repeated every round, each time to be bid on);
    * another epoch is accepted (the coordinator restarted; its counts start again) and the
      previous one is retired: a message of a retired epoch is old from then on;
    * epoch 0 (unknown: a sender of wire format 1, a message made by hand) is always accepted,
      as before epochs existed.
    """

    RETIRED_KEPT = 16

    def __init__(self) -> None:
        self.epoch: int | None = None
        self.last: dict[str, int] = {}
        self.retired: list[int] = []
        self.ignored = 0
        """Messages :meth:`accept` refused."""

    def accept(self, stream: str, epoch: int, count: int, strict: bool) -> bool:
        if epoch == 0:
            return True
        if epoch != self.epoch:
            if epoch in self.retired:
                self.ignored += 1
                return False
            if self.epoch is not None:
                self.retired = [*self.retired, self.epoch][-self.RETIRED_KEPT :]
            self.epoch, self.last = epoch, {}
        last = self.last.get(stream)
        if last is not None and (count < last or (strict and count == last)):
            self.ignored += 1
            return False
        self.last[stream] = count
        return True


@dataclass
class _Outgoing:
    """A progress report waiting for the coordinator's acknowledgement."""

    report: Progress
    sent_s: float | None = None
    """Mission time it was last sent (None: not yet: the link was down)."""


class Agent:
    """One agent (module docstring). The runtime calls :meth:`tick` and :meth:`control_step`."""

    def __init__(
        self,
        mission: Mission,
        agent_id: str,
        implementations: Implementations,
        backend: Backend,
        sensors: Sensors | None,
        navigator: Navigator,
        paths: PathCosts,
        link: AgentLink,
        clock: Callable[[], float],
        *,
        settings: Mapping[str, Any],
        emit: EmitEvent,
        namespace: str = "",
        services: Mapping[str, Any] | None = None,
        places: Mapping[str, tuple[float, float, float]] | None = None,
        cost_provider: CostProvider | None = None,
        substitutions: Substitutions | None = None,
        vehicle_link: Callable[[], bool] | None = None,
    ) -> None:
        spec = mission.agent(agent_id)
        self.id = agent_id
        self.mission = mission
        self.link = link
        self.clock = clock
        self.navigator = navigator
        self._emit = emit
        self.errors = ErrorReporter(
            self._leaf_event, lambda: (self.id, self.task.id if self.task else None)
        )
        """Exceptions raised by the library's leaves → ``leaf_error`` events (once each)."""
        self._warned: set[str] = set()
        self.blackboard = Blackboard(f"{namespace}/agents/{agent_id}")
        self.ctx = AgentContext(
            agent_id=agent_id,
            blackboard=self.blackboard,
            backend=backend,
            sensors=sensors,
            navigator=navigator,
            paths=paths,
            clock=clock,
            settings=settings,
            start=spec.start,
            agent=AgentView(self),
            events=self._leaf_event,
            services=services if services is not None else {},
        )
        self.blackboard.set("start", spec.start)
        self._vehicle_link = vehicle_link
        self.vehicle_link_up = True
        """The vehicle is heard (:attr:`Vehicle.link_ok`); the tree pauses while it is not."""
        self._resume_offboard_until: float | None = None
        self._mode_before_loss: Mode | None = None
        self.mission_tree = build_mission_tree(mission, agent_id)
        self.root = build_behaviour_tree(  # quiet: the status visitor needs no yields
            self.mission_tree.tree, self._leaf_factory(implementations, substitutions), quiet=True
        )
        self._branches = {
            child.name: child for child in self.root.children if child.name.startswith("task(")
        }
        self._commit_leaves = self._find_commit_leaves()
        self._default = next((c for c in self.root.children if c.name == "default"), None)
        self._blackboard_sent: dict[str, Any] = {}
        self._blackboard_version = -1
        """The blackboard as the last ``tree`` event showed it (its keys' display values)."""
        self.tree = LeanBehaviourTree(self.root)
        """The root in py_trees' tree custodian: ticks run its visitors and post-tick handlers."""
        self._tree_log = TreeStatusLogger(
            self.tree,
            self._tree_event,
            clock,
            settings_of(settings, TreeEventSettings).tree_event_s,
            dirty=lambda: self.blackboard.version != self._blackboard_version,
        )
        navigator.on_route = self._route_event
        depth = behaviour_depth(self.root)
        need = recursion_for_depth(depth, frames_per_level=4)
        deep = 4 * depth > sys.getrecursionlimit() // 2  # more than half the frames left
        self._recursion: int | None = need if deep else None
        """py_trees ticks and stops recurse once per level: a deep tree (a long chain library)
        gets the recursion limit it needs around those calls (see btmission.recursion); a
        tree that needs less than half the limit is ticked as it is (raising and restoring the
        limit at every tick cost a fleet's loop a few per cent)."""
        if need > main_thread_limit():  # the process would crash (SIGSEGV), not raise
            path = ("agents", next(i for i, a in enumerate(mission.agents) if a.id == agent_id))
            raise SpecError([Diagnostic(
                Severity.ERROR, "tree-too-deep",
                f"agent {agent_id}'s mission tree is {depth:,} levels deep; a run ticks trees up "
                f"to about {(main_thread_limit() - sys.getrecursionlimit()) // 4:,} levels with "
                "this stack (ulimit -s); synth, the exports and the dry run take deeper ones",
                format_path(path), mission.locate(path))])  # fmt: skip
        self.bidder = bidder_for_agent(
            mission,
            agent_id,
            provider=cost_provider if cost_provider is not None else paths,
            types=self.task_types,
            places=places,
        )
        self.task: TaskInfo | None = None
        self.committed = False
        self.idle_since = 0.0
        self.finished: set[str] = set()
        self.action = ""
        self._failure = ""
        self._refused = False
        """The failure noted this tick is the vehicle's refusal (:meth:`note_failure`)."""
        self._given_back: set[str] = set()
        """Tasks given up whose report the coordinator has not acknowledged yet."""
        self.alive = True
        self.recalled = False
        self.stood_down: str | None = None
        """Why the agent stands down (its vehicle was taken over: :meth:`_taken_over`), or
        None; the operator's include clears it."""
        self._seen: tuple[Mode, bool] | None = None
        """The vehicle's mode and whether it flew, at the last tick that heard it."""
        self.ticks = 0
        self.last_announcement: Announcement | None = None
        self.freshness = Freshness()
        """Which announcements and assignments are new enough to act on."""
        for hook in implementations.setup_hooks:
            try:
                hook(self.ctx)
            except Exception as exc:  # the library's code: a clear error, exit 2
                name = getattr(hook, "__qualname__", repr(hook))
                raise setup_failed(
                    "setup-failed",
                    f"library '{implementations.library}': setup hook {name} failed for agent "
                    f"{agent_id}: {describe(exc)}",
                    f"agents.{agent_id}",
                    mission.file,
                ) from exc
        coord = mission.spec.coordination
        self._timeout_s = float(coord.agent_timeout_s)
        self._lease_s = float(coord.lease_s)
        self._heard_s: float | None = None
        """When the coordinator was last heard (any message), None before the first tick."""
        self.coordinator_up = True
        """The coordinator was heard within ``agent_timeout_s`` (:meth:`_coordinator_heard`)."""
        self._outbox: dict[ProgressKey, _Outgoing] = {}
        """Progress reports not acknowledged yet, oldest first."""
        link.connect(self.on_announcement, self.on_assignment, self.on_ack)

    # ---------------------------------------------------------------- tree construction
    @property
    def task_types(self) -> list[str]:
        """The task types this agent's library can do (it bids on those only)."""
        return list(self.mission_tree.branches.keys() - {"default"})

    def _leaf_factory(
        self, impl: Implementations, substitutions: Substitutions | None = None
    ) -> Callable[[Node], py_trees.behaviour.Behaviour]:
        ctx = self.ctx

        def leaf(node: Node) -> py_trees.behaviour.Behaviour:
            if substitutions:  # a test replaces this leaf (btmission.runtime.substitution)
                substitute = substitutions.leaf(self.id, node, ctx)
                if substitute is not None:
                    return substitute
            builtin = node.role is Role.BUILTIN
            if node.kind is Kind.CONDITION:
                fn = BUILTIN_CONDITIONS[node.name] if builtin else impl.conditions[node.name]
                return ConditionLeaf(node, fn, ctx)
            cls: type[StatefulAction] = (
                BUILTIN_ACTIONS[node.name] if builtin else impl.actions[node.name]
            )
            return cls(node, ctx)

        return leaf

    def _find_commit_leaves(self) -> dict[str, list[py_trees.behaviour.Behaviour]]:
        """Per task branch with ``commit_after``, the condition leaves that check it."""
        out: dict[str, list[py_trees.behaviour.Behaviour]] = {}
        for node in self.mission_tree.tree.children:
            commit = node.get_meta("commit_after")
            if commit is None:
                continue
            branch = self._branches[node.name]
            out[node.name] = [
                b
                for b in branch.iterate()
                if isinstance(b, ConditionLeaf) and b.node.label == commit
            ]
        return out

    # ---------------------------------------------------------------- messages
    def on_announcement(self, ann: Announcement) -> None:
        """Bid on the announced tasks (stage 2 of the auction)."""
        if not self.alive:
            return
        self._heard(self.clock())
        if self.recalled or self.stood_down is not None:
            return
        if not self.freshness.accept("announcement", ann.epoch, ann.serial, strict=False):
            return  # an older announcement delivered late: its bid would be stale
        self.last_announcement = ann
        now = self.clock()
        self._send_progress(now)  # the coordinator is reachable: reports queued go first
        tel = self.ctx.telemetry()
        p = tel.position
        state = recorder(AgentState)(  # (every agent, every round)
            id=self.id,
            position=(float(p[0]), float(p[1]), float(p[2])),
            task=self.task.id if self.task is not None else None,
            committed=self.committed,
        )
        self.link.send_bid(self.bidder.bid(ann, state, now))

    def on_assignment(self, msg: Assignment) -> None:
        """Follow ``msg`` if it is newer than the last assignment followed (:class:`Freshness`;
        an older one delivered late would undo it) and names this agent."""
        if not self.alive:
            return
        self._heard(self.clock())
        if not self.freshness.accept("assignment", msg.announcement.epoch, msg.round, True):
            return
        if self.id not in msg.tasks:
            return
        task_id = msg.tasks[self.id]
        current = self.task.id if self.task is not None else None
        if task_id == current or (task_id is not None and task_id in self.finished):
            return
        if task_id in self._given_back:  # sent before the coordinator took the give-up
            return
        info = None
        if task_id is not None:
            for t in msg.announcement.tasks:
                if t.id == task_id:
                    info = t
                    break
            if info is None:
                return
        self._switch(info, msg.time_s)

    def _switch(self, info: TaskInfo | None, now: float) -> None:
        """Start executing ``info`` (None: no task). Halts the tree so every action restarts
        with the new task's fields."""
        if self.task is not None and info is None:
            self.idle_since = now
        self.task = info
        self.committed = False
        if info is not None:
            for k, v in info.fields.items():
                self.blackboard.set(k, tuple(v) if isinstance(v, list) else v)
            self.blackboard.set("task", info.id)
        else:
            self.blackboard.unset("task")
        self._deep(lambda: self.root.stop(Status.INVALID))
        self._tree_log.collect()
        self._emit(AgentTaskEvent(agent=self.id, task=info.id if info else None))

    # ---------------------------------------------------------------- ticking
    def _deep(self, fn: Callable[[], None]) -> None:
        """``fn()`` (a py_trees call that recurses per level) with the limit this tree needs."""
        if self._recursion is None:
            fn()
            return
        with recursion_limit(self._recursion):
            fn()

    def tick(self, now: float) -> Status:
        """Tick the mission tree once; report commit points, completions and failures."""
        if not self.alive:
            return Status.INVALID
        self._failure = ""
        self._refused = False
        self._send_progress(now)
        self._coordinator_heard(now)
        if not self._vehicle_heard(now):
            return Status.RUNNING  # paused: nothing the tree does can reach the vehicle
        if self._taken_over(now):
            return Status.RUNNING  # stood down: the autopilot or the pilot has the vehicle
        if self._resume_offboard_until is not None:
            self._resume_offboard(now)
        self._deep(self.tree.tick)
        self.ticks += 1
        task = self.task
        if task is not None:
            branch = self._branches.get(f"task({task.type})")
            if branch is not None:
                if not self.committed and any(
                    leaf.status is _SUCCESS for leaf in self._commit_leaves.get(branch.name, [])
                ):
                    self.committed = True
                    self._progress(task.id, "committed", now)
                    self._emit(CommittedEvent(agent=self.id, task=task.id))
                if branch.status is _SUCCESS:
                    self.finished.add(task.id)
                    self._progress(task.id, "done", now)
                    self.task = None
                    self.committed = False
                    self.idle_since = now
                    self._emit(AgentTaskEvent(agent=self.id, task=None))
                elif branch.status is _FAILURE:
                    reason = self._failure or "the task's behaviour tree failed"
                    if self._refused:  # the vehicle, not the task: another agent may do it
                        self._given_back.add(task.id)
                        self._progress(task.id, "gave_up", now, reason)
                    else:
                        self.finished.add(task.id)
                        self._progress(task.id, "failed", now, reason)
                    self.task = None
                    self.committed = False
                    self.idle_since = now
                    self._emit(AgentTaskEvent(agent=self.id, task=None))
        return self.root.status

    def _progress(self, task: str, event: str, now: float, reason: str = "") -> None:
        p = Progress(self.id, task, event, now, reason)  # type: ignore[arg-type]
        self._outbox[progress_key(p)] = _Outgoing(p)
        self._send_progress(now)
        self._emit(ProgressEvent(agent=self.id, task=task, event=event, reason=reason))

    def _send_progress(self, now: float) -> None:
        """Send the progress reports not sent yet, and resend those unacknowledged for
        ``PROGRESS_RESEND_S`` (a lossy transport); nothing while the link is down (they wait)."""
        if not self._outbox or not self.link.up:
            return
        for out in self._outbox.values():
            if out.sent_s is None or now - out.sent_s >= PROGRESS_RESEND_S:
                self.link.send_progress(out.report)
                out.sent_s = now

    def on_ack(self, ack: ProgressAck) -> None:
        """The coordinator took these reports: forget them (a task given up may be followed
        again when the coordinator assigns it anew)."""
        if self.alive:
            self._heard(self.clock())
        for key in ack.keys:
            if self._outbox.pop(key, None) is not None and key[1] == "gave_up":
                self._given_back.discard(key[0])

    @property
    def unacknowledged(self) -> list[Progress]:
        """Progress reports the coordinator has not acknowledged yet (queued while the link
        is down, or in flight)."""
        return [out.report for out in self._outbox.values()]

    def note_failure(self, action: str, reason: str, *, refused: bool = False) -> None:
        """Called by a failing action: the reason reported if the task fails; ``refused``: the
        vehicle refused the action (the task is given up, not failed)."""
        self._failure = f"{action}: {reason}" if reason else action
        self._refused = refused

    def unset_variables(self, leaf: str, names: list[str]) -> None:
        """An action could not start because ``names`` are not on the blackboard: a library
        variable (e.g. ``home``) nobody set. Warn once per variable (``warning`` event)."""
        for name in names:
            if name in self._warned:
                continue
            self._warned.add(name)
            self._emit(
                WarningEvent(
                    agent=self.id,
                    variable=name,
                    leaf=leaf,
                    message=f"'{name}' is not on the blackboard, so {leaf} cannot run: nothing "
                    f"sets this library variable (an on_setup hook or an action of the library "
                    "must set it; see docs/plugins.md, 'Library variables')",
                )
            )

    def _leaf_event(self, event: TypedEvent | str, /, **fields: Any) -> None:
        """What the library's leaves publish (``ctx.events``): a typed event as it is, or a kind
        of the library's own that has no class, by name with its fields (this agent's id
        first). A ``stage`` event names the action now running; a ``leaf_error`` ends it."""
        if not isinstance(event, TypedEvent):
            if event in ("stage", "leaf_error"):  # (a library's by name: as the typed ones)
                fields = {"task": self.task.id if self.task else None, **fields}
                self.action = str(fields.get("action", ""))
            event = GenericEvent(name=event, extra={"agent": self.id, **fields})
        elif fields:
            raise TypeError(f"{event.kind}: a typed event takes no other fields")
        elif isinstance(event, StageEvent):
            self.action = event.action
        elif isinstance(event, LeafErrorEvent):
            self.action = ""
        self._emit(event)

    def _tree_event(self, changes: list[list[Any]], nodes: list[list[Any]] | None) -> None:
        extra: dict[str, Any] = {"nodes": nodes} if nodes else {}
        self._blackboard_version = self.blackboard.version
        now = {k: blackboard_value(v) for k, v in self.blackboard.snapshot().items()}
        sent = self._blackboard_sent
        changed = {k: v for k, v in now.items() if k not in sent or sent[k] != v}
        unset = [k for k in sent if k not in now]
        self._blackboard_sent = now
        if changed:
            extra["blackboard"] = changed
        if unset:
            extra["unset"] = unset
        self._emit(TreeEvent(agent=self.id, changes=changes, **extra))

    def _route_event(self, points: Any, length_m: float) -> None:
        task = self.task.id if self.task is not None else None
        self._emit(
            RouteEvent(agent=self.id, task=task, points=route_points(points), length_m=length_m)
        )

    @property
    def tree_status(self) -> Mapping[int, str]:
        """Node uid (pre-order index in :attr:`tree`) → its status as of the last tick
        (``INVALID``, ``RUNNING``, ``SUCCESS``, ``FAILURE``): a read-only copy, for snapshots.
        :attr:`tree_nodes` names the nodes."""
        return self._tree_log.status

    @property
    def tree_nodes(self) -> list[list[Any]]:
        """``[name, parent uid, kind]`` per node, by uid (the root's parent is -1)."""
        return self._tree_log.nodes

    def flush_tree_events(self) -> None:
        """Publish the tree's status changes not published yet (the run ends)."""
        self._tree_log.flush()

    # ------------------------------------------------------------ coordinator link, lease
    def _heard(self, now: float) -> None:
        """A message from the coordinator arrived: it renews the lease on the agent's task;
        after a loss, the agent says it has its coordinator back."""
        if not self.coordinator_up:
            silent = now - (self._heard_s if self._heard_s is not None else now)
            self.coordinator_up = True
            self._emit(CoordinatorLinkEvent(agent=self.id, up=True, silent_s=round(silent, 3)))
        if self._heard_s is None or now > self._heard_s:
            self._heard_s = now

    @property
    def lease_guard_s(self) -> float:
        """How long before its lease ends a cut-off agent stops its task: ``agent_timeout_s``
        (the coordinator's clock for the lease starts at the agent's last bid, which the agent
        sends when it hears an announcement; the guard covers a link lost one way only for up
        to that long)."""
        return self._timeout_s

    def _coordinator_heard(self, now: float) -> None:
        """Follow the coordinator link: after ``agent_timeout_s`` without a message, say the
        coordinator is lost (the task goes on: the lease covers it); past ``lease_s −``
        :attr:`lease_guard_s`, stop the task (the default behaviour takes over, e.g. return
        home and land) and report that it was let go, so the coordinator, which re-offers it
        when the lease ends, never has two agents flying it."""
        if self._heard_s is None:
            self._heard_s = now  # (the first tick: the coordinator's first round is due)
            return
        silent = now - self._heard_s
        if silent <= self._timeout_s:
            return
        if self.coordinator_up:
            self.coordinator_up = False
            self._emit(CoordinatorLinkEvent(agent=self.id, up=False, silent_s=round(silent, 3)))
        task = self.task
        if task is None or silent <= self._lease_s - self.lease_guard_s:
            return
        reason = (
            f"its lease on {task.id} ran out (coordinator not heard for {silent:.1f} s, lease "
            f"{self._lease_s:g} s)"
        )
        self._emit(WarningEvent(agent=self.id, message=f"{self.id}: {reason}: {task.id} stopped"))
        self._given_back.add(task.id)
        self._progress(task.id, "gave_up", now, reason)
        self._switch(None, now)

    # ------------------------------------------------------------------ vehicle link
    RESUME_OFFBOARD_S = 5.0
    """After a vehicle link loss, how long the agent tries to take OFFBOARD back from the
    failsafe HOLD (PX4 needs a second of setpoints first)."""

    def _vehicle_heard(self, now: float) -> bool:
        """Follow the vehicle link (:attr:`vehicle_link_up`): on loss, log it and pause the tree;
        when it returns, resume the route where it was and, if the autopilot fell back from
        OFFBOARD to HOLD meanwhile (its offboard-loss failsafe), switch back to OFFBOARD. A
        vehicle the pilot has put in another mode is left alone."""
        if self._vehicle_link is None:
            return True
        up = bool(self._vehicle_link())
        if up != self.vehicle_link_up:
            self.vehicle_link_up = up
            self.blackboard.set("vehicle_link", up)
            tel = self.ctx.telemetry()
            if up:
                self._emit(VehicleLinkEvent(agent=self.id, up=True, mode=tel.mode.value))
                self.navigator.resume(now)
                if self._mode_before_loss is Mode.OFFBOARD and tel.mode is Mode.HOLD:
                    self._resume_offboard_until = now + self.RESUME_OFFBOARD_S
            else:
                self._mode_before_loss = tel.mode
                self._emit(VehicleLinkEvent(agent=self.id, up=False))
        return up

    def _resume_offboard(self, now: float) -> None:
        """Ask for OFFBOARD again while the autopilot's offboard-loss HOLD lasts (for
        ``RESUME_OFFBOARD_S`` from when it was seen)."""
        until = self._resume_offboard_until
        if until is None or now > until or self.ctx.telemetry().mode is not Mode.HOLD:
            self._resume_offboard_until = None
        else:
            self.ctx.backend.set_mode(Mode.OFFBOARD)

    _FLOWN = frozenset({Mode.OFFBOARD, Mode.TAKEOFF})
    """The modes the tree flies a multirotor in (HOLD too: the offboard-loss failsafe, which
    :meth:`_vehicle_heard` takes back)."""

    def _taken_over(self, now: float) -> bool:
        """Stand down (:attr:`stood_down`) when the vehicle, flying in a mode of the tree's
        at the last tick that heard it, is now in another one that the tree did not ask for
        (LAND without the navigator's landing; MANUAL: RTL, a pilot's mode): the autopilot's
        failsafe or the pilot took it over. What they decided is final — the tree would
        otherwise arm and launch it again after a failsafe landing — until the operator's
        include. The task goes back to the pool; no bid, setpoint or command follows."""
        if self.stood_down is not None:
            return True
        if self.navigator.kind is not VehicleKind.MULTIROTOR:
            return False
        tel = self.ctx.telemetry()
        seen, self._seen = self._seen, (tel.mode, not tel.landed)
        if seen is None or seen[0] not in self._FLOWN or not seen[1]:
            return False
        mode = tel.mode
        if mode is Mode.HOLD:  # the offboard-loss failsafe (setpoints were late): fly on
            if self._resume_offboard_until is None:
                self._resume_offboard_until = now + self.RESUME_OFFBOARD_S
                self._emit(
                    WarningEvent(
                        agent=self.id,
                        message=(
                            f"{self.id}: its autopilot fell back to HOLD in flight (its "
                            "offboard-loss failsafe: the setpoints came late); taking OFFBOARD "
                            "back"
                        ),
                    )
                )
            return False
        if mode in self._FLOWN or (mode is Mode.LAND and self.navigator.landing):
            return False
        who = "its autopilot's failsafe" if tel.failsafe else "its autopilot or its pilot"
        task = self.task
        final = self.ctx.settings_of(CommandRetrySettings).takeover_is_final
        self._emit(
            TakenOverEvent(
                agent=self.id, mode=mode.value, failsafe=tel.failsafe, final=final,
                task=task.id if task is not None and final else None,
            )
        )  # fmt: skip
        if not final:
            return False  # the mission says the tree flies on (runtime.settings)
        self.stood_down = f"{who} switched the vehicle to {mode.value}"
        if task is not None:
            self._given_back.add(task.id)
            self._progress(task.id, "gave_up", now, self.stood_down)
            self.task = None
            self.committed = False
            self.idle_since = now
            self._emit(AgentTaskEvent(agent=self.id, task=None))
        self._deep(lambda: self.root.stop(Status.INVALID))
        return True

    def include(self) -> None:
        """The operator includes the agent again: it no longer stands down (its tree runs and
        bids from the vehicle's state now)."""
        self.recalled = False
        self.stood_down = None
        self._seen = None

    def control_step(self, now: float) -> None:
        if self.alive and self.stood_down is not None:
            tel = self.ctx.telemetry()  # no setpoint: the others still keep clear of it
            self.link.share_prediction(now, tel.position[None, :].copy(), tel.velocity)
            return
        if self.alive:
            self.navigator.step(now)
            nav = self.navigator
            if nav.prediction is not None:
                self.link.share_prediction(now, nav.prediction, nav.shared_velocity)

    def status(self, now: float) -> AgentStatus:
        tel = self.ctx.telemetry()
        p = tel.position
        return AgentStatus(
            self.id,
            now,
            (float(p[0]), float(p[1]), float(p[2])),
            tel.mode.value,
            tel.armed,
            tel.battery,
            self.task.id if self.task else None,
            self.action,
            self.vehicle_link_up,
            self.at_rest,
        )

    @property
    def at_rest(self) -> bool:
        """No task, and the tree has nothing left to do: the default behaviour's goal holds
        (root SUCCESS), or there is no default behaviour and the agent waits."""
        if not self.alive:
            return True
        if self.stood_down is not None:  # at rest once its autopilot has landed and disarmed it
            tel = self.ctx.telemetry()
            return tel.landed and not tel.armed
        if self.task is not None:
            return False
        default = self._default
        if default is not None:
            return default.status is Status.SUCCESS
        return self.root.children[-1].status is Status.RUNNING

    def recall(self, now: float) -> None:
        """The operator recalled the agent: it drops its task, bids no more and runs its
        default behaviour (e.g. return home and land) at once, without the idle timeout."""
        self.recalled = True
        if self.task is not None:
            self._switch(None, now)
        self.idle_since = -math.inf

    def kill(self) -> None:
        """The agent stops: no more ticks, bids, setpoints or messages."""
        self.alive = False
        self.link.disconnect()
