"""Implementations of the ``ground`` capability library (spec: ``ground.yaml``).

A TurtleBot-class robot (seed 003): D*+ paths, tracked by the unicycle NMPC with the other robots'
shared predictions (eq. 11-12) or by pure pursuit; pick and place take a fixed time. The object
picked up is recorded on the blackboard (``holding``: the task's id and pick-up point), which is
the commit condition of ``pick_and_deliver`` tasks (k_bt = 0 once it holds, eq. 8-10); deliveries
are recorded per task too (``delivered``).

Settings (``runtime.settings`` of a mission, :class:`GroundSettings`): ``pick_time_s``,
``place_time_s`` and the navigator's (``speed_m_s``, ``tolerance_m``…), with defaults for a
TurtleBot.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.resources import files
from typing import Any

from py_trees.common import Status

from btmission.plugins import Implementations
from btmission.runtime import actions as A
from btmission.runtime.leaves import AgentContext, StatefulAction

SPEC = files(__package__).joinpath("ground.yaml")
"""The library file; the ``btmission.libraries`` entry point ``ground`` points here."""


@dataclass(frozen=True)
class GroundSettings:
    """The ``ground`` library's settings (``runtime.settings`` of a mission): its own, and the
    navigator's with a TurtleBot's defaults (0.4 m/s top speed, ~0.1 m radius, goals reached
    within 0.2 m)."""

    pick_time_s: float = 2.0
    """How long picking an object up takes (s)."""
    place_time_s: float = 2.0
    """How long putting it down takes (s)."""
    speed_m_s: float = 0.4
    """Top speed (m/s; the navigator's setting)."""
    tolerance_m: float = 0.2
    """A goal is reached within this distance (m; the navigator's setting)."""
    clearance_m: float = 0.25
    """Paths keep this far from obstacles (m; the navigator's setting)."""
    lookahead_m: float = 1.0
    """Carrot distance ahead on the route (m; the navigator's setting)."""


IMPLEMENTATIONS = Implementations("ground", vehicle="ground", settings=GroundSettings)


@IMPLEMENTATIONS.on_setup
def _home(ctx: AgentContext) -> None:
    """The robot's home is where it starts (seed 003 Fig. 6a)."""
    ctx.blackboard.set("home", ctx.start)


@IMPLEMENTATIONS.condition("is_localized")
def is_localized(ctx: AgentContext) -> bool:
    return bool(ctx.blackboard.get("localized", False))


def _load(ctx: AgentContext, *where: Any) -> tuple[Any, ...]:
    """The object of the current task: its id (the blackboard's ``task``) and places. State is
    kept per task, not per place: a second task with the same pick-up and drop-off is a new
    object to pick up, not one already delivered (issue #12, warehouse P7)."""
    return (ctx.blackboard.get("task"), *(A.point(p) for p in where))


@IMPLEMENTATIONS.condition("holding")
def holding(ctx: AgentContext, pickup: Any) -> bool:
    return bool(ctx.blackboard.get("holding") == _load(ctx, pickup))


@IMPLEMENTATIONS.condition("delivered")
def delivered(ctx: AgentContext, pickup: Any, dropoff: Any) -> bool:
    return _load(ctx, pickup, dropoff) in ctx.blackboard.get("delivered", ())


@IMPLEMENTATIONS.action("localize")
class Localize(StatefulAction):
    """The shared map's frame is the simulator's: localisation succeeds at once."""

    def on_start(self) -> Status:
        self.ctx.blackboard.set("localized", True)
        return Status.SUCCESS


@IMPLEMENTATIONS.action("pick")
class Pick(A.Timed):
    """Pick the object up (``pick_time_s``)."""

    def duration_s(self) -> float:
        return self.ctx.settings_of(GroundSettings).pick_time_s

    def finish(self) -> None:
        self.ctx.blackboard.set("holding", _load(self.ctx, self.args["pickup"]))


@IMPLEMENTATIONS.action("place")
class Place(A.Timed):
    """Put the object down at the drop-off (``place_time_s``)."""

    def duration_s(self) -> float:
        return self.ctx.settings_of(GroundSettings).place_time_s

    def finish(self) -> None:
        bb = self.ctx.blackboard
        done = set(bb.get("delivered", ()))
        done.add(_load(self.ctx, self.args["pickup"], self.args["dropoff"]))
        bb.set("delivered", frozenset(done))
        bb.unset("holding")


IMPLEMENTATIONS.condition("has_path")(A.has_path)
IMPLEMENTATIONS.condition("at_goal")(A.at_goal)
IMPLEMENTATIONS.action("update_path")(A.UpdatePath)
IMPLEMENTATIONS.action("drive_path")(A.FollowPath)
