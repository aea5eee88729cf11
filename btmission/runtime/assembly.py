"""Building a run: what :class:`~btmission.runtime.runner.MissionRun` assembles before its loop.

In the order the run calls them:

1. :func:`emit_header` — the log's first event, from the mission alone (nothing built yet: a run
   killed while its map builds still leaves a log ``btmission report`` reads);
2. :func:`run_settings`, then :func:`make_provider` — the vehicle provider of the agents this
   process runs (:func:`agents_here`: all, but for a distributed run's part);
3. :func:`road_costs` — the places and road costs of the mission's topological map, if any;
4. :func:`build_services` — one instance of every run-wide service of the agents' libraries;
5. :func:`build_agents` — each agent's vehicle from the provider, its navigator and its
   :class:`~btmission.runtime.agent.Agent` (tree, blackboard, link to the coordinator,
   :func:`agent_link`);
6. :func:`follow_coordinator` — an agent process of a distributed run waits for its
   coordinator's first assignment, which sets its clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from btmission.diagnostics import Diagnostic, Location, Severity, SpecError
from btmission.links.bus import AgentLink, neighbour_states
from btmission.runtime.agent import Agent
from btmission.runtime.distribution import ClockFollower, NoVehicles, remote_bid_window
from btmission.runtime.eventkinds import (
    BuiltEvent,
    ClockEvent,
    HeaderEvent,
    WarningEvent,
)
from btmission.runtime.events import (
    LOG_FORMAT,
    LOG_VERSION,
    world_reference,
)
from btmission.runtime.leaves import ErrorReporter, RunContext, describe, setup_failed
from btmission.runtime.navigation import Navigator
from btmission.settings import RunSettings
from btmission.spec.source import format_path
from btmission.types import FloatArray
from btmission.vehicles.base import Backend, VehicleKind
from btmission.vehicles.clock import ScaledWallClock
from btmission.vehicles.provider import (
    PHASES,
    AttachOptions,
    AttachRequest,
    ProviderError,
    VehicleProvider,
    VehicleUnavailable,
    missing_phases,
    provider_factory,
)

if TYPE_CHECKING:
    from btmission.missions import LoadedMission
    from btmission.runtime.roads import RoadCosts
    from btmission.runtime.runner import MissionRun

NEIGHBOUR_RANGE_M = 6.0
"""Agents farther than this are left out of each other's avoidance (APF, NMPC constraints)."""


def run_settings(mission: LoadedMission) -> RunSettings:
    """The run's settings: every library's defaults, then the mission's ``runtime.settings``
    (:func:`~btmission.runtime.runcheck.run_problems` checked their types); each settings
    dataclass is built from them once (:meth:`RunSettings.of`)."""
    values: dict[str, Any] = {}
    for loaded in mission.libraries.values():
        if loaded.implementations is not None:
            values.update(loaded.implementations.settings)
    values.update(mission.spec.runtime.settings)
    return RunSettings(values)


def make_provider(run: MissionRun) -> VehicleProvider:
    """The vehicle provider of the agents this process runs: the one their ``backend:``
    scheme names (one for the whole fleet: ``validate`` refuses mixed fleets, one run, one
    clock); none in a distributed run's coordinator process, which only keeps the time."""
    here = agents_here(run)
    part = run.part
    if part is not None and not here:  # the coordinator's process: no vehicles
        return NoVehicles(run.mission.spec.runtime.mavlink.time_scale, part.started_unix)
    scheme = here[0].vehicle.scheme if here else "sim"
    provider = provider_factory(scheme)(run.mission, run.map, run.seed)
    missing = missing_phases(provider)
    if missing:
        raise ProviderError(
            f"the '{scheme}' vehicle provider ({type(provider).__name__}) has no "
            f"{', '.join(missing)}(): every provider has the phases {', '.join(PHASES)} "
            "(btmission.vehicles.provider.ProviderBase gives warm_up, prepare, attach_all, "
            "start and fleet_sensing)"
        )
    return provider


def road_costs(run: MissionRun) -> RoadCosts | None:
    """Places and road costs of the mission's topological map, if it has one."""
    ref = run.mission.spec.world.topomap
    if ref is None:
        return None
    from btmission.runtime.roads import RoadCosts, RoadMapError
    from btmission.spec.topomap import topomap_ref

    top = run.map.origin[2] + run.map.shape[2] * run.map.resolution
    try:
        return RoadCosts(
            topomap_ref(ref, run.mission.base_dir),
            lambda x, y: run.map.ground_z((x, y, top)),
            run.paths,
            snap_m=max(25.0, 2 * run.map.resolution),
        )
    except RoadMapError as exc:
        where = Location(run.mission.file)
        raise SpecError(
            [Diagnostic(Severity.ERROR, "topomap", str(exc), "world.topomap", where)]
        ) from None


def build_services(run: MissionRun) -> dict[str, dict[str, Any]]:
    """One instance of every run-wide service of the libraries the agents use."""
    context = RunContext(
        run.mission,
        run.map,
        run.now,
        run.settings,
        run.seed,
        run.library_event,
        run.places,
        run.roads.tmap if run.roads is not None else None,
    )
    out: dict[str, dict[str, Any]] = {}
    made: dict[int, Any] = {}  # one instance per factory: variants (extend) share it
    for spec in run.mission.agents:
        impl = run.mission.library_of(spec.id).implementations
        assert impl is not None
        if impl.library not in out:
            out[impl.library] = {}
            for name, make in impl.services.items():
                if id(make) not in made:
                    try:
                        made[id(make)] = make(context)
                    except Exception as exc:  # the library's code: a clear error, exit 2
                        raise setup_failed(
                            "service-failed",
                            f"library '{impl.library}': service '{name}' failed to start: "
                            f"{describe(exc)}",
                            "agents",
                            run.mission.file,
                        ) from exc
                out[impl.library][name] = made[id(make)]
    return out


def build_agents(run: MissionRun) -> None:
    """Every agent of this process: the provider opens its links, attaches all their vehicles
    at once (a real provider connects them concurrently), then each agent gets its navigator
    and tree."""
    blind: list[str] = []
    here = agents_here(run)
    run.provider.prepare([spec.vehicle for spec in here])  # (links open together)
    kinds = {}
    for spec in here:
        impl = run.mission.library_of(spec.id).implementations
        assert impl is not None  # run_problems() checked it
        kinds[spec.id] = VehicleKind.of(impl.vehicle)
    requests = [
        AttachRequest(
            spec.id,
            kinds[spec.id],
            spec.start,
            spec.vehicle,
            AttachOptions(
                v_max=run.nav_config.speed_m_s if kinds[spec.id] is VehicleKind.GROUND else None
            ),
        )
        for spec in here
    ]
    try:
        vehicles = run.provider.attach_all(requests)
    except VehicleUnavailable as exc:
        raise VehicleUnavailable(unavailable(run, exc), exc.failures) from None
    for spec, vehicle in zip(here, vehicles, strict=True):
        loaded = run.mission.library_of(spec.id)
        impl = loaded.implementations
        assert impl is not None
        ground = kinds[spec.id] is VehicleKind.GROUND
        run.vehicles[spec.id] = vehicle
        if vehicle.sensors is None:
            blind.append(spec.id)
        control_dt = 0.1 if ground else run.dt
        link = agent_link(run, spec.id)  # the agent's end of the coordinator link

        def predictions(
            agent: str, _backend: Backend = vehicle.backend, _link: AgentLink = link
        ) -> list[Any]:
            pos = _backend.telemetry().position
            return _link.predictions(run.now(), 0.1, pos, NEIGHBOUR_RANGE_M)

        def neighbours(agent: str, pos: FloatArray, _link: AgentLink = link) -> FloatArray:
            return neighbour_states(_link, run.now(), 0.1, pos, NEIGHBOUR_RANGE_M)

        nav = Navigator(
            spec.id,
            vehicle.backend,
            vehicle.sensors,
            run.controller,
            run.nav_config,
            control_dt=control_dt,
            predictions=predictions,
            neighbours=neighbours,
            ground_at=run.map.ground_z,
            point_area_m2=run.map.resolution**2,
        )
        nav.defer_nmpc = True  # the agents' NMPC solves overlap; step() collects them
        run.agents[spec.id] = Agent(
            run.mission,
            spec.id,
            impl,
            vehicle.backend,
            vehicle.sensors,
            nav,
            run.paths,
            link,
            run.now,
            settings=run.settings,
            emit=run.emit_event,
            namespace=run.namespace,
            services=run.services[impl.library],
            places=run.places,
            cost_provider=run.roads if ground else None,  # road costs; drones fly
            substitutions=run.substitutions,
            vehicle_link=vehicle.link_ok,
        )
    if blind:
        run.emit_event(
            WarningEvent(
                message=f"{', '.join(blind)}: no exteroceptive sensors (a real vehicle's come "
                "from its drivers): planning on the prior map only, reactive avoidance (APF on "
                "the LiDAR) is off",
            )
        )


def unavailable(run: MissionRun, exc: VehicleUnavailable) -> str:
    """The error of a fleet that could not be had: each failing agent's reason at its
    ``backend:`` line (one line each), or the provider's message at ``agents`` when it named
    no agent."""
    index = {a.id: i for i, a in enumerate(run.mission.agents)}
    problems = []
    for agent, why in exc.failures.items():
        if agent in index:
            path = ("agents", index[agent], "backend")
            where = run.mission.locate(path)
            problems.append(
                Diagnostic(Severity.ERROR, "vehicle-unavailable", why, format_path(path), where)
            )
    if not problems:
        where = run.mission.locate(("agents",))
        problems = [Diagnostic(Severity.ERROR, "vehicle-unavailable", str(exc), "agents", where)]
    return "\n".join(p.format() for p in problems)


def agents_here(run: MissionRun) -> list[Any]:
    """The mission's agents this process runs (all of them, but for a :class:`Part`)."""
    if run.part is None:
        return list(run.mission.agents)
    return [a for a in run.mission.agents if a.id in run.part.agents]


def agent_link(run: MissionRun, agent: str) -> AgentLink:
    if run.part is None:
        return run.bus.agent_link(agent)

    def followed(before: float, now: float) -> None:
        run.emit_event(ClockEvent(agent=agent, was_s=before, now_s=now))
        run.clock_set()

    clock = run.provider.clock  # (the run's once the provider starts)
    if not isinstance(clock, ScaledWallClock):  # the agent process's clock is its vehicles'
        raise SpecError([Diagnostic(
            Severity.ERROR, "agent-process",
            f"agent {agent}: an agent process flies real-time vehicles (MAVLink), whose "
            "clock follows the coordinator's; this agent's provider has its own",
            f"agents.{agent}.backend", Location(run.mission.file))])  # fmt: skip
    return ClockFollower(run.part.agent_links[agent], clock, followed)


def follow_coordinator(run: MissionRun, timeout_s: float) -> None:
    """An agent process: wait (up to ``timeout_s`` of wall time) for its coordinator's
    first assignment, which sets this process's mission clock to the coordinator's
    (:class:`~btmission.runtime.distribution.ClockFollower`); the agents' idle timers start
    then. Without one, the run goes on on its own clock (a ``warning`` event)."""
    assert run.part is not None
    links = [run.agents[a].link for a in run.part.agents if a in run.agents]
    deadline = time.monotonic() + timeout_s
    while not all(getattr(lk, "synced", True) for lk in links):
        left = deadline - time.monotonic()
        if left <= 0:
            run.emit_event(
                WarningEvent(
                    message=f"no assignment from the coordinator within {timeout_s:g} s: the "
                    "agents run on their own clock until one comes",
                )
            )
            break
        for dispatch in run.dispatchers:
            dispatch(min(0.1, left))
    now = run.now()
    for a in run.agents.values():
        a.idle_since = now


def emit_header(run: MissionRun) -> None:
    """The log's first event, from the mission alone (nothing built yet)."""
    m = run.mission
    world = m.spec.world.model_dump(mode="json")

    def vehicle(agent: str) -> str:
        impl = m.library_of(agent).implementations
        assert impl is not None  # run_problems() checked it
        return VehicleKind.of(impl.vehicle).value

    run.emit_event(
        HeaderEvent(
            format=LOG_FORMAT,
            version=LOG_VERSION,
            mission=m.name,
            description=m.spec.description,
            file=m.file,
            seed=run.seed,
            controller=run.controller,
            world=world,
            world_ref=world_reference(world, m.base_dir),
            step_s=m.spec.runtime.sim.step_s,
            part=run.part.describe() if run.part is not None else None,
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
    )


def part_dispatchers(run: MissionRun) -> list[Callable[[float], Any]]:
    """A distributed run's process: its agents' links' ``dispatch`` (the coordinator's messages,
    handed to the agents in this thread); the coordinator's process expects its live agents
    and gives bids the time a network needs."""
    part = run.part
    if part is None:
        return []
    if part.runs_coordinator:
        run.coordinator.expect = part.live_agents
        if run.coordinator.bid_window_s <= 0:  # bids come back over a network
            run.coordinator.bid_window_s = remote_bid_window(
                run.coordinator.period_s, run.mission.spec.runtime.mavlink.time_scale
            )
    return [
        d
        for link in part.agent_links.values()
        if (d := getattr(link, "dispatch", None)) is not None
    ]


def emit_built(run: MissionRun, build_s: float) -> None:
    """The ``built`` event: the map, how long building took and, in a distributed run's
    coordinator process, when its mission's clock was zero."""
    vm = run.map
    run.emit_event(
        BuiltEvent(
            map={"shape": list(vm.shape), "resolution": vm.resolution, "origin": list(vm.origin)},
            build_s=build_s,
            started_unix=(  # when this mission's clock was zero
                run.provider.started_unix if isinstance(run.provider, NoVehicles) else None
            ),
        )
    )


def close_services(services: dict[str, dict[str, Any]], errors: ErrorReporter) -> None:
    """Close every run-wide service that has a ``close()``, once each (variants share one);
    what one raises is logged as a ``leaf_error`` and does not stop the others."""
    seen: set[int] = set()
    for library, by_name in services.items():
        for name, service in by_name.items():
            close = getattr(service, "close", None)
            if close is None or id(service) in seen:
                continue
            seen.add(id(service))
            try:
                close()
            except Exception as exc:  # a library's code
                errors.report(f"service {library}.{name}", "close", exc)
