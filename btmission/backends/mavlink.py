"""MAVLink vehicles as a :class:`~btmission.vehicles.provider.VehicleProvider` (scheme ``mavlink``).

One process drives every MAVLink vehicle of a mission (MAVSDK needs a server per drone; this does
not): the agents' ``backend:`` URLs (:mod:`btmission.backends.mavlink_url`) name the links, several
vehicles may share one link (told apart by ``?sysid=``), and **one I/O thread** serves them all:

* it waits on every link's socket at once (``select``), parses what arrives with pymavlink and
  files it into the vehicle's state (heartbeat, LOCAL_POSITION_NED, ATTITUDE, EXTENDED_SYS_STATE,
  SYS_STATUS, DISTANCE_SENSOR, HOME_POSITION, EKF_STATUS_REPORT, STATUSTEXT, COMMAND_ACK);
* it streams each vehicle's latest setpoint at a fixed rate (``setpoint_hz``, 20 Hz by default:
  PX4 wants more than 2 Hz before and during OFFBOARD) — but only while the mission keeps
  renewing it: a setpoint older than ``setpoint_stale_s`` is no longer sent, so a mission whose
  control loop has stopped lets the autopilot's offboard-loss failsafe act;
* it sends a GCS HEARTBEAT on every link once a second (PX4's data-link-loss and ArduPilot's GCS
  failsafes watch it).

Commands (arm, mode, take-off, land) are COMMAND_LONGs that wait for their COMMAND_ACK
(``ack_timeout_s``), are sent again (with ``confirmation`` counting up) when no answer comes, are
waited for while the autopilot says IN_PROGRESS and retried after a pause while it says
TEMPORARILY_REJECTED; a refusal comes back as ``Ack(False, reason)`` naming the MAV_RESULT and the
autopilot's STATUSTEXT (:func:`~btmission.backends.mavlink_modes.ack_of`). A command whose effect
already shows (armed, in the mode) is accepted without sending anything, and an arming refused by
the pre-arm checks is not sent again until a back-off has passed (0.5 s, doubling to 4 s): the
refusal's reason is answered meanwhile.

Frames: the mission world is ENU, z up; each vehicle's local NED frame has its origin at the
agent's start (or ``origin`` option), north along world +y
(:class:`~btmission.backends.mavlink_frames.LocalFrame`).

Time: real vehicles live on the wall clock; simulated ones may run faster (mavsim ``--speed``,
ArduPilot SITL ``--speedup``, PX4_SIM_SPEED_FACTOR) and the run's clock then runs as much faster
(``time_scale``). Telemetry times are the run clock's when the message arrived.
"""

from __future__ import annotations

import collections
import math
import os
import select
import socket
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from btmission.backends._pymavlink import mavlink, mavutil
from btmission.backends.autopilot import OFFBOARD_LOSS_S, STREAM_MIN_HZ, STREAM_MIN_S
from btmission.backends.mavlink_frames import (
    GeodeticOrigin,
    LocalFrame,
    agent_frame,
    mission_geodetic_origin,
    world_to_geodetic,
)
from btmission.backends.mavlink_modes import (
    Autopilot,
    UnsupportedMode,
    ack_of,
    autopilot_of,
    mode_of,
    mode_request,
    set_mode_params,
)
from btmission.backends.mavlink_setpoints import (
    PositionTarget,
    attitude_target,
    position_target,
    velocity_target,
)
from btmission.backends.mavlink_signing import enable_signing, load_key, signing_counters
from btmission.backends.mavlink_url import MavlinkAddress, parse_mavlink_url
from btmission.spec.vehicleref import SIM, VehicleRef
from btmission.types import FloatArray, Vec3
from btmission.vehicles.base import ACCEPTED, Ack, Mode, Sensors, Telemetry, VehicleKind
from btmission.vehicles.clock import ScaledWallClock
from btmission.vehicles.provider import (
    AttachOptions,
    ProviderBase,
    Vehicle,
    VehicleEvent,
    VehicleUnavailable,
)

if TYPE_CHECKING:
    from btmission.spec.mission import Mission
    from btmission.world.voxel import VoxelMap

GCS_SYSID = 255
GCS_COMPID = mavlink.MAV_COMP_ID_MISSIONPLANNER

MULTIROTOR_TYPES = frozenset(
    {
        mavlink.MAV_TYPE_QUADROTOR,
        mavlink.MAV_TYPE_HEXAROTOR,
        mavlink.MAV_TYPE_OCTOROTOR,
        mavlink.MAV_TYPE_TRICOPTER,
        mavlink.MAV_TYPE_COAXIAL,
        mavlink.MAV_TYPE_HELICOPTER,
        mavlink.MAV_TYPE_DECAROTOR,
        mavlink.MAV_TYPE_DODECAROTOR,
    }
)
GROUND_TYPES = frozenset({mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_TYPE_SURFACE_BOAT})

STREAMS = (
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    mavlink.MAVLINK_MSG_ID_ATTITUDE,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS,
    mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR,
)
"""Messages requested with SET_MESSAGE_INTERVAL at ``telemetry_hz`` (HEARTBEAT comes at 1 Hz
anyway; the estimator report at 2 Hz)."""
ESTIMATOR_STREAM = {
    Autopilot.ARDUPILOT: mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
    Autopilot.PX4: mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS,
}

EKF_POSITION_OK = mavlink.EKF_ATTITUDE | mavlink.EKF_VELOCITY_HORIZ | mavlink.EKF_POS_HORIZ_REL
"""EKF_STATUS_REPORT flags ArduPilot needs before it arms in GUIDED (a relative position)."""


class MavlinkError(VehicleUnavailable):
    """A MAVLink vehicle could not be connected (no heartbeat, wrong vehicle type...)."""


# ---------------------------------------------------------------------------- options
@dataclass(frozen=True)
class MavlinkOptions:
    """How the provider talks to its vehicles (defaults: what a drone engineer expects)."""

    connect_timeout_s: float = 120.0
    """Wall time to wait for a vehicle's first heartbeat and position estimate."""
    ack_timeout_s: float = 1.0
    """Wall time to wait for a COMMAND_ACK before sending the command again."""
    command_retries: int = 2
    """Times a command is sent again (no ack, or TEMPORARILY_REJECTED)."""
    in_progress_timeout_s: float = 5.0
    setpoint_hz: float = 20.0
    telemetry_hz: float = 50.0
    setpoint_stale_s: float = 0.3
    """Vehicle time after which a setpoint the mission stopped renewing is no longer streamed
    (the mission's own rate must stay above ~3 Hz; the control loop runs at 20 Hz)."""
    heartbeat_timeout_s: float = 3.0
    """Run-clock time without a vehicle heartbeat after which its link counts as lost."""
    hover_thrust: float = 0.5
    """Normalised hover throttle (PX4 MPC_THR_HOVER / ArduPilot MOT_THST_HOVER) for attitude
    setpoints."""
    takeoff_alt_m: float = 2.0
    """Take-off altitude when none is given (ArduCopter's automatic NAV_TAKEOFF)."""
    time_scale: float = 1.0
    """How much faster than the wall clock the vehicles' time runs (simulators' speed-up)."""
    signing_key: bytes | None = None
    """MAVLink 2 signing key (32 bytes): outgoing signed, unsigned incoming refused."""
    on_stop: str = "land"
    """What a flying vehicle is told when the provider closes: ``land`` (HOLD, then LAND) or
    ``hold``."""

    def __post_init__(self) -> None:
        for name in (
            "connect_timeout_s",
            "ack_timeout_s",
            "setpoint_hz",
            "telemetry_hz",
            "setpoint_stale_s",
            "heartbeat_timeout_s",
            "time_scale",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if not 0.0 < self.hover_thrust <= 1.0:
            raise ValueError(f"hover_thrust must be in (0, 1], got {self.hover_thrust}")


# ---------------------------------------------------------------------------- vehicle state
@dataclass
class _Pending:
    command: int
    event: threading.Event = field(default_factory=threading.Event)
    result: int | None = None
    text: str = ""


@dataclass
class _State:
    """What the I/O thread knows of one vehicle (written by it, read by the mission)."""

    sysid: int
    compid: int
    autopilot: Autopilot
    mav_type: int
    base_mode: int = 0
    custom_mode: int = 0
    system_status: int = 0
    heartbeat_at: float = -math.inf
    heartbeat_wall: float = -math.inf
    heartbeats: int = 0
    position: FloatArray | None = None
    """Local NED (m)."""
    velocity: FloatArray = field(default_factory=lambda: np.zeros(3))
    position_at: float = -math.inf
    attitude: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    """roll, pitch, yaw (FRD/NED, rad), yaw speed (rad/s)."""
    landed_state: int = mavlink.MAV_LANDED_STATE_UNDEFINED
    battery: float = 1.0
    range_m: float | None = None
    range_at: float = -math.inf
    home_alt_m: float | None = None
    global_origin: tuple[float, float, float] | None = None
    """The vehicle's EKF global origin (lat, lon, alt m), when it has told one."""
    ekf_flags: int | None = None
    estimator_ok: bool | None = None
    texts: collections.deque[tuple[float, int, str]] = field(
        default_factory=lambda: collections.deque(maxlen=20)
    )
    pending: dict[int, _Pending] = field(default_factory=dict)
    override: tuple[float, int | None, bool | None] | None = None
    """(wall time, custom_mode, armed) an accepted command set, until a newer heartbeat."""
    setpoint: Callable[[Any], None] | None = None
    stop: Callable[[Any], None] | None = None
    """Sent once when the mission stops renewing its setpoint (a ground robot's zero
    velocity: ArduRover would keep a GUIDED speed 3 s)."""
    stopped: bool = True
    setpoint_wall: float = -math.inf
    next_setpoint_wall: float = 0.0
    last_sent_wall: float = -math.inf
    setpoints_sent: int = 0
    send_times: list[float] | None = None
    """Wall time of every setpoint sent, when a benchmark asks (a list), else None."""
    messages: int = 0
    positions: int = 0
    """LOCAL_POSITION_NED messages received."""


@dataclass
class _Link:
    address: MavlinkAddress
    conn: Any
    lock: threading.Lock = field(default_factory=threading.Lock)
    vehicles: dict[int, _State] = field(default_factory=dict)
    claimed: set[int] = field(default_factory=set)
    next_heartbeat_wall: float = 0.0
    down: bool = False
    """A TCP link whose peer closed it (the vehicle or SITL restarted): reconnected every
    second."""
    next_reconnect_wall: float = 0.0

    def __post_init__(self) -> None:
        if self.address.transport == "tcp":  # pymavlink would print and spin on a closed socket
            self.conn.handle_eof = self._closed
            self.conn.handle_disconnect = self._closed

    def _closed(self) -> None:
        port = getattr(self.conn, "port", None)
        if port is not None:
            try:
                port.close()
            except OSError:
                pass
        self.conn.port = None
        self.down = True

    def reconnect(self, wall: float) -> None:
        """Try once to reconnect a closed TCP link (then again a second later)."""
        if wall < self.next_reconnect_wall:
            return
        self.next_reconnect_wall = wall + 1.0
        try:
            with self.lock:
                self.conn.do_connect()
        except OSError:
            return
        self.conn.fd = self.conn.port.fileno()
        self.down = False

    def send(self, fn: Callable[[Any], None]) -> None:
        if self.down:
            return
        with self.lock:
            fn(self.conn.mav)


def _check_udp_port_free(address: MavlinkAddress) -> None:
    """pymavlink binds with SO_REUSEADDR, so a second ground station on the same UDP port would
    bind too and the two would fight over the vehicle: refuse a port another process holds."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((address.host, address.port))
    except OSError as exc:
        raise MavlinkError(
            f"cannot listen at {address.url()}: {exc.strerror or exc} (another ground station "
            "or btmission run holds the port)"
        ) from None
    finally:
        probe.close()


def _open(address: MavlinkAddress, options: MavlinkOptions, deadline: float) -> Any:
    """A pymavlink connection for ``address`` (TCP: retried until ``deadline``)."""
    device = address.device()
    kwargs: dict[str, Any] = {"source_system": GCS_SYSID, "source_component": GCS_COMPID}
    if address.transport == "serial":
        kwargs["baud"] = address.baud
    if address.transport == "tcp":
        kwargs["retries"] = 0  # retried here, quietly, until the deadline
    if address.transport == "udp":
        _check_udp_port_free(address)
    while True:
        try:
            conn = mavutil.mavlink_connection(device, **kwargs)
            break
        except OSError as exc:
            if address.transport != "tcp" or time.monotonic() > deadline:
                raise MavlinkError(f"cannot open {address.url()}: {exc.strerror or exc}") from None
            time.sleep(0.2)
    conn.WIRE_PROTOCOL_VERSION = "2.0"
    if options.signing_key is not None:
        enable_signing(conn, options.signing_key)
    return conn


# ---------------------------------------------------------------------------- the I/O thread
class _LinkIO:
    """One thread for every link: receive, stream setpoints, send GCS heartbeats."""

    def __init__(self, clock: ScaledWallClock, options: MavlinkOptions) -> None:
        self.clock = clock
        self.options = options
        self.links: dict[str, _Link] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="mavlink-io", daemon=True)
        self._thread.start()

    def add(self, link: _Link) -> None:
        with self._lock:
            self.links[link.address.device()] = link
        self.wake()

    def wake(self) -> None:
        """Make the thread look at its schedule now (a new setpoint to send)."""
        try:
            os.write(self._wake_w, b"x")
        except (BlockingIOError, OSError):
            pass  # the pipe is full: it will wake anyway

    def close(self) -> None:
        self._stop.set()
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass
        self._thread.join(timeout=2.0)
        with self._lock:
            links = list(self.links.values())
            self.links.clear()
        for link in links:
            if link.down:
                continue  # its socket is closed already
            try:
                link.conn.close()
            except OSError:
                pass
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    # ------------------------------------------------------------------ loop
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                with self._lock:
                    links = list(self.links.values())
                timeout = self._periodic(links)
                fds: dict[int, _Link] = {}
                for link in links:
                    fd = _fileno(link.conn)
                    if fd is not None:
                        fds[fd] = link
                ready, _, _ = select.select([self._wake_r, *fds], [], [], timeout)
                for fd in ready:
                    if fd == self._wake_r:
                        try:
                            os.read(self._wake_r, 4096)
                        except OSError:
                            pass
                        continue
                    self._receive(fds[fd])
        except BaseException as exc:
            self.error = exc

    def _periodic(self, links: list[_Link]) -> float:
        """Send what is due; return how long select may wait."""
        wall = time.monotonic()
        opts = self.options
        period = 1.0 / (opts.setpoint_hz * opts.time_scale)  # the rate in the vehicle's time
        next_due = wall + 0.05
        for link in links:
            if link.down:
                link.reconnect(wall)
                continue
            if wall >= link.next_heartbeat_wall:
                link.next_heartbeat_wall = wall + 1.0 / opts.time_scale
                link.send(
                    lambda mav: mav.heartbeat_send(
                        mavlink.MAV_TYPE_GCS,
                        mavlink.MAV_AUTOPILOT_INVALID,
                        0,
                        0,
                        mavlink.MAV_STATE_ACTIVE,
                    )
                )
            next_due = min(next_due, link.next_heartbeat_wall)
            for st in list(link.vehicles.values()):
                sp = st.setpoint
                if sp is None or wall - st.setpoint_wall > opts.setpoint_stale_s / opts.time_scale:
                    if not st.stopped and st.stop is not None:
                        link.send(st.stop)
                    st.stopped = True
                    continue
                if wall >= st.next_setpoint_wall:
                    link.send(sp)
                    st.setpoints_sent += 1
                    st.last_sent_wall = wall
                    if st.send_times is not None:
                        st.send_times.append(time.monotonic())
                    st.next_setpoint_wall = wall + period  # re-sent if not renewed meanwhile
                next_due = min(next_due, st.next_setpoint_wall)
        return max(0.0, next_due - time.monotonic())

    def _receive(self, link: _Link) -> None:
        conn = link.conn
        for _ in range(1000):  # bounded: never starve the setpoint stream
            if link.down:
                return
            try:
                msg = conn.recv_msg()
            except (OSError, ConnectionError):
                return
            if msg is None:
                return
            self._file(link, msg)

    def _file(self, link: _Link, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":  # signing refusals are counted by pymavlink's signing state;
            return  # other bytes (a SITL's boot banner on its serial port) are not messages
        src = msg.get_srcSystem()
        st = link.vehicles.get(src)
        now = self.clock.now()
        if kind == "HEARTBEAT":
            if st is None:
                ap = autopilot_of(msg.autopilot)
                if ap is None or msg.type == mavlink.MAV_TYPE_GCS:
                    return
                st = _State(src, msg.get_srcComponent(), ap, msg.type)
                link.vehicles[src] = st
            elif msg.get_srcComponent() != st.compid:
                return  # a camera, a gimbal... of the same system
            st.base_mode = msg.base_mode
            st.custom_mode = msg.custom_mode
            st.system_status = msg.system_status
            st.heartbeat_at = now
            st.heartbeat_wall = time.monotonic()
            st.heartbeats += 1
            st.override = None
            st.messages += 1
            return
        if st is None:
            return
        st.messages += 1
        if kind == "LOCAL_POSITION_NED":
            st.positions += 1
            st.position = np.array([msg.x, msg.y, msg.z], dtype=float)
            st.velocity = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
            st.position_at = now
        elif kind == "ATTITUDE":
            st.attitude = (msg.roll, msg.pitch, msg.yaw, msg.yawspeed)
        elif kind == "EXTENDED_SYS_STATE":
            st.landed_state = msg.landed_state
        elif kind == "SYS_STATUS":
            if msg.battery_remaining >= 0:
                st.battery = msg.battery_remaining / 100.0
        elif kind == "BATTERY_STATUS":
            if msg.battery_remaining >= 0:
                st.battery = msg.battery_remaining / 100.0
        elif kind == "DISTANCE_SENSOR":
            if msg.orientation == mavlink.MAV_SENSOR_ROTATION_PITCH_270:
                st.range_m = msg.current_distance / 100.0
                st.range_at = now
        elif kind == "GPS_GLOBAL_ORIGIN":
            st.global_origin = (msg.latitude / 1e7, msg.longitude / 1e7, msg.altitude / 1000.0)
        elif kind == "HOME_POSITION":
            st.home_alt_m = msg.altitude / 1000.0
        elif kind == "EKF_STATUS_REPORT":
            st.ekf_flags = msg.flags
        elif kind == "ESTIMATOR_STATUS":
            st.estimator_ok = bool(msg.flags & mavlink.ESTIMATOR_POS_HORIZ_REL)
        elif kind == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace")
            st.texts.append((time.monotonic(), msg.severity, text.rstrip("\x00")))
        elif kind == "COMMAND_ACK":
            pending = st.pending.get(msg.command)
            if pending is not None:
                pending.result = msg.result
                pending.event.set()


def _fileno(conn: Any) -> int | None:
    port = getattr(conn, "port", None)
    if port is None:
        listen = getattr(conn, "listen", None)
        return listen.fileno() if listen is not None else None
    try:
        fd = port.fileno()
    except (OSError, ValueError):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


# ---------------------------------------------------------------------------- the vehicle
def _send_position_target(st: _State, target: PositionTarget) -> Callable[[Any], None]:
    """What sends ``target`` to the vehicle of ``st`` (SET_POSITION_TARGET_LOCAL_NED)."""

    def send(mav: Any) -> None:
        mav.set_position_target_local_ned_send(
            0, st.sysid, st.compid, mavlink.MAV_FRAME_LOCAL_NED, target.type_mask,
            *target.position, *target.velocity, 0.0, 0.0, 0.0, target.yaw, target.yaw_rate,
        )  # fmt: skip

    return send


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
        """A heartbeat came within ``heartbeat_timeout_s`` of the run clock."""
        return self.clock.now() - self.state.heartbeat_at <= self.options.heartbeat_timeout_s

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
            return Ack(
                False,
                f"{mavlink.enums['MAV_CMD'][command].name}: no COMMAND_ACK from sysid "
                f"{st.sysid} within {opts.ack_timeout_s:g} s "
                f"({opts.command_retries + 1} tries)"
                + ("" if self.link_ok() else "; the vehicle's link is lost"),
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
            ack = self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
            if ack.accepted:
                self._set_override(armed=True)
            return ack

        return self._with_backoff(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, send)

    def disarm(self) -> Ack:
        if not self._armed():
            return ACCEPTED
        if not self._landed():
            return Ack(False, "cannot disarm in the air")
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
            return Ack(False, "a ground robot cannot land")
        try:
            request = mode_request(self.autopilot, self.kind, mode)
        except UnsupportedMode as exc:
            return Ack(False, str(exc))
        if self._custom_mode() == request.custom_mode and (
            mode is not Mode.OFFBOARD or self._takeoff_target is None
        ):
            return ACCEPTED  # already in that mode
        if mode is Mode.OFFBOARD and self.autopilot is Autopilot.ARDUPILOT and not self.streaming():
            # GUIDED would take it; the backend keeps PX4's rule so trees behave the same
            return Ack(
                False,
                f"offboard refused: stream setpoints at > {STREAM_MIN_HZ:g} Hz for "
                f"{STREAM_MIN_S:g} s first (the backend's rule on every autopilot)",
            )
        ack = self.command(mavlink.MAV_CMD_DO_SET_MODE, *set_mode_params(self.autopilot, request))
        if ack.accepted:
            self._set_override(mode=request.custom_mode)
            if mode is not Mode.OFFBOARD:
                self._takeoff_target = None
        return ack

    def takeoff(self, altitude_m: float) -> Ack:
        if self.kind is VehicleKind.GROUND:
            return Ack(False, "a ground robot cannot take off")
        if not self._armed():
            return Ack(False, "takeoff refused: not armed")
        if not altitude_m > 0:
            return Ack(False, f"takeoff altitude must be > 0, got {altitude_m:g}")
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
            st.next_setpoint_wall = wall  # a new setpoint goes out now
            self._wake()
        else:  # sent moments ago: this one goes out one period after it (the rate is capped)
            st.next_setpoint_wall = st.last_sent_wall + self._period()

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

    def _position(self) -> FloatArray:
        p = self.state.position
        return np.asarray(self.frame.origin, dtype=float) if p is None else self.frame.to_world(p)

    def _ground_z(self) -> float:
        st = self.state
        here = self._position()
        if self.kind is VehicleKind.GROUND:
            return float(here[2])
        if st.range_m is not None and self.clock.now() - st.range_at < 1.0:
            return float(here[2] - st.range_m)
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
            battery=float(st.battery),
            ground_z=self._ground_z(),
        )


# ---------------------------------------------------------------------------- the provider
class MavlinkProvider(ProviderBase):
    """MAVLink vehicles for a run (module docstring)."""

    realtime = True

    def __init__(
        self,
        options: MavlinkOptions | None = None,
        ground_at: Callable[[FloatArray], float] | None = None,
        progress: Callable[[str], None] | None = None,
        *,
        geodetic: GeodeticOrigin | None = None,
        sensors: Callable[[MavlinkVehicle], Sensors] | None = None,
        frames: Mapping[str, LocalFrame] | None = None,
    ) -> None:
        """``geodetic``: where the world's origin is on Earth (``world.origin``): a vehicle
        that knows no global origin gets its own (SET_GPS_GLOBAL_ORIGIN). ``sensors``: map
        sensors for each vehicle (``runtime.mavlink.map_sensors``), else none. ``frames``: each
        agent's world ↔ local NED frame (its ``origin:`` in the mission); an agent without one
        has its start as origin, north along world +y."""
        self.options = options or MavlinkOptions()
        self._frames = dict(frames or {})
        self._geodetic = geodetic
        self._sensors = sensors
        self.clock = ScaledWallClock(self.options.time_scale)
        self._io = _LinkIO(self.clock, self.options)
        self._ground_at = ground_at
        self._progress = progress
        self.vehicles: dict[str, MavlinkVehicle] = {}
        self._closed = False

    def _link(self, address: MavlinkAddress, deadline: float) -> _Link:
        key = address.device()
        link = self._io.links.get(key)
        if link is None:
            link = _Link(address, _open(address, self.options, deadline))
            self._io.add(link)
        return link

    def prepare(self, vehicles: Sequence[VehicleRef]) -> None:
        """Open every link before the vehicles are attached one by one, so that vehicles that
        start on a connection (ArduPilot SITL waits for its TCP client) boot and warm up their
        estimators together. A link that cannot be opened now is left to :meth:`attach`."""
        deadline = time.monotonic() + 1.0
        for url in dict.fromkeys(v.url for v in vehicles):
            try:
                self._link(parse_mavlink_url(url), deadline)
            except (MavlinkError, ValueError):
                continue

    def start(self) -> None:
        """The mission starts now: the run clock restarts at zero (connecting took its time)."""
        self.clock.restart()

    def attach(
        self,
        agent_id: str,
        kind: VehicleKind,
        start: Vec3,
        ref: VehicleRef = SIM,
        options: AttachOptions = AttachOptions(),
    ) -> Vehicle:
        """Connect ``agent_id``'s vehicle at ``ref``'s URL: wait for an autopilot's
        heartbeat (the ``?sysid=`` one, else the first not taken), check its type, ask for its
        telemetry streams and wait for a position estimate. Its frame is the one the provider
        was given for ``agent_id`` (``frames``), else its origin is ``start``, north along
        world +y."""
        address = parse_mavlink_url(ref.url)
        opts = self.options
        deadline = time.monotonic() + opts.connect_timeout_s
        if self._progress is not None:
            self._progress(f"{agent_id}: connecting to {address.url()}")
        link = self._link(address, deadline)
        state = self._wait_heartbeat(agent_id, link, address, deadline)
        link.claimed.add(state.sysid)
        if kind is VehicleKind.MULTIROTOR and state.mav_type not in MULTIROTOR_TYPES:
            raise MavlinkError(
                f"{agent_id}: the vehicle at {address.url()} (sysid {state.sysid}) is a "
                f"{_type_name(state.mav_type)}, but the agent's library flies a multirotor"
            )
        if kind is VehicleKind.GROUND and state.mav_type not in GROUND_TYPES:
            raise MavlinkError(
                f"{agent_id}: the vehicle at {address.url()} (sysid {state.sysid}) is a "
                f"{_type_name(state.mav_type)}, but the agent's library drives a ground robot"
            )
        frame = self._frames.get(agent_id) or LocalFrame(
            (float(start[0]), float(start[1]), float(start[2]))
        )
        vehicle = MavlinkVehicle(
            agent_id, kind, link, state, frame, self.clock, opts, self._ground_at, self._io.wake
        )
        self._request_streams(vehicle)
        if self._geodetic is not None:
            self._set_global_origin(vehicle, deadline)
        if state.position is None and self._progress is not None:
            self._progress(f"{agent_id}: waiting for its position estimate (LOCAL_POSITION_NED)")
        while state.position is None:
            if time.monotonic() > deadline:
                raise MavlinkError(
                    f"{agent_id}: the vehicle at {address.url()} (sysid {state.sysid}) sends no "
                    f"LOCAL_POSITION_NED within {opts.connect_timeout_s:g} s: it has no local "
                    "position estimate (an EKF origin and a position source are needed)"
                )
            time.sleep(0.02)
        self._wait_estimator(vehicle, deadline)
        self.vehicles[agent_id] = vehicle
        if self._progress is not None:
            self._progress(
                f"{agent_id}: {state.autopilot.value} sysid {state.sysid} "
                f"({_type_name(state.mav_type)}) at {address.url()}"
            )
        sensors = self._sensors(vehicle) if self._sensors is not None else None
        return Vehicle(agent_id, kind, vehicle, sensors, link_ok=vehicle.link_ok)

    def _wait_heartbeat(
        self, agent_id: str, link: _Link, address: MavlinkAddress, deadline: float
    ) -> _State:
        while True:
            self._check_io()
            if address.sysid is not None:
                st = link.vehicles.get(address.sysid)
                if st is not None and address.sysid in link.claimed:
                    raise MavlinkError(
                        f"{agent_id}: sysid {address.sysid} at {address.url()} is already "
                        "another agent's vehicle"
                    )
                if st is not None and (address.compid is None or st.compid == address.compid):
                    return st
            else:
                free = [s for sid, s in sorted(link.vehicles.items()) if sid not in link.claimed]
                if free:
                    return free[0]
            if time.monotonic() > deadline:
                who = f"sysid {address.sysid}" if address.sysid is not None else "an autopilot"
                seen = sorted(link.vehicles)
                hint = (
                    f" (heard sysids {', '.join(map(str, seen))}, all taken)"
                    if seen
                    else " (is the vehicle on, and is its MAVLink output sent here?)"
                )
                raise MavlinkError(
                    f"{agent_id}: no heartbeat from {who} at {address.url()} within "
                    f"{self.options.connect_timeout_s:g} s{hint}"
                )
            time.sleep(0.02)

    def _request_streams(self, vehicle: MavlinkVehicle) -> None:
        interval_us = 1e6 / self.options.telemetry_hz
        requests = [(msg, interval_us) for msg in STREAMS]
        requests.append((ESTIMATOR_STREAM[vehicle.autopilot], 5e5))
        requests.append((mavlink.MAVLINK_MSG_ID_HEARTBEAT, 2e5))  # modes seen within 0.2 s
        for i, (msg_id, interval) in enumerate(requests):
            ack = vehicle.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), interval)
            if i == 0 and not ack.accepted and "no COMMAND_ACK" in ack.reason:
                signing = (
                    "the key may differ from the vehicle's"
                    if self.options.signing_key is not None
                    else "if it requires MAVLink 2 signing, give its key (--mavlink-key-file)"
                )
                raise MavlinkError(
                    f"{vehicle.id}: sysid {vehicle.state.sysid} is heard but does not answer "
                    f"commands ({signing})"
                )
            if not ack.accepted and self._progress is not None:
                self._progress(f"{vehicle.id}: stream {msg_id} not available ({ack.reason})")
        vehicle.command(
            mavlink.MAV_CMD_REQUEST_MESSAGE, float(mavlink.MAVLINK_MSG_ID_HOME_POSITION)
        )

    def _wait_estimator(self, vehicle: MavlinkVehicle, deadline: float) -> None:
        """Wait (until ``deadline``) for the estimator to report a usable position: ArduPilot's
        EKF_STATUS_REPORT with attitude, horizontal velocity and relative position OK, PX4's
        ESTIMATOR_STATUS with a relative position. A vehicle that sends neither within two
        seconds is taken as it is; one still not ready at the deadline is attached anyway, and
        its arming refusals will say why."""
        st = vehicle.state
        said = False
        quiet_until = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            if vehicle.estimator_ready():
                return
            if st.ekf_flags is None and st.estimator_ok is None and time.monotonic() > quiet_until:
                return  # it does not report its estimator
            if (
                not said
                and self._progress is not None
                and (st.ekf_flags is not None or st.estimator_ok is not None)
            ):
                self._progress(f"{vehicle.id}: waiting for its estimator (EKF) to have a position")
                said = True
            time.sleep(0.05)
        if self._progress is not None:
            self._progress(
                f"{vehicle.id}: the estimator has no usable position yet; arming will be refused "
                "until it has"
            )

    def _set_global_origin(self, vehicle: MavlinkVehicle, deadline: float) -> None:
        """Give a vehicle without a global origin (no GPS: underground) the geodetic position of
        its local origin, and wait until it confirms (GPS_GLOBAL_ORIGIN)."""
        assert self._geodetic is not None
        st = vehicle.state
        ack = vehicle.command(
            mavlink.MAV_CMD_REQUEST_MESSAGE, float(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
        )
        if ack.accepted:
            end = min(deadline, time.monotonic() + 1.0)
            while st.global_origin is None and time.monotonic() < end:
                time.sleep(0.02)
        if st.global_origin is not None:
            return  # it has one (its GPS, or set before)
        lat, lon, alt = world_to_geodetic(vehicle.frame.origin, self._geodetic)
        vehicle.link.send(
            lambda mav: mav.set_gps_global_origin_send(
                st.sysid, round(lat * 1e7), round(lon * 1e7), round(alt * 1000), 0
            )
        )
        end = min(deadline, time.monotonic() + 2.0)
        while st.global_origin is None and time.monotonic() < end:
            time.sleep(0.02)
        if self._progress is not None:
            said = "confirmed" if st.global_origin is not None else "not confirmed"
            self._progress(
                f"{vehicle.id}: global origin set to {lat:.7f}, {lon:.7f}, {alt:.1f} m ({said})"
            )

    def _check_io(self) -> None:
        if self._io.error is not None:
            raise MavlinkError(f"the MAVLink I/O thread stopped: {self._io.error!r}")

    def step(self, dt: float) -> list[VehicleEvent]:
        """Nothing to integrate: real time passes on its own. Raises if the I/O thread died."""
        self._check_io()
        return []

    def rejected(self) -> dict[str, int]:
        """Messages refused on every link with signing on, by reason: unsigned, a bad
        signature or a replay."""
        out: collections.Counter[str] = collections.Counter()
        for link in self._io.links.values():
            if self.options.signing_key is not None:
                counts = signing_counters(link.conn)
                counts.pop("signed_ok")
                out.update(counts)
        return {k: v for k, v in out.items() if v}

    def close(self) -> None:
        """Leave every vehicle safe, then close the links: a vehicle still flying is told to
        HOLD and then (``on_stop: land``, the default) to LAND, each command confirmed by its
        COMMAND_ACK; setpoints stop. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self.stop_vehicles()
            refused = self.rejected()
            if refused and self._progress is not None:
                self._progress(
                    "MAVLink messages refused: "
                    + ", ".join(
                        f"{why.replace('_', ' ')} {n}" for why, n in sorted(refused.items())
                    )
                )
        finally:
            self._io.close()

    def stop_vehicles(self) -> dict[str, list[Ack]]:
        """HOLD (then LAND) every vehicle that is armed and off the ground (:meth:`close`)."""
        out: dict[str, list[Ack]] = {}
        for vehicle in self.vehicles.values():
            vehicle.state.setpoint = None  # nothing more is streamed
            if self._io.error is not None or not vehicle.link_ok():
                continue
            tel = vehicle.telemetry()
            if not tel.armed or (tel.landed and vehicle.kind is VehicleKind.MULTIROTOR):
                continue
            acks = [vehicle.set_mode(Mode.HOLD)]
            if self.options.on_stop == "land" and vehicle.kind is VehicleKind.MULTIROTOR:
                acks.append(vehicle.land())
            out[vehicle.id] = acks
            if self._progress is not None:
                said = ", then ".join(
                    f"{what} {'accepted' if a else 'refused: ' + a.reason}"
                    for what, a in zip(("HOLD", "LAND"), acks, strict=False)
                )
                self._progress(f"{vehicle.id}: the run stopped: {said}")
        return out


def _type_name(mav_type: int) -> str:
    entry = mavlink.enums["MAV_TYPE"].get(mav_type)
    return entry.name if entry is not None else f"MAV_TYPE {mav_type}"


def mavlink_provider(mission: Mission, voxel_map: VoxelMap, seed: int) -> MavlinkProvider:
    """The ``mavlink`` entry point of ``btmission.providers``: the mission's
    ``runtime.mavlink`` settings, its ``world.origin``; ground heights from the mission map when
    a vehicle has no downward range finder; with ``map_sensors``, each vehicle's LiDAR and
    camera ray-cast in the mission map at the pose it reports
    (:class:`~btmission.backends.mapsensors.MapSensors`, as SITL users get from Gazebo)."""
    from btmission.backends.mapsensors import MapSensors
    from btmission.backends.sim import SimWorld, mission_artifacts, sim_config

    spec = mission.spec.runtime.mavlink
    options = MavlinkOptions(
        connect_timeout_s=spec.connect_timeout_s,
        ack_timeout_s=spec.ack_timeout_s,
        setpoint_hz=spec.setpoint_hz,
        telemetry_hz=spec.telemetry_hz,
        heartbeat_timeout_s=spec.heartbeat_timeout_s,
        hover_thrust=spec.hover_thrust,
        time_scale=spec.time_scale,
        signing_key=load_key(),
        on_stop=spec.on_stop,
    )
    world = SimWorld(voxel_map, mission_artifacts(mission))
    sensors: Callable[[MavlinkVehicle], Sensors] | None = None
    if spec.map_sensors:
        config = sim_config(mission)
        rng = np.random.default_rng(seed)

        def sensors(vehicle: MavlinkVehicle) -> Sensors:
            return MapSensors(world, config, rng, vehicle.telemetry)

    return MavlinkProvider(
        options,
        ground_at=world.ground_z,
        progress=_to_stderr,
        geodetic=mission_geodetic_origin(mission),
        sensors=sensors,
        frames={a.id: agent_frame(mission, a.id) for a in mission.agents},
    )


def _to_stderr(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
