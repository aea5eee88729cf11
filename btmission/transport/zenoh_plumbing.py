"""What the Zenoh links share underneath: checking what arrives, counting, queueing, publishing.

Zenoh runs subscriber callbacks on its own threads, where calling Zenoh again or blocking is not
allowed, so a link's callback only checks and decodes a sample (:func:`_check`: size, a valid
message of its key's channel naming its key's agent; a payload that fails is dropped and
counted in the link's :class:`LinkStats`, and a callback never raises) and queues it: an agent's
messages wait in a :class:`Mailbox` that its own loop empties. :class:`DecodeCache` decodes a
repeated announcement once (:data:`SHARED_DECODER`: one per process); ``_Session`` owns (or
borrows) a link's session and declares its publishers, blocking or dropping when Zenoh's queue
is full. The links themselves are :mod:`btmission.transport.zenoh_link`.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Progress
from btmission.limits import MAX_MESSAGE_BYTES
from btmission.links import wire
from btmission.links.bus import (
    AgentStatus,
    Assignment,
    MissionEnd,
    Prediction,
    ProgressAck,
)
from btmission.transport import keys
from btmission.transport.zenoh_session import (
    ZenohSettings,
    _bounded,
    import_zenoh,
    open_session,
)

if TYPE_CHECKING:
    import zenoh

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
    """Messages dropped both ways while the link was cut
    (:meth:`~btmission.transport.zenoh_link.ZenohAgentLink.set_link`)."""
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
repeated or replaced; :mod:`btmission.transport.zenoh_link`'s docstring)."""


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


__all__ = ["SHARED_DECODER", "DecodeCache", "LinkStats", "Mailbox"]
