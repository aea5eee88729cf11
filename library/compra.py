"""Implementations of the ``compra`` capability library (spec: ``compra.yaml``).

The COMPRA search-and-rescue workflow of seed 002 (Alg. 2) on a multirotor: gate calibration and
pre-flight checks, take-off to the mission altitude p_z^m, reactive exploration for the time
budget — carrot chasing 1 m ahead with the deepest-point heading regulation (DPHR, from the depth
camera) and the APF (from the LiDAR), recording breadcrumbs — while the object localiser buffers
and clusters the camera's detections, then the return along the breadcrumbs, landing, and the
report of the object list OL. The STOP behaviour (``stop_handled``) is ticked first on every
tick: while a ``stop`` signal is active (``MissionRun.signal(agent, "stop")``, the supervisor's
software STOP) the vehicle lands and stays down.

Settings (``runtime.settings`` of a mission, :class:`CompraSettings`): ``explore_time_s``
(T_mission^reference), ``altitude_m`` (p_z^m), ``speed_m_s``, ``preflight_s`` and the
navigator's others.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.resources import files
from typing import Any

from py_trees.common import Status

from btmission.plugins import Implementations
from btmission.runtime import actions as A
from btmission.runtime.eventkinds import (
    JunctionEvent,
    JunctionSwitchEvent,
    ObjectsEvent,
)
from btmission.runtime.leaves import AgentContext, StatefulAction

SPEC = files(__package__).joinpath("compra.yaml")
"""The library file; the ``btmission.libraries`` entry point ``compra`` points here."""


@dataclass(frozen=True)
class CompraSettings:
    """The ``compra`` library's settings (``runtime.settings`` of a mission)."""

    explore_time_s: float = 60.0
    """T_mission^reference: how long the drone explores before it returns (s)."""
    altitude_m: float = 1.5
    """p_z^m, the mission altitude (m; the navigator's setting, with this default)."""
    speed_m_s: float = 1.0
    """Cruise speed (m/s; the navigator's setting, with this default).

    DPHR's yaw-rate limit follows it."""
    preflight_s: float = 1.0
    """How long the pre-flight checks take (s)."""


IMPLEMENTATIONS = Implementations("compra", vehicle="multirotor", settings=CompraSettings)


# ------------------------------------------------------------------------------- state
def _explorer(ctx: AgentContext) -> Any:
    """The COMPRA explorer of this agent (created on first use)."""
    from btmission.control.compra import CompraConfig, CompraExplorer

    ex = ctx.state.get("explorer")
    if ex is None:
        settings = ctx.settings_of(CompraSettings)
        cfg = CompraConfig(
            mission_altitude_m=settings.altitude_m, mission_time_s=settings.explore_time_s
        )
        ex = ctx.state["explorer"] = CompraExplorer(cfg)
    return ex


DEAD_END_M = 2.0
"""Nothing deeper than this in view: a dead end, DPHR turns round (DphrConfig.dead_end_m)."""

SWITCH_OFFSET = 0.5
"""A jump of the followed branch's s̄_x by more than this within one junction is a switch."""

WIDTHS_M = {"survivor": (0.4, 0.8), "backpack": (0.3, 0.7), "drill": (0.1, 0.5)}
"""Metric width interval of each known object class: seed 002 §3.3.1's second outlier check
(a box whose centre falls on the wall behind an object gives a width far outside it)."""


def _localizer(ctx: AgentContext) -> Any:
    from btmission.control.compra import LocalizerConfig, ObjectLocalizer

    loc = ctx.state.get("localizer")
    if loc is None:
        loc = ctx.state["localizer"] = ObjectLocalizer(LocalizerConfig(width_bounds_m=WIDTHS_M))
    return loc


def _step_explorer(ctx: AgentContext, dphr: bool) -> Any:
    """One step of Alg. 2's loop: localise what the camera detects, then the explorer's
    command (with the DPHR yaw rate while exploring)."""
    from btmission.control.dphr import DphrConfig, deepest_point_heading, yaw_rate_limit_for_speed

    tel = ctx.telemetry()
    now = ctx.now()
    rate = 0.0
    sensors = ctx.sensors
    if sensors is not None:
        frame = sensors.camera()
        loc = _localizer(ctx)
        for det in frame.detections:
            loc.add(det, frame.depth_m, frame.intrinsics, frame.rotation, frame.translation)
        loc.update(now)
        if dphr:
            limit = yaw_rate_limit_for_speed(ctx.settings_of(CompraSettings).speed_m_s)
            prefer = ctx.state.get("dphr_branch")
            res = deepest_point_heading(
                frame.depth_m,
                DphrConfig(stride=1, yaw_rate_max=limit, dead_end_m=DEAD_END_M),
                prefer_offset=prefer,
            )
            rate = res.yaw_rate
            _commit_branch(ctx, res)
    return _explorer(ctx).step(
        now, tel.position, tel.yaw, tel.height_above_ground, dphr_yaw_rate=rate
    )


def _commit_branch(ctx: AgentContext, res: Any) -> None:
    """Remember the branch DPHR follows at a junction (several deep regions) so the next frames
    keep to it (``prefer_offset``). Logged: a ``junction`` event when one begins (the branches'
    offsets s̄_x and the chosen one), a ``junction_switch`` event if the followed branch jumps to
    another (a change of more than :data:`SWITCH_OFFSET` in s̄_x: dithering between two); one
    deep region again ends the junction."""
    prefer = ctx.state.get("dphr_branch")
    if len(res.branches) > 1:
        offsets = [round(b.offset, 3) for b in res.branches]
        if prefer is None:
            ctx.events(JunctionEvent(agent=ctx.agent_id, offsets=offsets, chosen=res.chosen))
        elif abs(res.offset - prefer) > SWITCH_OFFSET:
            ctx.events(
                JunctionSwitchEvent(
                    agent=ctx.agent_id, offsets=offsets, chosen=res.chosen, was=round(prefer, 3)
                )
            )
        ctx.state["dphr_branch"] = res.offset
    else:
        ctx.state["dphr_branch"] = None


# ------------------------------------------------------------------------------- conditions
@IMPLEMENTATIONS.condition("stop_handled")
def stop_handled(ctx: AgentContext) -> bool:
    """No STOP is active."""
    return not ctx.state.get("stop", False)


@IMPLEMENTATIONS.condition("has_world_frame")
def has_world_frame(ctx: AgentContext) -> bool:
    return bool(ctx.blackboard.get("world_frame", False))


@IMPLEMENTATIONS.condition("preflight_ok")
def preflight_ok(ctx: AgentContext) -> bool:
    return bool(ctx.blackboard.get("preflight_ok", False))


@IMPLEMENTATIONS.condition("time_budget_spent")
def time_budget_spent(ctx: AgentContext) -> bool:
    from btmission.control.compra import Mode

    ex = ctx.state.get("explorer")
    return ex is not None and ex.mode is not Mode.EXPLORE


@IMPLEMENTATIONS.condition("breadcrumbs_empty")
def breadcrumbs_empty(ctx: AgentContext) -> bool:
    from btmission.control.compra import Mode

    ex = ctx.state.get("explorer")
    return ex is not None and ex.mode is Mode.LAND


@IMPLEMENTATIONS.condition("landed")
def landed(ctx: AgentContext) -> bool:
    """On the ground with the motors off *after the return* (Alg. 2's "Land // mission
    completed"): standing on the launch pad before take-off does not count."""
    return breadcrumbs_empty(ctx) and A.landed(ctx)


@IMPLEMENTATIONS.condition("mission_complete")
def mission_complete(ctx: AgentContext) -> bool:
    return bool(ctx.blackboard.get("objects_reported", False))


# ------------------------------------------------------------------------------- actions
@IMPLEMENTATIONS.action("emergency_land")
class EmergencyLand(StatefulAction):
    """STOP: land at once and stay down (RUNNING) while the STOP is active."""

    def on_start(self) -> Status:
        self.ctx.navigator.land()
        return Status.RUNNING

    def on_running(self) -> Status:
        if self.ctx.navigator.status.command != "land" and not A.landed(self.ctx):
            self.ctx.navigator.land()
        return Status.RUNNING


@IMPLEMENTATIONS.action("calibrate_gate")
class CalibrateGate(StatefulAction):
    """Define the W frame (the simulator's frame: nothing to estimate)."""

    def on_start(self) -> Status:
        self.ctx.blackboard.set("world_frame", True)
        return Status.SUCCESS


@IMPLEMENTATIONS.action("preflight_checks")
class PreflightChecks(A.Timed):
    """Bring the stack up and check it (``preflight_s``)."""

    def duration_s(self) -> float:
        return self.ctx.settings_of(CompraSettings).preflight_s

    def finish(self) -> None:
        self.ctx.blackboard.set("preflight_ok", True)


@IMPLEMENTATIONS.action("explore")
class Explore(StatefulAction):
    """Carrot chasing with DPHR and APF until T_mission^reference (seed 002 §3.2.4, Alg. 2)."""

    def on_running(self) -> Status:
        from btmission.control.compra import Mode

        cmd = _step_explorer(self.ctx, dphr=True)
        if cmd.mode is not Mode.EXPLORE:
            return Status.SUCCESS
        self.ctx.navigator.goto(cmd.waypoint, None, cmd.yaw_rate_ref)
        return Status.RUNNING

    def on_halted(self) -> None:
        self.ctx.navigator.hold()


@IMPLEMENTATIONS.action("return_breadcrumbs")
class ReturnBreadcrumbs(StatefulAction):
    """Fly back crumb by crumb, heading ψ + π (Alg. 2's else branch), until BW is empty."""

    def on_running(self) -> Status:
        from btmission.control.compra import Mode

        cmd = _step_explorer(self.ctx, dphr=False)
        if cmd.mode is Mode.LAND:
            self.ctx.navigator.hold()
            return Status.SUCCESS
        self.ctx.navigator.goto(cmd.waypoint, cmd.yaw_ref, 0.0)
        return Status.RUNNING

    def on_halted(self) -> None:
        self.ctx.navigator.hold()


@IMPLEMENTATIONS.action("report_objects")
class ReportObjects(StatefulAction):
    """Publish OL: the localised objects (class, world position, observations)."""

    def on_start(self) -> Status:
        loc = _localizer(self.ctx)
        loc.flush()
        objects = [
            {"label": o.label, "p": [float(v) for v in o.position], "observations": o.observations}
            for o in loc.objects
        ]
        self.ctx.events(
            ObjectsEvent(agent=self.ctx.agent_id, objects=objects, rejected=dict(loc.rejected))
        )
        self.ctx.blackboard.set("objects_reported", True)
        return Status.SUCCESS


IMPLEMENTATIONS.condition("is_armed")(A.is_armed)
IMPLEMENTATIONS.condition("in_offboard")(A.in_offboard)
IMPLEMENTATIONS.condition("is_hovering")(A.is_flying)
IMPLEMENTATIONS.action("arm")(A.Arm)
IMPLEMENTATIONS.action("set_offboard")(A.SetOffboard)
IMPLEMENTATIONS.action("takeoff")(A.Takeoff)
IMPLEMENTATIONS.action("land")(A.Land)
