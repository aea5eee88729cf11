"""An agent's motion layer: path following with NMPC or a tracking controller, plus APF.

Behaviour-tree actions never fly the vehicle themselves; they give the :class:`Navigator` a
command (hold, take off, follow a D*+ route, go to a local waypoint, land) and poll its
:attr:`Navigator.status`. The navigator runs at the control rate (every simulator step) and
streams setpoints to the :class:`~btmission.vehicles.base.Backend` — continuously, as PX4
offboard requires, even while holding (DESIGN.md §8).

Path following (seed 000 §IV-C3, seed 002 §3.2.2-3.2.3, seed 003 §VI):

1. a *carrot* on the route, ``lookahead_m`` beyond the point of the route closest to the vehicle;
2. multirotors: the APF (seed 002 eq. 3, Alg. 1, :class:`~btmission.control.apf.PotentialField`)
   turns the carrot and the LiDAR scan into the normalised force F, and the reference is
   p_ref = p̂ + F·lookahead with velocity F·speed;
3. the controller tracks it:

   ``nmpc``  multirotor: the seed 002 NMPC (:class:`~btmission.control.nmpc.MavNmpc`, eq. 1-2,
             with the adaptive position weight of eq. 4 from the APF's raw repulsion) → attitude
             and thrust setpoints; ground robot: the seed 003 unicycle NMPC
             (:class:`~btmission.control.unicycle_nmpc.UnicycleNmpc`, eq. 11-12) with the other
             robots' shared predictions and a safe corridor from the LiDAR points at the
             robot's height (shelves, walls) → [u_v, u_ω].
   ``track`` multirotor: a position + velocity setpoint that the autopilot's own cascaded
             controller tracks (what PX4 does with offboard position setpoints); ground robot:
             pure pursuit of the carrot. Much cheaper: for large fleets.

This module holds the :class:`Navigator`. Its settings (:class:`NavConfig`,
:data:`SETTINGS_DOC`), its status (:class:`NavState`, :class:`NavStatus`) and the points of a
``route`` event (:func:`route_points`) are :mod:`btmission.runtime.navconfig`, re-exported here.
The route geometry and the control laws it computes with
(:class:`~btmission.runtime.navcontrol.Polyline`, the APF's sizing, the unicycle tracker, a ground
robot's obstacle points, their constants) are :mod:`btmission.runtime.navcontrol`; the commands
it carries out are :mod:`btmission.runtime.navcommands`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from btmission.control.apf import ApfConfig, PotentialField, limit_approach_speed, vector_norm
from btmission.control.mav_model import world_to_yaw_frame, wrap_angle, yaw_frame_to_world
from btmission.runtime.navcommands import _Command, _Follow, _Goto, _Hold, _Land, _Takeoff, _Track
from btmission.runtime.navconfig import (
    NavConfig,
    NavState,
    NavStatus,
)
from btmission.runtime.navcontrol import (
    AGENT_APF,
    AGENT_SEPARATION,
    APPROACH_CORRIDOR_M,
    APPROACH_DECEL_M_S2,
    APPROACH_MARGIN_M,
    APPROACH_REACTION_S,
    Polyline,
    adaptive_speed_scale,
    ground_obstacle_points,
    multirotor_apf_config,
    track_unicycle,
)
from btmission.types import FloatArray
from btmission.vehicles.base import Backend, LandedState, Mode, Sensors, Telemetry, VehicleKind

if TYPE_CHECKING:  # the NMPC (CasADi) is imported when a navigator first needs it
    from btmission.control.nmpc import NmpcResult, PendingSolve

CONTROLLERS = ("nmpc", "track")
KEEP_RIGHT_M = 1.2
"""A robot this close in front makes a ground robot keep to the right (NMPC)."""
KEEP_RIGHT_OFFSET_M = 0.5
PROGRESS_M = 0.1
"""Progress along a route counts when the distance left shrinks by this much."""
SETTLED_M_S = 0.5
"""A vehicle slower than this counts as stopped at its goal."""
LANDING_DRIFT_M = 2.0
"""How much further than ``tolerance_m`` from a ground-level goal a multirotor that is landing
there, or has landed, still counts as at it (:meth:`Navigator.at`; ``aerial``'s
``landed_at_home``): a hysteresis — the landing starts within the tolerance, and the descent
(AUTO.LAND holds where it was commanded, from a vehicle still creeping) or a landed vehicle's
drifting estimate moves it. Past the tolerance the tree abandoned the landing, or armed the
landed drone again, to fly back. On real PX4 SITL (SIH) the estimate moved 0.6-1.3 m during
AUTO.LAND: with 1.0 m, 2 of 11 landings were given up at 1.51 and 1.57 m from home, and the
drone climbed, flew home and landed again (docs/mavlink.md, "Flown on real PX4 SITL")."""
HEADING_GAIN = 1.0
"""Gain of the autopilot's heading loop (rad/s per rad), to turn a yaw rate into a heading."""
POSITION_GAIN = 1.0
"""Gain of the autopilot's position loop (1/s): velocity = gain · position error."""
NMPC_LEAD_S = 0.7
"""The NMPC's position target sits at most max(1 m, ``NMPC_LEAD_S``·speed) ahead, with the
velocity reference F·speed: with the weights of :class:`~btmission.control.nmpc.NmpcConfig` the
closed loop then cruises at the commanded speed (0.7 s: measured, see
``tests/unit/control/test_control_nmpc.py::test_cruise_lead_holds_the_commanded_speed``). A fixed 1 m target
(seed 002's carrot) holds it to ~1.8 m/s whatever the speed asked (the paper raises Q_p for its
2.3 m/s run instead). Up to 1.43 m/s the 1 m floor rules and nothing changes."""
_LANDING, _ON_GROUND = LandedState.LANDING, LandedState.ON_GROUND


_NO_STATES = np.zeros((0, 6))


PREDICTION_STEPS = 50
"""Horizon of the shared predictions (seed 003: N = 50 at 0.1 s)."""

Predictions = Callable[[str], Sequence[FloatArray]]
"""Other agents' predicted (N+1, 2) positions, for the ground NMPC (seed 003 §VI)."""


class Navigator:
    """One agent's motion layer (module docstring). Call :meth:`step` every control period."""

    def __init__(
        self,
        agent: str,
        backend: Backend,
        sensors: Sensors | None,
        controller: str = "nmpc",
        config: NavConfig | None = None,
        *,
        control_dt: float = 0.05,
        predictions: Predictions | None = None,
        neighbours: Callable[[str, FloatArray], FloatArray] | None = None,
        ground_at: Callable[[FloatArray], float] | None = None,
        point_area_m2: float = 0.25,
    ) -> None:
        if controller not in CONTROLLERS:
            raise ValueError(f"unknown controller '{controller}' (expected nmpc or track)")
        self.agent = agent
        self.backend = backend
        self.sensors = sensors
        self.controller = controller
        self.config = cfg = config or NavConfig()
        self.kind = backend.kind
        self.control_dt = control_dt
        self._predictions = predictions
        self._neighbours = neighbours
        """``neighbours(agent, position)``: where the other agents near ``position`` (this
        vehicle's, from its telemetry) are and how they move, (k, 6): position (z NaN: at this
        vehicle's height) and shared velocity (NaN: not shared), nearest first — the first
        points of ``predictions`` without the list (None: taken from those, velocities
        unknown)."""
        self._ground_at = ground_at
        self._cmd: _Command = _Hold(np.asarray(backend.telemetry().position, dtype=float))
        self._status = NavStatus(NavState.IDLE, "", "hold")
        self._apf = None
        self._apf_previous = np.zeros(3)
        self._nmpc = None
        self._uni = None
        self.prediction: FloatArray | None = None
        """This agent's predicted (N+1, 2) positions, shared with the others (ground NMPC)."""
        self.shared_velocity: FloatArray | None = None
        """This agent's velocity, shared with :attr:`prediction` (a drone's, from its
        telemetry: the others' separation rule credits it when it moves away from them)."""
        self._last_uni_t = -math.inf
        self._uni_u = np.zeros(2)
        self.solve_times: list[float] = []
        self.solve_cpu_s = 0.0
        """CPU time of every NMPC solver call so far (s; the threads that solved, whichever)."""
        self.defer_nmpc = False
        """Run the MAV NMPC's solve on the NMPC thread pool and apply its command in
        :meth:`finish_step` (the runner calls it for every agent, in a fixed order, after all
        agents' control steps): the agents' solves of one step overlap on the machine's cores,
        and the commands — each solve's result depends on its own inputs only — stay the same."""
        self._pending: tuple[PendingSolve, float] | None = None
        self.on_route: Callable[[FloatArray, float], None] | None = None
        """Called with the points and the length (m) of every route :meth:`follow` adopts that
        differs from the last one (the agent publishes it: ``route`` events)."""
        self._last_route: FloatArray | None = None
        g = cfg.apf_gain * point_area_m2
        if self.kind is VehicleKind.MULTIROTOR:
            self._apf = PotentialField(multirotor_apf_config(g, cfg.speed_m_s))
            if controller == "nmpc":
                from btmission.control.nmpc import MavNmpc, NmpcConfig

                # tol 1e-4: the same commands to a fraction of a percent, ~20 % fewer
                # interior-point iterations than the 1e-6 default; compiled NLP functions and a
                # warm barrier start: the same optimum, ~2.5x faster solves (docs/control.md)
                self._nmpc = MavNmpc(
                    NmpcConfig(dt_s=control_dt, tol=1e-4, compiled=True, warm_mu_init=1e-3)
                )
        elif controller == "nmpc":
            from btmission.control.unicycle_nmpc import UnicycleConfig, UnicycleNmpc

            # forward only, and a heading reference towards the way-point: with the heading
            # free (q_heading = 0) the optimiser reverses the whole way at v_min, or — forward
            # only, way-point straight behind — sits at the symmetric stationary point u = 0
            self._uni = UnicycleNmpc(UnicycleConfig(v_min=0.0, q_heading=0.5))
        else:  # the tracking controller steers through the APF (small robot: smaller radii)
            self._apf = PotentialField(
                ApfConfig(gain=(g, g, 0.0), r_influence_m=0.8, r_critical_m=0.3)
            )

    # ---------------------------------------------------------------- commands
    @property
    def status(self) -> NavStatus:
        return self._status

    def _set(self, cmd: _Command) -> None:
        self._cmd = cmd
        self._status = NavStatus(NavState.RUNNING, "", cmd.name)
        self._apf_previous = np.zeros(3)

    def hold(self, point: Sequence[float] | None = None) -> None:
        tel = self.backend.telemetry()
        p = tel.position if point is None else np.asarray(point, dtype=float)
        self._cmd = _Hold(np.asarray(p, dtype=float).copy())
        self._status = NavStatus(NavState.IDLE, "", "hold")

    def takeoff(self, altitude_m: float | None = None) -> None:
        tel = self.backend.telemetry()
        alt = self.config.altitude_m if altitude_m is None else altitude_m
        p = tel.position.copy()
        p[2] = tel.ground_z + alt
        self._set(_Takeoff(p))

    def follow(self, route: FloatArray, target: ArrayLike, now: float) -> None:
        """Follow ``route`` ((N, 3) waypoints) to ``target``."""
        tgt = np.asarray(target, dtype=float)
        pts = np.asarray(route, dtype=float).reshape(-1, 3).copy()
        ground_goal = False
        if self.kind is VehicleKind.MULTIROTOR:
            ground_goal = tgt[2] < self.ground_under(tgt) + 0.5
        if len(pts) == 0 or not np.allclose(pts[-1], tgt):
            pts = np.vstack([pts, tgt]) if len(pts) else tgt[None, :]
        line = Polyline(pts)
        self._set(_Follow(line, tgt, ground_goal, progress_t=now))
        last = self._last_route
        if self.on_route is not None and (last is None or not np.array_equal(last, pts)):
            self._last_route = pts
            self.on_route(pts, line.length)

    def goto(
        self, waypoint: Sequence[float], yaw: float | None = None, yaw_rate: float = 0.0
    ) -> None:
        """Head for a local waypoint (no route) with a heading or a yaw rate (COMPRA)."""
        w = np.asarray(waypoint, dtype=float)
        if isinstance(self._cmd, _Goto):
            self._cmd.waypoint, self._cmd.yaw, self._cmd.yaw_rate = w, yaw, yaw_rate
            return
        self._set(_Goto(w, yaw, yaw_rate))

    def track(self, point: ArrayLike, velocity: ArrayLike, now: float) -> None:
        """Keep to a moving reference: ``point`` at ``now``, moving at ``velocity`` (world) — a
        schedule to keep, not a place to reach (a truck on its dispatched timetable, seed 004
        §3.2). Call again whenever the schedule says where to be; in between the reference is
        extrapolated. Status stays RUNNING: the caller decides when the schedule is done."""
        p = np.asarray(point, dtype=float)
        v = np.asarray(velocity, dtype=float)
        if isinstance(self._cmd, _Track):
            self._cmd.point, self._cmd.velocity, self._cmd.t0 = p, v, now
            return
        self._set(_Track(p, v, now))

    def land(self) -> None:
        self._set(_Land())

    def resume(self, now: float) -> None:
        """The vehicle is heard again after its link was lost: the time without it does not
        count as a route without progress."""
        if isinstance(self._cmd, _Follow):
            self._cmd.progress_t = now

    # ---------------------------------------------------------------- geometry
    def ground_under(self, p: FloatArray) -> float:
        """Ground height under ``p`` from the agent's map (its telemetry's without one)."""
        if self._ground_at is not None:
            return float(self._ground_at(p))
        return float(self.backend.telemetry().ground_z)

    def flight_target(self, goal: ArrayLike) -> FloatArray:
        """Where a multirotor goes for ``goal``: the goal itself, raised to ``altitude_m`` above
        the ground when it lies on the ground (home, a landing spot)."""
        g = np.asarray(goal, dtype=float).copy()
        if self.kind is VehicleKind.MULTIROTOR:
            ground = self.ground_under(g)
            if g[2] < ground + 0.5:
                g[2] = ground + self.config.altitude_m
        return g

    def at(self, goal: ArrayLike, tel: Telemetry | None = None) -> bool:
        """Stopped within tolerance of ``goal``'s flight target (a goal on the ground: above it at
        any height up to the flight altitude, so a vehicle landing there still is at it).

        "Stopped" (slower than ``SETTLED_M_S``): a vehicle that passes through the tolerance
        sphere at speed has not reached the goal — it could not inspect it, nor land there. A
        multirotor over a ground-level goal whose autopilot says it is landing (or has landed)
        is at it whatever its speed, and up to ``LANDING_DRIFT_M`` further than the tolerance:
        AUTO.LAND descends faster than ``SETTLED_M_S`` (PX4 at ~0.8 m/s) and drifts a little,
        and a landing judged by speed and the tolerance alone was abandoned mid-descent to fly
        the route to the goal again. A landing this navigator has begun (braking over the
        spot, or waiting for the autopilot's landed state to say LANDING) counts the same: a
        vehicle that swung through the tolerance at walking pace (ArduCopter's GUIDED overshoots)
        and was braked there to land was otherwise called away from it in the next tick, then
        sent back."""
        tel = tel or self.backend.telemetry()
        tol = self.config.tolerance_m
        p = tel.position
        px, py, _ = p.tolist()  # (floats: numpy's scalar arithmetic costs more, same result)
        gx, gy = float(goal[0]), float(goal[1])  # type: ignore[index,arg-type]
        off = math.hypot(px - gx, py - gy)
        if off > tol:  # (most calls: far from it)
            if off > tol + LANDING_DRIFT_M or self.kind is VehicleKind.GROUND:
                return False
            if not (
                tel.landed_state is _LANDING
                or tel.landed_state is _ON_GROUND
                or self._landing_begun()
            ):
                return False
            # landing near a ground-level goal: within the hysteresis (LANDING_DRIFT_M)
            g = np.asarray(goal, dtype=float)
            return bool(self.flight_target(g)[2] != g[2])
        g = np.asarray(goal, dtype=float)
        v = tel.velocity
        settled = math.sqrt(float(v @ v)) <= SETTLED_M_S
        if self.kind is VehicleKind.GROUND:
            return settled
        landing = (
            tel.landed_state is _LANDING or tel.landed_state is _ON_GROUND or self._landing_begun()
        )
        if not (settled or landing):
            return False
        target = self.flight_target(g)
        if target[2] != g[2]:  # a ground-level goal
            return landing or bool(p[2] <= target[2] + tol)
        if not settled:
            return False
        return bool(abs(p[2] - target[2]) <= tol)

    @property
    def landing(self) -> bool:
        """The mission asked this navigator to land the vehicle (until its next command)."""
        return isinstance(self._cmd, _Land)

    def _landing_begun(self) -> bool:
        """This navigator is landing the vehicle where it is (:meth:`land` was asked and has
        not failed)."""
        return (
            isinstance(self._cmd, _Land)
            and self._cmd.hold is not None
            and (self._status.state is not NavState.FAILED)
        )

    # ---------------------------------------------------------------- control step
    def step(self, now: float) -> None:
        """Stream this period's setpoint to the backend and update :attr:`status`."""
        tel = self.backend.telemetry()
        if self.kind is VehicleKind.MULTIROTOR:
            self._step_multirotor(now, tel)
        else:
            self._step_ground(now, tel)

    def _finish(self, ok: bool, reason: str = "") -> None:
        self._status = NavStatus(
            NavState.ARRIVED if ok else NavState.FAILED, reason, self._cmd.name
        )

    def _step_multirotor(self, now: float, tel: Telemetry) -> None:
        cmd = self._cmd
        p = tel.position
        self.prediction = p[None, :].copy()  # shared with the others: where this vehicle is
        self.shared_velocity = tel.velocity  # ... and how it moves
        if isinstance(cmd, _Follow):  # (most steps of a mission: first, nothing allocated)
            f_ref, f_vel, f_yaw, f_repulsion = self._follow_reference(now, tel, cmd)
            self._command_multirotor(tel, f_ref, f_vel, f_yaw, 0.0, f_repulsion)
            return
        cfg = self.config
        ref = p.copy()
        vel = np.zeros(3)
        yaw: float | None = None
        yaw_rate = 0.0
        repulsion = 0.0
        if isinstance(cmd, _Land):
            if cmd.hold is None:
                cmd.hold = p.copy()
            speed = vector_norm(tel.velocity)
            if tel.mode is not Mode.LAND and tel.armed and not tel.landed and speed > 0.3:
                self._command_multirotor(tel, cmd.hold, np.zeros(3), None, 0.0, 0.0)
                return  # brake over the landing spot first: AUTO.LAND lands where it is
            if tel.mode is not Mode.LAND and tel.armed:
                ack = self.backend.land()
                if not ack.accepted and not ack.pending:  # (pending: asked again next step)
                    self._finish(False, ack.reason)
            if tel.landed and not tel.armed:
                self._finish(True)
                self._cmd = _Hold(p.copy())
            self._stream_hold(tel, p)
            return
        if isinstance(cmd, _Hold):
            ref = self._separated_setpoint(tel, cmd.point)
        elif isinstance(cmd, _Takeoff):
            ref = self._separated_setpoint(tel, cmd.point)
            vel = np.array([0.0, 0.0, 0.0])
            if abs(p[2] - cmd.point[2]) < 0.2 and not tel.landed:
                self._finish(True)
                self._cmd = _Hold(cmd.point.copy())
        elif isinstance(cmd, _Goto):
            scan = self._lidar()  # one scan for the APF and the approach bound
            ref, vel, _, repulsion = self._apf_reference(tel, cmd.waypoint, cfg.speed_m_s, scan)
            vel = self._stopping_limit(tel, vel * adaptive_speed_scale(repulsion), scan)
            # the position reference consistent with that velocity: where the NMPC's lead puts
            # it (or the autopilot's position loop flies at it), not the 1 m carrot, which alone
            # drives the NMPC at ~0.7 m/s — into the rock the bound is stopping it for
            lead_s = NMPC_LEAD_S if self._nmpc is not None else 1.0 / POSITION_GAIN
            ref = p + vel * lead_s
            yaw, yaw_rate = cmd.yaw, cmd.yaw_rate
        elif isinstance(cmd, _Track):
            ref, vel = cmd.reference(now), cmd.velocity
        self._command_multirotor(tel, ref, vel, yaw, yaw_rate, repulsion)

    def _stream_hold(self, tel: Telemetry, p: FloatArray) -> None:
        if self._nmpc is not None:
            self.backend.set_attitude_setpoint(0.0, 0.0, 0.0, 0.0)
        else:
            self.backend.set_position_setpoint(p)

    def _lidar(self) -> FloatArray:
        """This step's LiDAR points (yaw frame); none without sensors."""
        return self.sensors.lidar() if self.sensors is not None else np.zeros((0, 3))

    def _apf_reference(
        self, tel: Telemetry, goal: FloatArray, speed: float, points: FloatArray | None = None
    ) -> tuple[FloatArray, FloatArray, float | None, float]:
        """APF (seed 002 eq. 3, Alg. 1) on the LiDAR scan (``points``, or this step's), plus
        the other agents' shared positions and velocities (:meth:`_agent_states`): reference point and
        velocity, and ‖F^r‖ before shaping (for eq. 4). One compiled call
        (:func:`~btmission.control._apf_kernels.navigator_force`): p_ref = F + p̂ (seed 002),
        stretched at cruise so that the autopilot's position loop (v = K_p·(p_ref − p̂)) flies
        at ‖F‖·speed; near the goal (‖F‖ < 1) p_ref is the goal."""
        from btmission.control._apf_kernels import navigator_force

        assert self._apf is not None
        if points is None:
            points = self._lidar()
        others = self._agent_states(tel)
        out = navigator_force(
            np.ascontiguousarray(points, dtype=float),
            np.ascontiguousarray(others[:, :3]),
            float(tel.position[0]),
            float(tel.position[1]),
            float(tel.position[2]),
            float(tel.velocity[0]),
            float(tel.velocity[1]),
            float(tel.velocity[2]),
            np.array(goal, dtype=float),
            float(tel.yaw),
            self._apf_previous,
            self.kind is VehicleKind.GROUND,
            float(speed),
            POSITION_GAIN,
            self._apf.config.packed,
            AGENT_APF[self.kind].packed,
            AGENT_SEPARATION[self.kind].packed,
            np.ascontiguousarray(others[:, 3:]),
        )
        self._apf_previous = out[6:9]
        return out[0:3], out[3:6], None, float(out[9])

    def _separated_setpoint(self, tel: Telemetry, point: FloatArray) -> FloatArray:
        """A take-off's or a hold's setpoint ``point`` held back by the separation rule: the
        move the autopilot's position loop makes of it (v = K_p·(p_sp − p̂)) with its approach
        to every other agent bounded (:data:`AGENT_SEPARATION`,
        :func:`~btmission.control.apf.separation_bound`), as a setpoint again. A drone whose
        pad lies under another (hovering, or flying over the start area) climbs no closer than
        the stand-off and goes on when the other has moved away; one holding where another now
        is waits beside it. Climbing beside the neighbours' pads (a vertical climb does not
        approach them) or holding still, nothing changes."""
        sep = AGENT_SEPARATION[self.kind]
        if sep.stand_off_m <= 0:
            return point
        others = self._agent_states(tel)
        if not len(others):
            return point
        from btmission.control.apf import separation_bound

        p = tel.position
        v = POSITION_GAIN * (point - p)
        bounded = separation_bound(v, others[:, :3] - p, sep, others[:, 3:], tel.velocity)
        if np.array_equal(bounded, v):
            return point
        return p + bounded / POSITION_GAIN

    def _stopping_limit(self, tel: Telemetry, vel: FloatArray, points: FloatArray) -> FloatArray:
        """``vel`` (world) with its approach to the rock bounded by the stopping distance: towards
        each near LiDAR point (``points``, yaw frame), no faster than can still stop before the
        safety-critical radius r_c (:func:`~btmission.control.apf.limit_approach_speed`);
        sliding along a wall and moving away from it are untouched."""
        if self._apf is None or len(points) == 0:
            return vel
        body = world_to_yaw_frame(vel, tel.yaw)
        limited = limit_approach_speed(
            body,
            points,
            self._apf.config.r_critical_m + APPROACH_MARGIN_M,
            APPROACH_DECEL_M_S2,
            APPROACH_REACTION_S,
            corridor_m=APPROACH_CORRIDOR_M,
            heading=world_to_yaw_frame(tel.velocity, tel.yaw),
        )
        return yaw_frame_to_world(limited, tel.yaw)

    def _agent_states(self, tel: Telemetry) -> FloatArray:
        """The other agents' shared positions and velocities (k, 6), nearest first, for
        :meth:`_apf_reference`: their repulsion is eq. 3 with one point per agent and its own
        radii (:data:`AGENT_APF`), so that vehicles keep apart before their LiDARs would push
        them; when it opposes the way ahead the vehicle also sidesteps to its right, so two
        vehicles meeting head-on in a tunnel pass each other; and the separation rule
        (:data:`AGENT_SEPARATION`) bounds the approach to each. A vehicle that shares a 2D
        position is taken at this vehicle's height; a velocity not shared is NaN."""
        if self._neighbours is not None:
            out = self._neighbours(self.agent, tel.position)
        elif self._predictions is not None:
            from btmission.links.bus import first_points

            out = np.full((0, 6), np.nan)
            pos = first_points(self._predictions(self.agent))
            if len(pos):
                out = np.full((len(pos), 6), np.nan)
                out[:, :3] = pos
        else:
            return _NO_STATES
        zs = out[:, 2]
        if any(z != z for z in zs.tolist()):  # a NaN (a few rows: cheaper than numpy's any)
            zs[np.isnan(zs)] = tel.position[2]
        return out

    def _route_step(
        self, now: float, tel: Telemetry, cmd: _Follow
    ) -> tuple[str, FloatArray, float, FloatArray]:
        """Where a route stands — ``arrived`` (stopped at the target), ``stuck`` (no progress for
        ``stuck_s``) or ``go`` — with the carrot, the arc length of the closest point and the
        point twice the lookahead along (where the heading looks)."""
        cfg = self.config
        lookahead = cfg.lookahead_m
        cmd.seg, arc, carrot, ahead = cmd.route.carrots(
            tel.position, cmd.seg, lookahead, 2 * lookahead
        )
        left = cmd.route.length - arc
        if left < cmd.best_left - PROGRESS_M:
            cmd.best_left = left
            cmd.progress_t = now
        if self.at(cmd.target, tel):
            self._finish(True)
            return "arrived", cmd.target, arc, ahead
        if now - cmd.progress_t > cfg.stuck_s:
            self._finish(False, f"no progress along the route for {cfg.stuck_s:g} s")
            return "stuck", tel.position, arc, ahead
        return "go", carrot, arc, ahead

    def _follow_reference(
        self, now: float, tel: Telemetry, cmd: _Follow
    ) -> tuple[FloatArray, FloatArray, float | None, float]:
        p = tel.position
        cfg = self.config
        state, c, arc, ahead = self._route_step(now, tel, cmd)
        if state != "go":
            hold = p.copy()
            if state == "arrived" and not cmd.ground_goal:
                hold = self.flight_target(cmd.target)
            self._cmd = _Hold(hold)
            return hold, np.zeros(3), None, 0.0
        goal = c
        left = cmd.route.length - arc
        if cmd.ground_goal and left < cfg.lookahead_m:
            goal = self.flight_target(cmd.target)
        ref, vel, _, repulsion = self._apf_reference(tel, goal, cfg.speed_m_s)
        hx, hy = float(ahead[0]) - float(p[0]), float(ahead[1]) - float(p[1])
        yaw = math.atan2(hy, hx) if math.hypot(hx, hy) > 0.3 else None
        return ref, vel, yaw, repulsion

    def finish_batch(
        self,
        now: float,
        row: Sequence[float],
        apf_previous: FloatArray,
        where: FloatArray,
        xy: Sequence[float],
        velocity: FloatArray,
    ) -> bool:
        """Apply this step's row of :func:`~btmission.runtime._fleet_kernels.fleet_follow` for
        the route this navigator follows (a multirotor's under the tracking controller:
        :class:`~btmission.runtime.fleetstep.FleetFollow` checks) — what
        :meth:`_step_multirotor` does with the same
        numbers (:meth:`_route_step`'s progress, :meth:`_follow_reference`'s heading, the
        setpoint). False, with nothing changed, when the row leaves the step to
        :meth:`step` (code 1: maybe arrived, or a ground goal's last stretch) or the route has
        made no progress for ``stuck_s``.

        ``row`` is the kernel's row as floats, ``apf_previous`` its APF memory (a view of the
        kernel's output), ``where`` the vehicle's position as shared on the bus ((1, 3),
        read-only), ``xy`` its horizontal position and ``velocity`` its velocity as shared,
        all from this step's telemetry."""
        if row[0]:
            return False
        cmd = self._cmd
        assert isinstance(cmd, _Follow)
        left = cmd.route.length - row[2]
        best, since = cmd.best_left, cmd.progress_t
        if left < best - PROGRESS_M:
            best, since = left, now
        if now - since > self.config.stuck_s:
            return False
        cmd.seg, cmd.best_left, cmd.progress_t = int(row[1]), best, since
        self.prediction = where
        self.shared_velocity = velocity
        self._apf_previous = apf_previous
        hx, hy = row[13] - xy[0], row[14] - xy[1]
        yaw = math.atan2(hy, hx) if math.hypot(hx, hy) > 0.3 else None
        # _command_multirotor under the tracking controller: the position loop
        self.backend.set_position_setpoint((row[3], row[4], row[5]), None, yaw)
        return True

    def _command_multirotor(
        self,
        tel: Telemetry,
        ref: FloatArray,
        vel: FloatArray,
        yaw: float | None,
        yaw_rate: float,
        repulsion: float,
    ) -> None:
        if self._nmpc is None:
            # the autopilot's position loop (v = K_p·(p_sp − p)) turns the APF step into the
            if yaw is None and yaw_rate:  # a rate (DPHR) through the autopilot's heading P loop
                yaw = wrap_angle(tel.yaw + yaw_rate / HEADING_GAIN)
            self.backend.set_position_setpoint(ref, None, yaw)
            return
        from btmission.control.mav_model import yaw_rate_pd

        if (
            not tel.armed
            or tel.mode is not Mode.OFFBOARD
            or (tel.landed and ref[2] <= tel.position[2] + 0.1)
        ):
            self.backend.set_attitude_setpoint(0.0, 0.0, 0.0, 0.0)
            self._nmpc.reset()
            return
        psi = tel.yaw
        x = np.concatenate(
            [
                world_to_yaw_frame(tel.position, psi),
                world_to_yaw_frame(tel.velocity, psi),
                [tel.roll, tel.pitch],
            ]
        )
        lead = max(1.0, NMPC_LEAD_S * float(np.linalg.norm(vel)))  # ≥ the Goto's own lead
        target = tel.position + (ref - tel.position) * min(
            1.0, lead / max(float(np.linalg.norm(ref - tel.position)), 1e-9)
        )
        x_ref = np.concatenate(
            [world_to_yaw_frame(target, psi), world_to_yaw_frame(vel, psi), [0.0, 0.0]]
        )
        rate = yaw_rate_pd(psi, yaw, tel.yaw_rate) if yaw is not None else yaw_rate
        if self.defer_nmpc:
            self._pending = (self._nmpc.solve_async(x, x_ref, repulsive_force=repulsion), rate)
            return
        self._apply_nmpc(self._nmpc.solve(x, x_ref, repulsive_force=repulsion), rate)

    def finish_step(self) -> None:
        """Apply the command of a deferred NMPC solve (:attr:`defer_nmpc`); a no-op otherwise."""
        if self._pending is not None:
            pending, rate = self._pending
            self._pending = None
            self._apply_nmpc(pending.result(), rate)

    def _apply_nmpc(self, res: NmpcResult, rate: float) -> None:
        self.solve_times.append(res.solve_time_s)
        self.solve_cpu_s += res.solve_cpu_s
        self.backend.set_attitude_setpoint(float(res.u[0]), float(res.u[1]), float(res.u[2]), rate)

    # ---------------------------------------------------------------- ground robots
    def _step_ground(self, now: float, tel: Telemetry) -> None:
        cmd = self._cmd
        p = tel.position
        if isinstance(cmd, (_Hold, _Land, _Takeoff)):
            self._drive(now, tel, None)
            return
        if isinstance(cmd, _Goto):
            self._drive(now, tel, cmd.waypoint[:2])
            return
        if isinstance(cmd, _Track):
            uv, uw = track_unicycle(
                p[:2], tel.yaw, cmd.reference(now)[:2], cmd.velocity[:2], self.config.speed_m_s
            )
            heading = np.array([math.cos(tel.yaw), math.sin(tel.yaw), 0.0])
            self.prediction = np.tile(p[:2], (PREDICTION_STEPS + 1, 1))
            self.backend.set_velocity_setpoint(heading * uv, uw)
            return
        assert isinstance(cmd, _Follow)
        state, c, _, _ = self._route_step(now, tel, cmd)
        if state != "go":
            self._cmd = _Hold(p.copy())
            self._drive(now, tel, None)
            return
        self._drive(now, tel, c[:2])

    def _keep_right(
        self, x: FloatArray, goal: FloatArray, shared: Sequence[FloatArray]
    ) -> FloatArray:
        """The NMPC's way-point, moved to the right of the way ahead while another robot is
        close in front: the set-exclusion constraints (eq. 12) stop two robots meeting head-on
        in an aisle, each waiting for the other; a common side lets them pass."""
        d = goal - x[:2]
        dist = float(np.hypot(*d))
        if dist < 1e-6:
            return goal
        ahead = d / dist
        for other in shared:
            rel = other[0, :2] - x[:2]
            r = float(np.hypot(*rel))
            if r < KEEP_RIGHT_M and float(rel @ ahead) > 0.5 * r:
                right = np.array([ahead[1], -ahead[0]])
                return goal + KEEP_RIGHT_OFFSET_M * right
        return goal

    def _static_points(self, tel: Telemetry, shared: Sequence[FloatArray]) -> FloatArray:
        """The ground NMPC's obstacle points (:func:`ground_obstacle_points`) from the LiDAR;
        (0, 2) without sensors."""
        if self.sensors is None:
            return np.zeros((0, 2))
        return ground_obstacle_points(
            self.sensors.lidar(), tel.position, tel.yaw, [o[0, :2] for o in shared]
        )

    def _drive(self, now: float, tel: Telemetry, goal: FloatArray | None) -> None:
        """[u_v, u_ω] towards ``goal`` (None: stop), streamed as a velocity setpoint."""
        psi = tel.yaw
        x = np.array([tel.position[0], tel.position[1], psi])
        if self._uni is not None:
            cfg = self._uni.config
            if now - self._last_uni_t >= cfg.dt_s - 1e-9:
                shared = list(self._predictions(self.agent)) if self._predictions else []
                n = cfg.horizon + 1
                others = [  # a vehicle sharing only its position stands still over the horizon
                    o[:n] if len(o) >= n else np.vstack([o, np.repeat(o[-1:], n - len(o), axis=0)])
                    for o in shared[: cfg.max_agents]
                ]
                target = x[:2] if goal is None else self._keep_right(x, goal, shared)
                d = target - x[:2]
                heading = math.atan2(d[1], d[0]) if float(np.hypot(*d)) > 0.05 else x[2]
                res = self._uni.solve(
                    x,
                    np.array([target[0], target[1], heading]),
                    others,
                    obstacles=self._static_points(tel, shared),
                )
                self.solve_times.append(res.solve_time_s)
                self.solve_cpu_s += res.solve_cpu_s
                self._uni_u = res.u
                self.prediction = res.predicted_positions
                self._last_uni_t = now
            uv, uw = float(self._uni_u[0]), float(self._uni_u[1])
            if goal is None:
                uv, uw = 0.0, 0.0
        else:
            if goal is None:
                uv = uw = 0.0
            else:
                if self._apf is not None:  # seed 002 eq. 3 / Alg. 1: steer at p̂ + F
                    goal3 = np.array([goal[0], goal[1], tel.position[2]])
                    ref, _, _, _ = self._apf_reference(tel, goal3, 1.0)
                    goal = ref[:2] if float(np.hypot(*(goal - x[:2]))) > 0.05 else goal
                d = goal - x[:2]
                err = wrap_angle(math.atan2(d[1], d[0]) - psi)
                dist = float(np.hypot(*d))
                uw = float(np.clip(2.0 * err, -1.5, 1.5))
                uv = (
                    0.0
                    if abs(err) > math.pi / 3
                    else min(0.4, self.config.speed_m_s, 0.8 * dist) * math.cos(err)
                )
            self.prediction = np.tile(x[:2], (PREDICTION_STEPS + 1, 1))
        heading = np.array([math.cos(psi), math.sin(psi), 0.0])
        self.backend.set_velocity_setpoint(heading * uv, uw)
