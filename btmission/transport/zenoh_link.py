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
* an agent's announcements, assignments and acknowledgements wait in its
  :class:`~btmission.transport.zenoh_plumbing.Mailbox`; :meth:`ZenohAgentLink.dispatch` hands them to the agent's handlers in the calling thread (the
  agent's own loop), which may then send (a bid answering an announcement). Agents that share a
  process may share a mailbox, so one loop serves them all. Predictions are kept per agent
  (the latest) for :meth:`ZenohAgentLink.predictions`.

A payload that is over ``BTMISSION_MAX_MESSAGE_BYTES``, is not a valid message, is of another
kind than its key's channel, or names another agent than its key is dropped and counted
(:class:`~btmission.transport.zenoh_plumbing.LinkStats`); a callback never raises.

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

Sessions. :class:`~btmission.transport.zenoh_session.ZenohSettings` builds the Zenoh
configuration: explicit ``listen`` and ``connect`` endpoints (the coordinator listens on
``tcp/127.0.0.1:7447`` by default, agents connect to it as clients), multicast and gossip
scouting off unless asked for, optionally a Zenoh JSON5 file for TLS, authentication and access
control. Every wait is bounded: opening a session (``connect_timeout_s``),
:meth:`ZenohCoordinatorLink.wait`, :meth:`ZenohAgentLink.dispatch`. See docs/distributed.md.

This module holds the two links and :func:`agent_links` / :func:`close_all`. The sessions, their
settings, the transport's errors and the endpoint helpers are
:mod:`btmission.transport.zenoh_session`; what both links share underneath (the checks of what
arrives, the counters, the decode cache, the mailbox, the publishers) is
:mod:`btmission.transport.zenoh_plumbing`.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Collection, Iterable
from typing import TYPE_CHECKING, Any, Final

import numpy as np

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Progress
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
from btmission.transport.zenoh_plumbing import (
    _BLOCK,
    _DROP,
    SHARED_DECODER,
    DecodeCache,
    LinkStats,
    Mailbox,
    _check,
    _payload,
    _Session,
)
from btmission.transport.zenoh_session import (
    TransportError,
    ZenohSettings,
    _bounded,
    open_session,
)
from btmission.types import FloatArray

if TYPE_CHECKING:
    import zenoh

EMBED_EVERY: Final = 10
"""The coordinator's link embeds the announcement in at least every 10th assignment."""


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

    def share_prediction(
        self, time_s: float, positions: FloatArray, velocity: FloatArray | None = None
    ) -> None:
        """Publish this agent's predicted positions (to every agent of the mission). The wire's
        ``prediction`` message has no velocity yet: ``velocity`` is dropped, and the other
        agents' separation rule takes this one's as unknown (no credit for moving away)."""
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
    "ZenohAgentLink",
    "ZenohCoordinatorLink",
    "agent_links",
    "close_all",
]
