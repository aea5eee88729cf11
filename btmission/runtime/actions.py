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
from btmission.runtime.eventkinds import RetryEvent
from btmission.runtime.leaves import AgentContext, StatefulAction
from btmission.runtime.navconfig import NavState
from btmission.runtime.paths import Route
from btmission.vehicles.base import Ack, Mode

_ARRIVED, _FAILED = NavState.ARRIVED, NavState.FAILED
"""(read by the path follower every tick: a global costs a fifth of an Enum member on Python
3.11; so do the statuses, :mod:`btmission.fastpaths.ticks`'s)"""

Point = tuple[float, float, float]

COMMAND_TIMEOUT_S = 5.0
"""How long one try of an autopilot command lasts: the command is sent again every tick (the
vehicle decides how often it really asks its autopilot) until its effect shows."""


@dataclass(frozen=True)
class CommandRetrySettings:
    """The runtime's retries of a refused vehicle command (every run has these settings)."""

    refusal_retries: int = 3
    """How many more tries an action makes when its vehicle refuses a command transiently
    (arming refused by a pre-arm check, OFFBOARD denied, no answer) for a whole try
    (``COMMAND_TIMEOUT_S``, 5 s), each after a back-off; then the agent gives its task back (0:
    no retry)."""
    refusal_backoff_s: float = 2.0
    """The back-off before the first retry (s of mission time); it doubles after each one."""
    takeover_is_final: bool = True
    """A vehicle its autopilot's failsafe (or its pilot) took over makes its agent stand down
    until the operator includes it again (false: a ``taken_over`` event, then the tree flies on
    from the vehicle's state: it arms and launches a drone its failsafe landed)."""


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
    """Send an autopilot command until it is accepted and its effect shows in the telemetry.

    One *try* sends it every tick for ``COMMAND_TIMEOUT_S`` (PX4 refuses OFFBOARD until the
    setpoints have streamed for a second: the usual try ends accepted). How a try that ends
    refused goes on depends on the refusal, as the vehicle typed it
    (:class:`~btmission.vehicles.base.Ack`):

    * **transient** (arming refused by a pre-arm check, a mode denied for now, no answer; an
      accepted command whose effect never showed counts as one): the action keeps RUNNING,
      sends nothing for a back-off (``refusal_backoff_s``, doubling; mission time, no sleep)
      and tries again, each retry a ``retry`` event with the refusal; after
      ``refusal_retries`` retries it fails and says it gave up;
    * **final** (a mode the vehicle does not have, a battery too low): it fails at once.

    Either way the failure is a *refusal* (:attr:`refused`): the agent hands its task back to
    the pool for another agent instead of failing it (docs/running.md, "When a task fails").
    """

    def send(self) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError

    def done(self) -> bool:  # pragma: no cover - overridden
        raise NotImplementedError

    def on_start(self) -> Status:
        self._t0 = self.ctx.now()
        self._retry = 0
        self._wait_until: float | None = None
        return self.on_running()

    def on_running(self) -> Status:
        if self.done():
            return Status.SUCCESS
        now = self.ctx.now()
        if self._wait_until is not None:  # backing off before the next try
            if now < self._wait_until:
                return Status.RUNNING
            self._wait_until = None
            self._t0 = now
        ack: Ack = self.send()
        if self.done():
            return Status.SUCCESS
        if not ack.accepted and not ack.transient:  # final: asking again will not help
            return self._refused(ack.reason or "refused")
        if now - self._t0 > COMMAND_TIMEOUT_S:
            return self._try_failed(ack, now)
        return Status.RUNNING

    def _try_failed(self, ack: Ack, now: float) -> Status:
        """A try ended without the command's effect: back off and retry, or give up."""
        if ack.accepted:
            reason = f"accepted, but not seen within {COMMAND_TIMEOUT_S:g} s"
        else:
            reason = ack.reason or "not accepted"
        cfg = self.ctx.settings_of(CommandRetrySettings)
        if self._retry >= cfg.refusal_retries:
            tries = self._retry + 1
            return self._refused(
                f"{reason} (gave up after {tries} tr{'y' if tries == 1 else 'ies'})"
            )
        self._retry += 1
        wait = cfg.refusal_backoff_s * 2 ** (self._retry - 1)
        self._wait_until = now + wait
        agent = self.ctx.agent
        task = agent.task if agent is not None else None
        self.ctx.events(
            RetryEvent(
                agent=self.ctx.agent_id,
                task=task.id if task is not None else None,
                action=self.name,
                retry=self._retry,
                retries=cfg.refusal_retries,
                reason=reason,
                wait_s=wait,
            )
        )
        return Status.RUNNING

    def _refused(self, reason: str) -> Status:
        self.reason = reason
        self.refused = True
        return Status.FAILURE


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
        start = (float(p[0]), float(p[1]), float(p[2]))
        route = self.ctx.paths.route(start, point(target))
        if route is None:
            why = self.ctx.paths.problem(point(target)) or self.ctx.paths.start_problem(start)
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
