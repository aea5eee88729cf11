"""Implementations of the ``haulage`` capability library (spec: ``haulage.yaml``).

Haul trucks on the roads of a topological mine map, dispatched by the GA fleet planner
(seed 004 §5). A mission using this library names a ``world.topomap``; its tasks name map nodes
(``pickup: L1n``, ``dropoff: O``).

One run-wide service, :class:`HaulageFleet` (``ctx.services["fleet"]``), holds the
:class:`~btmission.dispatch.service.FleetDispatcher` and **keeps every truck on its dispatched
schedule at every step**: where the adopted mission puts the truck now — standing at a node, or a
fraction along a segment — is what its navigator tracks (:meth:`Navigator.track
<btmission.runtime.navigation.Navigator.track>`). The plan fixes each truck's whole trajectory in
time (§3.2), so no leaf may stop a truck on its own: a leaf halted half-way (the auction gave the
truck another haul) leaves it driving its schedule to the end of the mission, collision-free.

The leaves are therefore thin: ``request_dispatch`` queues a request and waits for the plan,
``drive_mission`` waits for the schedule to end, ``wait_at_pause`` waits at a secondary
destination for the onward mission, ``load`` / ``offload`` take a random time at the node
(2-5 min and 30-60 s in the paper, settings below), ``park`` asks for the nearest free pause node.

Settings (``runtime.settings``, :class:`HaulageSettings`): ``load_min_s``, ``load_max_s``,
``offload_min_s``, ``offload_max_s``; ``dispatch_opt_time_s`` (mission time charged per
optimisation, §5), ``dispatch_generations`` (GA generations per optimisation: runs are
reproducible) and ``dispatch_budget_s`` (wall-clock cap per optimisation); ``speed_m_s`` is the
trucks' top speed (above the schedule's 30 km/h so that a truck behind its schedule catches up).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.resources import files
from typing import Any

import numpy as np
from py_trees.common import Status

from btmission.diagnostics import Diagnostic, Severity, SpecError
from btmission.dispatch.dynamic import DynamicConfig
from btmission.dispatch.follow import MissionFollower, MissionState
from btmission.dispatch.ga import GAParams
from btmission.dispatch.missions import Mission
from btmission.dispatch.service import FleetDispatcher
from btmission.dispatch.topomap import TopoMap
from btmission.plugins import Implementations
from btmission.runtime.eventkinds import DispatchEvent
from btmission.runtime.events import (
    TypedEvent,
    register_event,
)
from btmission.runtime.leaves import AgentContext, RunContext, StatefulAction, resolve
from btmission.spec.mission import Mission as MissionFile

SPEC = files(__package__).joinpath("haulage.yaml")
"""The library file; the ``btmission.libraries`` entry point ``haulage`` points here."""


@dataclass(frozen=True)
class HaulageSettings:
    """The ``haulage`` library's settings (``runtime.settings`` of a mission)."""

    load_min_s: float = 120.0
    """Shortest loading at a loading site (s; the paper's 2-5 min)."""
    load_max_s: float = 300.0
    """Longest loading at a loading site (s)."""
    offload_min_s: float = 30.0
    """Shortest offloading at an offloading site (s; the paper's 30-60 s)."""
    offload_max_s: float = 60.0
    """Longest offloading at an offloading site (s)."""
    dispatch_opt_time_s: float = 3.0
    """Mission time charged per optimisation of the fleet's plan (s, seed 004 §5)."""
    dispatch_generations: int = 200
    """GA generations per optimisation (a fixed count: runs are reproducible)."""
    dispatch_budget_s: float = 2.0
    """Wall-clock cap per optimisation (s)."""
    speed_m_s: float = 12.0
    """Top speed (m/s; the navigator's setting): 43 km/h, above the schedule's 30 km/h.

    A truck behind its schedule catches up."""


IMPLEMENTATIONS = Implementations("haulage", vehicle="ground", settings=HaulageSettings)

START_SNAP_M = 30.0
"""A truck must start this close to a node of the map (it is placed on that node)."""


@dataclass
class Truck:
    """One truck's state outside the tree: its agent context, load and random stream."""

    name: str
    rng: np.random.Generator
    ctx: AgentContext | None = None
    cargo: str | None = None
    """Name of the loading site the load on board comes from (None: empty)."""
    hauled: dict[str, tuple[str, str]] = field(default_factory=dict)
    """Task id → (pickup, dropoff) of every load offloaded so far (a mine repeats hauls: the
    same pickup and dropoff in a new task is a new haul)."""

    @property
    def idle(self) -> bool:
        """No task (the default behaviour may be running)."""
        agent = self.ctx.agent if self.ctx is not None else None
        return agent is not None and agent.task is None

    @property
    def task(self) -> str | None:
        agent = self.ctx.agent if self.ctx is not None else None
        return agent.task.id if agent is not None and agent.task is not None else None


class HaulageFleet:
    """The run-wide service (module docstring): the dispatcher and every truck's schedule."""

    def __init__(self, run: RunContext) -> None:
        mission = run.mission
        if run.topomap is None:
            raise SpecError([_no_topomap(mission)])
        self.tmap: TopoMap = run.topomap
        self.places = run.places
        starts, problems = truck_starts(mission, self.tmap)
        if problems:
            raise SpecError(problems)
        settings = run.settings_of(HaulageSettings)
        ga = GAParams(
            budget_s=settings.dispatch_budget_s, max_generations=settings.dispatch_generations
        )
        cfg = DynamicConfig(
            vehicles=len(starts),
            opt_time_s=settings.dispatch_opt_time_s,
            ga=ga,
            seed=run.seed,
        )
        self.dispatcher = FleetDispatcher(self.tmap, starts, cfg, _dispatch_events(run))
        self.trucks = {
            name: Truck(name, np.random.default_rng([run.seed, zlib.crc32(name.encode())]))
            for name in starts
        }
        self._followers: dict[str, MissionFollower] = {}

    def state(self, truck: str, now: float) -> MissionState:
        """Where the truck's dispatched schedule puts it at ``now``."""
        m: Mission = self.dispatcher.mission(truck)
        f = self._followers.get(truck)
        if f is None or f.mission is not m:
            f = self._followers[truck] = MissionFollower(self.tmap, m)
        return f.state(now)

    def reference(self, st: MissionState) -> tuple[np.ndarray, np.ndarray]:
        """Position and velocity the schedule asks for (world frame, on the ground)."""
        a = np.array(self.places[self.tmap.nodes[st.node].name])
        if st.phase != "moving":
            return a, np.zeros(3)
        b = np.array(self.places[self.tmap.nodes[st.next].name])
        span = float(self.tmap.ttime[st.node, st.next])
        return a + st.fraction * (b - a), (b - a) / span

    def step(self, now: float) -> None:
        """Run the dispatcher, move idle trucks out of the way, then point every truck's
        navigator at its schedule."""
        d = self.dispatcher
        for name, truck in self.trucks.items():
            # an idle truck standing where another truck has to go leaves (parks) by itself:
            # no truck waits at a pause node for one that has nothing to do
            if truck.idle and not d.waiting(name):
                st = self.state(name, now)
                if st.done and d.wanted(st.node, name):
                    d.park(name)
        d.step(now)
        for name, truck in self.trucks.items():
            if truck.ctx is not None:
                ref, vel = self.reference(self.state(name, now))
                truck.ctx.navigator.track(ref, vel, now)


def _nearest(tmap: TopoMap, p: tuple[float, float, float]) -> tuple[int, float]:
    best, dist = 0, math.inf
    for i, n in enumerate(tmap.nodes):
        if n.xy is not None:
            d = math.hypot(p[0] - n.xy[0], p[1] - n.xy[1])
            if d < dist:
                best, dist = i, d
    return best, dist


def _no_topomap(mission: MissionFile) -> Diagnostic:
    return Diagnostic(Severity.ERROR, "no-topomap",
        "library 'haulage' needs a topological map: set world.topomap (e.g. 'mine')",
        "world.topomap", mission.locate(("world",)))  # fmt: skip


def truck_starts(mission: MissionFile, tmap: TopoMap) -> tuple[dict[str, int], list[Diagnostic]]:
    """Each truck's start node, and the problems: a truck farther than ``START_SNAP_M`` from
    every node, two trucks on one node."""
    starts: dict[str, int] = {}
    problems = []
    for i, spec in enumerate(mission.agents):
        impl = mission.library_of(spec.id).implementations
        if impl is None or impl.services.get("fleet") is not _fleet:
            continue  # not a truck (haulage, or a variant made with extend())
        where = mission.locate(("agents", i, "start"))
        node, d = _nearest(tmap, spec.start)
        if d > START_SNAP_M:
            problems.append(Diagnostic(Severity.ERROR, "start-off-road",
                f"agent '{spec.id}' starts {d:.0f} m from the nearest node of map "
                f"'{tmap.name}' ({tmap.nodes[node].name}); trucks must start on a "
                f"node (within {START_SNAP_M:g} m)", f"agents.{spec.id}.start", where))  # fmt: skip
        other = next((a for a, n in starts.items() if n == node), None)
        if other is not None:
            problems.append(Diagnostic(Severity.ERROR, "same-start",
                f"agents '{other}' and '{spec.id}' both start at node "
                f"{tmap.nodes[node].name}: one truck per node",
                f"agents.{spec.id}.start", where))  # fmt: skip
        starts[spec.id] = node
    return starts, problems


def check_mission(mission: MissionFile) -> list[Diagnostic]:
    """What :class:`HaulageFleet` would refuse, found before any run (``validate`` and ``run``
    call it through :func:`btmission.runtime.runcheck.run_problems`)."""
    from btmission.spec.topomap import topomap_ref

    if mission.spec.world.topomap is None:
        return [_no_topomap(mission)]
    try:
        tmap = topomap_ref(mission.spec.world.topomap, mission.base_dir)
    except SpecError:
        return []  # loading the mission reports it
    return truck_starts(mission, tmap)[1]


def _dispatch_events(run: RunContext) -> Callable[..., None]:
    """The dispatcher's ``events(kind, **fields)`` (an algorithm, it knows no run: its kind is
    ``dispatch``) as the run's typed events (:class:`~btmission.runtime.events.DispatchEvent`)."""

    def publish(kind: str, **fields: Any) -> None:
        if kind != DispatchEvent.KIND:
            raise ValueError(f"the dispatcher published a '{kind}' event")
        run.events(DispatchEvent(**fields))

    return publish


@IMPLEMENTATIONS.service("fleet")
def _fleet(run: RunContext) -> HaulageFleet:
    return HaulageFleet(run)


@IMPLEMENTATIONS.on_setup
def _attach(ctx: AgentContext) -> None:
    """The fleet keeps this truck's navigator on its schedule from the first step."""
    fleet: HaulageFleet = ctx.services["fleet"]
    fleet.trucks[ctx.agent_id].ctx = ctx


def _fleet_of(ctx: AgentContext) -> HaulageFleet:
    fleet: HaulageFleet = ctx.services["fleet"]
    return fleet


def _node(ctx: AgentContext, name: str) -> int:
    """The node called ``name`` (-1 if the map has none: conditions on it are false, and
    ``request_dispatch`` fails with the reason)."""
    return _fleet_of(ctx).tmap.index.get(str(name), -1)


def _state(ctx: AgentContext) -> MissionState:
    return _fleet_of(ctx).state(ctx.agent_id, ctx.now())


# ------------------------------------------------------------------------------- conditions
@IMPLEMENTATIONS.condition("at_node")
def at_node(ctx: AgentContext, goal: str) -> bool:
    """The schedule is done and ends at ``goal``."""
    st = _state(ctx)
    return st.done and st.node == _node(ctx, goal)


@IMPLEMENTATIONS.condition("dispatched")
def dispatched(ctx: AgentContext, goal: str) -> bool:
    """The adopted plan has a mission for this truck towards ``goal`` that is not finished."""
    st = _state(ctx)
    d = _fleet_of(ctx).dispatcher
    return not st.done and d.primary(ctx.agent_id) == _node(ctx, goal)


@IMPLEMENTATIONS.condition("released")
def released(ctx: AgentContext, goal: str) -> bool:
    """False only while parked at a secondary destination (a pause node) on the way to
    ``goal``, its onward mission not given yet."""
    st = _state(ctx)
    fleet = _fleet_of(ctx)
    g = _node(ctx, goal)
    held = st.done and fleet.tmap.is_pause[st.node] and st.node != g
    return not (held and fleet.dispatcher.primary(ctx.agent_id) == g)


@IMPLEMENTATIONS.condition("loaded")
def loaded(ctx: AgentContext, pickup: str) -> bool:
    return _fleet_of(ctx).trucks[ctx.agent_id].cargo == str(pickup)


@IMPLEMENTATIONS.condition("hauled")
def hauled(ctx: AgentContext, pickup: str, dropoff: str) -> bool:
    """This task's load from ``pickup`` has been offloaded at ``dropoff``."""
    truck = _fleet_of(ctx).trucks[ctx.agent_id]
    return truck.hauled.get(truck.task or "") == (str(pickup), str(dropoff))


@IMPLEMENTATIONS.condition("parked")
def parked(ctx: AgentContext) -> bool:
    """Stopped out of every other truck's way: at a pause node no other truck targets (or,
    when all of them are, at a free non-prioritised terminal)."""
    st = _state(ctx)
    return st.done and st.node == _fleet_of(ctx).dispatcher.park_target(ctx.agent_id)


# ------------------------------------------------------------------------------- actions
class _Haulage(StatefulAction):
    @property
    def fleet(self) -> HaulageFleet:
        return _fleet_of(self.ctx)

    @property
    def truck(self) -> str:
        return self.ctx.agent_id

    def on_halted(self) -> None:
        """Halted because the truck's task changed (the auction gave it another haul, or took
        its haul away): the dispatcher forgets what was asked for the old one. Halted for any
        other reason (a condition above now holds), nothing changes."""
        goal = self.args.get("goal")
        if goal is None:
            return
        agent = self.ctx.agent
        now = resolve(self.ctx, self.node) if agent is not None and agent.task else None
        if now is None or str(now.get("goal")) != str(goal):
            self.fleet.dispatcher.withdraw(self.truck)


@IMPLEMENTATIONS.action("request_dispatch")
class RequestDispatch(_Haulage):
    """Queue one request, then RUNNING until a plan towards the goal is adopted (a failed
    optimisation is re-queued by the dispatcher)."""

    def on_start(self) -> Status:
        node = _node(self.ctx, self.args["goal"])
        if node < 0:
            self.reason = f"no node '{self.args['goal']}' in map '{self.fleet.tmap.name}'"
            return Status.FAILURE
        self.fleet.dispatcher.request(self.truck, node)
        return self.on_running()

    def on_running(self) -> Status:
        goal = self.args["goal"]
        if dispatched(self.ctx, goal) or at_node(self.ctx, goal):
            return Status.SUCCESS
        d = self.fleet.dispatcher
        if not d.waiting(self.truck):  # served without moving us (e.g. already there): ask again
            d.request(self.truck, _node(self.ctx, goal))
        return Status.RUNNING


@IMPLEMENTATIONS.action("drive_mission")
class DriveMission(_Haulage):
    """Wait while the fleet service drives the dispatched schedule; SUCCESS when it ends (at
    the goal, or at a secondary destination — then ``released`` is false and
    ``wait_at_pause`` takes over)."""

    def on_running(self) -> Status:
        self.feedback_message = f"{_state(self.ctx).phase} on the dispatched schedule"
        return Status.SUCCESS if _state(self.ctx).done else Status.RUNNING


@IMPLEMENTATIONS.action("wait_at_pause")
class WaitAtPause(_Haulage):
    """RUNNING while parked at a secondary destination; SUCCESS once the onward mission is
    there. When the primary destination is free and no request is queued for this truck, it
    asks for the onward mission itself (it does not wait for another truck's request)."""

    def on_running(self) -> Status:
        goal = self.args["goal"]
        if released(self.ctx, goal):
            return Status.SUCCESS
        d = self.fleet.dispatcher
        g = _node(self.ctx, goal)
        k = d.names.index(self.truck)
        if not d.waiting(self.truck) and g not in d.planner.targets(k):
            d.request(self.truck, g)
        return Status.RUNNING


@register_event
@dataclass(frozen=True, kw_only=True)
class LoadEvent(TypedEvent):
    """This library's own event: a truck started loading at its pickup, ``until`` (mission time)."""

    KIND = "load"
    agent: str
    until: float


@register_event
@dataclass(frozen=True, kw_only=True)
class OffloadEvent(TypedEvent):
    """A truck started offloading at its dropoff, ``until`` (mission time)."""

    KIND = "offload"
    agent: str
    until: float


class _Process(_Haulage):
    """Stand at the node for a random duration in :meth:`window_s`'s [shortest, longest]."""

    event_class: type[LoadEvent | OffloadEvent]
    """The event it publishes when it starts."""

    def window_s(self, settings: HaulageSettings) -> tuple[float, float]:  # pragma: no cover
        raise NotImplementedError

    def on_start(self) -> Status:
        lo, hi = self.window_s(self.ctx.settings_of(HaulageSettings))
        rng = self.fleet.trucks[self.truck].rng
        self._until = self.ctx.now() + lo + float(rng.random()) * max(0.0, hi - lo)
        self.ctx.events(self.event_class(agent=self.ctx.agent_id, until=round(self._until, 3)))
        return self.on_running()

    def on_running(self) -> Status:
        if self.ctx.now() < self._until:
            return Status.RUNNING
        self.finish(self.fleet.trucks[self.truck])
        return Status.SUCCESS

    def finish(self, truck: Truck) -> None:  # pragma: no cover - overridden
        raise NotImplementedError


@IMPLEMENTATIONS.action("load")
class Load(_Process):
    event_class = LoadEvent

    def window_s(self, settings: HaulageSettings) -> tuple[float, float]:
        return settings.load_min_s, settings.load_max_s

    def finish(self, truck: Truck) -> None:
        truck.cargo = str(self.args["pickup"])


@IMPLEMENTATIONS.action("offload")
class Offload(_Process):
    event_class = OffloadEvent

    def window_s(self, settings: HaulageSettings) -> tuple[float, float]:
        return settings.offload_min_s, settings.offload_max_s

    def finish(self, truck: Truck) -> None:
        truck.hauled[truck.task or ""] = (str(self.args["pickup"]), str(self.args["dropoff"]))
        truck.cargo = None


@IMPLEMENTATIONS.action("park")
class Park(_Haulage):
    """Ask to be parked out of the way (:meth:`FleetDispatcher.park_target
    <btmission.dispatch.service.FleetDispatcher.park_target>`), then wait until the schedule has
    the truck there."""

    def on_start(self) -> Status:
        return self.on_running()

    def on_running(self) -> Status:
        if parked(self.ctx):
            return Status.SUCCESS
        d = self.fleet.dispatcher
        if not d.waiting(self.truck) and _state(self.ctx).done:
            d.park(self.truck)
        return Status.RUNNING
