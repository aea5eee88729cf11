"""Run a mission end to end: coordinator, agents, the vehicles of a provider, events.

:class:`MissionRun` builds everything from a validated :class:`~btmission.spec.mission.Mission`
and advances it in fixed steps of simulated time (``runtime.sim.step_s``). One step, at time t:

1. callbacks scheduled for t run (:meth:`MissionRun.at`), then every command queued since the
   last step is applied (:mod:`btmission.runtime.commands`: add or cancel a task, change its
   priority, recall or kill an agent, cut a link, stop), each logged as a ``command`` event;
2. the coordinator's side (:class:`~btmission.runtime.loops.CoordinatorRuntime`) steps the
   libraries' run-wide services and runs an auction round if one is due
   (``coordination.auction_rate_hz``): announce → every agent bids → allocate → every agent
   gets its assignment;
3. the agents' sides (:class:`~btmission.runtime.loops.AgentRuntime`): agents whose tick is due
   tick their mission tree (``runtime.tick_hz``); every agent's navigator streams this period's
   setpoints; status reports go to the coordinator and pose events to the observers
   (``runtime.status_hz``);
4. the vehicle provider advances (the simulator: every vehicle by one step) and reports
   collisions;
5. an immutable :class:`~btmission.runtime.snapshot.RunSnapshot` of the run is published
   (:attr:`MissionRun.snapshot`) for readers on other threads — when
   :data:`SNAPSHOT_PERIOD_S` of wall time has passed since the last one (a real-time run: every
   step; a fast simulated one takes hundreds of steps a second, which no viewer or console
   reads), after every applied command and at the end. The thread that steps the run always
   reads the last step's.

Time comes from the vehicle provider's clock: the simulator's (or the fake provider's) fixed
steps, never the wall clock, so a simulated run is deterministic for a seed and goes as fast as
the machine allows; ``realtime=True`` — always, with real vehicles, whose provider's clock is the
wall clock — steps once per ``runtime.sim.step_s`` of wall time. The mission's time is 0 when
the provider starts (:meth:`VehicleProvider.start <btmission.vehicles.provider.VehicleProvider.
start>`, once every vehicle is attached): what is published while the run is built and its
vehicles connect (the header, a vehicle without sensors) is stamped 0, never with the time
connecting took (a restarted coordinator: its log's last time).

The run ends when every task is done (or failed, or unreachable by any agent), nothing is left
to arrive and every agent has finished its default behaviour (or waits, if it has none); or at
``runtime.max_duration_s`` / ``until``; or when :meth:`MissionRun.stop` is called (Ctrl-C,
SIGTERM).

This module is the loop; its parts live beside it: building a run in
:mod:`~btmission.runtime.assembly`, operator commands in :mod:`~btmission.runtime.command_port`,
pacing against the clock in :mod:`~btmission.runtime.pacing`, snapshots in
:mod:`~btmission.runtime.snapshot` and how a run ends in :mod:`~btmission.runtime.ending`.
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from typing import Any

from btmission.allocation.tasks import TaskInfo
from btmission.diagnostics import SpecError
from btmission.links.bus import InMemoryBus, MissionEnd
from btmission.missions import LoadedMission
from btmission.runtime.agent import Agent
from btmission.runtime.assembly import (
    NEIGHBOUR_RANGE_M,
    build_agents,
    build_services,
    close_services,
    emit_built,
    emit_header,
    follow_coordinator,
    make_provider,
    part_dispatchers,
    road_costs,
    run_settings,
)
from btmission.runtime.command_port import CommandPort
from btmission.runtime.commands import (
    CancelTask,
    Command,
    CommandQueue,
    KillAgent,
    Outcome,
    RecallAgent,
    SetLink,
    SetPriority,
    Signal,
    Stop,
)
from btmission.runtime.coordinator import Coordinator
from btmission.runtime.distribution import Part
from btmission.runtime.ending import (
    RunResult,
    end_before_build,
    heard_end,
    publish_end,
    result_of,
    why_finished,
)
from btmission.runtime.eventkinds import CollisionEvent, PoseEvent, ResumedEvent, WarningEvent
from btmission.runtime.events import EventStream, GenericEvent, Observer, TypedEvent, event_of
from btmission.runtime.fleetstep import FleetFollow
from btmission.runtime.leaves import ErrorReporter
from btmission.runtime.loops import AgentRuntime, CoordinatorRuntime
from btmission.runtime.navconfig import NavConfig
from btmission.runtime.pacing import Pacer
from btmission.runtime.paths import PathCosts
from btmission.runtime.prewarm import prewarm_run
from btmission.runtime.runcheck import run_problems
from btmission.runtime.snapshot import RunSnapshot, SnapshotTaker
from btmission.runtime.substitution import SubstitutionRules, Substitutions
from btmission.settings import RunSettings
from btmission.vehicles.clock import Clock, ManualClock
from btmission.vehicles.provider import Vehicle, VehicleProvider
from btmission.world.voxel import VoxelMap

SNAPSHOT_PERIOD_S = 0.04
"""Wall time between the snapshots the steps publish (module docstring, item 5): readers on other
threads poll a few times a second (the live viewer samples poses at 10 Hz); 25 a second keeps
them fresh without a fast run spending a twentieth of its time on snapshots of 30 agents."""


class MissionRun:
    """A mission running on the vehicles of its provider (module docstring)."""

    def __init__(
        self,
        mission: LoadedMission,
        *,
        seed: int = 0,
        controller: str | None = None,
        observers: Iterable[Observer] = (),
        voxel_map: VoxelMap | None = None,
        realtime: bool = False,
        substitutions: Substitutions | SubstitutionRules | None = None,
        speed: float = 1.0,
        part: Part | None = None,
        fleet_step: bool = True,
    ) -> None:
        """``realtime`` paces the simulator to the wall clock, ``speed`` times faster than real
        time (real vehicles always go at their own clock). ``part``: what this process runs of
        a mission spread over processes (:mod:`btmission.runtime.distribution`; default: all of
        it, over the in-memory bus). ``substitutions``: leaves of the agents' trees to replace, for tests
        (:mod:`btmission.runtime.substitution`; a rule that replaces no leaf raises
        :class:`~btmission.runtime.substitution.SubstitutionError` before anything is
        published). ``fleet_step``: compute the route-following drones' control steps together
        where that gives the same result (:mod:`btmission.runtime.fleetstep`); False: one by
        one, always."""
        from btmission.planning.risk import RiskParams
        from btmission.world.build import world_from_spec

        problems = run_problems(  # the checks `validate` makes too (the vehicles: this part's)
            mission, agents=part.agents if part is not None else None
        )
        if problems:
            raise SpecError(problems)
        self.substitutions = Substitutions.of(substitutions)
        if self.substitutions is not None:
            self.substitutions.check(mission)
        self.mission = mission
        self.part = part
        rt = mission.spec.runtime
        self.seed = seed
        self.controller = controller or rt.controller
        self.realtime = realtime
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed must be a number > 0 (got {speed})")
        self.speed = speed
        self.events = EventStream(observers)
        self.last_t = 0.0
        self.clock: Clock = ManualClock(  # until the vehicle provider starts (module docstring)
            part.resumed_at_s if part is not None and part.resumed_from is not None else 0.0
        )
        build0 = time.perf_counter()
        # the header first: building the map and the planners can take long, and a run killed
        # meanwhile must still leave a log that `btmission report` reads (docs/running.md)
        if part is not None and part.resumed_from is not None:  # a restarted coordinator
            self.emit_event(  # (at the log's last time)
                ResumedEvent(t=part.resumed_at_s, log=part.resumed_from, last_s=part.resumed_at_s)
            )
        else:
            emit_header(self)
        self.map = (
            voxel_map
            if voxel_map is not None
            else world_from_spec(mission.spec.world, mission.base_dir)
        )
        self.settings: RunSettings = run_settings(mission)
        self.nav_config = self.settings.of(NavConfig)
        # one provider for every agent (run_problems refused mixed fleets: one run, one clock)
        self.provider: VehicleProvider = make_provider(self)
        self.realtime = realtime or self.provider.realtime  # real vehicles: the wall clock
        self._pacer = Pacer(
            self.provider.clock,  # (the run's from the start on)
            rt.sim.step_s,
            vehicles_realtime=self.provider.realtime,
            realtime=self.realtime,
            speed=self.speed,
            emit=self.emit_event,
        )
        """Waits between the steps as the clock asks (:mod:`btmission.runtime.pacing`)."""
        self.vehicles: dict[str, Vehicle] = {}
        self.steps = 0
        self.paths = PathCosts(
            self.map,
            RiskParams(rt.risk_radius_m, rt.unknown_cost),
            clearance_m=self.nav_config.clearance_m,
            max_bytes=rt.path_fields_mb << 20,
            reserve=len(mission.tasks) + len(mission.agents),  # their goals, and home
        )
        prewarm_run(self.provider)  # the loop's kernels loaded now, not at its first round
        self.roads = road_costs(self)
        self.places = self.roads.places if self.roads is not None else {}
        self.bus = InMemoryBus()
        self.coordinator = Coordinator(
            mission,
            part.coordinator_link if part is not None and part.coordinator_link else self.bus,
            self.now,
            self.emit_event,
            check_location=self.paths.problem,
            places=self.places,
        )
        self.namespace = f"/run-{uuid.uuid4().hex[:8]}"
        self.agents: dict[str, Agent] = {}
        self.commands = CommandQueue()
        """Commands waiting for the next step (:meth:`submit`)."""
        self.port = CommandPort(self)
        """Checks, queues and applies operator commands (:mod:`btmission.runtime.command_port`)."""
        self.stop_asked: str | None = None
        """Why the loop must end after the current step (a plain attribute: :meth:`stop` runs
        in signal handlers, where taking a lock could deadlock)."""
        self.dt = rt.sim.step_s
        self.collisions = 0
        self.wall_used = 0.0
        self.ended: RunResult | None = None
        self.errors = ErrorReporter(self.emit_event)
        """Exceptions raised by services' ``step`` → ``leaf_error`` events (once each)."""
        self.services: dict[str, dict[str, Any]] = build_services(self)
        self.coordinator_side = CoordinatorRuntime(self.coordinator, self.services, self.errors)
        self.runs_coordinator = part is None or part.runs_coordinator
        """This process runs the coordinator (one process, or the coordinator's of several)."""
        self.dispatchers: list[Callable[[float], Any]] = part_dispatchers(self)
        """An agent process's links' ``dispatch``: the coordinator's messages, handed to the
        agents in this (their) thread."""
        try:
            build_agents(self)
        except BaseException:  # a vehicle that would not connect, Ctrl-C while connecting
            self.provider.close()
            raise
        self.provider.start()  # the mission's time starts now, however long connecting took
        self.clock = self.provider.clock  # (what happened before it: at the start, t = 0)
        if part is not None and not part.runs_coordinator:
            follow_coordinator(self, part.sync_timeout_s)
        t0 = self.now()
        self.agent_sides = [
            AgentRuntime(
                a,
                tick_period_s=1.0 / rt.tick_hz,
                status_period_s=1.0 / rt.status_hz,
                start_s=t0,
            )
            for a in self.agents.values()
        ]
        self._fleet = (
            FleetFollow.build(
                self.agent_sides, self.bus, NEIGHBOUR_RANGE_M, self.provider.fleet_sensing()
            )
            if fleet_step and part is None
            else None
        )
        """The fleet's control step (None: the agents' own, one by one)."""
        self._snapshots = SnapshotTaker()
        self._owner = threading.get_ident()
        """The thread that steps the run (:attr:`snapshot`)."""
        self._published_wall = 0.0
        self._published: RunSnapshot = self.publish()
        emit_built(self, time.perf_counter() - build0)

    def knows_task(self, task_id: str) -> bool:
        """Whether ``task_id`` is taken: in the pool or queued to enter it (any thread)."""
        return self.port.knows(task_id)

    def link_up(self, agent: str) -> bool:
        """Whether ``agent``'s link to its coordinator is up (as this process sees it)."""
        if self.part is not None and agent in self.part.agent_links:
            return self.part.agent_links[agent].up
        return self.bus.link_up(agent)

    def clock_set(self) -> None:
        """This process's clock was set (an agent process follows its coordinator's): the
        steps' schedule counts from now, and the jump is no step falling behind."""
        self._pacer.start(self.steps)

    # ---------------------------------------------------------------- API
    def now(self) -> float:
        """Mission time (s), from the clock (the simulator's)."""
        return self.clock.now()

    def emit_event(self, event: TypedEvent) -> None:
        """Publish a typed event (:mod:`btmission.runtime.events`) at its time ``event.t`` — now,
        for an event made without one. Events go out in time order: one stamped earlier than
        the last published (something reported late) goes out at the last time, with its own
        time as ``reported_s``."""
        when = self.now() if math.isnan(event.t) else event.t
        data = event.to_data()
        if when < self.last_t - 1e-9:
            data["reported_s"] = when
            when = self.last_t
        self.last_t = when
        self.events.emit(when, event.kind, **data)

    def emit(self, kind: str, t: float | None = None, **data: Any) -> None:
        """Publish an event of a kind given by name (a library's own kind nobody registered a
        class for), with its fields, at mission time ``t`` (default: now): as
        :meth:`emit_event`."""
        self.emit_event(GenericEvent(t=math.nan if t is None else t, name=kind, extra=data))

    def library_event(self, event: TypedEvent | str, /, **fields: Any) -> None:
        """What a library's run-wide service publishes (its
        :attr:`RunContext.events <btmission.runtime.leaves.RunContext.events>`): a typed event,
        or a kind of its own by name with its fields (:func:`~btmission.runtime.events.event_of`)."""
        self.emit_event(event_of(event, fields))

    # ---------------------------------------------------------------- commands
    # (btmission.runtime.command_port checks, queues and applies them: these are its doors)
    def submit(self, command: Command) -> Future[Outcome]:
        """Queue a command for the next step (thread-safe; :mod:`btmission.runtime.commands`);
        the future of its :class:`~btmission.runtime.commands.Outcome`, set when that step
        applied or refused it. Raises :class:`~btmission.runtime.commands.CommandError` at once
        for a command that names an unknown agent or task, and
        :class:`~btmission.runtime.taskcheck.TaskError` for a task that cannot be added or a
        priority out of bounds (a task is checked, and its id reserved, right here)."""
        return self.port.submit(command)

    def add_task(self, task: Mapping[str, Any] | TaskInfo, *, by: str = "api") -> TaskInfo:
        """Add a task while the mission runs (thread-safe): ``{"id": "T8", "type": "inspect",
        "location": [x, y, z]}``, optionally with ``priority`` (a number or a name: ``high``)
        and ``at``; without ``id``, the next free one. It is checked as a task of the mission
        file is (:mod:`btmission.runtime.taskcheck`): :class:`~btmission.runtime.taskcheck.
        TaskError` says why it cannot be used. It enters the pool at the next step; the task as
        the pool will have it."""
        return self.port.add_task(task, by)[0]

    def cancel_task(self, task: str, reason: str = "cancelled by the operator") -> None:
        """Take a task out of the pool (state ``cancelled``); its agent stops executing it."""
        self.submit(CancelTask(task, reason))

    def set_priority(self, task: str, priority: float) -> None:
        """Change a task's priority (it is announced again with it)."""
        self.submit(SetPriority(task, priority))

    def recall_agent(self, agent: str) -> None:
        """The agent gives up its task, stops bidding and runs its default behaviour now."""
        self.submit(RecallAgent(agent))

    def kill_agent(self, agent: str, reason: str = "killed") -> None:
        """The agent's computer stops: no more ticks, bids or setpoints (its vehicle's
        autopilot falls back to HOLD when the setpoints stop)."""
        self.submit(KillAgent(agent, reason))

    def signal(self, agent: str, name: str, value: Any = True) -> None:
        """Set a supervisor signal on an agent (its leaves read ``ctx.state[name]``), e.g. the
        COMPRA library's ``stop``."""
        self.submit(Signal(agent, name, value))

    def set_link(self, agent: str, up: bool) -> None:
        """Cut or restore an agent's link to the coordinator; the agent keeps executing."""
        self.submit(SetLink(agent, up))

    def stop(self, reason: str = "interrupted", *, by: str = "api") -> None:
        """Ask the run to end after the current step (thread-safe, and safe in a signal
        handler: what Ctrl-C does)."""
        self.stop_asked = reason
        self.commands.put(Stop(reason, by=by))

    def at(self, t: float, fn: Callable[[MissionRun], None] | Command) -> None:
        """At mission time ``t`` (before that step's auction round), call ``fn(run)`` — or
        submit the command ``fn`` (:meth:`CommandPort.at <btmission.runtime.command_port.
        CommandPort.at>`; any thread)."""
        self.port.at(t, fn)

    # ---------------------------------------------------------------- running
    def step(self) -> None:
        """One fixed step (module docstring)."""
        now = self.now()
        self.port.run_due(now)
        self.port.apply_queued()
        if self.runs_coordinator:
            self.coordinator_side.step(now)
        for dispatch in self.dispatchers:  # the coordinator's messages, to the agents here
            dispatch(0.0)
        sides = self.agent_sides
        for side in sides:
            side.tick(now)
        if self._fleet is not None:  # (tracking controllers only: no deferred solves to collect)
            self._fleet.control(now)
        else:
            for side in sides:
                side.control(now)
            for side in sides:  # the deferred NMPC solves of this step, in a fixed order
                side.finish_control()
        for side in sides:
            if side.report(now):
                self.emit_event(PoseEvent.of(side.id, self.vehicles[side.id]))
        self.steps += 1
        for ev in self.provider.step(self.dt):
            if ev.kind == "warning":
                self.emit_event(WarningEvent(agent=ev.vehicle, message=ev.message))
                continue
            self.collisions += 1
            self.emit_event(CollisionEvent(agent=ev.vehicle, other=ev.other, p=list(ev.position)))
        if time.perf_counter() - self._published_wall >= SNAPSHOT_PERIOD_S:
            self.publish()

    @property
    def snapshot(self) -> RunSnapshot:
        """The run as it stands (immutable; any thread may read it and keep it). On the thread
        that steps the run it is the last step's; on others it is at most
        :data:`SNAPSHOT_PERIOD_S` of wall time older (module docstring, item 5)."""
        snap = self._published
        if snap.steps != self.steps and snap.ended is None and threading.get_ident() == self._owner:
            snap = self.publish()
        return snap

    def publish(self, ended: str | None = None) -> RunSnapshot:
        """Build and publish the snapshot of now (module docstring, item 5)."""
        snap = self._published = self._snapshots.take(self, ended)
        self._published_wall = time.perf_counter()
        return snap

    def finished(self) -> str | None:
        """Why the run should end now (None: go on; :func:`~btmission.runtime.ending.why_finished`)."""
        return why_finished(self)

    @property
    def mission_end(self) -> MissionEnd | None:
        """The coordinator's end of the mission, once an agent process has heard it."""
        return heard_end(self.part)

    def run(
        self,
        until: float | None = None,
        *,
        progress: Callable[[MissionRun], None] | None = None,
        progress_every_s: float = 1.0,
    ) -> RunResult:
        """Step until the mission ends (or mission time ``until``); can be called again to
        continue. ``progress(run)`` is called every ``progress_every_s`` of mission time."""
        limit = self.mission.spec.runtime.max_duration_s
        stop_at = limit if until is None else min(until, limit)
        self._owner = threading.get_ident()
        wall0 = time.perf_counter()
        self._pacer.start(self.steps)
        next_progress = self.now()
        reason = ""
        self.stop_asked = None  # (a stop asked before is still queued as a command)
        try:
            while True:
                self.port.apply_queued()  # a stop asked between steps is logged
                if self.stop_asked is not None:
                    reason = self.stop_asked
                    break
                done = self.finished()
                if done:
                    reason = done
                    break
                if self.now() >= stop_at - 1e-9:
                    reason = "time limit" if stop_at >= limit else "until"
                    break
                self.step()
                if progress is not None and self.now() >= next_progress:
                    progress(self)
                    next_progress += progress_every_s
                self._pacer.after_step(self.steps)
        finally:
            self.wall_used += time.perf_counter() - wall0
        return self.result(reason)

    def result(self, reason: str) -> RunResult:
        """How the run stands now, ended for ``reason`` (what :meth:`run` returns)."""
        return result_of(self, reason)

    end_before_build = staticmethod(end_before_build)

    def close(self) -> None:
        """Release what the run holds: every run-wide service that has a ``close()`` (its
        errors are logged as ``leaf_error`` events, they do not stop the others), then the
        vehicle provider (sockets, threads of real vehicles). Idempotent."""
        close_services(self.services, self.errors)
        self.provider.close()

    def end(self, result: RunResult) -> None:
        """Publish the ``end`` event (once): the run is over."""
        if self.ended is None:
            self.ended = result
            publish_end(self, result)
