"""Reusable leaf implementations for capability libraries (built-in and third-party).

A library module registers these under its own action and condition names, e.g.::

    IMPLEMENTATIONS.action("update_path")(UpdatePath)
    IMPLEMENTATIONS.condition("at_goal")(at_goal)

Every action follows the request-and-poll pattern of :class:`~btmission.runtime.leaves.StatefulAction`:
it asks the backend, the path service or the navigator for something and watches the answer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from py_trees.common import Status

from btmission.fastpaths.ticks import FAILURE as _FAILURE
from btmission.fastpaths.ticks import RUNNING as _RUNNING
from btmission.fastpaths.ticks import SUCCESS as _SUCCESS
from btmission.runtime.leaves import AgentContext, StatefulAction
from btmission.runtime.navigation import NavState
from btmission.runtime.paths import Route
from btmission.vehicles.base import Mode

_ARRIVED, _FAILED = NavState.ARRIVED, NavState.FAILED
"""(read by the path follower every tick: a global costs a fifth of an Enum member on Python
3.11; so do the statuses, :mod:`btmission.fastpaths.ticks`'s)"""

Point = tuple[float, float, float]

COMMAND_TIMEOUT_S = 5.0
"""How long an action retries a refused autopilot command before it fails."""


def point(value: Any) -> Point:
    """A blackboard position as a tuple (task fields may arrive as lists)."""
    return (float(value[0]), float(value[1]), float(value[2]))


@dataclass(frozen=True)
class PlannedPath:
    """What ``update_path`` leaves on the blackboard (key ``path``)."""

    goal: Point
    route: Route


# ------------------------------------------------------------------------------- conditions
def is_armed(ctx: AgentContext) -> bool:
    return ctx.telemetry().armed


def in_offboard(ctx: AgentContext) -> bool:
    return ctx.telemetry().mode is Mode.OFFBOARD


def is_flying(ctx: AgentContext) -> bool:
    """Airborne and armed, clear of the ground."""
    tel = ctx.telemetry()
    return tel.armed and not tel.landed and tel.height_above_ground >= 0.5


def landed(ctx: AgentContext) -> bool:
    tel = ctx.telemetry()
    return tel.landed and not tel.armed


def vehicle_link_ok(ctx: AgentContext) -> bool:
    """The vehicle's autopilot is heard (always true in the simulator): libraries may branch on
    it, e.g. a ground robot that keeps a local plan going. The runtime pauses the whole tree
    while the link is lost, so this is False only in a tree ticked by other means (tests)."""
    return bool(ctx.blackboard.get("vehicle_link", True))


def has_path(ctx: AgentContext, goal: Any) -> bool:
    planned = ctx.blackboard.get("path")
    return isinstance(planned, PlannedPath) and planned.goal == point(goal)


def at_goal(ctx: AgentContext, goal: Any) -> bool:
    return ctx.navigator.at(point(goal))


# ------------------------------------------------------------------------------- actions
class Command(StatefulAction):
    """Send an autopilot command until it is accepted and its effect shows in the telemetry
    (retried every tick for ``COMMAND_TIMEOUT_S``, then FAILURE with the autopilot's reason)."""

    def send(self) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError

    def done(self) -> bool:  # pragma: no cover - overridden
        raise NotImplementedError

    def on_start(self) -> Status:
        self._t0 = self.ctx.now()
        return self.on_running()

    def on_running(self) -> Status:
        if self.done():
            return Status.SUCCESS
        ack = self.send()
        if self.done():
            return Status.SUCCESS
        if self.ctx.now() - self._t0 > COMMAND_TIMEOUT_S:
            self.reason = ack.reason or "not accepted"
            return Status.FAILURE
        return Status.RUNNING


class Arm(Command):
    def send(self) -> Any:
        return self.ctx.backend.arm()

    def done(self) -> bool:
        return is_armed(self.ctx)


class SetOffboard(Command):
    """Switch to OFFBOARD: the navigator streams setpoints all the time, so the autopilot
    accepts once the stream has run for a second (PX4's rule)."""

    def send(self) -> Any:
        return self.ctx.backend.set_mode(Mode.OFFBOARD)

    def done(self) -> bool:
        return in_offboard(self.ctx)


class Takeoff(StatefulAction):
    """Climb to ``altitude_m`` above the ground with offboard setpoints."""

    def on_start(self) -> Status:
        tel = self.ctx.telemetry()
        if not tel.armed:
            self.reason = "not armed"
            return Status.FAILURE
        self.ctx.navigator.takeoff()
        return Status.RUNNING

    def on_running(self) -> Status:
        st = self.ctx.navigator.status
        if st.command == "takeoff" and st.state is NavState.ARRIVED:
            return Status.SUCCESS
        if st.state is NavState.FAILED:
            self.reason = st.reason
            return Status.FAILURE
        if st.command != "takeoff":  # something else took the navigator: climb again
            self.ctx.navigator.takeoff()
        return Status.RUNNING

    def on_halted(self) -> None:
        self.ctx.navigator.hold()


class UpdatePath(StatefulAction):
    """Plan the D*+ path to ``goal`` from where the agent is (seed 000 §IV-C2)."""

    def on_start(self) -> Status:
        goal = point(self.args["goal"])
        nav = self.ctx.navigator
        target = nav.flight_target(goal)
        p = self.ctx.telemetry().position
        route = self.ctx.paths.route((float(p[0]), float(p[1]), float(p[2])), point(target))
        if route is None:
            why = self.ctx.paths.problem(point(target))
            self.reason = f"no path to {_fmt(goal)}" + (f" ({why})" if why else "")
            return Status.FAILURE
        self.ctx.blackboard.set("path", PlannedPath(goal, route))
        return Status.SUCCESS


class FollowPath(StatefulAction):
    """Track the planned path to ``goal`` (NMPC or tracking controller, with APF); when the
    vehicle makes no progress (blocked by another vehicle, pushed off by the APF) it replans
    from where it is, up to the ``replans`` setting, before failing."""

    def on_start(self) -> Status:
        self._tries = 0
        return self._go()

    def _go(self) -> Status:
        goal = point(self.args["goal"])
        planned = self.ctx.blackboard.get("path")
        if not isinstance(planned, PlannedPath) or planned.goal != goal:
            self.reason = f"no path to {_fmt(goal)} on the blackboard"
            return _FAILURE
        nav = self.ctx.navigator
        nav.follow(planned.route.waypoints, nav.flight_target(goal), self.ctx.now())
        return _RUNNING

    def on_running(self) -> Status:
        st = self.ctx.navigator.status
        if st.command == "follow" and st.state is _ARRIVED:
            return _SUCCESS
        if st.command != "follow" or st.state is _FAILED:
            self._tries += 1
            if self._tries > self.ctx.navigator.config.replans:
                self.reason = st.reason or "path following stopped"
                return _FAILURE
            goal = point(self.args["goal"])
            p = self.ctx.telemetry().position
            route = self.ctx.paths.route(
                (float(p[0]), float(p[1]), float(p[2])),
                point(self.ctx.navigator.flight_target(goal)),
            )
            if route is None:
                self.reason = f"no path to {_fmt(goal)} any more"
                return _FAILURE
            self.ctx.blackboard.set("path", PlannedPath(goal, route))
            return self._go()
        return _RUNNING

    def on_halted(self) -> None:
        self.ctx.navigator.hold()


class Land(StatefulAction):
    """Land where the vehicle is (AUTO.LAND) and wait until it has disarmed."""

    def on_start(self) -> Status:
        self.ctx.navigator.land()
        return Status.RUNNING

    def on_running(self) -> Status:
        st = self.ctx.navigator.status
        if landed(self.ctx):
            return Status.SUCCESS
        if st.state is NavState.FAILED:
            self.reason = st.reason
            return Status.FAILURE
        if st.command != "land":
            self.ctx.navigator.land()
        return Status.RUNNING


class Timed(StatefulAction):
    """Stand still for :meth:`duration_s` (a setting), then apply :meth:`finish`."""

    setting = ""
    default_s = 2.0

    def duration_s(self) -> float:
        """How long to stand still. A subclass reads its library's typed settings
        (``self.ctx.settings_of(MySettings).pick_time_s``); this default reads the setting
        named by ``setting``, or ``default_s`` (the untyped path of subclasses written before
        typed settings, :meth:`~btmission.runtime.leaves.AgentContext.setting`)."""
        return float(self.ctx.setting(self.setting, self.default_s))

    def on_start(self) -> Status:
        self._t0 = self.ctx.now()
        self._duration_s = self.duration_s()
        self.ctx.navigator.hold()
        return self.on_running()

    def on_running(self) -> Status:
        if self.ctx.now() - self._t0 >= self._duration_s:
            self.finish()
            return Status.SUCCESS
        return Status.RUNNING

    def finish(self) -> None:  # pragma: no cover - overridden
        pass


def _fmt(p: Point) -> str:
    return "[" + ", ".join(f"{v:g}" for v in p) + "]"
