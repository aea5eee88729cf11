"""Implementations of the ``haulage`` capability library (spec: ``haulage.yaml``).

The leaves talk to a :class:`HaulageContext` handed to ``setup(ctx=...)`` (the runtime issue
provides it: the truck's id, the clock, the backend and a :class:`Dispatcher` in front of
:mod:`btmission.dispatch`). The drive action does no planning of its own: at every tick it asks
:class:`~btmission.dispatch.follow.MissionFollower` where the dispatched mission's schedule puts
the truck now — waiting at a node, or a fraction along a segment — and commands exactly that, so
the fleet keeps to the collision-free plan the GA found (seed 004 §3-5).

Conditions are functions ``(ctx, **params) -> bool``; actions are py_trees behaviours whose
parameters (node names, as in the mission's task fields) are given to the constructor.
"""

from __future__ import annotations

from importlib.resources import files
from typing import Any, Protocol

import py_trees

from btmission.dispatch.follow import MissionFollower, MissionState
from btmission.dispatch.missions import Mission
from btmission.dispatch.topomap import TopoMap
from btmission.plugins import Implementations

SPEC = files(__package__).joinpath("haulage.yaml")
"""The library file; the ``btmission.libraries`` entry point ``haulage`` points here."""

IMPLEMENTATIONS = Implementations("haulage")
Status = py_trees.common.Status


class Dispatcher(Protocol):
    """The fleet dispatcher as a truck sees it (a front for seed 004 §5 dynamic planning)."""

    tmap: TopoMap

    def request(self, truck: str, goal: int) -> None:
        """Queue a re-planning request: ``truck`` wants a mission to node ``goal``."""

    def mission(self, truck: str) -> Mission | None:
        """The truck's mission in the adopted fleet mission (None before the first plan)."""

    def primary(self, truck: str) -> int | None:
        """The primary destination of that mission (its end node may be a secondary one)."""

    def park(self, truck: str) -> None:
        """Ask for a mission to the nearest free pause node."""


class HaulageContext(Protocol):
    """What the leaves need from the runtime."""

    truck: str
    dispatcher: Dispatcher
    cargo: str | None
    """Name of the loading site the load on board comes from (None: empty)."""
    hauls: set[tuple[str, str]]
    """(pickup, dropoff) of every load offloaded so far."""

    def now(self) -> float:
        """Mission time in s (the dispatcher's clock)."""

    def command(self, state: MissionState) -> None:
        """Send the backend where the truck must be now (wait at a node / along a segment)."""

    def process(self, kind: str, node: int) -> bool:
        """Start or continue loading/offloading (``kind``) at ``node``; True once finished."""


def _node(ctx: HaulageContext, name: str) -> int:
    return ctx.dispatcher.tmap.id(name)


def _state(ctx: HaulageContext) -> MissionState | None:
    m = ctx.dispatcher.mission(ctx.truck)
    return None if m is None else MissionFollower(ctx.dispatcher.tmap, m).state(ctx.now())


# ------------------------------------------------------------------------------- conditions
@IMPLEMENTATIONS.condition("at_node")
def at_node(ctx: HaulageContext, goal: str, **_: Any) -> bool:
    """The schedule is done and ends at ``goal``."""
    st = _state(ctx)
    return st is not None and st.done and st.node == _node(ctx, goal)


@IMPLEMENTATIONS.condition("dispatched")
def dispatched(ctx: HaulageContext, goal: str, **_: Any) -> bool:
    """The adopted plan has a mission for this truck towards ``goal`` that is not finished."""
    st = _state(ctx)
    return st is not None and not st.done and ctx.dispatcher.primary(ctx.truck) == _node(ctx, goal)


@IMPLEMENTATIONS.condition("released")
def released(ctx: HaulageContext, goal: str, **_: Any) -> bool:
    """False only while parked at a pause node (secondary destination) with no onward mission."""
    st = _state(ctx)
    if st is None or not st.done:
        return True
    tmap = ctx.dispatcher.tmap
    return not (tmap.is_pause[st.node] and st.node != _node(ctx, goal))


@IMPLEMENTATIONS.condition("loaded")
def loaded(ctx: HaulageContext, pickup: str, **_: Any) -> bool:
    return ctx.cargo == pickup


@IMPLEMENTATIONS.condition("hauled")
def hauled(ctx: HaulageContext, pickup: str, dropoff: str, **_: Any) -> bool:
    return (pickup, dropoff) in ctx.hauls


@IMPLEMENTATIONS.condition("parked")
def parked(ctx: HaulageContext, **_: Any) -> bool:
    st = _state(ctx)
    if st is None:
        return True
    kind = ctx.dispatcher.tmap.nodes[st.node].kind.name
    return st.done and kind in ("PAUSE", "TERMINAL")


# ------------------------------------------------------------------------------- actions
class _Leaf(py_trees.behaviour.Behaviour):  # type: ignore[misc]
    """A leaf bound to a :class:`HaulageContext` in ``setup(ctx=...)``."""

    def __init__(self, name: str = "", **params: str) -> None:
        super().__init__(name or type(self).__name__)
        self.params = params
        self.ctx: HaulageContext | None = None

    def setup(self, **kwargs: Any) -> None:
        ctx = kwargs.get("ctx")
        if ctx is None:
            raise KeyError(f"{self.name}: setup() needs ctx= (a HaulageContext)")
        self.ctx = ctx

    def _ctx(self) -> HaulageContext:
        if self.ctx is None:
            raise RuntimeError(f"{self.name}: ticked before setup(ctx=...)")
        return self.ctx

    def _drive(self) -> MissionState | None:
        """Command where the dispatched schedule puts the truck now (None: no mission yet)."""
        ctx = self._ctx()
        st = _state(ctx)
        if st is not None:
            ctx.command(st)
        return st


@IMPLEMENTATIONS.action("request_dispatch")
class RequestDispatch(_Leaf):
    """Queue one request, then RUNNING until a plan towards the goal is adopted."""

    def initialise(self) -> None:
        ctx = self._ctx()
        ctx.dispatcher.request(ctx.truck, _node(ctx, self.params["goal"]))

    def update(self) -> Status:
        return Status.SUCCESS if dispatched(self._ctx(), self.params["goal"]) else Status.RUNNING


@IMPLEMENTATIONS.action("drive_mission")
class DriveMission(_Leaf):
    """Keep to the dispatched schedule; SUCCESS when the mission ends (at the goal or at a
    secondary destination — then ``released`` is false and ``wait_at_pause`` takes over)."""

    def update(self) -> Status:
        st = self._drive()
        if st is None:
            return Status.FAILURE
        return Status.SUCCESS if st.done else Status.RUNNING


@IMPLEMENTATIONS.action("wait_at_pause")
class WaitAtPause(_Leaf):
    """RUNNING while parked at a secondary destination; SUCCESS once the onward mission is there."""

    def update(self) -> Status:
        ok = released(self._ctx(), self.params["goal"])
        return Status.SUCCESS if ok else Status.RUNNING


class _Process(_Leaf):
    kind = ""
    at = ""

    def update(self) -> Status:
        ctx = self._ctx()
        if not ctx.process(self.kind, _node(ctx, self.params[self.at])):
            return Status.RUNNING
        self.finish(ctx)
        return Status.SUCCESS

    def finish(self, ctx: HaulageContext) -> None:
        raise NotImplementedError


@IMPLEMENTATIONS.action("load")
class Load(_Process):
    kind, at = "load", "pickup"

    def finish(self, ctx: HaulageContext) -> None:
        ctx.cargo = self.params["pickup"]


@IMPLEMENTATIONS.action("offload")
class Offload(_Process):
    kind, at = "offload", "dropoff"

    def finish(self, ctx: HaulageContext) -> None:
        ctx.hauls.add((self.params["pickup"], self.params["dropoff"]))
        ctx.cargo = None


@IMPLEMENTATIONS.action("park")
class Park(_Leaf):
    """Ask for the nearest free pause node, then drive there on the dispatched schedule."""

    def initialise(self) -> None:
        ctx = self._ctx()
        ctx.dispatcher.park(ctx.truck)

    def update(self) -> Status:
        if self._drive() is None:
            return Status.RUNNING
        return Status.SUCCESS if parked(self._ctx()) else Status.RUNNING
