"""Run a mission end to end in the embedded simulator: coordinator, agents, vehicles, events.

:class:`MissionRun` builds everything from a validated :class:`~btmission.spec.mission.Mission`
and advances it in fixed steps of simulated time (``runtime.sim.step_s``). One step, at time t:

1. callbacks scheduled for t run (:meth:`MissionRun.at`), tasks added through the API enter
   the pool;
2. the coordinator runs an auction round if one is due (``coordination.auction_rate_hz``):
   announce → every agent bids → allocate → every agent gets its assignment;
3. agents whose tick is due tick their mission tree (``runtime.tick_hz``);
4. every agent's navigator streams this period's setpoints;
5. status reports go to the coordinator and pose events to the observers (``runtime.status_hz``);
6. the simulator advances every vehicle by one step and reports collisions.

Time comes from the simulator, never from the wall clock, so a run is deterministic for a seed
and goes as fast as the machine allows; ``realtime=True`` paces it against the wall clock.

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
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from btmission.allocation.tasks import TaskInfo, TaskState
from btmission.backends.base import VehicleKind
from btmission.backends.sim import Artifact, SimConfig, Simulator
from btmission.diagnostics import Diagnostic, Location, Severity, SpecError
from btmission.plugins import Implementations
from btmission.runtime.agent import Agent
from btmission.runtime.bus import InMemoryBus
from btmission.runtime.clock import Clock, ManualClock, SimClock
from btmission.runtime.coordinator import Coordinator
from btmission.runtime.events import (
    LOG_FORMAT,
    LOG_VERSION,
    Event,
    EventStream,
    Observer,
    world_reference,
)
from btmission.runtime.leaves import (
    ErrorReporter,
    RunContext,
    describe,
    setup_failed,
)
from btmission.runtime.navigation import NavConfig, Navigator
from btmission.runtime.paths import PathCosts
from btmission.spec.mission import Mission
from btmission.spec.runcheck import run_problems
from btmission.world.voxel import VoxelMap

if TYPE_CHECKING:
    from btmission.runtime.roads import RoadCosts

NEIGHBOUR_RANGE_M = 6.0
"""Agents farther than this are left out of each other's avoidance (APF, NMPC constraints)."""


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

    @property
    def speedup(self) -> float:
        return self.time_s / self.wall_s if self.wall_s > 0 else math.inf


def vehicle_kind(impl: Implementations) -> VehicleKind:
    """What the simulator builds for an agent whose library has these implementations."""
    return VehicleKind.GROUND if impl.vehicle == "ground" else VehicleKind.MULTIROTOR


class MissionRun:
    """A mission running in the embedded simulator (module docstring)."""

    def __init__(
        self,
        mission: Mission,
        *,
        seed: int = 0,
        controller: str | None = None,
        observers: Iterable[Observer] = (),
        voxel_map: VoxelMap | None = None,
        realtime: bool = False,
    ) -> None:
        from btmission.planning.risk import RiskParams
        from btmission.world.build import world_from_spec

        problems = run_problems(mission)  # the checks `validate` makes too
        if problems:
            raise SpecError(problems)
        self.mission = mission
        rt = mission.spec.runtime
        self.seed = seed
        self.controller = controller or rt.controller
        self.realtime = realtime
        self.events = EventStream(observers)
        self._last_t = 0.0
        self.clock: Clock = ManualClock(0.0)  # until the simulator is built
        build0 = time.perf_counter()
        # the header first: building the map and the planners can take long, and a run killed
        # meanwhile must still leave a log that `btmission report` reads (docs/running.md)
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
        self.sim = Simulator(
            self.map,
            SimConfig(
                step_s=sim_spec.step_s,
                lidar_range_m=sim_spec.lidar_range_m,
                dust_points=sim_spec.dust_points,
                detection_noise_px=sim_spec.detection_noise_px,
            ),
            seed=seed,
            artifacts=[Artifact(a.label, a.position, a.size_m) for a in sim_spec.artifacts],
        )
        self.clock = SimClock(self.sim)
        self.paths = PathCosts(
            self.map,
            RiskParams(rt.risk_radius_m, rt.unknown_cost),
            clearance_m=self.nav_config.clearance_m,
        )
        self.roads = self._roads()
        self.places = self.roads.places if self.roads is not None else {}
        self.bus = InMemoryBus()
        self.coordinator = Coordinator(
            mission,
            self.bus,
            self.now,
            self.emit,
            check_location=self.paths.problem,
            places=self.places,
        )
        self._namespace = f"/run-{uuid.uuid4().hex[:8]}"
        self.agents: dict[str, Agent] = {}
        self._schedule: list[tuple[float, int, Callable[[MissionRun], None]]] = []
        self._stop = threading.Event()
        self._stop_reason = "interrupted"
        self.dt = sim_spec.step_s
        self._tick_period = 1.0 / rt.tick_hz
        self._status_period = 1.0 / rt.status_hz
        self._next_tick = 0.0
        self._next_status = 0.0
        self.collisions = 0
        self._wall0: float | None = None
        self._wall_used = 0.0
        self._ended: RunResult | None = None
        self.errors = ErrorReporter(self.emit)
        """Exceptions raised by services' ``step`` → ``leaf_error`` events (once each)."""
        self.services: dict[str, dict[str, Any]] = self._build_services()
        self._build_agents()
        vm = self.map
        self.emit(
            "built",
            map={"shape": list(vm.shape), "resolution": vm.resolution, "origin": list(vm.origin)},
            build_s=time.perf_counter() - build0,
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
        for spec in self.mission.agents:
            loaded = self.mission.library_of(spec.id)
            impl = loaded.implementations
            assert impl is not None  # run_problems() checked it
            ground = vehicle_kind(impl) is VehicleKind.GROUND
            if ground:
                vehicle = self.sim.add_ground(spec.id, spec.start, v_max=self.nav_config.speed_m_s)
                control_dt = 0.1
            else:
                vehicle = self.sim.add_multirotor(spec.id, spec.start)
                control_dt = self.dt
            aid = spec.id

            def predictions(agent: str, _aid: str = aid) -> list[Any]:
                pos = self.sim.backends[_aid].telemetry().position
                return self.bus.predictions(agent, self.now(), 0.1, pos, NEIGHBOUR_RANGE_M)

            nav = Navigator(
                spec.id,
                vehicle,
                vehicle,
                self.controller,
                self.nav_config,
                control_dt=control_dt,
                predictions=predictions,
                ground_at=self.map.ground_z,
                point_area_m2=self.map.resolution**2,
            )
            self.agents[spec.id] = Agent(
                self.mission,
                spec.id,
                impl,
                vehicle,
                vehicle,
                nav,
                self.paths,
                self.bus,
                self.now,
                settings=self.settings,
                emit=self.emit,
                namespace=self._namespace,
                services=self.services[impl.library],
                places=self.places,
                provider=self.roads if ground else None,  # drones fly
            )

    def _emit_header(self) -> None:
        """The log's first event, from the mission alone (nothing built yet)."""
        m = self.mission
        world = m.spec.world.model_dump(mode="json")

        def vehicle(agent: str) -> str:
            impl = m.library_of(agent).implementations
            assert impl is not None  # run_problems() checked it
            return vehicle_kind(impl).value

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

    def add_task(self, task: Mapping[str, Any] | TaskInfo) -> TaskInfo:
        """Add a task while the mission runs (thread-safe): ``{"id": "T8", "type": "inspect",
        "location": [x, y, z]}``, optionally with ``priority`` and ``at``. Raises
        :class:`~btmission.runtime.coordinator.TaskError` when it cannot be used."""
        return self.coordinator.add_task(task, self.now())

    def at(self, t: float, fn: Callable[[MissionRun], None]) -> None:
        """Call ``fn(run)`` at mission time ``t`` (before that step's auction round)."""
        self._schedule.append((t, len(self._schedule), fn))
        self._schedule.sort()

    def kill_agent(self, agent: str, reason: str = "killed") -> None:
        """The agent's computer stops: no more ticks, bids or setpoints (its vehicle's
        autopilot falls back to HOLD when the setpoints stop)."""
        a = self.agents[agent]
        if a.alive:
            a.kill()
            self.emit("agent_lost", agent=agent, reason=reason)

    def signal(self, agent: str, name: str, value: Any = True) -> None:
        """Set a supervisor signal on an agent (its leaves read ``ctx.state[name]``), e.g. the
        COMPRA library's ``stop``. Thread-safe enough: one dict assignment."""
        self.agents[agent].ctx.state[name] = value
        self.emit("signal", agent=agent, name=name, value=value)

    def set_link(self, agent: str, up: bool) -> None:
        """Cut or restore an agent's link to the coordinator; the agent keeps executing."""
        self.bus.set_link(agent, up)
        self.emit("link", agent=agent, up=up)

    def stop(self, reason: str = "interrupted") -> None:
        """Ask the run to end after the current step (thread-safe; what Ctrl-C does)."""
        self._stop_reason = reason
        self._stop.set()

    # ---------------------------------------------------------------- running
    def step(self) -> None:
        """One fixed step (module docstring)."""
        now = self.now()
        while self._schedule and self._schedule[0][0] <= now + 1e-9:
            _, _, fn = self._schedule.pop(0)
            fn(self)
        for library, services in self.services.items():
            for name, service in services.items():
                step = getattr(service, "step", None)
                if step is not None:
                    try:
                        step(now)
                    except Exception as exc:  # a library's code must not end the run
                        self.errors.report(f"service {library}.{name}", "step", exc)
        self.coordinator.step(now)
        if now + 1e-9 >= self._next_tick:
            for a in self.agents.values():
                a.tick(now)
            self._next_tick += self._tick_period
        for a in self.agents.values():
            a.control_step(now)
        if now + 1e-9 >= self._next_status:
            self._report(now)
            self._next_status += self._status_period
        for ev in self.sim.step():
            self.collisions += 1
            self.emit("collision", agent=ev.vehicle, other=ev.other, p=list(ev.position))

    def _report(self, now: float) -> None:
        for aid, a in self.agents.items():
            if a.alive:
                self.bus.send_status(a.status(now))
            tel = self.sim.backends[aid].telemetry()
            v = self.sim.vehicle(aid)
            self.emit(
                "pose",
                agent=aid,
                p=tel.position,
                v=tel.velocity,
                yaw=tel.yaw,
                mode=tel.mode.value,
                armed=tel.armed,
                flying=not tel.landed,
                odometer_m=v.odometer_m,
                clearance_m=self.sim.take_clearance(aid),
            )

    def finished(self) -> str | None:
        """Why the run should end now (None: go on)."""
        live = [a for a in self.agents.values() if a.alive]
        pool = self.coordinator.state.pool
        if not self.coordinator.settled(self.now()):
            if not live and any(not t.state.terminal for t in pool):
                return "no agents left"
            return None
        if not all(a.at_rest for a in live):
            return None
        if all(t.state is TaskState.DONE for t in pool):
            return "completed"
        return "finished with open tasks"

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
        wall0 = time.perf_counter()
        sim0 = self.now()
        next_progress = self.now()
        reason = ""
        self._stop.clear()
        try:
            while True:
                if self._stop.is_set():
                    reason = self._stop_reason
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
                if self.realtime:
                    lag = (self.now() - sim0) - (time.perf_counter() - wall0)
                    if lag > 0:
                        time.sleep(lag)
        finally:
            self._wall_used += time.perf_counter() - wall0
        return self.result(reason)

    def result(self, reason: str) -> RunResult:
        """How the run stands now, ended for ``reason`` (what :meth:`run` returns)."""
        now = self.now()
        everything = self.coordinator.state.pool
        pool = [t for t in everything if t.info.arrival_s <= now + 1e-9]
        return RunResult(  # tasks still to arrive (``at:`` later) are neither done nor open
            reason,
            now,
            self._wall_used,
            self.sim.steps,
            [t.id for t in pool if t.state is TaskState.DONE],
            {t.id: f"{t.state.value}: {t.note}" for t in pool if t.state is not TaskState.DONE},
            self.collisions,
            [t.id for t in everything if t.info.arrival_s > now + 1e-9],
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

    def end(self, result: RunResult) -> None:
        """Publish the ``end`` event (once): the run is over."""
        if self._ended is not None:
            return
        self._ended = result
        for a in self.agents.values():
            a.flush_tree_events()
        self.emit(
            "end",
            reason=result.reason,
            wall_s=result.wall_s,
            steps=result.steps,
            done=result.done,
            open=result.open,
            pending=result.pending,
        )
