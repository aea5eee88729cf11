"""A test transport: duplicate, delay and reorder messages, from a seed, around any link.

A real network can deliver a message twice, late, or after one sent later. The coordinator is
built for that (bid serials, late and stale bids, progress acknowledged and deduplicated:
:mod:`btmission.runtime.coordinator`); these wrappers inject exactly those faults so tests can
show it, around the in-memory bus and the Zenoh links alike:

* :class:`FaultyCoordinatorLink` wraps a :class:`~btmission.links.bus.CoordinatorLink`: what
  the coordinator receives (bids, progress, statuses) and what it sends (announcements,
  assignments, acknowledgements) each pass through a :class:`FaultyStream`;
* :class:`FaultyAgentLink` wraps an :class:`~btmission.links.bus.AgentLink` the same way.

Time is counted in *ticks*, not seconds, so nothing depends on the machine's speed: the
coordinator's side ticks at every :meth:`FaultyCoordinatorLink.drain`, an agent's at every
:meth:`FaultyAgentLink.tick`. A message is delivered at once, or held for 1 to ``max_delay``
ticks; with probability ``duplicate`` a second copy follows (with its own delay); the messages
due at one tick come out in a shuffled order when ``reorder`` is set.

What happens to the ``i``-th message of a stream is :func:`fate` of (faults, stream name, i), and
the order of the ``k``-th tick's batch is :func:`shuffle` of (faults, stream name, k): pure
functions of the seed, so a run that sends the same messages in the same order gets the same
faults (Python's string seeding is stable across processes and ``PYTHONHASHSEED``).
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Progress
from btmission.links.bus import (
    AgentLink,
    AgentStatus,
    Assignment,
    CoordinatorInbox,
    CoordinatorLink,
    ForwardingAgentLink,
    OnAck,
    OnAnnouncement,
    OnAssignment,
    ProgressAck,
)

T = TypeVar("T")


@dataclass(frozen=True)
class Faults:
    """What to inject (probabilities per message) and the seed that decides where."""

    duplicate: float = 0.0
    """Probability that a message is delivered twice."""
    delay: float = 0.0
    """Probability that a copy is held back for 1 … ``max_delay`` ticks."""
    max_delay: int = 2
    reorder: bool = False
    """Shuffle the messages that come out at the same tick."""
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("duplicate", "delay"):
            p = getattr(self, name)
            if not (isinstance(p, (int, float)) and 0.0 <= p <= 1.0):
                raise ValueError(f"{name} must be a probability in [0, 1], got {p!r}")
        if not (isinstance(self.max_delay, int) and self.max_delay >= 1):
            raise ValueError(
                f"max_delay must be a whole number of ticks ≥ 1, got {self.max_delay!r}"
            )

    @property
    def none(self) -> bool:
        """Nothing is injected."""
        return self.duplicate == 0 and self.delay == 0 and not self.reorder


NO_FAULTS = Faults()


@dataclass(frozen=True)
class Fate:
    """What happens to one message: one delay (in ticks, 0 = at once) per delivered copy."""

    delays: tuple[int, ...]

    @property
    def copies(self) -> int:
        return len(self.delays)


def fate(faults: Faults, stream: str, index: int) -> Fate:
    """The fate of message ``index`` (0, 1, …) of ``stream`` under ``faults`` (pure)."""
    if faults.duplicate == 0 and faults.delay == 0:
        return Fate((0,))
    rng = random.Random(f"btmission-faults/{faults.seed}/{stream}/{index}")
    copies = 2 if rng.random() < faults.duplicate else 1
    delays = []
    for _ in range(copies):
        held = rng.random() < faults.delay
        delays.append(rng.randint(1, faults.max_delay) if held else 0)
    return Fate(tuple(delays))


def shuffle(faults: Faults, stream: str, tick: int, n: int) -> list[int]:
    """The order (a permutation of ``range(n)``) of the ``n`` messages due at ``tick`` (pure)."""
    order = list(range(n))
    if faults.reorder and n > 1:
        random.Random(f"btmission-faults/{faults.seed}/{stream}/order/{tick}").shuffle(order)
    return order


@dataclass
class FaultStats:
    """What a stream did to its messages."""

    messages: int = 0
    duplicated: int = 0
    delayed: int = 0
    reordered: int = 0
    """Ticks whose batch came out in another order than it went in."""
    delivered: int = 0


@dataclass
class FaultyStream(Generic[T]):
    """One direction of a link under :class:`Faults`: :meth:`push` messages in, :meth:`due`
    takes what is delivered at the current tick, :meth:`advance` moves to the next tick."""

    faults: Faults
    name: str
    tick: int = 0
    stats: FaultStats = field(default_factory=FaultStats)
    _held: list[tuple[int, int, T]] = field(default_factory=list)
    _seq: int = 0

    def push(self, msg: T) -> None:
        f = fate(self.faults, self.name, self.stats.messages)
        self.stats.messages += 1
        self.stats.duplicated += f.copies - 1
        for d in f.delays:
            self.stats.delayed += d > 0
            self._held.append((self.tick + d, self._seq, msg))
            self._seq += 1

    def due(self) -> list[T]:
        """The messages delivered now (in their shuffled order when reordering)."""
        now = [h for h in self._held if h[0] <= self.tick]
        if not now:
            return []
        self._held = [h for h in self._held if h[0] > self.tick]
        now.sort(key=lambda h: (h[0], h[1]))  # in order of sending, the late ones first
        order = shuffle(self.faults, self.name, self.tick, len(now))
        self.stats.reordered += order != sorted(order)
        self.stats.delivered += len(now)
        return [now[i][2] for i in order]

    def advance(self) -> None:
        self.tick += 1

    @property
    def held(self) -> int:
        """Copies waiting for a later tick."""
        return len(self._held)


Outgoing = Announcement | Assignment | ProgressAck
Incoming = Bid | Progress | AgentStatus


class FaultyCoordinatorLink:
    """A :class:`~btmission.links.bus.CoordinatorLink` whose traffic goes through
    :class:`Faults` (module docstring). One tick per :meth:`drain`."""

    def __init__(self, inner: CoordinatorLink, faults: Faults) -> None:
        self.inner = inner
        self.faults = faults
        self.incoming: FaultyStream[Incoming] = FaultyStream(faults, "to-coordinator")
        self.outgoing: FaultyStream[Outgoing] = FaultyStream(faults, "from-coordinator")
        self.sent = 0
        """Messages passed on to the inner link (copies included)."""

    def _send(self, msg: Outgoing) -> None:
        self.outgoing.push(msg)
        self._flush()

    def _flush(self) -> None:
        for m in self.outgoing.due():
            self.sent += 1
            if isinstance(m, Announcement):
                self.inner.announce(m)
            elif isinstance(m, Assignment):
                self.inner.assign(m)
            else:
                self.inner.acknowledge(m)

    def announce(self, announcement: Announcement) -> None:
        self._send(announcement)

    def assign(self, assignment: Assignment) -> None:
        self._send(assignment)

    def acknowledge(self, ack: ProgressAck) -> None:
        self._send(ack)

    def drain(self) -> CoordinatorInbox:
        """What the inner link received, through the faults; then the next tick (held
        outgoing messages due then are sent)."""
        got = self.inner.drain()
        arrived: list[Incoming] = [*got.bids, *got.progress, *got.statuses]
        for m in arrived:
            self.incoming.push(m)
        out = CoordinatorInbox(late_bids=got.late_bids)
        for m in self.incoming.due():
            if isinstance(m, Bid):
                out.bids.append(m)
            elif isinstance(m, Progress):
                out.progress.append(m)
            else:
                out.statuses.append(m)
        self.incoming.advance()
        self.outgoing.advance()
        self._flush()
        return out

    @property
    def held(self) -> int:
        return self.incoming.held + self.outgoing.held


class FaultyAgentLink(ForwardingAgentLink):
    """An :class:`~btmission.links.bus.AgentLink` whose traffic goes through
    :class:`Faults` (module docstring). One tick per :meth:`tick`."""

    def __init__(self, inner: AgentLink, faults: Faults) -> None:
        super().__init__(inner)
        self.faults = faults
        name = inner.agent
        self.incoming: FaultyStream[Outgoing] = FaultyStream(faults, f"to-{name}")
        self.outgoing: FaultyStream[Incoming] = FaultyStream(faults, f"from-{name}")
        self._handlers: tuple[OnAnnouncement, OnAssignment, OnAck] | None = None

    def connect(
        self, on_announcement: OnAnnouncement, on_assignment: OnAssignment, on_ack: OnAck
    ) -> None:
        self._handlers = (on_announcement, on_assignment, on_ack)
        self.inner.connect(self._receive, self._receive, self._receive)

    def disconnect(self) -> None:
        self._handlers = None
        self.inner.disconnect()

    def _receive(self, msg: Outgoing) -> None:
        self.incoming.push(msg)
        self._deliver()

    def _deliver(self) -> None:
        for m in self.incoming.due():
            if self._handlers is None:
                continue
            on_announcement, on_assignment, on_ack = self._handlers
            if isinstance(m, Announcement):
                on_announcement(m)
            elif isinstance(m, Assignment):
                on_assignment(m)
            else:
                on_ack(m)

    def _send(self, msg: Incoming) -> None:
        self.outgoing.push(msg)
        self._flush()

    def _flush(self) -> None:
        for m in self.outgoing.due():
            if isinstance(m, Bid):
                self.inner.send_bid(m)
            elif isinstance(m, Progress):
                self.inner.send_progress(m)
            else:
                self.inner.send_status(m)

    def tick(self) -> None:
        """The next tick: held messages due then are delivered and sent."""
        self.incoming.advance()
        self.outgoing.advance()
        self._deliver()
        self._flush()

    def send_bid(self, bid: Bid) -> None:
        self._send(bid)

    def send_progress(self, progress: Progress) -> None:
        self._send(progress)

    def send_status(self, status: AgentStatus) -> None:
        self._send(status)
