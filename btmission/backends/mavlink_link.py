"""The MAVLink links of a run and the one I/O thread that serves them all (the ``mavlink`` provider's
plumbing: :mod:`btmission.backends.mavlink`).

A link is one connection (a UDP port, a TCP socket, a serial port) that may carry several vehicles,
told apart by their system id. :class:`_LinkIO` waits on every link at once, files what arrives
into each vehicle's :class:`_State`, streams each vehicle's latest setpoint at ``setpoint_hz`` while
the mission renews it, and sends the GCS heartbeat. :class:`MavlinkOptions` are the provider's
settings (``runtime.mavlink``), :class:`MavlinkError` what it raises when a vehicle cannot be had.

What keeps the streams on time when the machine is busy (issue #36):

* setpoints and heartbeats are due on absolute deadlines
  (:class:`~btmission.backends.mavlink_schedule.Deadlines`): a late wake-up sends at once and the
  schedule does not drift; after a stall one message goes out and the grid resumes;
* each turn of the loop sends what is due *before* it reads, and reads at most
  :data:`RECEIVE_BUDGET` messages per link, stopping early when a send falls due: a flood of
  telemetry cannot hold a setpoint back, and what it left unread is read on the next turn;
* nothing on the thread blocks: a TCP link that closed is reconnected by a helper thread;
* each vehicle's stream is watched (:class:`~btmission.backends.mavlink_schedule.StreamHealth`):
  a rate below 80 % of ``setpoint_hz`` over a second or a gap over 0.2 s (vehicle time) becomes
  a warning the provider hands to the run (:meth:`_LinkIO.take_warnings`);
* a UDP link sends only to addresses an autopilot's HEARTBEAT came from (valid, and signed when
  signing is on): pymavlink would answer every address that ever sent it a datagram.
"""

from __future__ import annotations

import collections
import math
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from btmission.backends._pymavlink import mavlink, mavutil
from btmission.backends.mavlink_modes import (
    Autopilot,
    autopilot_of,
)
from btmission.backends.mavlink_schedule import Deadlines, StreamHealth
from btmission.backends.mavlink_setpoints import (
    PositionTarget,
)
from btmission.backends.mavlink_signing import enable_signing
from btmission.backends.mavlink_url import MavlinkAddress
from btmission.types import FloatArray
from btmission.vehicles.clock import ScaledWallClock
from btmission.vehicles.provider import (
    VehicleUnavailable,
)

if TYPE_CHECKING:
    pass


RECEIVE_BUDGET = 64
"""Messages (UDP: datagrams) read from one link per turn of the I/O loop before the thread looks
at its schedule again."""
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
anyway and is asked for at 5 Hz, CURRENT_MODE at ``telemetry_hz``: the mode is read from whichever
came last, :mod:`btmission.backends.mavlink_connect`; the estimator report at 2 Hz)."""
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
    """Wall time (whatever ``time_scale``) without a vehicle heartbeat after which its link
    counts as lost."""
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
    answers: list[int] = field(default_factory=list)
    """Every COMMAND_ACK result for ``command``, in order: a connect sends several requests of
    one command at once (:mod:`btmission.backends.mavlink_connect`) and counts their answers."""


@dataclass
class _State:
    """What the I/O thread knows of one vehicle (written by it, read by the mission)."""

    sysid: int
    compid: int
    autopilot: Autopilot
    mav_type: int
    base_mode: int = 0
    custom_mode: int = 0
    """The mode, from HEARTBEAT or CURRENT_MODE, whichever came last."""
    changes: int = 0
    """How many times the telemetry told another mode or arming state."""
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
    """The downward range finder's last reading within its declared range (m); None: its
    last message had no reading (:func:`range_reading`)."""
    range_below_min: bool = False
    """Its last message read below its minimum distance (on or just above the ground)."""
    range_at: float = -math.inf
    boot: tuple[float, float] | None = None
    """The vehicle's own clock (LOCAL_POSITION_NED's ``time_boot_ms``, s) and the wall time it
    was read: what tells a paused vehicle from a lost link (:class:`VehicleClockWatch`)."""
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
    schedule: Deadlines = field(default_factory=lambda: Deadlines(0.05))
    """When the setpoint is due (the I/O thread's; the provider sets its period)."""
    health: StreamHealth = field(default_factory=lambda: StreamHealth(20.0))
    send_now_at: float | None = None
    """A new setpoint the mission hands over at once: the wall time it asked (the I/O thread
    re-anchors the schedule there, :meth:`Deadlines.restart`)."""
    last_sent_wall: float = -math.inf
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
    heartbeat: Deadlines = field(default_factory=lambda: Deadlines(1.0))
    down: bool = False
    """A TCP link whose peer closed it (the vehicle or SITL restarted): reconnected every
    second."""
    next_reconnect_wall: float = 0.0
    reconnecting: threading.Thread | None = None
    read_wall: float = -math.inf
    """When the I/O thread last found nothing more to read on this link (wall): a vehicle's
    silence counts only up to then. A process that was itself stopped (``kill -STOP``, a long
    pause of a busy machine) has not read what came meanwhile, and must not take the gap for a
    lost link (:meth:`MavlinkVehicle.link_ok <btmission.backends.mavlink_vehicle.MavlinkVehicle.
    link_ok>`)."""

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
        """Try to reconnect a closed TCP link, at most once a second, on a helper thread: a
        connect to a host that does not answer can block for long, and the I/O thread must
        keep every other vehicle's stream going meanwhile."""
        if wall < self.next_reconnect_wall or self.reconnecting is not None:
            return
        self.next_reconnect_wall = wall + 1.0
        self.reconnecting = threading.Thread(
            target=self._reconnect, name="mavlink-reconnect", daemon=True
        )
        self.reconnecting.start()

    def _reconnect(self) -> None:
        try:
            with self.lock:
                self.conn.do_connect()
                self.conn.fd = self.conn.port.fileno()
                self.down = False
        except OSError:
            pass
        finally:
            self.reconnecting = None

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
        self._period = 1.0 / (options.setpoint_hz * options.time_scale)
        """Wall time between two setpoints (the rate is in the vehicle's time)."""
        self._warnings: collections.deque[tuple[_State, str]] = collections.deque(maxlen=1000)
        self._thread = threading.Thread(target=self._run, name="mavlink-io", daemon=True)
        self._thread.start()

    def add(self, link: _Link) -> None:
        link.heartbeat = Deadlines(1.0 / self.options.time_scale)
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

    def take_warnings(self) -> list[tuple[_State, str]]:
        """The stream warnings since the last call (the vehicle's state, the text)."""
        out = []
        while self._warnings:
            out.append(self._warnings.popleft())
        return out

    # ------------------------------------------------------------------ loop
    def _run(self) -> None:
        """Each turn: send what is due, wait for a socket or the next deadline, then read —
        at most :data:`RECEIVE_BUDGET` messages per link, and no further link once a send is
        due (the first link read is read anyway, so that reading is never starved). The links
        are read round-robin, starting after the last one read."""
        last_fd = -1
        try:
            while not self._stop.is_set():
                with self._lock:
                    links = list(self.links.values())
                next_due = self._periodic(links)
                fds: dict[int, _Link] = {}
                for link in links:
                    fd = None if link.down else _fileno(link.conn)
                    if fd is not None:
                        fds[fd] = link
                timeout = max(0.0, next_due - time.monotonic())
                ready, _, _ = select.select([self._wake_r, *fds], [], [], timeout)
                looked = time.monotonic()
                for fd, link in fds.items():
                    if fd not in ready:
                        link.read_wall = looked  # nothing came on it up to now
                if self._wake_r in ready:
                    try:
                        os.read(self._wake_r, 4096)
                    except OSError:
                        pass
                order = sorted((fd for fd in ready if fd in fds), key=lambda f: (f <= last_fd, f))
                for i, fd in enumerate(order):
                    if i and time.monotonic() >= next_due:
                        break  # a send is due: it goes first, the rest is read next turn
                    last_fd = fd
                    self._receive(fds[fd], next_due)
        except BaseException as exc:
            self.error = exc

    def _periodic(self, links: list[_Link]) -> float:
        """Send what is due (each stream at most once); return the next deadline (wall)."""
        wall = time.monotonic()
        opts = self.options
        stale = opts.setpoint_stale_s / opts.time_scale  # the vehicle's time
        next_due = wall + 0.05
        warnings = self._warnings
        for link in links:
            if link.down:
                link.reconnect(wall)
                continue
            if link.heartbeat.due(wall):
                link.send(_gcs_heartbeat)
            next_due = min(next_due, link.heartbeat.next)
            for st in list(link.vehicles.values()):
                sp = st.setpoint
                if sp is None or wall - st.setpoint_wall > stale:
                    if not st.stopped:
                        if st.stop is not None:
                            link.send(st.stop)
                        st.health.pause()  # stopped on purpose: no gap
                    st.stopped = True
                    continue
                schedule = st.schedule
                at = st.send_now_at
                if at is not None:
                    st.send_now_at = None
                    schedule.restart(at)
                if schedule.due(wall):
                    link.send(sp)
                    sent = time.monotonic()
                    st.last_sent_wall = sent
                    if st.send_times is not None:
                        st.send_times.append(sent)
                    warning = st.health.sent(sent)
                    if warning is not None:
                        warnings.append((st, warning))
                next_due = min(next_due, schedule.next)
        return next_due

    def _receive(self, link: _Link, until: float) -> None:
        """Read what ``link`` has, up to :data:`RECEIVE_BUDGET` messages (UDP: datagrams), and
        stop early at ``until`` (a send falls due) once a few have been read."""
        conn = link.conn
        transport = link.address.transport
        n = 0
        while n < RECEIVE_BUDGET:
            if link.down:
                return
            if n >= 8 and time.monotonic() >= until:
                return
            if transport in ("udp", "udpout"):  # whole datagrams, each filed with its sender
                try:
                    data, addr = conn.port.recvfrom(65535)
                except (BlockingIOError, InterruptedError):
                    link.read_wall = time.monotonic()  # read to the end
                    return
                except ConnectionRefusedError:  # an ICMP error of an earlier send
                    n += 1
                    continue
                except OSError:
                    return
                n += 1
                sender = addr if transport == "udp" else None  # udpout: one fixed peer
                for msg in conn.mav.parse_buffer(data) or ():
                    self._file(link, msg, sender)
            elif transport == "tcp":  # a chunk of the stream; a partial frame stays buffered
                try:
                    data = conn.recv(4096)
                except (OSError, ConnectionError):
                    return
                if not data:
                    link.read_wall = time.monotonic()
                    return  # nothing more, or the peer closed it (_Link._closed)
                msgs = conn.mav.parse_buffer(data) or ()
                n += max(1, len(msgs))
                for msg in msgs:
                    self._file(link, msg)
            else:
                try:
                    msg = conn.recv_msg()
                except (OSError, ConnectionError):
                    return
                if msg is None:
                    link.read_wall = time.monotonic()
                    return
                n += 1
                self._file(link, msg)

    def _file(self, link: _Link, msg: Any, addr: tuple[str, int] | None = None) -> None:
        """File one message into its vehicle's state. ``addr``: the UDP address it came from;
        only an address an autopilot's HEARTBEAT came from is answered (and heard)."""
        kind = msg.get_type()
        if kind == "BAD_DATA":  # signing refusals are counted by pymavlink's signing state;
            return  # other bytes (a SITL's boot banner on its serial port) are not messages
        if addr is not None and addr not in link.conn.clients:
            if kind != "HEARTBEAT" or msg.type == mavlink.MAV_TYPE_GCS:
                return  # a stranger: not heard, not answered
            if autopilot_of(msg.autopilot) is None:
                return
            with link.lock:  # the mission's sends iterate the clients under the lock
                link.conn.clients.add(addr)
                link.conn.clients_last_alive[addr] = time.time()
        src = msg.get_srcSystem()
        st = link.vehicles.get(src)
        now = self.clock.now()
        if kind == "HEARTBEAT":
            if st is None:
                ap = autopilot_of(msg.autopilot)
                if ap is None or msg.type == mavlink.MAV_TYPE_GCS:
                    return
                st = _State(
                    src,
                    msg.get_srcComponent(),
                    ap,
                    msg.type,
                    schedule=Deadlines(self._period),
                    health=StreamHealth(self.options.setpoint_hz, self.options.time_scale),
                )
                link.vehicles[src] = st
            elif msg.get_srcComponent() != st.compid:
                return  # a camera, a gimbal... of the same system
            armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            if msg.custom_mode != st.custom_mode or (msg.base_mode ^ st.base_mode) & armed:
                st.changes += 1
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
            st.boot = (msg.time_boot_ms / 1000.0, time.monotonic())
        elif kind == "CURRENT_MODE":  # the mode between two 1 Hz heartbeats (PX4)
            if msg.custom_mode != st.custom_mode:
                st.changes += 1
            st.custom_mode = msg.custom_mode
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
                st.range_m, st.range_below_min = range_reading(
                    msg.current_distance, msg.min_distance, msg.max_distance
                )
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
                pending.answers.append(msg.result)
                pending.event.set()


def range_reading(current_cm: int, min_cm: int, max_cm: int) -> tuple[float | None, bool]:
    """A DISTANCE_SENSOR's ``current_distance`` (cm) as (metres, below its minimum): metres
    only within the sensor's declared [``min_distance``, ``max_distance``]; outside, no
    reading — PX4 SIH sends 65533 cm (above its 10000 cm maximum) while the vehicle sits a few
    cm below its origin on the ground, which taken as real put the ground 655 m below the
    drone and kept it from taking off. UINT16_MAX is MAVLink's "unknown"; a maximum of 0 says
    none was declared. Below the minimum is no distance either, but says the ground is closer
    than the sensor can measure (the vehicle decides what that means: on the ground when its
    autopilot says it has landed)."""
    if current_cm >= 0xFFFF or (max_cm > 0 and current_cm > max_cm):
        return None, False
    if current_cm < min_cm:
        return None, True
    return current_cm / 100.0, False


def _gcs_heartbeat(mav: Any) -> None:
    mav.heartbeat_send(
        mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
    )


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
