"""The coordinator ↔ agent links over Eclipse Zenoh (the ``net`` extra).

:class:`ZenohCoordinatorLink` is a :class:`~btmission.links.bus.CoordinatorLink` and
:class:`ZenohAgentLink` an :class:`~btmission.links.bus.AgentLink`, each over a Zenoh session.
They carry exactly the :mod:`btmission.links.wire` encodings (versioned JSON) on the keys of
:mod:`btmission.transport.keys`, so any program that speaks Zenoh can listen in or take part.

Receiving. Zenoh runs subscriber callbacks on its own threads, where calling Zenoh again or
blocking is not allowed. So a callback only checks and decodes the message and queues it:

* the coordinator's bids, progress reports and statuses wait in a thread-safe inbox that
  :meth:`ZenohCoordinatorLink.drain` empties (as :class:`~btmission.links.bus.InMemoryBus`'s);
  :meth:`ZenohCoordinatorLink.wait` waits (bounded) for something to arrive;
* an agent's announcements, assignments and acknowledgements wait in its :class:`Mailbox`;
  :meth:`ZenohAgentLink.dispatch` hands them to the agent's handlers in the calling thread (the
  agent's own loop), which may then send (a bid answering an announcement). Agents that share a
  process may share a mailbox, so one loop serves them all. Predictions are kept per agent
  (the latest) for :meth:`ZenohAgentLink.predictions`.

A payload that is over ``BTMISSION_MAX_MESSAGE_BYTES``, is not a valid message, is of another
kind than its key's channel, or names another agent than its key is dropped and counted
(:class:`LinkStats`); a callback never raises.

Assignments. The coordinator's link embeds the announcement in an assignment only when it is
another announcement than the one the previous assignment carried, and every
``embed_every``-th assignment; the others name it (epoch and serial, wire format 2). The
announcement is also published every round, so an agent that (re)connects has it after one
round; an assignment naming an announcement the agent has not seen is dropped and counted
(``unresolved``), and the next one is followed.

Congestion. When Zenoh's queue towards a peer is full, the coordinator's publications
(announcements, assignments, acknowledgements) are dropped after a short wait (Zenoh's
``wait_before_drop``, 1 ms), never blocking its loop on a slow agent: each is repeated (the
announcement and an assignment every round; an acknowledgement answers every copy of a progress
report, which the agent resends until acknowledged). An agent's bids, progress and statuses
wait for room (block, bounded by Zenoh's ``wait_before_close``, after which the connection is
closed and opened again); its predictions are dropped (the next one replaces them).

Link loss. As with the in-memory bus, :meth:`ZenohAgentLink.set_link` cuts an agent off (for
tests and drills): messages both ways are dropped and counted, and :attr:`ZenohAgentLink.up` is
False. ``up`` is also False while the coordinator's liveliness token is not seen (its session
is gone, or the network between them is).

Sessions. :class:`ZenohSettings` builds the Zenoh configuration: explicit ``listen`` and
``connect`` endpoints (the coordinator listens on ``tcp/127.0.0.1:7447`` by default, agents
connect to it as clients), multicast and gossip scouting off unless asked for, optionally a
Zenoh JSON5 file for TLS, authentication and access control. Every wait is bounded: opening a
session (``connect_timeout_s``), :meth:`ZenohCoordinatorLink.wait`,
:meth:`ZenohAgentLink.dispatch`. See docs/distributed.md.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
import threading
from collections import deque
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, Final, cast

import numpy as np

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Progress
from btmission.errors import BtmissionError
from btmission.limits import MAX_MESSAGE_BYTES
from btmission.links import wire
from btmission.links.bus import (
    AgentStatus,
    Assignment,
    CoordinatorInbox,
    MissionEnd,
    OnAck,
    OnAnnouncement,
    OnAssignment,
    Prediction,
    ProgressAck,
    advance_predictions,
)
from btmission.transport import keys
from btmission.types import FloatArray

if TYPE_CHECKING:
    import zenoh

NEEDS_NET: Final = (
    "the Zenoh transport needs the net extra: pip install 'btmission[net]' (make installs it)"
)
DEFAULT_PORT: Final = 7447
DEFAULT_ENDPOINT: Final = f"tcp/127.0.0.1:{DEFAULT_PORT}"
MODES: Final = ("peer", "client")
EMBED_EVERY: Final = 10
"""The coordinator's link embeds the announcement in at least every 10th assignment."""


class TransportError(BtmissionError, RuntimeError):
    """The transport cannot do what was asked (the text says why and what to do)."""


class ZenohMissing(TransportError):
    """eclipse-zenoh is not installed (:data:`NEEDS_NET`)."""


def zenoh_available() -> bool:
    """Whether eclipse-zenoh can be imported (without importing it)."""
    return importlib.util.find_spec("zenoh") is not None


def import_zenoh() -> ModuleType:
    """The ``zenoh`` module, or :class:`ZenohMissing` saying how to install it."""
    try:
        import zenoh
    except ImportError:
        raise ZenohMissing(NEEDS_NET) from None
    return zenoh


def _bounded(timeout_s: float, what: str = "timeout_s") -> float:
    t = float(timeout_s)
    if not (math.isfinite(t) and t >= 0):
        raise ValueError(f"{what} must be a finite number of seconds ≥ 0, got {timeout_s!r}")
    return t


# ------------------------------------------------------------------------------------ config
_ENDPOINT = re.compile(r"[a-z][a-z0-9-]*/\S+")


def check_endpoint(endpoint: str) -> str:
    """``endpoint`` if it looks like a Zenoh endpoint ``<protocol>/<address>`` (e.g.
    ``tcp/127.0.0.1:7447``, ``tls/base.local:7447``), else :class:`ValueError`."""
    if not isinstance(endpoint, str) or not _ENDPOINT.fullmatch(endpoint):
        raise ValueError(
            f"{endpoint!r} is not a Zenoh endpoint (expected <protocol>/<address>, e.g. "
            f"{DEFAULT_ENDPOINT})"
        )
    return endpoint


def loopback(port: int = DEFAULT_PORT, protocol: str = "tcp") -> str:
    """``tcp/127.0.0.1:<port>`` (port 0: one the system picks)."""
    if not (isinstance(port, int) and 0 <= port <= 65535):
        raise ValueError(f"port must be 0-65535, got {port!r}")
    return f"{protocol}/127.0.0.1:{port}"


def is_loopback(endpoint: str) -> bool:
    """Whether ``endpoint``'s address is a loopback one (127.x.x.x, localhost, [::1])."""
    address = endpoint.split("/", 1)[-1].split("#", 1)[0].split("?", 1)[0]
    host = address.rsplit(":", 1)[0] if not address.startswith("[") else address[1:].split("]")[0]
    return host == "localhost" or host == "::1" or host.startswith("127.")


@dataclass(frozen=True)
class ZenohSettings:
    """How to open a Zenoh session (module docstring). The defaults are a coordinator's:
    :meth:`coordinator` and :meth:`agent` give each side's."""

    mode: str = "peer"
    """``peer`` (the coordinator; agents in a mesh) or ``client`` (an agent of a star)."""
    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Endpoints to accept sessions on (ignored in client mode)."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to."""
    multicast_scouting: bool = False
    """Find other sessions by UDP multicast (Zenoh's default; off here unless asked for)."""
    gossip_scouting: bool = False
    """Learn other peers' locators from connected ones (a mesh of peers needs it)."""
    config_file: str | None = None
    """A Zenoh JSON5 configuration to start from (TLS, authentication, access control ...); the
    settings above override its mode, endpoints and scouting."""
    options: tuple[tuple[str, str], ...] = ()
    """Raw ``(key, JSON5 value)`` configuration entries, applied last (as zenoh's ``--cfg``)."""
    connect_timeout_s: float = 5.0
    """A client waits this long for one of its ``connect`` endpoints, then opening fails."""
    shared_memory: bool = True
    """Let sessions on one host pass large payloads through shared memory (Zenoh's default)."""
    admin_space: bool = False
    """Serve Zenoh's read-only admin space (``@/<zid>/**``): :func:`locators` needs it."""

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        for ep in (*self.listen, *self.connect):
            check_endpoint(ep)
        if self.mode == "client" and not self.connect:
            raise ValueError("a client needs at least one connect endpoint")
        _bounded(self.connect_timeout_s, "connect_timeout_s")
        if self.config_file is not None and not Path(self.config_file).is_file():
            raise ValueError(f"Zenoh config file {self.config_file} does not exist")

    @classmethod
    def coordinator(cls, listen: Iterable[str] = (DEFAULT_ENDPOINT,), **kw: Any) -> ZenohSettings:
        """A coordinator: a peer listening on ``listen``."""
        return cls(mode="peer", listen=tuple(listen), **kw)

    @classmethod
    def agent(cls, connect: Iterable[str] = (DEFAULT_ENDPOINT,), **kw: Any) -> ZenohSettings:
        """An agent: a client of the coordinator at ``connect`` (it routes for its clients, so
        predictions reach the other agents through it)."""
        return cls(mode="client", listen=(), connect=tuple(connect), **kw)

    def with_(self, **changes: Any) -> ZenohSettings:
        return replace(self, **changes)

    def entries(self) -> list[tuple[str, str]]:
        """The configuration entries these settings write, as ``(key, JSON5 value)``."""
        out = [
            ("mode", json.dumps(self.mode)),
            ("listen/endpoints", json.dumps(list(self.listen) if self.mode == "peer" else [])),
            ("connect/endpoints", json.dumps(list(self.connect))),
            ("scouting/multicast/enabled", json.dumps(self.multicast_scouting)),
            ("scouting/gossip/enabled", json.dumps(self.gossip_scouting)),
        ]
        if self.mode == "client":
            out.append(("connect/timeout_ms", json.dumps(round(self.connect_timeout_s * 1000))))
        if not self.shared_memory:
            out.append(("transport/shared_memory/enabled", "false"))
        if self.admin_space:
            out.append(("adminspace/enabled", "true"))
            out.append(("adminspace/permissions", '{"read": true, "write": false}'))
        return out + list(self.options)

    def config(self) -> zenoh.Config:
        """The :class:`zenoh.Config` (:class:`TransportError` for a bad entry or file)."""
        z = import_zenoh()
        try:
            cfg = z.Config.from_file(self.config_file) if self.config_file else z.Config()
        except Exception as exc:
            raise TransportError(f"Zenoh config file {self.config_file}: {exc}") from None
        for k, v in self.entries():
            try:
                cfg.insert_json5(k, v)
            except Exception as exc:
                raise TransportError(f"Zenoh configuration {k} = {v}: {exc}") from None
        return cast("zenoh.Config", cfg)


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """A Zenoh session for ``settings``; :class:`TransportError` (with the endpoints) when it
    cannot be opened, e.g. a port already taken or no coordinator to connect to."""
    z = import_zenoh()
    cfg = settings.config()
    try:
        return cast("zenoh.Session", z.open(cfg))
    except Exception as exc:
        where = ", ".join(
            [f"listen {ep}" for ep in settings.listen if settings.mode == "peer"]
            + [f"connect {ep}" for ep in settings.connect]
        )
        raise TransportError(
            f"cannot open a Zenoh session ({settings.mode}; {where or 'no endpoints'}): "
            f"{_first_line(exc)}"
        ) from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    first = text[0] if text else type(exc).__name__
    return re.sub(r"\s+at /\S+\.rs:\d+\.?$", "", first)  # Zenoh appends its source location


def locators(session: zenoh.Session, timeout_s: float = 2.0) -> list[str]:
    """The endpoints ``session`` accepts connections on, from its admin space (open it with
    ``admin_space=True``). :class:`TransportError` when the admin space does not answer."""
    zid = str(session.zid())
    for reply in session.get(f"@/{zid}/*", timeout=_bounded(timeout_s)):
        ok = reply.ok
        if ok is None or str(ok.key_expr).rsplit("/", 1)[-1] not in ("peer", "client", "router"):
            continue
        try:
            info = json.loads(ok.payload.to_bytes())
        except ValueError:
            continue
        return [str(x) for x in info.get("locators", [])]
    raise TransportError(
        "the session's admin space did not answer: open it with ZenohSettings(admin_space=True)"
    )


# ------------------------------------------------------------------------------------ plumbing
_KIND_OF: Final[dict[type, str]] = {
    Announcement: "announcement",
    Bid: "bid",
    Assignment: "assignment",
    AgentStatus: "status",
    Progress: "progress",
    ProgressAck: "ack",
    Prediction: "prediction",
    MissionEnd: "end",
}


@dataclass
class LinkStats:
    """What a link sent and received, and what it dropped and why (thread-safe counters)."""

    sent: int = 0
    sent_bytes: int = 0
    received: int = 0
    received_bytes: int = 0
    oversized: int = 0
    """Payloads over ``BTMISSION_MAX_MESSAGE_BYTES`` (not parsed)."""
    malformed: int = 0
    """Payloads that are not a valid message (:class:`~btmission.links.wire.WireError`)."""
    mismatched: int = 0
    """Valid messages of another kind than their key's channel, or naming another agent."""
    cut: int = 0
    """Messages dropped both ways while the link was cut (:meth:`ZenohAgentLink.set_link`)."""
    unresolved: int = 0
    """Assignments naming an announcement this end has not seen (the next one is awaited)."""
    overflow: int = 0
    """Messages dropped because the receiving queue was full (nobody drains it)."""
    errors: int = 0
    """Anything else that went wrong in a callback (counted; the callback never raises)."""
    last_problem: str = ""
    """The text of the last drop (which key, which check)."""
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    @property
    def dropped(self) -> int:
        return (
            self.oversized
            + self.malformed
            + self.mismatched
            + self.unresolved
            + self.cut
            + self.overflow
            + self.errors
        )

    def count(self, name: str, problem: str = "") -> None:
        with self._lock:
            setattr(self, name, getattr(self, name) + 1)
            if problem:
                self.last_problem = problem

    def add(self, name: str, n: int) -> None:
        with self._lock:
            setattr(self, name, getattr(self, name) + n)

    def snapshot(self) -> dict[str, int | str]:
        with self._lock:
            return {
                k: getattr(self, k)
                for k in (
                    "sent",
                    "sent_bytes",
                    "received",
                    "received_bytes",
                    "oversized",
                    "malformed",
                    "mismatched",
                    "unresolved",
                    "cut",
                    "overflow",
                    "errors",
                    "last_problem",
                )
            }


class DecodeCache:
    """Decodes payloads, reusing the last announcement seen: the coordinator repeats one
    announcement every round and inside every assignment, and decoding 400 tasks takes ~2 ms
    (:func:`btmission.links.wire.decode`'s ``known``: only an exact encoding of it is reused).
    Agents sharing a process share one, so a broadcast is decoded about once, not once per
    agent. Messages are immutable: sharing one is what the in-memory bus does too.

    It also keeps the last ``keep`` announcements seen, which an assignment that does not embed
    its own may name (an assignment can arrive after the next announcement: Zenoh orders each
    key, not the keys between them)."""

    def __init__(self, keep: int = 8) -> None:
        self.keep = keep
        self.recent: tuple[Announcement, ...] = ()
        """The last announcements seen, the latest first."""
        self.reused = 0

    @property
    def known(self) -> Announcement | None:
        """The last announcement seen."""
        recent = self.recent
        return recent[0] if recent else None

    def decode(self, data: bytes) -> wire.Message:
        recent = self.recent
        msg = wire.decode(data, recent)
        ann = msg if isinstance(msg, Announcement) else getattr(msg, "announcement", None)
        if isinstance(ann, Announcement):
            if any(a is ann for a in recent):  # reused, or named by an assignment
                self.reused += 1
            else:  # one tuple replaces another: safe for Zenoh's threads without a lock
                self.recent = (ann, *recent)[: self.keep]
        return msg


SHARED_DECODER = DecodeCache()
"""The process-wide :class:`DecodeCache` agent links use unless given their own."""


def _check(
    data: bytes, key: str, stats: LinkStats, decode: Callable[[bytes], wire.Message]
) -> tuple[keys.Parsed, wire.Message] | None:
    """The parsed key and message of a sample, or None (counted in ``stats``) if it must be
    dropped. Never raises."""
    try:
        size = len(data)
        if size > MAX_MESSAGE_BYTES.limit:
            stats.count("oversized", f"{key}: {MAX_MESSAGE_BYTES.exceeded('the payload', size)}")
            return None
        parsed = keys.parse(key)
        try:
            msg = decode(data)
        except wire.UnknownAnnouncement as exc:
            stats.count("unresolved", f"{key}: {exc}")
            return None
        except wire.WireError as exc:
            stats.count("malformed", f"{key}: {exc}")
            return None
        kind = _KIND_OF.get(type(msg))
        if kind != parsed.kind:
            stats.count("mismatched", f"{key}: a {kind} message on the {parsed.channel} channel")
            return None
        agent = getattr(msg, "agent", None)
        if parsed.agent is not None and agent != parsed.agent:
            stats.count("mismatched", f"{key}: a {kind} of agent {agent!r}")
            return None
        stats.count("received")
        stats.add("received_bytes", size)
        return parsed, msg
    except keys.KeyExprError as exc:
        stats.count("malformed", str(exc))
    except Exception as exc:  # a callback must not raise into Zenoh
        stats.count("errors", f"{key}: {type(exc).__name__}: {exc}")
    return None


def _payload(sample: Any) -> bytes:
    return bytes(sample.payload.to_bytes())


class Mailbox:
    """Messages waiting for their handler, filled by Zenoh's threads and emptied by
    :meth:`dispatch` in the caller's (thread-safe, bounded: past ``limit`` the oldest is
    dropped and counted in ``overflow``)."""

    def __init__(self, limit: int = 10_000) -> None:
        self.limit = limit
        self._items: deque[tuple[Callable[[Any], None], Any]] = deque()
        self._cond = threading.Condition()
        self.overflow = 0

    def put(self, handler: Callable[[Any], None], msg: Any) -> None:
        with self._cond:
            if len(self._items) >= self.limit:
                self._items.popleft()
                self.overflow += 1
            self._items.append((handler, msg))
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    def wake(self) -> None:
        """Wake a thread waiting in :meth:`wait` or :meth:`dispatch` (something else changed)."""
        with self._cond:
            self._cond.notify_all()

    def wait(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a message; whether one is waiting."""
        with self._cond:
            return self._cond.wait_for(lambda: bool(self._items), _bounded(timeout_s))

    def dispatch(self, timeout_s: float = 0.0) -> int:
        """Hand every waiting message to its handler, here; if none is waiting, wait up to
        ``timeout_s`` for the first. Returns how many were handled. A handler's exception
        propagates (it is the caller's code); the messages after it stay queued."""
        timeout_s = _bounded(timeout_s)
        with self._cond:
            if not self._items and timeout_s > 0:
                self._cond.wait_for(lambda: bool(self._items), timeout_s)
            n = len(self._items)
        done = 0
        for _ in range(n):
            with self._cond:
                if not self._items:
                    break
                handler, msg = self._items.popleft()
            handler(msg)
            done += 1
        return done


_BLOCK, _DROP = "block", "drop"
"""Congestion control of a publisher: wait for room in a full queue (an agent's bids, progress
and statuses), or drop the message (the coordinator's publications and the predictions: each is
repeated or replaced; module docstring)."""


class _Session:
    """A session and whether the link owns (and so closes) it."""

    def __init__(self, session: zenoh.Session | None, settings: ZenohSettings | None) -> None:
        if (session is None) == (settings is None):
            raise ValueError("give either an open session or the settings to open one")
        self.owned = session is None
        self.session: zenoh.Session = session if session is not None else open_session(settings)  # type: ignore[arg-type]
        self.z = import_zenoh()

    def publisher(self, key: str, congestion: str) -> Any:
        cc = (
            self.z.CongestionControl.BLOCK
            if congestion == _BLOCK
            else self.z.CongestionControl.DROP
        )
        # not ``express``: Zenoh may then batch a burst (50 statuses from one session) instead
        # of queueing one batch per message, which overflowed the queue in the benchmark
        return self.session.declare_publisher(key, congestion_control=cc)

    def close(self, declared: Iterable[Any]) -> None:
        for obj in declared:
            try:
                obj.undeclare()
            except Exception:  # already gone with a closed session
                pass
        if self.owned and not self.session.is_closed():
            self.session.close()


# ------------------------------------------------------------------------------------ coordinator
class ZenohCoordinatorLink:
    """The coordinator's side over Zenoh (module docstring): a
    :class:`~btmission.links.bus.CoordinatorLink`.

    ``session``: an open session the link uses (and does not close); or ``settings`` to open
    one it owns (default: :meth:`ZenohSettings.coordinator`). ``max_pending`` bounds the inbox
    (messages past it are dropped and counted in ``stats.overflow``). ``embed_every``: an
    assignment carries its announcement when that changed since the previous assignment and
    at least every ``embed_every`` assignments (1: always); the others name it by serial.
    """

    def __init__(
        self,
        mission: str,
        session: zenoh.Session | None = None,
        settings: ZenohSettings | None = None,
        *,
        max_pending: int = 100_000,
        embed_every: int = EMBED_EVERY,
    ) -> None:
        self.mission = keys.check_name(mission, "mission")
        if not (isinstance(embed_every, int) and embed_every >= 1):
            raise ValueError(f"embed_every must be a whole number ≥ 1, got {embed_every!r}")
        self.embed_every = embed_every
        self._embedded: Announcement | None = None
        self._since_embedded = 0
        if session is None and settings is None:
            settings = ZenohSettings.coordinator()
        self._s = _Session(session, settings)
        self.session = self._s.session
        self.stats = LinkStats()
        self.max_pending = max_pending
        self._cond = threading.Condition()
        self._inbox = CoordinatorInbox()
        self._pending = 0
        self._waiting: list[Callable[[CoordinatorInbox], bool]] = []
        self._closed = False
        self._agents: set[str] = set()
        self._encoded: tuple[Announcement, bytes] | None = None
        self._declared: list[Any] = []
        try:
            self._announce = self._s.publisher(keys.key(mission, keys.ANNOUNCE), _DROP)
            self._assign = self._s.publisher(keys.key(mission, keys.ASSIGN), _DROP)
            self._end = self._s.publisher(keys.key(mission, keys.END), _BLOCK)
            self._declared += [self._announce, self._assign, self._end]
            self._acks: dict[str, Any] = {}
            for channel in keys.TO_COORDINATOR:
                self._declared.append(
                    self.session.declare_subscriber(
                        keys.every_agent(mission, channel), self._on_sample
                    )
                )
            live = self.session.liveliness()
            self._declared.append(live.declare_token(keys.coordinator_token(mission)))
            self._declared.append(
                live.declare_subscriber(keys.agent_tokens(mission), self._on_agent, history=True)
            )
        except Exception:
            self.close()
            raise

    # ---------------------------------------------------------------- Zenoh's threads
    def _on_sample(self, sample: Any) -> None:
        if self._closed:
            return
        got = _check(_payload(sample), str(sample.key_expr), self.stats, wire.decode)
        if got is None:
            return
        msg = got[1]
        with self._cond:
            if self._pending >= self.max_pending:
                self.stats.count("overflow", f"inbox full ({self.max_pending} messages)")
                return
            if isinstance(msg, Bid):
                self._inbox.bids.append(msg)
            elif isinstance(msg, Progress):
                self._inbox.progress.append(msg)
            elif isinstance(msg, AgentStatus):
                self._inbox.statuses.append(msg)
            self._pending += 1
            # wake a waiting thread only when what it waits for holds (not for each of 50 bids)
            if not self._waiting or any(self._holds(w) for w in self._waiting):
                self._cond.notify_all()

    def _on_agent(self, sample: Any) -> None:
        try:
            agent = str(sample.key_expr).rsplit("/", 1)[-1]
            put = sample.kind == self._s.z.SampleKind.PUT
            with self._cond:
                (self._agents.add if put else self._agents.discard)(agent)
                self._cond.notify_all()
        except Exception as exc:
            self.stats.count("errors", f"liveliness: {exc}")

    # ---------------------------------------------------------------- CoordinatorLink
    def announce(self, announcement: Announcement) -> None:
        """To every agent (the encoding of an unchanged announcement is reused)."""
        cached = self._encoded
        if cached is not None and cached[0] is announcement:
            data = cached[1]
        else:
            data = wire.encode(announcement)
            self._encoded = (announcement, data)
        self._put(self._announce, data)

    def assign(self, assignment: Assignment) -> None:
        """To every agent: with its announcement when that is another than the previous
        assignment's, or ``embed_every`` assignments went without; else naming it."""
        ann = assignment.announcement
        self._since_embedded += 1
        embed = ann is not self._embedded or self._since_embedded >= self.embed_every
        if embed:
            self._embedded, self._since_embedded = ann, 0
        self._put(self._assign, wire.encode(assignment, embed=embed))

    def end(self, end: MissionEnd) -> None:
        """Tell every agent the mission is over (their processes stop)."""
        self._put(self._end, wire.encode(end))

    def acknowledge(self, ack: ProgressAck) -> None:
        pub = self._acks.get(ack.agent)
        if pub is None:
            pub = self._s.publisher(keys.key(self.mission, keys.ACK, ack.agent), _DROP)
            self._acks[ack.agent] = pub
            self._declared.append(pub)
        self._put(pub, wire.encode(ack))

    def _put(self, publisher: Any, data: bytes) -> None:
        if self._closed:
            raise TransportError("the coordinator's Zenoh link is closed")
        publisher.put(data)
        self.stats.count("sent")
        self.stats.add("sent_bytes", len(data))

    def drain(self) -> CoordinatorInbox:
        """Bids, progress and statuses that arrived since the last call (in arrival order)."""
        with self._cond:
            inbox, self._inbox = self._inbox, CoordinatorInbox()
            self._pending = 0
        return inbox

    # ---------------------------------------------------------------- waiting
    def wait(self, until: Callable[[CoordinatorInbox], bool], timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until ``until(pending inbox)`` holds (it is called under the
        link's lock, on what :meth:`drain` would return; it must not keep it). Returns whether
        it held."""
        timeout_s = _bounded(timeout_s)
        with self._cond:
            self._waiting.append(until)
            try:
                return self._cond.wait_for(lambda: until(self._inbox), timeout_s)
            finally:
                self._waiting.remove(until)

    def _holds(self, until: Callable[[CoordinatorInbox], bool]) -> bool:
        try:
            return until(self._inbox)
        except Exception:  # the waiter's predicate: it will raise in its own thread
            return True

    def wait_for_bids(self, serial: int, agents: int | Collection[str], timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until bids answering announcement ``serial`` are pending
        from ``agents`` (a number of distinct agents, or these ids)."""

        def enough(inbox: CoordinatorInbox) -> bool:
            have = {b.agent for b in inbox.bids if b.serial == serial}
            return len(have) >= agents if isinstance(agents, int) else have.issuperset(agents)

        return self.wait(enough, timeout_s)

    @property
    def agents(self) -> frozenset[str]:
        """The agents whose liveliness token is seen (their session is up and reachable)."""
        with self._cond:
            return frozenset(self._agents)

    def wait_for_agents(self, agents: Collection[str], timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until every one of ``agents`` is :attr:`agents`."""
        want = set(agents)
        with self._cond:
            return self._cond.wait_for(lambda: want <= self._agents, _bounded(timeout_s))

    def close(self) -> None:
        """Undeclare everything; close the session if the link opened it. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._s.close(reversed(getattr(self, "_declared", [])))

    def __enter__(self) -> ZenohCoordinatorLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ------------------------------------------------------------------------------------ agent
class ZenohAgentLink:
    """One agent's side over Zenoh (module docstring): an
    :class:`~btmission.links.bus.AgentLink`.

    ``session`` / ``settings`` as for :class:`ZenohCoordinatorLink` (default settings:
    :meth:`ZenohSettings.agent`). Several agents of one process may share a session and a
    ``mailbox`` (then one :meth:`dispatch` serves them all). Call :meth:`dispatch` from the
    agent's loop: the handlers given to :meth:`connect` run there.
    """

    def __init__(
        self,
        mission: str,
        agent: str,
        session: zenoh.Session | None = None,
        settings: ZenohSettings | None = None,
        *,
        mailbox: Mailbox | None = None,
        decoder: DecodeCache | None = None,
    ) -> None:
        self.mission = keys.check_name(mission, "mission")
        self._agent = keys.check_name(agent, "agent id")
        if session is None and settings is None:
            settings = ZenohSettings.agent()
        self._s = _Session(session, settings)
        self.session = self._s.session
        self.stats = LinkStats()
        self.mailbox = mailbox if mailbox is not None else Mailbox()
        self._decoder = decoder if decoder is not None else SHARED_DECODER
        self._lock = threading.Lock()
        self._cut = False
        self._coordinator = threading.Event()
        self._closed = False
        self._handlers: tuple[OnAnnouncement, OnAssignment, OnAck] | None = None
        self._predictions: dict[str, Prediction] = {}
        self.ended: MissionEnd | None = None
        """The coordinator's end of the mission, once it has arrived (set on Zenoh's thread)."""
        self._declared: list[Any] = []
        self._connected: list[Any] = []
        try:
            m = mission
            self._bids = self._s.publisher(keys.key(m, keys.BIDS, agent), _BLOCK)
            self._progress = self._s.publisher(keys.key(m, keys.PROGRESS, agent), _BLOCK)
            self._status = self._s.publisher(keys.key(m, keys.STATUS, agent), _BLOCK)
            self._predict = self._s.publisher(keys.key(m, keys.PREDICT, agent), _DROP)
            self._declared += [self._bids, self._progress, self._status, self._predict]
            self._declared.append(
                self.session.liveliness().declare_subscriber(
                    keys.coordinator_token(m), self._on_coordinator, history=True
                )
            )
        except Exception:
            self.close()
            raise

    @property
    def agent(self) -> str:
        return self._agent

    @property
    def up(self) -> bool:
        """Not cut (:meth:`set_link`) and the coordinator's liveliness token is seen."""
        return not self._cut and self._coordinator.is_set()

    @property
    def coordinator_seen(self) -> bool:
        """The coordinator's liveliness token is seen (whatever :meth:`set_link` says)."""
        return self._coordinator.is_set()

    def set_link(self, up: bool) -> None:
        """Cut (``up=False``) or restore this agent's link, as
        :meth:`~btmission.links.bus.InMemoryBus.set_link` does: while cut, messages both ways
        are dropped (counted in ``stats.cut``)."""
        self._cut = not up

    # ---------------------------------------------------------------- AgentLink
    def connect(
        self, on_announcement: OnAnnouncement, on_assignment: OnAssignment, on_ack: OnAck
    ) -> None:
        """Subscribe; the coordinator's messages go to these handlers at :meth:`dispatch`."""
        if self._closed:
            raise TransportError(f"agent {self._agent}'s Zenoh link is closed")
        self.disconnect()
        self._handlers = (on_announcement, on_assignment, on_ack)
        m, a = self.mission, self._agent
        subs = [
            (keys.key(m, keys.ANNOUNCE), self._on_message),
            (keys.key(m, keys.ASSIGN), self._on_message),
            (keys.key(m, keys.ACK, a), self._on_message),
            (keys.key(m, keys.END), self._on_end),
            (keys.every_agent(m, keys.PREDICT), self._on_prediction),
        ]
        for k, cb in subs:
            self._connected.append(self.session.declare_subscriber(k, cb))
        self._connected.append(self.session.liveliness().declare_token(keys.agent_token(m, a)))

    def disconnect(self) -> None:
        """Stop receiving (and withdraw the agent's liveliness token)."""
        self._handlers = None
        connected, self._connected = self._connected, []
        for obj in reversed(connected):
            try:
                obj.undeclare()
            except Exception:
                pass
        with self._lock:
            self._predictions.clear()

    def send_bid(self, bid: Bid) -> None:
        self._put(self._bids, bid)

    def send_progress(self, progress: Progress) -> None:
        self._put(self._progress, progress)

    def send_status(self, status: AgentStatus) -> None:
        self._put(self._status, status)

    def share_prediction(self, time_s: float, positions: FloatArray) -> None:
        """Publish this agent's predicted positions (to every agent of the mission)."""
        pred = Prediction(self._agent, time_s, np.asarray(positions, dtype=float))
        self._put(self._predict, pred)

    def predictions(
        self,
        time_s: float,
        step_s: float,
        near: FloatArray | None = None,
        within_m: float = math.inf,
    ) -> list[FloatArray]:
        """The other agents' latest predictions
        (:func:`~btmission.links.bus.advance_predictions`)."""
        with self._lock:
            shared = dict(self._predictions)
        return advance_predictions(shared, self._agent, time_s, step_s, near, within_m)

    def _put(self, publisher: Any, msg: wire.Message) -> None:
        if self._closed:
            raise TransportError(f"agent {self._agent}'s Zenoh link is closed")
        if self._cut:
            self.stats.count("cut")
            return
        data = wire.encode(msg)
        publisher.put(data)
        self.stats.count("sent")
        self.stats.add("sent_bytes", len(data))

    # ---------------------------------------------------------------- receiving
    def dispatch(self, timeout_s: float = 0.0) -> int:
        """Hand the waiting messages to the handlers, in this thread (:meth:`Mailbox.dispatch`:
        waits up to ``timeout_s`` for the first). With a shared mailbox, every agent's."""
        return self.mailbox.dispatch(timeout_s)

    def _on_message(self, sample: Any) -> None:
        if self._closed:
            return
        got = _check(_payload(sample), str(sample.key_expr), self.stats, self._decoder.decode)
        if got is None:
            return
        if self._cut:
            self.stats.count("cut")
            return
        handlers = self._handlers
        if handlers is None:
            return
        parsed, msg = got
        on_announcement, on_assignment, on_ack = handlers
        handler: Callable[[Any], None] = (
            on_announcement
            if parsed.channel == keys.ANNOUNCE
            else on_assignment
            if parsed.channel == keys.ASSIGN
            else on_ack
        )
        before = self.mailbox.overflow
        self.mailbox.put(handler, msg)
        if self.mailbox.overflow != before:
            self.stats.count("overflow", "mailbox full: call dispatch() from the agent's loop")

    def _on_end(self, sample: Any) -> None:
        if self._closed:
            return
        got = _check(_payload(sample), str(sample.key_expr), self.stats, self._decoder.decode)
        if got is not None and isinstance(got[1], MissionEnd) and not self._cut:
            self.ended = got[1]
            self.mailbox.wake()

    def _on_prediction(self, sample: Any) -> None:
        if self._closed or self._cut:
            return
        got = _check(_payload(sample), str(sample.key_expr), self.stats, self._decoder.decode)
        if got is None:
            return
        msg = got[1]
        if isinstance(msg, Prediction) and msg.agent != self._agent:
            with self._lock:
                self._predictions[msg.agent] = msg

    def _on_coordinator(self, sample: Any) -> None:
        try:
            if sample.kind == self._s.z.SampleKind.PUT:
                self._coordinator.set()
            else:
                self._coordinator.clear()
        except Exception as exc:
            self.stats.count("errors", f"liveliness: {exc}")

    def wait_for_coordinator(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until the coordinator's liveliness token is seen."""
        return self._coordinator.wait(_bounded(timeout_s))

    def close(self) -> None:
        """Disconnect, undeclare everything; close the session if the link opened it."""
        if self._closed:
            return
        self._closed = True
        self.disconnect()
        self._s.close(reversed(getattr(self, "_declared", [])))

    def __enter__(self) -> ZenohAgentLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def agent_links(
    mission: str,
    agents: Iterable[str],
    settings: ZenohSettings | None = None,
    *,
    shared_session: bool = False,
) -> list[ZenohAgentLink]:
    """Links for ``agents`` of one process sharing one mailbox: each with its own session
    (as on separate robots), or all on one (``shared_session``; the caller closes it with
    :func:`close_all`)."""
    settings = settings if settings is not None else ZenohSettings.agent()
    mailbox = Mailbox()
    links: list[ZenohAgentLink] = []
    session = open_session(settings) if shared_session else None
    try:
        for a in agents:
            if session is None:
                links.append(ZenohAgentLink(mission, a, settings=settings, mailbox=mailbox))
            else:
                links.append(ZenohAgentLink(mission, a, session, mailbox=mailbox))
        if session is not None and links:
            links[0]._s.owned = True  # it closes the session (close_all closes it last)
    except Exception:
        close_all(links)
        raise
    finally:
        if session is not None and not links:
            session.close()
    return links


def close_all(links: Iterable[ZenohAgentLink | ZenohCoordinatorLink]) -> None:
    """Close ``links`` (the owner of a shared session last)."""
    items = list(links)
    for link in sorted(items, key=lambda lk: lk._s.owned):
        link.close()


__all__ = [
    "DEFAULT_ENDPOINT",
    "NEEDS_NET",
    "DecodeCache",
    "LinkStats",
    "Mailbox",
    "TransportError",
    "ZenohAgentLink",
    "ZenohCoordinatorLink",
    "ZenohMissing",
    "ZenohSettings",
    "agent_links",
    "check_endpoint",
    "close_all",
    "import_zenoh",
    "is_loopback",
    "locators",
    "loopback",
    "open_session",
    "zenoh_available",
]
