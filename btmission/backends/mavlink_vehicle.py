"""One MAVLink vehicle as the run sees it: :class:`MavlinkVehicle`, a
:class:`~btmission.vehicles.base.Backend` over a link of :mod:`btmission.backends.mavlink_link`
(commands that wait for their COMMAND_ACK, setpoints streamed by the link's I/O thread, telemetry
in the mission's world frame). The ``mavlink`` provider (:mod:`btmission.backends.mavlink`)
connects and hands them out.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from btmission.backends._pymavlink import mavlink
from btmission.backends.autopilot import OFFBOARD_LOSS_S, STREAM_MIN_HZ, STREAM_MIN_S
from btmission.backends.mavlink_frames import (
    LocalFrame,
)
from btmission.backends.mavlink_modes import (
    Autopilot,
    UnsupportedMode,
    ack_of,
    armable,
    mode_of,
    mode_request,
    set_mode_params,
)
from btmission.backends.mavlink_setpoints import (
    attitude_target,
    position_target,
    velocity_target,
)
from btmission.types import FloatArray, Vec3
from btmission.vehicles.base import ACCEPTED, Ack, LandedState, Mode, Telemetry, VehicleKind
from btmission.vehicles.clock import ScaledWallClock

if TYPE_CHECKING:
    pass

from btmission.backends.mavlink_link import (
    EKF_POSITION_OK,
    MavlinkOptions,
    _Link,
    _Pending,
    _send_position_target,
    _State,
)

_LANDED_STATES = {
    mavlink.MAV_LANDED_STATE_ON_GROUND: LandedState.ON_GROUND,
    mavlink.MAV_LANDED_STATE_IN_AIR: LandedState.IN_AIR,
    mavlink.MAV_LANDED_STATE_TAKEOFF: LandedState.TAKEOFF,
    mavlink.MAV_LANDED_STATE_LANDING: LandedState.LANDING,
}
"""MAV_LANDED_STATE → :class:`LandedState` (UNDEFINED otherwise)."""
_FAILSAFE_STATES = frozenset({mavlink.MAV_STATE_CRITICAL, mavlink.MAV_STATE_EMERGENCY})
"""HEARTBEAT system_status while a failsafe is active (PX4: ``failsafe`` set; ArduCopter:
``any_failsafe_triggered()``)."""


class MavlinkVehicle:
    """One MAVLink vehicle as a :class:`~btmission.vehicles.base.Backend` (module docstring)."""

    def __init__(
        self,
        agent_id: str,
        kind: VehicleKind,
        link: _Link,
        state: _State,
        frame: LocalFrame,
        clock: ScaledWallClock,
        options: MavlinkOptions,
        ground_at: Callable[[FloatArray], float] | None = None,
        wake: Callable[[], None] | None = None,
    ) -> None:
        self.id = agent_id
        self._wake = wake or (lambda: None)
        self.kind = kind
        self.link = link
        self.state = state
        self.frame = frame
        self.clock = clock
        self.options = options
        self._ground_at = ground_at
        self._backoff: dict[int, tuple[float, float, Ack]] = {}
        """command → (wall time it may be sent again, back-off, the refusal meanwhile)."""
        self._takeoff_target: float | None = None
        self._takeoff_sent_wall = -math.inf
        self.commands_sent = 0
        self._last_set = -math.inf
        self._stream_since = math.inf
        self._ready_sent = -math.inf
        if kind is VehicleKind.GROUND:
            state.stop = _send_position_target(state, velocity_target(frame, (0.0, 0.0, 0.0)))

    # ------------------------------------------------------------------ state
    @property
    def autopilot(self) -> Autopilot:
        return self.state.autopilot

    def link_ok(self) -> bool:
        """A heartbeat came within the last ``heartbeat_timeout_s`` of wall time (not of the
        vehicles' time: at ``time_scale`` 4, a 0.75 s pause of a busy machine is 3 s of theirs,
        and the link did not fail)."""
        return time.monotonic() - self.state.heartbeat_wall <= self.options.heartbeat_timeout_s

    def _armed(self) -> bool:
        st = self.state
        if st.override is not None and st.override[2] is not None:
            return st.override[2]
        return bool(st.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def _custom_mode(self) -> int:
        st = self.state
        if st.override is not None and st.override[1] is not None:
            return st.override[1]
        return st.custom_mode

    def estimator_ready(self) -> bool:
        """The estimator reports a usable position (module :data:`EKF_POSITION_OK`)."""
        st = self.state
        if st.ekf_flags is not None:
            return bool(st.ekf_flags & EKF_POSITION_OK == EKF_POSITION_OK)
        return bool(st.estimator_ok)

    def mode_name(self) -> Mode | str:
        """The autopilot's mode as the backend's :class:`Mode`, or its own name."""
        return mode_of(self.autopilot, self.kind, self._custom_mode())

    def statustexts(self) -> list[str]:
        return [text for _, _, text in self.state.texts]

    # ------------------------------------------------------------------ commands
    def _send_command(self, command: int, params: tuple[float, ...], confirmation: int) -> None:
        st = self.state
        p = list(params) + [0.0] * (7 - len(params))
        self.link.send(
            lambda mav: mav.command_long_send(st.sysid, st.compid, command, confirmation, *p)
        )
        self.commands_sent += 1

    def command(self, command: int, *params: float) -> Ack:
        """Send COMMAND_LONG ``command`` and wait for its COMMAND_ACK (module docstring)."""
        opts = self.options
        st = self.state
        pending = _Pending(command)
        st.pending[command] = pending
        since = time.monotonic()
        try:
            for attempt in range(opts.command_retries + 1):
                pending.event.clear()
                self._send_command(command, params, attempt)
                deadline = time.monotonic() + opts.ack_timeout_s
                while True:
                    if not pending.event.wait(max(0.0, deadline - time.monotonic())):
                        break  # no answer: send it again
                    pending.event.clear()
                    result = pending.result
                    if result == mavlink.MAV_RESULT_IN_PROGRESS:
                        deadline = time.monotonic() + opts.in_progress_timeout_s
                        continue
                    if (
                        result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                        and attempt < opts.command_retries
                    ):
                        time.sleep(min(0.5, opts.ack_timeout_s) * (attempt + 1))
                        break
                    assert result is not None
                    if result == mavlink.MAV_RESULT_ACCEPTED:
                        return ACCEPTED
                    return ack_of(command, result, self._reason_since(since))
            return Ack.refused(  # nobody answered: asking again later may work
                f"{mavlink.enums['MAV_CMD'][command].name}: no COMMAND_ACK from sysid "
                f"{st.sysid} within {opts.ack_timeout_s:g} s "
                f"({opts.command_retries + 1} tries)"
                + ("" if self.link_ok() else "; the vehicle's link is lost"),
                transient=True,
            )
        finally:
            st.pending.pop(command, None)

    def _reason_since(self, since: float) -> str:
        """The autopilot's STATUSTEXTs since ``since`` (a refusal's reason), warnings first."""
        texts = [(sev, text) for wall, sev, text in self.state.texts if wall >= since - 0.2]
        texts.sort(key=lambda t: t[0])
        unique = list(dict.fromkeys(text for _, text in texts))  # a retried refusal says it again
        return "; ".join(unique[:2])

    def _with_backoff(self, command: int, send: Callable[[], Ack]) -> Ack:
        wall = time.monotonic()
        held = self._backoff.get(command)
        if held is not None and wall < held[0]:
            return held[2]
        ack = send()
        if ack.accepted:
            self._backoff.pop(command, None)
        else:  # 0.5 s, doubling to 4 s, of the vehicle's time
            delay = 0.5 if held is None else min(4.0, held[1] * 2)
            self._backoff[command] = (wall + delay / self.options.time_scale, delay, ack)
        return ack

    def arm(self) -> Ack:
        if self._armed():
            return ACCEPTED  # already armed counts as success

        def send() -> Ack:
            ready = self._to_armable_mode()
            if not ready.accepted:
                return ready
            ack = self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
            if ack.accepted:
                self._set_override(armed=True)
            return ack

        return self._with_backoff(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, send)

    def _to_armable_mode(self) -> Ack:
        """Put an ArduCopter that is in a mode it refuses to arm in (LAND, RTL, AUTO, BRAKE
        ..., :data:`~btmission.backends.mavlink_modes.COPTER_NOT_ARMABLE`: "Arm: Mode not
        armable") in GUIDED, the mode it flies the mission in, before it is armed. A copter that
        landed stays in LAND, so without this the next task of a drone that landed could never
        arm it. ACCEPTED when nothing had to change; else the mode change's answer."""
        if armable(self.autopilot, self.kind, self._custom_mode()):
            return ACCEPTED
        guided = mode_request(self.autopilot, self.kind, Mode.OFFBOARD)
        ack = self.command(mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(self.autopilot, guided))
        if ack.accepted:
            self._set_override(mode=guided.custom_mode)
            self._takeoff_target = None
        return ack

    def disarm(self) -> Ack:
        if not self._armed():
            return ACCEPTED
        if not self._landed():
            return Ack.refused("cannot disarm in the air", transient=True)
        ack = self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0)
        if ack.accepted:
            self._set_override(armed=False)
        return ack

    def _set_override(self, *, mode: int | None = None, armed: bool | None = None) -> None:
        prev = self.state.override
        old_mode, old_armed = (prev[1], prev[2]) if prev is not None else (None, None)
        self.state.override = (
            time.monotonic(),
            mode if mode is not None else old_mode,
            armed if armed is not None else old_armed,
        )

    def streaming(self) -> bool:
        """The mission has renewed its setpoint for a second without gaps (PX4's rule for
        OFFBOARD: more than 2 Hz for 1 s), in the vehicle's time."""
        now = self.clock.now()
        return (
            now - self._last_set <= self.options.setpoint_stale_s
            and now - self._stream_since >= STREAM_MIN_S
        )

    def _ground_ready(self, now: float) -> None:
        """A ground robot's library has no arm or mode actions (the simulator's robots drive
        their cmd_vel as they are): when the mission drives it, arm it and put it in GUIDED
        (ArduRover) or OFFBOARD (PX4, once the stream has run a second), without waiting for
        the acks (once a second until the telemetry shows it)."""
        wall = time.monotonic()
        if wall - self._ready_sent < 1.0 / self.options.time_scale:
            return
        wanted = mode_request(self.autopilot, self.kind, Mode.OFFBOARD)
        armed, in_mode = self._armed(), self._custom_mode() == wanted.custom_mode
        if armed and in_mode:
            return
        if self.autopilot is Autopilot.PX4 and not self.streaming():
            return
        self._ready_sent = wall
        if not armed:
            self._send_command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1.0,), 0)
        if not in_mode:
            self._send_command(
                mavlink.MAV_CMD_DO_SET_MODE, set_mode_params(self.autopilot, wanted), 0
            )

    def set_mode(self, mode: Mode) -> Ack:
        if mode is Mode.TAKEOFF:
            return self.takeoff(self.options.takeoff_alt_m)
        if mode is Mode.LAND and self.kind is VehicleKind.GROUND:
            return Ack.refused("a ground robot cannot land", transient=False)
        try:
            request = mode_request(self.autopilot, self.kind, mode)
        except UnsupportedMode as exc:
            return Ack.refused(str(exc), transient=False)
        if self._custom_mode() == request.custom_mode and (
            mode is not Mode.OFFBOARD or self._takeoff_target is None
        ):
            return ACCEPTED  # already in that mode
        if mode is Mode.OFFBOARD and self.autopilot is Autopilot.ARDUPILOT and not self.streaming():
            # GUIDED would take it; the backend keeps PX4's rule so trees behave the same
            return Ack.refused(
                f"offboard refused: stream setpoints at > {STREAM_MIN_HZ:g} Hz for "
                f"{STREAM_MIN_S:g} s first (the backend's rule on every autopilot)",
                transient=True,
            )
        ack = self.command(mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(self.autopilot, request))
        if ack.accepted:
            self._set_override(mode=request.custom_mode)
            if mode is not Mode.OFFBOARD:
                self._takeoff_target = None
        return ack

    def takeoff(self, altitude_m: float) -> Ack:
        if self.kind is VehicleKind.GROUND:
            return Ack.refused("a ground robot cannot take off", transient=False)
        if not self._armed():
            return Ack.refused("takeoff refused: not armed", transient=True)
        if not altitude_m > 0:
            return Ack.refused(f"takeoff altitude must be > 0, got {altitude_m:g}", transient=False)
        if self.autopilot is Autopilot.ARDUPILOT:
            guided = mode_request(self.autopilot, self.kind, Mode.OFFBOARD)
            if self._custom_mode() != guided.custom_mode:
                ack = self.command(
                    mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(self.autopilot, guided)
                )
                if not ack.accepted:
                    return ack
                self._set_override(mode=guided.custom_mode)
            param7 = float(altitude_m)  # ArduPilot: metres above home
        else:
            home = self.state.home_alt_m
            param7 = math.nan if home is None else home + float(altitude_m)  # PX4: AMSL
        ack = self.command(
            mavlink.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, 0.0, math.nan, math.nan, math.nan, param7
        )
        if ack.accepted:
            self._takeoff_target = self._ground_z() + float(altitude_m)
            self.state.setpoint = None  # a take-off flies on its own
        return ack

    def land(self) -> Ack:
        return self.set_mode(Mode.LAND)

    # ------------------------------------------------------------------ setpoints
    def _period(self) -> float:
        """Wall time between two setpoints streamed to the vehicle."""
        return 1.0 / (self.options.setpoint_hz * self.options.time_scale)

    def _stream(self, send: Callable[[Any], None], climb_to: float | None) -> None:
        st = self.state
        wall = time.monotonic()
        now = self.clock.now()
        if now - self._last_set > self.options.setpoint_stale_s:
            self._stream_since = now  # a new stream starts
        self._last_set = now
        if (
            self.autopilot is Autopilot.ARDUPILOT
            and self.kind is VehicleKind.MULTIROTOR
            and self._landed()
            and self._armed()
            and climb_to is not None
            and self._ardupilot_takeoff(climb_to)
        ):
            # a GUIDED target would cancel the take-off and keep the copter on the ground
            # (ModeGuided leaves its take-off submode): nothing is streamed until it is up
            st.setpoint = None
            return
        self._takeoff_target = None if not self._landed() else self._takeoff_target
        st.setpoint = send
        st.stopped = False
        if self.kind is VehicleKind.GROUND:
            self._ground_ready(now)
        st.setpoint_wall = wall
        if wall - st.last_sent_wall >= 0.75 * self._period():
            # a new setpoint goes out now, and the stream's grid is re-anchored at the time the
            # mission asked (not at the I/O thread's wake-up, which may be late)
            st.send_now_at = wall
            self._wake()
        # else: sent moments ago: this one goes out at the stream's next deadline (the rate is
        # capped at 1 / (0.75 period))

    def _ardupilot_takeoff(self, climb_to: float) -> bool:
        """ArduCopter does not leave the ground on GUIDED targets: it needs NAV_TAKEOFF. When
        a setpoint asks a landed, armed copter in GUIDED to climb, send it (once a second of
        vehicle time) and say so (True: the setpoint must wait until the copter is up)."""
        guided = mode_request(self.autopilot, self.kind, Mode.OFFBOARD)
        height = climb_to - self._ground_z()
        if self._custom_mode() != guided.custom_mode or height < 0.3:
            return False
        wall = time.monotonic()
        if wall - self._takeoff_sent_wall < 1.0 / self.options.time_scale:
            return True
        self._takeoff_sent_wall = wall
        st = self.state
        p = [0.0, 0.0, 0.0, math.nan, math.nan, math.nan, float(height)]
        self.link.send(
            lambda mav: mav.command_long_send(
                st.sysid, st.compid, mavlink.MAV_CMD_NAV_TAKEOFF, 0, *p
            )
        )
        return True

    def set_position_setpoint(
        self,
        position: Vec3 | FloatArray,
        velocity: Vec3 | FloatArray | None = None,
        yaw: float | None = None,
    ) -> None:
        target = position_target(self.frame, position, velocity, yaw)
        self._stream(
            _send_position_target(self.state, target),
            float(np.asarray(position, dtype=float)[2]),
        )

    def set_velocity_setpoint(self, velocity: Vec3 | FloatArray, yaw_rate: float = 0.0) -> None:
        target = velocity_target(self.frame, velocity, yaw_rate)
        v = np.asarray(velocity, dtype=float)
        climb = self._ground_z() + self.options.takeoff_alt_m if v[2] > 0.2 else None
        self._stream(
            _send_position_target(self.state, target),
            climb,
        )

    def set_attitude_setpoint(
        self, thrust: float, roll: float, pitch: float, yaw_rate: float = 0.0
    ) -> None:
        if self.kind is VehicleKind.GROUND:
            raise ValueError("a ground robot takes velocity setpoints, not attitude setpoints")
        yaw = self.frame.yaw_to_world(self.state.attitude[2])
        target = attitude_target(
            self.frame, thrust, roll, pitch, yaw, yaw_rate, hover=self.options.hover_thrust
        )
        st = self.state
        climb = self._ground_z() + self.options.takeoff_alt_m if thrust > 1.05 * 9.81 else None
        self._stream(
            lambda mav: mav.set_attitude_target_send(
                0,
                st.sysid,
                st.compid,
                target.type_mask,
                list(target.q),
                0.0,
                0.0,
                target.body_yaw_rate,
                target.thrust,
            ),
            climb,
        )

    # ------------------------------------------------------------------ telemetry
    def _landed(self) -> bool:
        st = self.state
        if self.kind is VehicleKind.GROUND:
            return True
        if st.landed_state == mavlink.MAV_LANDED_STATE_UNDEFINED:
            return not self._armed()
        return bool(st.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND)

    def _landed_state(self) -> LandedState:
        """EXTENDED_SYS_STATE's landed state (UNDEFINED when the vehicle does not send it; a
        ground robot is always on the ground)."""
        if self.kind is VehicleKind.GROUND:
            return LandedState.ON_GROUND
        return _LANDED_STATES.get(self.state.landed_state, LandedState.UNDEFINED)

    def _position(self) -> FloatArray:
        p = self.state.position
        return np.asarray(self.frame.origin, dtype=float) if p is None else self.frame.to_world(p)

    def _ground_z(self) -> float:
        st = self.state
        here = self._position()
        if self.kind is VehicleKind.GROUND:
            return float(here[2])
        if self.clock.now() - st.range_at < 1.0:  # a fresh range-finder message
            if st.range_m is not None:
                return float(here[2] - st.range_m)
            if st.range_below_min and self._landed():
                return float(here[2])  # closer than it measures, and landed: on the ground
        # out of the sensor's range (or none): the map, else the vehicle's origin
        if self._ground_at is not None:
            return float(self._ground_at(here))
        return float(self.frame.origin[2])

    def _mode(self) -> Mode:
        mode = self.mode_name()
        if not isinstance(mode, Mode):
            return Mode.MANUAL  # a mode of the pilot's (ALTCTL, RTL ...): not ours
        if self.autopilot is Autopilot.ARDUPILOT and mode is Mode.OFFBOARD:
            return self._guided_mode()
        return mode

    def _guided_mode(self) -> Mode:
        """ArduPilot's GUIDED seen as PX4 would show it: TAKEOFF while a NAV_TAKEOFF climbs,
        HOLD once it is up and no target has come since, OFFBOARD otherwise."""
        target = self._takeoff_target
        if self.clock.now() - self._last_set > self.options.setpoint_stale_s + OFFBOARD_LOSS_S:
            if self._last_set > -math.inf and self.state.setpoint is not None:
                return Mode.HOLD  # the mission stopped its targets: GUIDED holds the last one
        if target is None or self.state.setpoint is not None:
            return Mode.OFFBOARD
        climbing = abs(float(self.state.velocity[2])) > 0.1
        if self._landed() or abs(self._position()[2] - target) > 0.2 or climbing:
            return Mode.TAKEOFF
        return Mode.HOLD

    def telemetry(self) -> Telemetry:
        st = self.state
        roll, pitch, yaw, yawspeed = st.attitude
        velocity = self.frame.vector_to_world(st.velocity)
        return Telemetry(
            time_s=st.position_at if st.position is not None else self.clock.now(),
            position=self._position(),
            velocity=velocity,
            yaw=self.frame.yaw_to_world(yaw),
            roll=float(roll),
            pitch=float(-pitch),
            yaw_rate=self.frame.yaw_rate_to_world(yawspeed),
            mode=self._mode(),
            armed=self._armed(),
            landed=self._landed(),
            landed_state=self._landed_state(),
            battery=float(st.battery),
            ground_z=self._ground_z(),
            failsafe=self.state.system_status in _FAILSAFE_STATES,
        )


# ---------------------------------------------------------------------------- the provider
