"""Connecting a fleet of MAVLink vehicles at once (the ``mavlink`` provider's ``attach_all``).

Connected one after the other (issue #36), ten vehicles took 9.2-9.8 s on a quiet machine,
14-73 s under load, and thirty gave up. Each vehicle's turn began by opening its link (when the
caller had not opened them all first) and waiting for its autopilot's next HEARTBEAT, which comes
once a second: the turns fell in step with it, a second each. Then came eight request/answer
round trips in turn (a simulator step or a radio's latency each), the estimator's report, and
only then the next vehicle. Here every vehicle's connect is a small state machine
(:class:`_Connect`), and one loop in the caller's thread advances all of them until each is
connected or the run's ``connect_timeout_s`` is over, so a fleet connects in about the time of its
slowest vehicle: up to a second for the heartbeat, then a round trip or two.
Each vehicle, concurrently with the others:

1. **link** — its link opens (on a helper thread per link, :class:`_Opening`: a TCP connect is
   retried, 0.1 s doubling to 1 s, until the vehicle listens; a host that does not answer
   blocks no other vehicle);
2. **heartbeat** — its autopilot's HEARTBEAT (the ``?sysid=`` one, else the first not taken, in
   the mission's order), of the type the agent's library flies or drives. With a signing key,
   a vehicle whose messages all fail the signature check (or come unsigned) is never heard:
   once :data:`SIGNING_VERDICT_MIN` of them have been refused over :data:`SIGNING_VERDICT_S`
   with none passing, its connect stops, saying so (a wrong key, not a vehicle that is off);
3. **requests** — every telemetry stream (SET_MESSAGE_INTERVAL) and HOME_POSITION
   (REQUEST_MESSAGE) sent at once rather than one round trip after another. COMMAND_ACK names
   the command, not the request: the answers to one batch are told apart by their order (a
   vehicle answers a link's commands in the order sent,
   :class:`~btmission.backends.mavlink_requests._Commands`). A batch not fully answered is sent again after ``ack_timeout_s``, then twice and four times that
   (``command_retries`` more sends) — one request at a time once some of its answers came but
   not all (which one was lost is unknown). A vehicle that answers none is heard but does not
   answer commands (a signing key missing or wrong): that stops the connect at once;
4. **telemetry** — LOCAL_POSITION_NED; while none comes, its stream is asked for again after 1,
   2, 4 ... s (at most 8 s apart);
5. **estimator** — EKF_STATUS_REPORT (ArduPilot) or ESTIMATOR_STATUS (PX4) with a relative
   position. A vehicle that reports neither within 2 s of being asked is taken as it is; one
   still not ready at the deadline is taken anyway (its arming refusals will say why);
6. **origin** (only with the world's ``origin``) — GPS_GLOBAL_ORIGIN asked; a vehicle without
   one (no GPS: underground) is sent SET_GPS_GLOBAL_ORIGIN, again after 1 s, and its
   confirmation waited for 2 s.

A long connect prints who is connected and who still waits, for what (after 2 s, then every
5 s); at the deadline the error names every vehicle that did not connect and what it lacked.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from btmission.backends._pymavlink import CURRENT_MODE_ID, mavlink
from btmission.backends.mavlink_frames import GeodeticOrigin, LocalFrame, world_to_geodetic
from btmission.backends.mavlink_link import (
    ESTIMATOR_STREAM,
    GROUND_TYPES,
    MULTIROTOR_TYPES,
    STREAMS,
    MavlinkError,
    MavlinkOptions,
    _Link,
    _LinkIO,
    _open,
    _Pending,
    _State,
)
from btmission.backends.mavlink_modes import ack_of
from btmission.backends.mavlink_requests import _Commands, _Request
from btmission.backends.mavlink_signing import rejections
from btmission.backends.mavlink_url import MavlinkAddress, parse_mavlink_url
from btmission.backends.mavlink_vehicle import MavlinkVehicle
from btmission.types import FloatArray
from btmission.vehicles.base import VehicleKind
from btmission.vehicles.clock import ScaledWallClock
from btmission.vehicles.provider import AttachRequest

POLL_S = (0.005, 0.02)
"""How often the connect loop looks at every vehicle (wall seconds): the I/O thread files what
arrives meanwhile, so this only bounds how late a step of a connect follows its cause — the
first, then (a connect still going after :data:`NOTE_AFTER_S` waits for something slow: an EKF,
a vehicle being switched on) the second."""
NOTE_AFTER_S = 2.0
NOTE_EVERY_S = 5.0
"""A connect still going after :data:`NOTE_AFTER_S` says who waits for what, then every
:data:`NOTE_EVERY_S`."""
ESTIMATOR_QUIET_S = 2.0
"""A vehicle that sends no estimator report this long after being asked is taken as it is."""
RETRY_STREAM_S = (1.0, 8.0)
"""While no LOCAL_POSITION_NED comes, its stream is asked again after the first, doubling up to
the second (wall seconds)."""
ORIGIN_WAIT_S = 1.0
"""How long a vehicle that accepted the request has to send its GPS_GLOBAL_ORIGIN."""
ORIGIN_CONFIRM_S = 2.0
"""How long SET_GPS_GLOBAL_ORIGIN is waited for (sent again after half of it)."""
SIGNING_VERDICT_S = 3.0
SIGNING_VERDICT_MIN = 3
"""A vehicle not heard whose messages the link refused (signed with another key, or unsigned
when a key is given), at least :data:`SIGNING_VERDICT_MIN` of them over
:data:`SIGNING_VERDICT_S` wall seconds with none passing, fails its connect then, naming the
cause, instead of waiting out ``connect_timeout_s`` for a heartbeat (a heartbeat once a second
gives three in three seconds)."""
OPEN_RETRY_S = (0.1, 1.0)
"""A TCP link that refuses is tried again after the first, doubling up to the second."""


@dataclass(frozen=True)
class ConnectTimes:
    """When one vehicle's connect reached its steps: wall seconds since ``attach_all`` began."""

    heard_s: float
    """Its first HEARTBEAT was heard (and claimed)."""
    requested_s: float
    """Its first request (a telemetry stream) went out."""
    connected_s: float
    """It was connected."""


class _Opening:
    """One link being opened on a helper thread (a TCP connect may block; each is retried,
    :data:`OPEN_RETRY_S`, until it opens or the connect is over)."""

    def __init__(self, address: MavlinkAddress, options: MavlinkOptions) -> None:
        self.address = address
        self.options = options
        self.conn: Any = None
        self.error = ""
        """Why the last try failed (a UDP port in use, a TCP connection refused)."""
        self.done = threading.Event()
        """Set when the link is open (:attr:`conn`) or cannot be (anything but TCP: its first
        failure is final; :attr:`error`)."""
        self._cancel = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"mavlink-open {address.device()}", daemon=True
        )
        self._thread.start()

    def _run(self) -> None:
        delay = OPEN_RETRY_S[0]
        while not self._cancel.is_set():
            try:
                conn = _open(self.address, self.options, -math.inf)  # one try
            except MavlinkError as exc:
                self.error = str(exc)
                if self.address.transport != "tcp":
                    self.done.set()
                    return
                self._cancel.wait(delay)
                delay = min(OPEN_RETRY_S[1], 2 * delay)
                continue
            except Exception as exc:  # pymavlink's own errors: say them, do not die silently
                self.error = f"cannot open {self.address.url()}: {exc}"
                self.done.set()
                return
            if self._cancel.is_set():
                conn.close()  # the connect is over: nobody will use it
                return
            self.conn = conn
            self.done.set()
            return

    def cancel(self) -> None:
        """Stop retrying (a link opened after this is closed at once)."""
        self._cancel.set()


@dataclass
class _Connect:
    """One vehicle's connect (module docstring): :meth:`advance` does what can be done now."""

    request: AttachRequest
    address: MavlinkAddress
    fleet: FleetConnect
    link: _Link | None = None
    state: _State | None = None
    vehicle: MavlinkVehicle | None = None
    requests: list[_Request] = field(default_factory=list)
    """Every request made while connecting."""
    commands: dict[int, _Commands] = field(default_factory=dict)
    position_request: _Request | None = None
    next_position_ask: float = math.inf
    position_ask_wait: float = RETRY_STREAM_S[0]
    estimator_request: _Request | None = None
    origin_request: _Request | None = None
    mode_requests: list[_Request] = field(default_factory=list)
    """A faster HEARTBEAT and CURRENT_MODE: how its mode changes are seen sooner."""
    origin_sent_wall: float = -math.inf
    origin_sends: int = 0
    origin_settled: bool = False
    heard_wall: float = math.inf
    signing_base: tuple[dict[int, int], int] = ({}, 0)
    """The link's signing refusals when this connect got it (:func:`rejections`)."""
    refused_since: float = math.inf
    """When this connect first saw its vehicle's messages refused by the signing check."""
    requested_wall: float = math.inf
    done_wall: float = math.inf
    announced: bool = False

    @property
    def agent(self) -> str:
        return self.request.agent_id

    @property
    def done(self) -> bool:
        return self.done_wall < math.inf

    # ------------------------------------------------------------------ steps
    def advance(self, wall: float) -> None:
        """One look at this vehicle: open, claim, send what is due, read the answers, and note
        when it is connected. Raises :class:`MavlinkError` when it cannot be had at all."""
        if self.done:
            return
        if self.link is None:
            try:
                self.link = self.fleet.link(self.address)
            except MavlinkError as exc:
                raise MavlinkError(f"{self.agent}: {exc}") from None
            if self.link is None:
                return
            self.signing_base = rejections(self.link.conn)
        if self.state is None:
            self.state = self._heard()
            if self.state is None:
                self._signing_verdict(wall)
                return
            self.heard_wall = wall
            self._claim(self.state)
        vehicle = self.vehicle
        assert vehicle is not None
        for commands in self.commands.values():
            commands.step(wall, lambda r: vehicle._send_command(r.command, r.params, r.sends))
        self.requested_wall = min(c.first_sent for c in self.commands.values())
        if not self.answered and all(r.settled for r in self.requests):
            raise MavlinkError(self._silent())
        self._ask_position(wall)
        self._origin(wall)
        if self._ready(wall, final=False):
            self.done_wall = wall

    def _signing_refused(self) -> tuple[int, bool]:
        """How many of this vehicle's messages the signing check refused since the connect got
        the link, and whether they were unsigned (else signed with another key). Bad signatures
        count per sender: the ``?sysid=`` one, else any not heard on the link. Unsigned ones
        name no sender: they count only on a link where no vehicle is heard at all."""
        link = self.link
        if link is None or self.fleet.options.signing_key is None:
            return 0, False
        bad, unsigned = rejections(link.conn)
        base_bad, base_unsigned = self.signing_base
        sysid = self.address.sysid
        senders = [sysid] if sysid is not None else [s for s in bad if s not in link.vehicles]
        n_bad = sum(bad.get(s, 0) - base_bad.get(s, 0) for s in senders)
        n_unsigned = unsigned - base_unsigned if not link.vehicles else 0
        return (n_unsigned, True) if n_unsigned > n_bad else (n_bad, False)

    def _signing_verdict(self, wall: float) -> None:
        """Stop the connect of a vehicle whose messages are all refused by the signing check
        (:data:`SIGNING_VERDICT_S`): raises :class:`MavlinkError` naming the cause."""
        n, _ = self._signing_refused()
        if n == 0:
            return
        self.refused_since = min(self.refused_since, wall)
        if n >= SIGNING_VERDICT_MIN and wall - self.refused_since >= SIGNING_VERDICT_S:
            raise MavlinkError(self._signing_failure(wall - self.refused_since))

    def _signing_failure(self, seconds: float | None = None) -> str:
        """The signing check refused this vehicle's messages: which way, and what to check
        (``seconds``: over how long, when the verdict came before the connect's deadline)."""
        n, unsigned = self._signing_refused()
        where = f"{self.agent} ({self.address.url()})"
        sysid = f" from sysid {self.address.sysid}" if self.address.sysid is not None else ""
        during = (
            f"within {self.fleet.options.connect_timeout_s:g} s"
            if seconds is None
            else f"in {seconds:.0f} s"
        )
        if unsigned:
            return (
                f"{where}: its messages are not signed ({n}{sysid} refused {during}), "
                "and a signing key is given (--mavlink-key-file): set the same key up on the "
                "vehicle (SETUP_SIGNING), or run without a key"
            )
        return (
            f"{where}: its messages are signed with another key ({n}{sysid} rejected "
            f"{during}); check --mavlink-key-file / the vehicle's key"
        )

    def _heard(self) -> _State | None:
        """The autopilot this agent gets on its link, once heard (claimed in the mission's
        order: :meth:`FleetConnect.connect` advances the agents in it)."""
        link, address = self.link, self.address
        assert link is not None
        if address.sysid is not None:
            st = link.vehicles.get(address.sysid)
            if st is not None and address.sysid in link.claimed:
                raise MavlinkError(
                    f"{self.agent}: sysid {address.sysid} at {address.url()} is already "
                    "another agent's vehicle"
                )
            if st is not None and (address.compid is None or st.compid == address.compid):
                return st
            return None
        free = [s for sid, s in sorted(link.vehicles.items()) if sid not in link.claimed]
        return free[0] if free else None

    def _claim(self, st: _State) -> None:
        """Take the vehicle, check its type, and queue the requests (module docstring, 3)."""
        link = self.link
        assert link is not None
        link.claimed.add(st.sysid)
        kind, url = self.request.kind, self.address.url()
        if kind is VehicleKind.MULTIROTOR and st.mav_type not in MULTIROTOR_TYPES:
            raise MavlinkError(
                f"{self.agent}: the vehicle at {url} (sysid {st.sysid}) is a "
                f"{type_name(st.mav_type)}, but the agent's library flies a multirotor"
            )
        if kind is VehicleKind.GROUND and st.mav_type not in GROUND_TYPES:
            raise MavlinkError(
                f"{self.agent}: the vehicle at {url} (sysid {st.sysid}) is a "
                f"{type_name(st.mav_type)}, but the agent's library drives a ground robot"
            )
        fleet = self.fleet
        start = self.request.start
        frame = fleet.frames.get(self.agent) or LocalFrame(
            (float(start[0]), float(start[1]), float(start[2]))
        )
        self.vehicle = MavlinkVehicle(
            self.agent, kind, link, st, frame, fleet.clock, fleet.options, fleet.ground_at,
            fleet.io.wake,
        )  # fmt: skip
        for command in (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_REQUEST_MESSAGE):
            pending = st.pending[command] = _Pending(command)
            self.commands[command] = _Commands(pending, fleet.options, self._refused)
        interval_us = 1e6 / fleet.options.telemetry_hz
        for msg_id in STREAMS:
            r = self._stream(msg_id, interval_us)
            if msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
                self.position_request = r
        self.estimator_request = self._stream(ESTIMATOR_STREAM[st.autopilot], 5e5)
        # modes seen within a telemetry period: CURRENT_MODE where the autopilot has it (PX4
        # refuses a faster HEARTBEAT), else a 5 Hz HEARTBEAT (ArduPilot)
        self.mode_requests = [
            self._stream(mavlink.MAVLINK_MSG_ID_HEARTBEAT, 2e5),
            self._stream(CURRENT_MODE_ID, interval_us),
        ]
        self._add(self._message(mavlink.MAVLINK_MSG_ID_HOME_POSITION))
        if fleet.geodetic is not None:
            self.origin_request = self._message(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
            self._add(self.origin_request)
        else:
            self.origin_settled = True

    def _stream(self, msg_id: int, interval_us: float) -> _Request:
        r = _Request(
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (float(msg_id), interval_us),
            f"stream {message_name(msg_id)}",
        )  # fmt: skip
        self._add(r)
        return r

    def _add(self, r: _Request) -> None:
        self.requests.append(r)
        self.commands[r.command].queue.append(r)

    @property
    def answered(self) -> bool:
        """The vehicle answered a command (it hears them: the signing key is right)."""
        return any(c.answered for c in self.commands.values())

    def _refused(self, r: _Request, result: int) -> None:
        if r in self.mode_requests:  # one of the two is enough: said only when both fail
            if all(
                m.settled and m.result != mavlink.MAV_RESULT_ACCEPTED for m in self.mode_requests
            ):
                self.fleet.note(
                    f"{self.agent}: modes are seen at the autopilot's own HEARTBEAT rate (neither "
                    "a faster HEARTBEAT nor CURRENT_MODE is available)"
                )
            return
        if r is not self.origin_request:  # (a vehicle without an origin: it gets one)
            self.fleet.note(
                f"{self.agent}: {r.what} not available ({ack_of(r.command, result).reason})"
            )

    @staticmethod
    def _message(msg_id: int) -> _Request:
        return _Request(
            mavlink.MAV_CMD_REQUEST_MESSAGE, (float(msg_id),), f"message {message_name(msg_id)}"
        )

    def _ask_position(self, wall: float) -> None:
        """Ask for LOCAL_POSITION_NED again while none comes (1 s, doubling to 8 s)."""
        st, first = self.state, self.position_request
        assert st is not None and first is not None
        if st.position is not None or not first.settled:
            return
        if self.next_position_ask == math.inf:
            self.next_position_ask = first.settled_wall + self.position_ask_wait
        if wall < self.next_position_ask:
            return
        self._add(_Request(first.command, first.params, first.what))
        self.position_ask_wait = min(RETRY_STREAM_S[1], 2 * self.position_ask_wait)
        self.next_position_ask = wall + self.position_ask_wait

    def _origin(self, wall: float) -> None:
        """Module docstring, 6: ask for the vehicle's global origin, else give it the world's
        (sent again after half of :data:`ORIGIN_CONFIRM_S`, confirmed or not after all of it)."""
        if self.origin_settled:
            return
        st, asked, geodetic = self.state, self.origin_request, self.fleet.geodetic
        vehicle = self.vehicle
        assert st is not None and asked is not None and geodetic is not None
        assert vehicle is not None
        lat, lon, alt = world_to_geodetic(vehicle.frame.origin, geodetic)
        if st.global_origin is not None:
            self.origin_settled = True
            if self.origin_sends:  # the one it was given, confirmed
                self._origin_note(lat, lon, alt, "confirmed")
            return  # else it has one (its GPS, or set before)
        if not asked.settled:
            return
        if (
            asked.result == mavlink.MAV_RESULT_ACCEPTED
            and wall < asked.settled_wall + ORIGIN_WAIT_S
        ):
            return  # it may be sending it
        since = wall - self.origin_sent_wall
        if self.origin_sends >= 2 and since >= ORIGIN_CONFIRM_S:
            self.origin_settled = True
            self._origin_note(lat, lon, alt, "not confirmed")
            return
        if self.origin_sends == 0 or (self.origin_sends == 1 and since >= ORIGIN_CONFIRM_S / 2):
            sysid = st.sysid
            vehicle.link.send(
                lambda mav: mav.set_gps_global_origin_send(
                    sysid, round(lat * 1e7), round(lon * 1e7), round(alt * 1000), 0
                )
            )
            if self.origin_sends == 0:
                self.origin_sent_wall = wall
            self.origin_sends += 1

    def _origin_note(self, lat: float, lon: float, alt: float, said: str) -> None:
        self.fleet.note(
            f"{self.agent}: global origin set to {lat:.7f}, {lon:.7f}, {alt:.1f} m ({said})"
        )

    # ------------------------------------------------------------------ where it stands
    def _estimator_ok(self, wall: float) -> bool:
        """Ready, or silent about it :data:`ESTIMATOR_QUIET_S` after being asked."""
        vehicle, st, asked = self.vehicle, self.state, self.estimator_request
        assert vehicle is not None and st is not None and asked is not None
        if vehicle.estimator_ready():
            return True
        reported = st.ekf_flags is not None or st.estimator_ok is not None
        return not reported and asked.settled and wall >= asked.settled_wall + ESTIMATOR_QUIET_S

    def _ready(self, wall: float, *, final: bool) -> bool:
        """Connected: heard, answering, a position, its requests settled, its estimator ready
        (or silent) and its origin settled. ``final`` (the deadline): heard, answering and a
        position are enough."""
        st = self.state
        if st is None or not self.answered or st.position is None:
            return False
        if final:
            return True
        return (
            all(r.settled for r in self.requests)
            and self._estimator_ok(wall)
            and self.origin_settled
        )

    def lacks(self, wall: float) -> str:
        """What it waits for now, in a few words."""
        st = self.state
        if self.link is None:
            error = self.fleet.open_error(self.address)
            error = error.removeprefix(f"cannot open {self.address.url()}: ")  # (said: its URL)
            return f"its link ({error})" if error else "its link to open"
        if st is None:
            return "a heartbeat"
        if not self.answered:
            return "an answer to its commands"
        if st.position is None:
            return "telemetry (LOCAL_POSITION_NED)"
        if not self._estimator_ok(wall):
            return "its estimator (EKF) to have a position"
        if not self.origin_settled:
            return "its global origin to be confirmed"
        return "answers to its requests"

    def failure(self) -> str:
        """Why it did not connect by the deadline (what it lacked), naming it."""
        opts, address, st = self.fleet.options, self.address, self.state
        timeout = f"{opts.connect_timeout_s:g} s"
        if self.link is None:
            error = self.fleet.open_error(address) or f"cannot open {address.url()}"
            return f"{self.agent}: {error} (tried for {timeout})"
        if st is None:
            if self._signing_refused()[0] > 0:  # not silent: refused by the signing check
                return self._signing_failure()
            link = self.link
            who = f"sysid {address.sysid}" if address.sysid is not None else "an autopilot"
            seen = sorted(link.vehicles)
            hint = (
                f" (heard sysids {', '.join(map(str, seen))}, all taken)"
                if seen
                else " (is the vehicle on, and is its MAVLink output sent here?)"
            )
            return (
                f"{self.agent}: no heartbeat from {who} at {address.url()} within {timeout}{hint}"
            )
        if not self.answered:
            return self._silent()
        return (
            f"{self.agent}: the vehicle at {address.url()} (sysid {st.sysid}) sends no "
            f"LOCAL_POSITION_NED within {timeout}: it has no local position estimate (an EKF "
            "origin and a position source are needed)"
        )

    def _silent(self) -> str:
        assert self.state is not None
        signing = (
            "the key may differ from the vehicle's"
            if self.fleet.options.signing_key is not None
            else "if it requires MAVLink 2 signing, give its key (--mavlink-key-file)"
        )
        return (
            f"{self.agent}: sysid {self.state.sysid} is heard but does not answer commands "
            f"({signing})"
        )

    def finish(self) -> None:
        """The connect is over: stop filing answers for it (later commands wait their own)."""
        st = self.state
        if st is None:
            return
        for command, commands in self.commands.items():
            if st.pending.get(command) is commands.pending:
                del st.pending[command]


class FleetConnect:
    """The links being opened and the vehicles being connected for one provider (module
    docstring). :meth:`open` starts opening links (``prepare``); :meth:`connect` connects a
    fleet (``attach_all``)."""

    def __init__(
        self,
        io: _LinkIO,
        clock: ScaledWallClock,
        options: MavlinkOptions,
        *,
        frames: Mapping[str, LocalFrame],
        geodetic: GeodeticOrigin | None,
        ground_at: Callable[[FloatArray], float] | None,
        progress: Callable[[str], None] | None,
    ) -> None:
        self.io = io
        self.clock = clock
        self.options = options
        self.frames = frames
        self.geodetic = geodetic
        self.ground_at = ground_at
        self.progress = progress
        self._openings: dict[str, _Opening] = {}
        self.times: dict[str, ConnectTimes] = {}
        """Each connected agent's :class:`ConnectTimes` (its last connect)."""

    def note(self, text: str) -> None:
        if self.progress is not None:
            self.progress(text)

    def open(self, address: MavlinkAddress) -> None:
        """Start opening ``address``'s link, unless it is open or being opened."""
        device = address.device()
        if device not in self.io.links and device not in self._openings:
            self._openings[device] = _Opening(address, self.options)

    def link(self, address: MavlinkAddress) -> _Link | None:
        """``address``'s link once open (None meanwhile). Raises :class:`MavlinkError` when it
        cannot be opened (a UDP port another program holds)."""
        device = address.device()
        link = self.io.links.get(device)
        if link is not None:
            return link
        self.open(address)
        opening = self._openings[device]
        if not opening.done.is_set():
            return None
        if opening.conn is None:
            raise MavlinkError(opening.error)
        del self._openings[device]
        link = _Link(opening.address, opening.conn)
        self.io.add(link)
        return link

    def open_error(self, address: MavlinkAddress) -> str:
        opening = self._openings.get(address.device())
        return opening.error if opening is not None else ""

    def cancel(self, devices: Sequence[str] | None = None) -> None:
        """Stop opening these devices' links (default: all; the provider closes): one still
        retrying stops, one that failed is forgotten (the next connect tries again). A link
        opened but not yet used is kept for a later connect, or closed when all are."""
        for device in list(self._openings) if devices is None else devices:
            opening = self._openings.get(device)
            if opening is None or (devices is not None and opening.conn is not None):
                continue
            opening.cancel()
            del self._openings[device]
            if opening.conn is not None:
                opening.conn.close()

    def connect(
        self,
        requests: Sequence[AttachRequest],
        check_io: Callable[[], None],
    ) -> list[MavlinkVehicle]:
        """Connect every requested vehicle at once (module docstring); their vehicles in the
        order asked. Raises :class:`MavlinkError` with ``failures`` (agent → what it lacked)
        for the vehicles that could not be had."""
        opts = self.options
        began = time.monotonic()
        deadline = began + opts.connect_timeout_s
        jobs = [_Connect(r, parse_mavlink_url(r.ref.url), self) for r in requests]
        for job in jobs:
            self.note(f"{job.agent}: connecting to {job.address.url()}")
        next_note = began + NOTE_AFTER_S
        try:
            while True:
                check_io()
                wall = time.monotonic()
                final = wall >= deadline
                failed: dict[str, str] = {}
                for job in jobs:
                    try:
                        job.advance(wall)
                    except MavlinkError as exc:  # this vehicle cannot be had at all
                        failed[job.agent] = str(exc)
                        continue
                    if not job.done and final and job._ready(wall, final=True):
                        job.done_wall = wall  # what it still lacks is not needed to fly
                        self._late(job, wall)
                    if job.done and not job.announced:
                        job.announced = True
                        self._connected(job, began)
                waiting = [j for j in jobs if not j.done and j.agent not in failed]
                if final and waiting:
                    if len(jobs) > 1:  # (one vehicle's error says it all)
                        self._summary(jobs, wall - began)
                    failed.update({j.agent: j.failure() for j in waiting})
                if failed:
                    raise _failure(failed, jobs)
                if not waiting:
                    return [j.vehicle for j in jobs if j.vehicle is not None]
                if wall >= next_note:
                    self._summary(jobs, wall - began)
                    next_note = wall + NOTE_EVERY_S
                time.sleep(POLL_S[0] if wall - began < NOTE_AFTER_S else POLL_S[1])
        finally:
            for job in jobs:
                job.finish()
            self.cancel([j.address.device() for j in jobs])

    def _connected(self, job: _Connect, began: float) -> None:
        st = job.state
        assert st is not None
        self.times[job.agent] = ConnectTimes(
            job.heard_wall - began, job.requested_wall - began, job.done_wall - began
        )
        self.note(
            f"{job.agent}: {st.autopilot.value} sysid {st.sysid} "
            f"({type_name(st.mav_type)}) at {job.address.url()}"
        )

    def _late(self, job: _Connect, wall: float) -> None:
        """At the deadline a vehicle that has all it needs to fly is taken, saying what it
        still lacked."""
        if not job._estimator_ok(wall):
            self.note(
                f"{job.agent}: the estimator has no usable position yet; arming will be refused "
                "until it has"
            )
        for r in job.requests:
            if not r.settled:
                self.note(f"{job.agent}: no answer to its {r.what} request")

    def _summary(self, jobs: Sequence[_Connect], elapsed: float) -> None:
        """Who is connected and who waits for what."""
        wall = time.monotonic()
        done = [j.agent for j in jobs if j.done]
        by_lack: dict[str, list[str]] = {}
        for j in jobs:
            if not j.done:
                by_lack.setdefault(j.lacks(wall), []).append(j.agent)
        waits = "; ".join(f"{', '.join(agents)} for {what}" for what, agents in by_lack.items())
        self.note(
            f"connecting: {len(done)} of {len(jobs)} vehicle(s) connected after {elapsed:.1f} s"
            + (f"; waiting: {waits}" if waits else "")
        )


def _failure(failed: Mapping[str, str], jobs: Sequence[_Connect]) -> MavlinkError:
    """One error naming every vehicle that could not be had (in the mission's order)."""
    order = [j.agent for j in jobs if j.agent in failed]
    failures = {agent: failed[agent] for agent in order}
    text = "\n".join(failures.values())
    if len(failures) > 1:
        text = f"{len(failures)} of {len(jobs)} vehicles could not be connected:\n{text}"
    return MavlinkError(text, failures)


def type_name(mav_type: int) -> str:
    entry = mavlink.enums["MAV_TYPE"].get(mav_type)
    return entry.name if entry is not None else f"MAV_TYPE {mav_type}"


def message_name(msg_id: int) -> str:
    cls = mavlink.mavlink_map.get(msg_id)
    return cls.msgname if cls is not None else f"message {msg_id}"  # type: ignore[no-any-return]
