"""One MAVLink vehicle as the run sees it: :class:`MavlinkVehicle`, a
:class:`~btmission.vehicles.base.Backend` over a link of :mod:`btmission.backends.mavlink_link`
(commands answered by their COMMAND_ACK, setpoints streamed by the link's I/O thread, telemetry
in the mission's world frame). The ``mavlink`` provider (:mod:`btmission.backends.mavlink`)
connects and hands them out.

**Commands never wait.** ``arm``, ``disarm``, ``set_mode``, ``takeoff`` and ``land`` are called
from the mission loop, which streams every vehicle's setpoints: a command that slept until its
answer came (on real PX4 a TEMPORARILY_REJECTED stalled every vehicle 1.2 s) would stall them all.
The first call sends COMMAND_LONG and returns at once a pending :class:`Ack`
(:meth:`Ack.waiting <btmission.vehicles.base.Ack.waiting>`, "waiting for COMMAND_ACK of …"); each
later call of the same command looks at what came meanwhile (:class:`_Asked`) and returns the
latest answer. What used to be waited for happens on deadlines those calls check: no answer
within ``ack_timeout_s`` → sent again (``command_retries`` times, then a transient refusal);
TEMPORARILY_REJECTED → sent again after 0.5 s, 1 s … of the vehicle's time; IN_PROGRESS → its final answer waited for
``in_progress_timeout_s``. An answer is kept: a refusal for a back-off (0.5 s of vehicle time,
doubling; arming up to 4 s, other commands up to 1 s), an acceptance for
:data:`ACCEPTED_HOLD_S` (at least ``ack_timeout_s``, and only until the telemetry tells another mode or arming
state) — meanwhile calls return it, and answers that still come are collected:
a later refusal overrides an earlier ACCEPTED (PX4 acknowledges a mode change twice, ACCEPTED at
once from its MAVLink module, then the commander's real result). A mode counts as set only when
the telemetry shows it (HEARTBEAT or CURRENT_MODE); an accepted arming or disarming shows at
once, until the next heartbeat says otherwise. Where the mission loop does not run (the stop
sequence, tests) :meth:`MavlinkVehicle.wait` calls a command until its answer is in.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
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
    command_name,
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
PX4_OFFBOARD_LOSS_MODES = frozenset({"POSCTL", "ALTCTL"})
"""PX4 modes that, entered in a failsafe (system status CRITICAL), are its offboard-loss action
(``COM_OBL_RC_ACT`` 0 = Position, the default, or 1 = Altitude): read as HOLD, the offboard-loss
failsafe the agent takes back (docs/mavlink.md, "When the autopilot takes over"). PX4 returns to
OFFBOARD by itself once the setpoints stream again; seen on PX4 v1.16 SITL after btmission was
stopped 2 s and 8 s ("Failsafe activated", custom mode 196608, CRITICAL). Without RC, Position
mode descends: the agent asks for OFFBOARD back at once rather than standing down, which a
pilot's Position mode (not CRITICAL) still makes it do."""


ACCEPTED_HOLD_S = 1.5
"""Vehicle time an accepted command's answer is kept (later calls return it, a later refusal
overrides it) before the command is sent again when its effect does not show: more than a
HEARTBEAT period, so that a mode change is seen even without CURRENT_MODE — and never less than
``ack_timeout_s`` of wall time (a busy machine's telemetry may lag: sent again too soon, a LAND
reached a drone that had landed and disarmed meanwhile, and was refused)."""
REFUSAL_HOLD_S = (0.5, 1.0, 4.0)
"""A refused command's answer is kept this long (vehicle time) before it is sent again: the
first, doubling after each refusal up to the second (arming: the third)."""


@dataclass
class _Asked:
    """One command sent to the vehicle and what came back (module docstring)."""

    command: int
    params: tuple[float, ...]
    pending: _Pending
    """Where the I/O thread files its COMMAND_ACKs (:attr:`_State.pending`)."""
    since: float
    """Wall time of its first send (the reason of a refusal is the STATUSTEXTs since)."""
    hold_s: float
    """How long a refusal is kept (vehicle time; :data:`REFUSAL_HOLD_S`)."""
    on_accept: Callable[[], None] | None = None
    """Run once when it is accepted (what the acceptance shows before the telemetry does)."""
    before: Ack | None = None
    """The refusal of the same request before this one (said while this one waits)."""
    sends: int = 0
    send_at: float = -math.inf
    """Wall time it is sent (again) unless an answer came."""
    seen: int = 0
    """Answers read so far."""
    answer: Ack | None = None
    """Its latest final answer (None: none yet)."""
    rejected: Ack | None = None
    """A TEMPORARILY_REJECTED being sent again: said while it waits."""
    renew_at: float = math.inf
    """Wall time after which a new call sends it anew (the answer is no longer kept)."""
    accepted_once: bool = False
    changes: int = 0
    """The vehicle's :attr:`_State.changes` when it was last sent (an answer may be read long
    after it came: what the telemetry told since counts)."""


def _same(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    """Equal parameters (NaN, "unset", equals NaN)."""
    return len(a) == len(b) and all(x == y or (x != x and y != y) for x, y in zip(a, b))


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
        self._asked: dict[int, _Asked] = {}
        """command → its latest request (module docstring)."""
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
        """A heartbeat came within ``heartbeat_timeout_s`` of wall time (not of the vehicles'
        time: at ``time_scale`` 4, a 0.75 s pause of a busy machine is 3 s of theirs, and the
        link did not fail) before the I/O thread last read the link to its end
        (:attr:`_Link.read_wall <btmission.backends.mavlink_link._Link.read_wall>`). Silence is
        counted up to then, not up to now: after btmission itself was stopped for 8 s, the
        heartbeats of those 8 s wait unread in the socket, and the link was never lost (which
        was logged as a loss and a recovery 0.025 s apart). A closed TCP link is silent up to
        now."""
        link = self.link
        read = time.monotonic() if link.down else link.read_wall
        return read - self.state.heartbeat_wall <= self.options.heartbeat_timeout_s

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

    def command(
        self, command: int, *params: float, on_accept: Callable[[], None] | None = None
    ) -> Ack:
        """Ask for COMMAND_LONG ``command`` without waiting (module docstring): the first call
        sends it and returns a pending Ack; later calls send it again when due and return the
        latest answer. Another request of the same command (other parameters), or a call after
        the answer's hold, sends it anew. ``on_accept`` runs once, when it is accepted."""
        wall = time.monotonic()
        asked = self._asked.get(command)
        same = asked is not None and _same(asked.params, params)
        if asked is None or not same or wall >= asked.renew_at or self._outdated(asked):
            hold, before = REFUSAL_HOLD_S[0], None
            if same and asked is not None and asked.answer is not None and not asked.answer:
                cap = REFUSAL_HOLD_S[2 if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM else 1]
                hold = min(cap, 2 * asked.hold_s)  # refused again: wait longer
                before = asked.answer
            asked = _Asked(command, params, _Pending(command), wall, hold, on_accept, before)
            self._asked[command] = asked
            self.state.pending[command] = asked.pending
        self._advance(asked, wall)
        if asked.answer is not None:
            return asked.answer
        if asked.rejected is not None:
            return Ack.waiting(f"{asked.rejected.reason}: sending it again")
        if asked.before is not None:  # what it said last time, while it is asked again
            return Ack.waiting(f"{asked.before.reason}; asked again")
        return Ack.waiting(f"waiting for COMMAND_ACK of {command_name(command)}")

    def _outdated(self, asked: _Asked) -> bool:
        """An accepted answer whose time is over: the vehicle's mode or arming changed since it
        was sent (its effect came and went — a failsafe HOLD after an accepted OFFBOARD — or something
        else happened), so a new call asks anew."""
        return bool(asked.answer) and self.state.changes != asked.changes

    def _advance(self, asked: _Asked, wall: float) -> None:
        """Read the answers that came, send again what is due (never waits)."""
        opts = self.options
        answers = asked.pending.answers[asked.seen :]
        asked.seen += len(answers)
        for result in answers:
            if result == mavlink.MAV_RESULT_IN_PROGRESS:  # its final answer will follow
                asked.send_at = max(asked.send_at, wall + opts.in_progress_timeout_s)
                continue
            ack = ack_of(asked.command, result, self._reason_since(asked.since))
            if (
                result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                and asked.sends <= opts.command_retries
            ):  # busy or not ready yet: asked again after a pause of the vehicle's time (a
                # SITL at ×10 refusing OFFBOARD until the stream has run 1 s is asked 0.05 s
                # wall later, not 0.5 s: 5 s of its time)
                asked.answer, asked.rejected, asked.renew_at = None, ack, math.inf
                pause = min(0.5, opts.ack_timeout_s) * asked.sends / opts.time_scale
                asked.send_at = wall + pause
                continue
            self._settle(asked, ack, wall)
        if asked.answer is not None or wall < asked.send_at:
            return
        if asked.sends > opts.command_retries:  # nobody answered: asking again later may work
            self._settle(
                asked,
                Ack.refused(
                    f"{command_name(asked.command)}: no COMMAND_ACK from sysid "
                    f"{self.state.sysid} within {opts.ack_timeout_s:g} s "
                    f"({opts.command_retries + 1} tries)"
                    + ("" if self.link_ok() else "; the vehicle's link is lost"),
                    transient=True,
                ),
                wall,
            )
            return
        self._send_command(asked.command, asked.params, asked.sends)
        asked.changes = self.state.changes
        asked.sends += 1
        asked.send_at = wall + opts.ack_timeout_s

    def _settle(self, asked: _Asked, ack: Ack, wall: float) -> None:
        """``ack`` is the command's answer now (it replaces an earlier one)."""
        opts = self.options
        scale = opts.time_scale
        asked.answer, asked.rejected, asked.send_at = ack, None, math.inf
        if ack.accepted:
            asked.renew_at = wall + max(ACCEPTED_HOLD_S / scale, opts.ack_timeout_s)
            if not asked.accepted_once:
                asked.accepted_once = True
                if asked.on_accept is not None:
                    asked.on_accept()
            return
        asked.renew_at = wall + asked.hold_s / scale
        if asked.accepted_once:  # refused after all (PX4's second answer): nothing shows it
            self.state.override = None

    def wait(
        self,
        call: Callable[[], Ack],
        shown: Callable[[], bool] | None = None,
        timeout_s: float | None = None,
    ) -> Ack:
        """Call ``call`` (a command of this vehicle) until its answer is in — and, when
        accepted, until ``shown()`` (its effect in the telemetry) — or ``timeout_s`` (wall; by
        default as long as its retries may take). Blocks: only where the mission loop does not
        run (the stop sequence, tests)."""
        opts = self.options
        if timeout_s is None:
            timeout_s = (opts.ack_timeout_s + 0.5) * (opts.command_retries + 1) + (
                ACCEPTED_HOLD_S / opts.time_scale
            )
        end = time.monotonic() + timeout_s
        while True:
            ack = call()
            done = not ack.pending and (not ack.accepted or shown is None or shown())
            if done or time.monotonic() >= end:
                break
            time.sleep(0.005)
        if ack.accepted and shown is not None and not shown():
            return Ack.refused(
                f"accepted, but not seen in the telemetry within {timeout_s:.1f} s", transient=True
            )
        return ack

    def set_mode_and_wait(self, mode: Mode) -> Ack:
        """:meth:`set_mode`, waited for until the telemetry shows ``mode`` (:meth:`wait`)."""
        try:
            wanted = mode_request(self.autopilot, self.kind, mode).custom_mode
        except UnsupportedMode:
            return self.set_mode(mode)
        return self.wait(lambda: self.set_mode(mode), lambda: self._custom_mode() == wanted)

    def _reason_since(self, since: float) -> str:
        """The autopilot's STATUSTEXTs since ``since`` (a refusal's reason), warnings first."""
        texts = [(sev, text) for wall, sev, text in self.state.texts if wall >= since - 0.2]
        texts.sort(key=lambda t: t[0])
        unique = list(dict.fromkeys(text for _, text in texts))  # a retried refusal says it again
        return "; ".join(unique[:2])

    def _shown(self, command: int) -> Ack:
        """ACCEPTED: the telemetry already shows what ``command`` would do. A request of it still
        waiting for its answer is over: its answer, read later, must not be taken for a later
        request's (an arming shown by the HEARTBEAT before its COMMAND_ACK was read; landed and
        disarmed, the next ``arm()`` took that old ACCEPTED and sent nothing)."""
        asked = self._asked.get(command)
        if asked is not None and asked.answer is None:
            del self._asked[command]
            if self.state.pending.get(command) is asked.pending:
                del self.state.pending[command]
        return ACCEPTED

    def arm(self) -> Ack:
        if self._armed():
            return self._shown(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)  # already armed: success
        self._takeoff_target = None  # disarmed: a take-off asked before is over
        ready = self._to_armable_mode()
        if not ready.accepted:
            return ready  # (pending while the mode change waits for its answer)
        return self.command(
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
            1.0,
            on_accept=lambda: self._set_override(armed=True),
        )

    def _to_armable_mode(self) -> Ack:
        """Put an ArduCopter that is in a mode it refuses to arm in (LAND, RTL, AUTO, BRAKE
        ..., :data:`~btmission.backends.mavlink_modes.COPTER_NOT_ARMABLE`: "Arm: Mode not
        armable") in GUIDED, the mode it flies the mission in, before it is armed. A copter that
        landed stays in LAND, so without this the next task of a drone that landed could never
        arm it. ACCEPTED when nothing had to change; else the mode change's answer."""
        if armable(self.autopilot, self.kind, self._custom_mode()):
            return self._shown(mavlink.MAV_CMD_DO_SET_MODE)
        guided = mode_request(self.autopilot, self.kind, Mode.OFFBOARD)
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(self.autopilot, guided))

    def disarm(self) -> Ack:
        if not self._armed():
            return self._shown(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
        if not self._landed():
            return Ack.refused("cannot disarm in the air", transient=True)
        return self.command(
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
            0.0,
            on_accept=lambda: self._set_override(armed=False),
        )

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
        if mode is Mode.LAND and self._landed_state() is LandedState.ON_GROUND:
            # landed: nothing to ask (PX4's HEARTBEAT, the only message with the armed flag,
            # comes at 1 Hz, CURRENT_MODE faster: a drone that has landed, disarmed and left
            # LAND may look armed a moment longer, and a LAND sent then is refused)
            return ACCEPTED
        try:
            request = mode_request(self.autopilot, self.kind, mode)
        except UnsupportedMode as exc:
            return Ack.refused(str(exc), transient=False)
        if self._custom_mode() == request.custom_mode and (
            mode is not Mode.OFFBOARD or self._takeoff_target is None
        ):
            return self._shown(mavlink.MAV_CMD_DO_SET_MODE)  # already in that mode
        if mode is Mode.OFFBOARD and self.autopilot is Autopilot.ARDUPILOT and not self.streaming():
            # GUIDED would take it; the backend keeps PX4's rule so trees behave the same
            return Ack.refused(
                f"offboard refused: stream setpoints at > {STREAM_MIN_HZ:g} Hz for "
                f"{STREAM_MIN_S:g} s first (the backend's rule on every autopilot)",
                transient=True,
            )
        # (a mode counts as set when the telemetry shows it, not on its first ACCEPTED)
        return self.command(
            mavlink.MAV_CMD_DO_SET_MODE,
            *set_mode_params(self.autopilot, request),
            on_accept=None if mode is Mode.OFFBOARD else self._no_takeoff,
        )

    def _no_takeoff(self) -> None:
        self._takeoff_target = None

    def takeoff(self, altitude_m: float) -> Ack:
        if self.kind is VehicleKind.GROUND:
            return Ack.refused("a ground robot cannot take off", transient=False)
        if not self._armed():
            return Ack.refused("takeoff refused: not armed", transient=True)
        if not altitude_m > 0:
            return Ack.refused(f"takeoff altitude must be > 0, got {altitude_m:g}", transient=False)
        if self._takeoff_target is not None and self._mode() is Mode.TAKEOFF:
            return ACCEPTED  # taking off: not asked again
        if self.autopilot is Autopilot.ARDUPILOT:
            # two steps, one per call: GUIDED, and once it is accepted (ArduPilot answers after
            # switching), NAV_TAKEOFF
            guided = mode_request(self.autopilot, self.kind, Mode.OFFBOARD)
            if self._custom_mode() != guided.custom_mode:
                ack = self.command(
                    mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(self.autopilot, guided)
                )
                if not ack.accepted:
                    return ack
            param7 = float(altitude_m)  # ArduPilot: metres above home
        else:
            home = self.state.home_alt_m
            param7 = math.nan if home is None else home + float(altitude_m)  # PX4: AMSL

        def taking_off() -> None:
            self._takeoff_target = self._ground_z() + float(altitude_m)
            self.state.setpoint = None  # a take-off flies on its own

        return self.command(
            mavlink.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, 0.0, math.nan, math.nan, math.nan, param7,
            on_accept=taking_off,
        )  # fmt: skip

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
            if mode in PX4_OFFBOARD_LOSS_MODES and self.state.system_status in _FAILSAFE_STATES:
                return Mode.HOLD  # PX4's offboard-loss failsafe, the default action's way
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
