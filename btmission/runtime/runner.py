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
wall clock — steps once per ``runtime.sim.step_s`` of wall time.

The run ends when every task is done (or failed, or unreachable by any agent), nothing is left
to arrive and every agent has finished its default behaviour (or waits, if it has none); or at
``runtime.max_duration_s`` / ``until``; or when :meth:`MissionRun.stop` is called (Ctrl-C,
SIGTERM).
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from btmission.allocation.tasks import TaskInfo, TaskState
from btmission.diagnostics import Diagnostic, Location, Severity, SpecError
from btmission.runtime.agent import Agent
from btmission.runtime.bus import AgentLink, InMemoryBus, MissionEnd, neighbour_positions
from btmission.runtime.commands import (
    AddTask,
    CancelTask,
    Command,
    CommandError,
    CommandQueue,
    ExcludeAgent,
    IncludeAgent,
    KillAgent,
    Outcome,
    RecallAgent,
    Refused,
    SetAllocation,
    SetLink,
    SetPriority,
    Signal,
    Stop,
)
from btmission.runtime.coordinator import Coordinator, TaskError
from btmission.runtime.distribution import ClockFollower, NoVehicles, Part, remote_bid_window
from btmission.runtime.events import (
    LOG_FORMAT,
    LOG_VERSION,
    Event,
    EventStream,
    Observer,
    world_reference,
)
from btmission.runtime.fleetstep import FleetFollow
from btmission.runtime.leaves import (
    ErrorReporter,
    RunContext,
    describe,
    setup_failed,
)
from btmission.runtime.loops import AgentRuntime, CoordinatorRuntime
from btmission.runtime.navigation import NavConfig, Navigator
from btmission.runtime.paths import PathCosts
from btmission.runtime.runcheck import run_problems
from btmission.runtime.snapshot import AgentSnapshot, RunSnapshot
from btmission.runtime.substitution import SubstitutionRules, Substitutions
from btmission.spec.mission import Mission
from btmission.spec.source import format_path
from btmission.types import FloatArray
from btmission.vehicles.base import Backend, VehicleKind
from btmission.vehicles.clock import Clock, ManualClock, ScaledWallClock
from btmission.vehicles.provider import (
    Vehicle,
    VehicleProvider,
    VehicleUnavailable,
    provider_factory,
    scheme_of,
)
from btmission.warmup import prepare_run
from btmission.world.voxel import VoxelMap

if TYPE_CHECKING:
    from btmission.runtime.roads import RoadCosts

LATE_STEPS_WARNING = 400
"""Steps a run against a real provider's clock makes before it may warn that it falls behind
(more than 5 % of its steps late by more than a step: the start's first NMPC solves are slow)."""

NEIGHBOUR_RANGE_M = 6.0
"""Agents farther than this are left out of each other's avoidance (APF, NMPC constraints)."""

SNAPSHOT_PERIOD_S = 0.04
"""Wall time between the snapshots the steps publish (module docstring, item 5): readers on other
threads poll a few times a second (the live viewer samples poses at 10 Hz); 25 a second keeps
them fresh without a fast run spending a twentieth of its time on snapshots of 30 agents."""


@dataclass
class RunResult:
    """How a run ended."""

    reason: str
    """completed, finished with open tasks, time limit, until, interrupted, no agents left."""
    time_s: float
    wall_s: float
    steps: int
    done: list[str] = field(default_factory=list)
    open: dict[str, str] = field(default_factory=dict)
    """Tasks not done → state and reason (tasks that have arrived)."""
    collisions: int = 0
    pending: list[str] = field(default_factory=list)
    """Tasks still to arrive (``at:`` after the end: the run was cut short)."""
    cancelled: list[str] = field(default_factory=list)
    """Tasks the operator cancelled (not counted as open)."""

    @property
    def speedup(self) -> float:
        return self.time_s / self.wall_s if self.wall_s > 0 else math.inf


class MissionRun:
    """A mission running on the vehicles of its provider (module docstring)."""

    def __init__(
        self,
        mission: Mission,
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
        self._last_t = 0.0
        self.clock: Clock = ManualClock(0.0)  # until the vehicle provider is built
        build0 = time.perf_counter()
        # the header first: building the map and the planners can take long, and a run killed
        # meanwhile must still leave a log that `btmission report` reads (docs/running.md)
        if part is not None and part.resumed_from is not None:  # a restarted coordinator
            self.emit(  # (its clock is not built yet: at the log's last time)
                "resumed", t=part.resumed_at_s, log=part.resumed_from, last_s=part.resumed_at_s
            )
        else:
            self._emit_header()
        self.map = (
            voxel_map
            if voxel_map is not None
            else world_from_spec(mission.spec.world, mission.base_dir)
        )
        self.settings: dict[str, Any] = {}
        for loaded in mission.libraries.values():
            if loaded.implementations is not None:
                self.settings.update(loaded.implementations.settings)
        self.settings.update(rt.settings)
        self.nav_config = NavConfig.from_settings(self.settings)
        sim_spec = rt.sim
        # one provider for every agent (run_problems refused mixed fleets: one run, one clock)
        here = self._here()
        self.provider: VehicleProvider
        if part is not None and not here:  # the coordinator's process: no vehicles
            scale = rt.mavlink.time_scale
            self.provider = NoVehicles(scale, part.started_unix)
        else:
            scheme = scheme_of(here[0].backend) if here else "sim"
            self.provider = provider_factory(scheme)(mission, self.map, seed)
        self.clock = self.provider.clock
        self.realtime = realtime or self.provider.realtime  # real vehicles: the wall clock
        self.vehicles: dict[str, Vehicle] = {}
        self.steps = 0
        self.paths = PathCosts(
            self.map,
            RiskParams(rt.risk_radius_m, rt.unknown_cost),
            clearance_m=self.nav_config.clearance_m,
            max_bytes=rt.path_fields_mb << 20,
            reserve=len(mission.tasks) + len(mission.agents),  # their goals, and home
        )
        prepare_run()  # the loop's kernels and solver loaded now, not at its first round
        self.roads = self._roads()
        self.places = self.roads.places if self.roads is not None else {}
        self.bus = InMemoryBus()
        self.coordinator = Coordinator(
            mission,
            part.coordinator_link if part is not None and part.coordinator_link else self.bus,
            self.now,
            self.emit,
            check_location=self.paths.problem,
            places=self.places,
        )
        self._namespace = f"/run-{uuid.uuid4().hex[:8]}"
        self.agents: dict[str, Agent] = {}
        self._schedule: list[tuple[float, int, Callable[[MissionRun], None]]] = []
        self.commands = CommandQueue()
        """Commands waiting for the next step (:meth:`submit`)."""
        self._schedule_lock = threading.Lock()
        self._stop_asked: str | None = None
        """Why the loop must end after the current step (a plain attribute: :meth:`stop` runs
        in signal handlers, where taking a lock could deadlock)."""
        self.dt = sim_spec.step_s
        self.collisions = 0
        self._wall0: float | None = None
        self._late_steps = 0
        self._late_warned = False
        self._wall_used = 0.0
        self._ended: RunResult | None = None
        self.errors = ErrorReporter(self.emit)
        """Exceptions raised by services' ``step`` → ``leaf_error`` events (once each)."""
        self.services: dict[str, dict[str, Any]] = self._build_services()
        self.coordinator_side = CoordinatorRuntime(self.coordinator, self.services, self.errors)
        self.runs_coordinator = part is None or part.runs_coordinator
        """This process runs the coordinator (one process, or the coordinator's of several)."""
        self._dispatchers: list[Callable[[float], Any]] = [
            d
            for link in (part.agent_links.values() if part is not None else ())
            if (d := getattr(link, "dispatch", None)) is not None
        ]
        """An agent process's links' ``dispatch``: the coordinator's messages, handed to the
        agents in this (their) thread."""
        if part is not None and part.runs_coordinator:
            self.coordinator.expect = part.live_agents
            if self.coordinator.bid_window_s <= 0:  # bids come back over a network
                self.coordinator.bid_window_s = remote_bid_window(
                    self.coordinator.period_s, rt.mavlink.time_scale
                )
        try:
            self._build_agents()
        except BaseException:  # a vehicle that would not connect, Ctrl-C while connecting
            self.provider.close()
            raise
        start = getattr(self.provider, "start", None)
        if start is not None:  # the mission's time starts now, however long connecting took
            start()
        if part is not None and not part.runs_coordinator:
            self._follow_coordinator(part.sync_timeout_s)
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
            FleetFollow.build(self.agent_sides, self.bus, NEIGHBOUR_RANGE_M)
            if fleet_step and part is None
            else None
        )
        """The fleet's control step (None: the agents' own, one by one)."""
        self._trees: dict[str, tuple[tuple[int, Any], Mapping[int, str]]] = {}
        self._nodes: dict[str, tuple[tuple[str, int, str], ...]] = {}
        self._owner = threading.get_ident()
        """The thread that steps the run (:attr:`snapshot`)."""
        self._published_wall = 0.0
        self._published: RunSnapshot = self._publish()
        vm = self.map
        started: dict[str, Any] = {}
        if isinstance(self.provider, NoVehicles):  # when this mission's clock was zero
            started["started_unix"] = self.provider.started_unix
        self.emit(
            "built",
            map={"shape": list(vm.shape), "resolution": vm.resolution, "origin": list(vm.origin)},
            build_s=time.perf_counter() - build0,
            **started,
        )

    # ---------------------------------------------------------------- construction
    def _roads(self) -> RoadCosts | None:
        """Places and road costs of the mission's topological map, if it has one."""
        ref = self.mission.spec.world.topomap
        if ref is None:
            return None
        from btmission.dispatch.maps import topomap_ref
        from btmission.runtime.roads import RoadCosts, RoadMapError

        top = self.map.origin[2] + self.map.shape[2] * self.map.resolution
        try:
            return RoadCosts(
                topomap_ref(ref, self.mission.base_dir),
                lambda x, y: self.map.ground_z((x, y, top)),
                self.paths,
                snap_m=max(25.0, 2 * self.map.resolution),
            )
        except RoadMapError as exc:
            where = Location(self.mission.file)
            raise SpecError(
                [Diagnostic(Severity.ERROR, "topomap", str(exc), "world.topomap", where)]
            ) from None

    def _build_services(self) -> dict[str, dict[str, Any]]:
        """One instance of every run-wide service of the libraries the agents use."""
        run = RunContext(
            self.mission,
            self.map,
            self.now,
            self.settings,
            self.seed,
            self.emit,
            self.places,
            self.roads.tmap if self.roads is not None else None,
        )
        out: dict[str, dict[str, Any]] = {}
        made: dict[int, Any] = {}  # one instance per factory: variants (extend) share it
        for spec in self.mission.agents:
            impl = self.mission.library_of(spec.id).implementations
            assert impl is not None
            if impl.library not in out:
                out[impl.library] = {}
                for name, make in impl.services.items():
                    if id(make) not in made:
                        try:
                            made[id(make)] = make(run)
                        except Exception as exc:  # the library's code: a clear error, exit 2
                            raise setup_failed(
                                "service-failed",
                                f"library '{impl.library}': service '{name}' failed to start: "
                                f"{describe(exc)}",
                                "agents",
                                self.mission.file,
                            ) from exc
                    out[impl.library][name] = made[id(make)]
        return out

    def _build_agents(self) -> None:
        blind: list[str] = []
        prepare = getattr(self.provider, "prepare", None)
        if prepare is not None:  # a real provider opens every link first (vehicles boot together)
            prepare([spec.backend for spec in self._here()])
        for spec in self._here():
            loaded = self.mission.library_of(spec.id)
            impl = loaded.implementations
            assert impl is not None  # run_problems() checked it
            kind = VehicleKind.of(impl.vehicle)
            ground = kind is VehicleKind.GROUND
            options: dict[str, Any] = {"v_max": self.nav_config.speed_m_s} if ground else {}
            try:
                vehicle = self.provider.attach(
                    spec.id, kind, spec.start, url=spec.backend, **options
                )
            except VehicleUnavailable as exc:
                path = ("agents", self.mission.agents.index(spec), "backend")
                where = self.mission.locate(path)
                problem = Diagnostic(
                    Severity.ERROR, "vehicle-unavailable", str(exc), format_path(path), where
                )
                raise VehicleUnavailable(problem.format()) from None
            self.vehicles[spec.id] = vehicle
            if vehicle.sensors is None:
                blind.append(spec.id)
            control_dt = 0.1 if ground else self.dt
            link = self._agent_link(spec.id)  # the agent's end of the coordinator link

            def predictions(
                agent: str, _backend: Backend = vehicle.backend, _link: AgentLink = link
            ) -> list[Any]:
                pos = _backend.telemetry().position
                return _link.predictions(self.now(), 0.1, pos, NEIGHBOUR_RANGE_M)

            def neighbours(agent: str, pos: FloatArray, _link: AgentLink = link) -> FloatArray:
                return neighbour_positions(_link, self.now(), 0.1, pos, NEIGHBOUR_RANGE_M)

            nav = Navigator(
                spec.id,
                vehicle.backend,
                vehicle.sensors,
                self.controller,
                self.nav_config,
                control_dt=control_dt,
                predictions=predictions,
                neighbours=neighbours,
                ground_at=self.map.ground_z,
                point_area_m2=self.map.resolution**2,
            )
            nav.defer_nmpc = True  # the agents' NMPC solves overlap; step() collects them
            self.agents[spec.id] = Agent(
                self.mission,
                spec.id,
                impl,
                vehicle.backend,
                vehicle.sensors,
                nav,
                self.paths,
                link,
                self.now,
                settings=self.settings,
                emit=self.emit,
                namespace=self._namespace,
                services=self.services[impl.library],
                places=self.places,
                cost_provider=self.roads if ground else None,  # road costs; drones fly
                substitutions=self.substitutions,
                vehicle_link=vehicle.link_ok,
            )
        if blind:
            self.emit(
                "warning",
                message=f"{', '.join(blind)}: no exteroceptive sensors (a real vehicle's come "
                "from its drivers): planning on the prior map only, reactive avoidance (APF on "
                "the LiDAR) is off",
            )

    def _here(self) -> list[Any]:
        """The mission's agents this process runs (all of them, but for a :class:`Part`)."""
        if self.part is None:
            return list(self.mission.agents)
        return [a for a in self.mission.agents if a.id in self.part.agents]

    def _agent_link(self, agent: str) -> AgentLink:
        if self.part is None:
            return self.bus.agent_link(agent)

        def followed(before: float, now: float) -> None:
            self.emit("clock", agent=agent, was_s=before, now_s=now)

        clock = self.clock
        if not isinstance(clock, ScaledWallClock):  # the agent process's clock is its vehicles'
            raise SpecError([Diagnostic(
                Severity.ERROR, "agent-process",
                f"agent {agent}: an agent process flies real-time vehicles (MAVLink), whose "
                "clock follows the coordinator's; this agent's provider has its own",
                f"agents.{agent}.backend", Location(self.mission.file))])  # fmt: skip
        return ClockFollower(self.part.agent_links[agent], clock, followed)

    def _follow_coordinator(self, timeout_s: float) -> None:
        """An agent process: wait (up to ``timeout_s`` of wall time) for its coordinator's
        first assignment, which sets this process's mission clock to the coordinator's
        (:class:`~btmission.runtime.distribution.ClockFollower`); the agents' idle timers start
        then. Without one, the run goes on on its own clock (a ``warning`` event)."""
        assert self.part is not None
        links = [self.agents[a].link for a in self.part.agents if a in self.agents]
        deadline = time.monotonic() + timeout_s
        while not all(getattr(lk, "synced", True) for lk in links):
            left = deadline - time.monotonic()
            if left <= 0:
                self.emit(
                    "warning",
                    message=f"no assignment from the coordinator within {timeout_s:g} s: the "
                    "agents run on their own clock until one comes",
                )
                break
            for dispatch in self._dispatchers:
                dispatch(min(0.1, left))
        now = self.now()
        for a in self.agents.values():
            a.idle_since = now

    def link_up(self, agent: str) -> bool:
        """Whether ``agent``'s link to its coordinator is up (as this process sees it)."""
        if self.part is not None and agent in self.part.agent_links:
            return self.part.agent_links[agent].up
        return self.bus.link_up(agent)

    def _emit_header(self) -> None:
        """The log's first event, from the mission alone (nothing built yet)."""
        m = self.mission
        world = m.spec.world.model_dump(mode="json")

        def vehicle(agent: str) -> str:
            impl = m.library_of(agent).implementations
            assert impl is not None  # run_problems() checked it
            return VehicleKind.of(impl.vehicle).value

        extra: dict[str, Any] = {} if self.part is None else {"part": self.part.describe()}
        self.emit(
            "header",
            format=LOG_FORMAT,
            version=LOG_VERSION,
            mission=m.name,
            description=m.spec.description,
            file=m.file,
            seed=self.seed,
            controller=self.controller,
            world=world,
            world_ref=world_reference(world, m.base_dir),
            step_s=m.spec.runtime.sim.step_s,
            **extra,
            auction_rate_hz=m.spec.coordination.auction_rate_hz,
            agents=[
                {
                    "id": a.id,
                    "library": m.library_of(a.id).library.name,
                    "vehicle": vehicle(a.id),
                    "start": list(a.start),
                }
                for a in m.agents
            ],
            tasks=[
                {"id": t.id, "type": t.type, "at": t.at, "fields": dict(t.fields)} for t in m.tasks
            ],
            artifacts=[
                {"label": a.label, "p": list(a.position), "size_m": a.size_m}
                for a in m.spec.runtime.sim.artifacts
            ],
        )

    # ---------------------------------------------------------------- API
    def now(self) -> float:
        """Mission time (s), from the clock (the simulator's)."""
        return self.clock.now()

    def emit(self, kind: str, t: float | None = None, **data: Any) -> None:
        """Publish an event at mission time ``t`` (default: now). Events go out in time order:
        one stamped earlier than the last published (something reported late) goes out at the
        last time, with its own time as ``reported_s``."""
        when = self.now() if t is None else t
        if when < self._last_t - 1e-9:
            data["reported_s"] = when
            when = self._last_t
        self._last_t = when
        self.events.emit(when, kind, **data)

    # ---------------------------------------------------------------- commands
    def submit(self, command: Command) -> Future[Outcome]:
        """Queue a command for the next step (thread-safe; :mod:`btmission.runtime.commands`);
        the future of its :class:`~btmission.runtime.commands.Outcome`, set when that step
        applied or refused it. Raises :class:`~btmission.runtime.commands.CommandError` at once
        for a command that names an unknown agent or task, and
        :class:`~btmission.runtime.coordinator.TaskError` for a task that cannot be added (it is
        checked, and its id reserved, right here)."""
        self._check_command(command)
        if isinstance(command, AddTask):
            self.coordinator.add_task(command.task, self.now(), command.by)
        return self.commands.put(command)

    def _refuse_after_end(self, name: str) -> None:
        if self._ended is not None:
            raise CommandError(f"{name}: the run has ended ({self._ended.reason})")

    def _check_command(self, command: Command, *, tasks: bool = True) -> None:
        """Refuse a command naming an unknown agent (or, with ``tasks``, an unknown task), and
        any command once the run has ended."""
        self._refuse_after_end(command.name)
        agent = getattr(command, "agent", None)
        if agent is not None and agent not in self.agents:
            raise CommandError(
                f"{command.name}: unknown agent '{agent}' (agents: {', '.join(self.agents)})"
            )
        if tasks and isinstance(command, (CancelTask, SetPriority)):
            if not self.coordinator.knows(command.task):
                raise CommandError(f"{command.name}: unknown task '{command.task}'")
        if isinstance(command, SetPriority):
            p = command.priority
            if not (isinstance(p, (int, float)) and math.isfinite(p) and p > 0):
                raise CommandError(f"set_priority: priority must be a number > 0, got {p!r}")

    def add_task(self, task: Mapping[str, Any] | TaskInfo, *, by: str = "api") -> TaskInfo:
        """Add a task while the mission runs (thread-safe): ``{"id": "T8", "type": "inspect",
        "location": [x, y, z]}``, optionally with ``priority`` and ``at``. Raises
        :class:`~btmission.runtime.coordinator.TaskError` when it cannot be used; it enters the
        pool at the next step."""
        self._refuse_after_end("add_task")
        info = self.coordinator.add_task(task, self.now(), by)
        data = dict(task) if isinstance(task, Mapping) else {
            "id": info.id, "type": info.type, **info.fields, "priority": info.priority,
            "at": info.arrival_s,
        }  # fmt: skip
        self.commands.put(AddTask(data, by=by))
        return info

    def cancel_task(self, task: str, reason: str = "cancelled by the operator") -> None:
        """Take a task out of the pool (state ``cancelled``); its agent stops executing it."""
        self.submit(CancelTask(task, reason))

    def set_priority(self, task: str, priority: float) -> None:
        """Change a task's priority (it is announced again with it)."""
        self.submit(SetPriority(task, priority))

    def recall_agent(self, agent: str) -> None:
        """The agent gives up its task, stops bidding and runs its default behaviour now."""
        self.submit(RecallAgent(agent))

    def at(self, t: float, fn: Callable[[MissionRun], None] | Command) -> None:
        """At mission time ``t`` (before that step's auction round), call ``fn(run)`` — or
        submit the command ``fn``."""
        call: Callable[[MissionRun], None]
        if isinstance(fn, Command):
            command = fn
            self._check_command(command, tasks=False)  # its task may be added before then

            def call(run: MissionRun) -> None:
                try:
                    run.submit(command)
                except (CommandError, TaskError) as exc:  # e.g. a task id taken meanwhile
                    run._log_command(command, str(exc))

        else:
            call = fn
        with self._schedule_lock:  # any thread may schedule
            self._schedule.append((t, len(self._schedule), call))
            self._schedule.sort(key=lambda x: (x[0], x[1]))

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
        self._stop_asked = reason
        self.commands.put(Stop(reason, by=by))

    def _apply_commands(self) -> None:
        """Apply every queued command, in order, each logged as a ``command`` event."""
        settled: list[tuple[Future[Outcome], Outcome]] = []
        for command, future in self.commands.take():
            error = ""
            try:
                self._apply(command)
            except (CommandError, TaskError) as exc:
                error = str(exc)
            settled.append((future, self._log_command(command, error)))
        if settled:  # whoever waits for an outcome then reads a snapshot that shows it
            self._publish()
            _settle(settled)

    def _log_command(self, command: Command, error: str) -> Outcome:
        """The ``command`` event: who, what, its arguments, and whether it was refused; the
        command's outcome."""
        data: dict[str, Any] = {"command": command.name, "by": command.by}
        if isinstance(command, Refused):  # refused before it reached the run: as it was asked
            data["command"] = command.command
            data.update(command.args)
            error = command.error
        else:
            data.update(command.to_data())
        if isinstance(command, AddTask):
            data["task"] = dict(command.task).get("id")
        data["ok"] = not error
        if error:
            data["error"] = error
        self.emit("command", **data)
        return Outcome(self._last_t, not error, error, data)

    def _apply(self, command: Command) -> None:
        now = self.now()
        coord = self.coordinator
        if isinstance(command, Refused):
            raise CommandError(command.error)
        if isinstance(command, AddTask):  # checked and queued with the coordinator when
            coord.intake(now)  # submitted: it enters the pool now (later commands may name it)
        elif isinstance(command, Stop):
            self._stop_asked = command.reason
        elif isinstance(command, CancelTask):
            coord.cancel_task(command.task, now, command.reason)
        elif isinstance(command, SetPriority):
            coord.set_priority(command.task, float(command.priority), now)
        elif isinstance(command, RecallAgent):
            a = self.agents[command.agent]
            if not a.alive:
                raise CommandError(f"recall_agent: agent {command.agent} is not running")
            coord.recall(command.agent, now)
            a.recall(now)
        elif isinstance(command, ExcludeAgent):
            coord.exclude(command.agent, True)
        elif isinstance(command, IncludeAgent):
            a = self.agents[command.agent]
            if not a.alive:
                raise CommandError(f"include_agent: agent {command.agent} is not running")
            coord.exclude(command.agent, False)
            a.recalled = False
        elif isinstance(command, SetAllocation):
            coord.pause(bool(command.paused))
        elif isinstance(command, KillAgent):
            a = self.agents[command.agent]
            if a.alive:
                a.kill()
                self.emit("agent_lost", agent=command.agent, reason=command.reason)
        elif isinstance(command, SetLink):
            self.bus.set_link(command.agent, command.up)
            self.emit("link", agent=command.agent, up=command.up)
        elif isinstance(command, Signal):
            self.agents[command.agent].ctx.state[command.signal] = command.value
            self.emit("signal", agent=command.agent, name=command.signal, value=command.value)
        else:  # pragma: no cover - every command of commands.COMMANDS is handled above
            raise CommandError(f"unknown command {command!r}")

    # ---------------------------------------------------------------- running
    def step(self) -> None:
        """One fixed step (module docstring)."""
        now = self.now()
        while True:
            with self._schedule_lock:
                if not self._schedule or self._schedule[0][0] > now + 1e-9:
                    break
                _, _, fn = self._schedule.pop(0)
            fn(self)
        self._apply_commands()
        if self.runs_coordinator:
            self.coordinator_side.step(now)
        for dispatch in self._dispatchers:  # the coordinator's messages, to the agents here
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
                self._pose(side.id)
        self.steps += 1
        for ev in self.provider.step(self.dt):
            self.collisions += 1
            self.emit("collision", agent=ev.vehicle, other=ev.other, p=list(ev.position))
        if time.perf_counter() - self._published_wall >= SNAPSHOT_PERIOD_S:
            self._publish()

    def _pose(self, aid: str) -> None:
        """A ``pose`` event: the vehicle's telemetry, and the provider's ground truth (the
        simulator's odometer and clearance; null on real vehicles)."""
        vehicle = self.vehicles[aid]
        tel = vehicle.backend.telemetry()
        self.emit(
            "pose",
            agent=aid,
            p=tel.position,
            v=tel.velocity,
            yaw=tel.yaw,
            mode=tel.mode.value,
            armed=tel.armed,
            flying=not tel.landed,
            odometer_m=vehicle.odometer_m() if vehicle.odometer_m else None,
            clearance_m=vehicle.clearance_m() if vehicle.clearance_m else None,
        )

    def _tree_nodes(self, agent: Agent) -> tuple[tuple[str, int, str], ...]:
        """The agent's tree nodes as immutable tuples (built once: the tree never changes)."""
        nodes = self._nodes.get(agent.id)
        if nodes is None:
            nodes = self._nodes[agent.id] = tuple(
                (str(n[0]), int(n[1]), str(n[2])) for n in agent.tree_nodes
            )
        return nodes

    @property
    def snapshot(self) -> RunSnapshot:
        """The run as it stands (immutable; any thread may read it and keep it). On the thread
        that steps the run it is the last step's; on others it is at most
        :data:`SNAPSHOT_PERIOD_S` of wall time older (module docstring, item 5)."""
        snap = self._published
        if snap.steps != self.steps and snap.ended is None and threading.get_ident() == self._owner:
            snap = self._publish()
        return snap

    def _publish(self, ended: str | None = None) -> RunSnapshot:
        """Build and publish the snapshot of now (module docstring, item 5)."""
        snap = self._published = self._snapshot(ended)
        self._published_wall = time.perf_counter()
        return snap

    def _snapshot(self, ended: str | None = None) -> RunSnapshot:
        agents = []
        for aid, a in self.agents.items():
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
                    self.link_up(aid),
                    a.task.id if a.task is not None else None,
                    a.action,
                    tree,
                    self._tree_nodes(a),
                    a.recalled,
                )
            )
        state = self.coordinator.state
        return RunSnapshot(
            self.now(),
            self.steps,
            tuple(agents),
            state.pool,
            ended,
            state.paused,
            state.excluded,
        )

    def finished(self) -> str | None:
        """Why the run should end now (None: go on)."""
        if self.part is not None:
            return self._part_finished()
        agents = self.agents.values()
        pool = self.coordinator.state.pool
        if not self.coordinator.settled(self.now()):
            if any(a.alive and not a.recalled for a in agents):  # (every step, mostly)
                return None  # someone can still take the open tasks
            live = [a for a in agents if a.alive]  # killed or recalled: nobody can any more
            if any(not t.state.terminal for t in pool) and all(a.at_rest for a in live):
                return "no agents left"  # (the recalled ones are home)
            return None
        live = [a for a in agents if a.alive]
        if not all(a.at_rest for a in live):
            return None
        if all(t.state in (TaskState.DONE, TaskState.CANCELLED) for t in pool):
            return "completed"  # (what the operator cancelled is not left open)
        return "finished with open tasks"

    def _part_finished(self) -> str | None:
        """An agent process ends when its coordinator says the mission is over; the
        coordinator's when every task is settled and every agent it hears from is at rest
        (its last status, within the agent timeout) — or when none is left to do them."""
        if not self.runs_coordinator:
            ended = self.mission_end
            return ended.reason if ended is not None else None
        now = self.now()
        timeout = self.coordinator.state.config.agent_timeout_s
        heard = {a: st for a, st in self.coordinator.statuses.items() if now - st.time_s <= timeout}
        pool = self.coordinator.state.pool
        if not self.coordinator.settled(now):
            return None
        if not heard and any(not t.state.terminal for t in pool):
            return None  # nobody to do them yet (agents may come back)
        if not all(st.at_rest for st in heard.values()):
            return None
        if all(t.state in (TaskState.DONE, TaskState.CANCELLED) for t in pool):
            return "completed"
        return "finished with open tasks"

    @property
    def mission_end(self) -> MissionEnd | None:
        """The coordinator's end of the mission, once an agent process has heard it."""
        if self.part is None:
            return None
        for link in self.part.agent_links.values():
            ended = getattr(link, "ended", None)
            if ended is not None:
                return ended  # type: ignore[no-any-return]
        return None

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
        steps0 = self.steps
        clock0 = self.clock.now()
        next_progress = self.now()
        reason = ""
        self._stop_asked = None  # (a stop asked before is still queued as a command)
        try:
            while True:
                self._apply_commands()  # a stop asked between steps is logged
                if self._stop_asked is not None:
                    reason = self._stop_asked
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
                if self.provider.realtime:  # real vehicles: one step per ``dt`` of their time
                    due = clock0 + (self.steps - steps0) * self.dt
                    if self.clock.now() > due + self.dt:  # late (a slow step): no catch-up burst
                        clock0 += self.clock.now() - due
                        self._late_steps += 1
                        late, steps = self._late_steps, self.steps - steps0
                        if (
                            not self._late_warned
                            and steps >= LATE_STEPS_WARNING
                            and late > 0.05 * steps
                        ):
                            self._late_warned = True
                            self.emit(
                                "warning",
                                message=f"the run falls behind its vehicles' clock ({late} of "
                                f"{steps} steps late by more than {self.dt:g} s): the control loop "
                                "cannot keep up; lower runtime.mavlink.time_scale or use the track "
                                "controller",
                            )
                    else:
                        self.clock.sleep_until(due)
                elif self.realtime:  # the simulator, paced: one step per dt / speed of wall time
                    ahead = (
                        wall0 + (self.steps - steps0) * self.dt / self.speed - time.perf_counter()
                    )
                    if ahead > 0:
                        time.sleep(ahead)  # (at most about one step: a stop waits that long)
        finally:
            self._wall_used += time.perf_counter() - wall0
        return self.result(reason)

    def result(self, reason: str) -> RunResult:
        """How the run stands now, ended for ``reason`` (what :meth:`run` returns)."""
        now = self.now()
        ended = self.mission_end if not self.runs_coordinator else None
        if ended is not None:  # an agent process: the mission as its coordinator ended it
            return RunResult(
                reason, now, self._wall_used, self.steps, list(ended.done), dict(ended.open),
                self.collisions,
            )  # fmt: skip
        everything = self.coordinator.state.pool
        pool = [t for t in everything if t.info.arrival_s <= now + 1e-9]
        return RunResult(  # tasks still to arrive (``at:`` later) are neither done nor open
            reason,
            now,
            self._wall_used,
            self.steps,
            [t.id for t in pool if t.state is TaskState.DONE],
            {
                t.id: f"{t.state.value}: {t.note}"
                for t in pool
                if t.state not in (TaskState.DONE, TaskState.CANCELLED)
            },
            self.collisions,
            [
                t.id
                for t in everything
                if t.info.arrival_s > now + 1e-9 and t.state is not TaskState.CANCELLED
            ],
            [t.id for t in everything if t.state is TaskState.CANCELLED],
        )

    @staticmethod
    def end_before_build(mission: Mission, reason: str, wall_s: float) -> Event:
        """The ``end`` event of a run stopped while it was being built (after its header):
        nothing ran, every task is still to arrive."""
        return Event(
            0.0,
            "end",
            {
                "reason": reason,
                "wall_s": wall_s,
                "steps": 0,
                "done": [],
                "open": {},
                "pending": [t.id for t in mission.tasks],
            },
        )

    def close(self) -> None:
        """Release what the run holds: every run-wide service that has a ``close()`` (its
        errors are logged as ``leaf_error`` events, they do not stop the others), then the
        vehicle provider (sockets, threads of real vehicles). Idempotent."""
        seen: set[int] = set()
        for library, services in self.services.items():
            for name, service in services.items():
                close = getattr(service, "close", None)
                if close is None or id(service) in seen:
                    continue
                seen.add(id(service))
                try:
                    close()
                except Exception as exc:  # a library's code
                    self.errors.report(f"service {library}.{name}", "close", exc)
        self.provider.close()

    def end(self, result: RunResult) -> None:
        """Publish the ``end`` event (once): the run is over."""
        if self._ended is not None:
            return
        self._ended = result
        settled = [  # the run ended before their step came
            (future, self._log_command(
                command, "" if isinstance(command, Stop) else "not applied: the run had ended"
            ))
            for command, future in self.commands.take()
        ]  # fmt: skip
        self._publish(result.reason)
        _settle(settled)
        for a in self.agents.values():
            a.flush_tree_events()
        data: dict[str, Any] = {
            "reason": result.reason,
            "wall_s": result.wall_s,
            "steps": result.steps,
            "done": result.done,
            "open": result.open,
            "pending": result.pending,
        }
        if result.cancelled:
            data["cancelled"] = result.cancelled
        self.emit("end", **data)
        send_end = getattr(self.coordinator.link, "end", None)
        if self.part is not None and self.runs_coordinator and send_end is not None:
            send_end(MissionEnd(self.now(), result.reason, tuple(result.done), result.open))


def _settle(outcomes: Iterable[tuple[Future[Outcome], Outcome]]) -> None:
    """Give each waiting submitter its command's outcome."""
    for future, outcome in outcomes:
        if not future.done():
            future.set_result(outcome)
