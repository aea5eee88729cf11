"""Implementations of the ``aerial`` capability library (spec: ``aerial.yaml``).

A multirotor under PX4 offboard control (seed 000 Table I, Fig. 8 and 9): every leaf goes through
the agent's context — the autopilot backend, the D*+ path service and the navigator (NMPC or
tracking controller with APF) — following the request-and-poll pattern of
:class:`~btmission.runtime.leaves.StatefulAction`.

Settings (``runtime.settings`` of a mission): the navigator's (``speed_m_s``, ``altitude_m``,
``tolerance_m``…).
"""

from __future__ import annotations

import math
from importlib.resources import files

from py_trees.common import Status

from btmission.plugins import Implementations
from btmission.runtime import actions as A
from btmission.runtime.leaves import AgentContext, StatefulAction
from btmission.runtime.navigation import LANDING_DRIFT_M

SPEC = files(__package__).joinpath("aerial.yaml")
"""The library file; the ``btmission.libraries`` entry point ``aerial`` points here."""

IMPLEMENTATIONS = Implementations("aerial", vehicle="multirotor")


@IMPLEMENTATIONS.condition("has_home")
def has_home(ctx: AgentContext) -> bool:
    return "home" in ctx.blackboard


@IMPLEMENTATIONS.condition("landed_at_home")
def landed_at_home(ctx: AgentContext) -> bool:
    """On the ground with the motors off, at home (or where it started, if it never set one).

    "At home" has a hysteresis: the tree lands only within ``tolerance_m`` of home
    (``at_goal(home)``), and a landed vehicle counts as there up to
    :data:`~btmission.runtime.navigation.LANDING_DRIFT_M` further. The descent can end a few decimetres off the spot, and a landed vehicle's
    estimate drifts (PX4's by decimetres): either, past the tolerance, made the tree arm the
    drone again to fly back the few decimetres home, and land, and again."""
    if not A.landed(ctx):
        return False
    home = ctx.blackboard.get("home", ctx.start)
    p = ctx.telemetry().position
    reach = ctx.navigator.config.tolerance_m + LANDING_DRIFT_M
    return math.hypot(p[0] - home[0], p[1] - home[1]) <= reach


@IMPLEMENTATIONS.action("set_home")
class SetHome(StatefulAction):
    """Store the current position as home."""

    def on_start(self) -> Status:
        p = self.ctx.telemetry().position
        self.ctx.blackboard.set("home", (float(p[0]), float(p[1]), float(p[2])))
        return Status.SUCCESS


IMPLEMENTATIONS.condition("is_armed")(A.is_armed)
IMPLEMENTATIONS.condition("in_offboard")(A.in_offboard)
IMPLEMENTATIONS.condition("is_flying")(A.is_flying)
IMPLEMENTATIONS.condition("has_path")(A.has_path)
IMPLEMENTATIONS.condition("at_goal")(A.at_goal)
IMPLEMENTATIONS.action("arm")(A.Arm)
IMPLEMENTATIONS.action("set_offboard")(A.SetOffboard)
IMPLEMENTATIONS.action("takeoff")(A.Takeoff)
IMPLEMENTATIONS.action("update_path")(A.UpdatePath)
IMPLEMENTATIONS.action("follow_path")(A.FollowPath)
IMPLEMENTATIONS.action("land")(A.Land)
