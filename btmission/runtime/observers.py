"""Observers that may be slow without slowing the run: :class:`QueuedObserver`.

A run publishes its events on its own thread, to each observer in turn (:class:`~btmission.
runtime.events.EventStream`): an observer that takes long — a live viewer drawing, a socket to a
remote console — would hold the run up. Wrapped in a :class:`QueuedObserver`, it receives the
same events, in the same order, on a thread of its own, from a bounded queue:

* the run only appends to the queue (it never waits for the observer);
* when the queue is full, the events that only say how something *is* make room: a ``pose``
  superseded by a later pose of the same agent (queued or arriving: the arriving event's agent
  first, its oldest pose), else such a ``route``; they are counted
  (:attr:`QueuedObserver.dropped`). Each agent's latest pose and route always reach the
  observer;
* every other event (task, assignment, round, progress, end, ``tree``: its changes are deltas,
  ...) is never dropped: when nothing may be dropped the queue grows past ``maxsize`` rather
  than lose one or block the run (it then holds at most one pose and one route per agent, and
  the events that matter).
* :meth:`QueuedObserver.close` delivers what is queued and joins the thread.

An exception raised by the wrapped observer is kept (:attr:`QueuedObserver.errors`, the first one
in :attr:`QueuedObserver.error`) and delivery goes on with the next event.
"""

from __future__ import annotations

import threading
from collections import Counter, deque

from btmission.runtime.events import Event, Observer

DROPPABLE = ("pose", "route")
"""Kinds a full queue may drop, in this order (module docstring)."""

Key = tuple[str, object]
"""(kind, agent) of a droppable event."""


class _Slot:
    """A queued event; ``event`` None once dropped (it stays in the queue, skipped)."""

    __slots__ = ("event",)

    def __init__(self, event: Event) -> None:
        self.event: Event | None = event


class QueuedObserver:
    """Delivers events to ``observer`` on its own thread through a queue of ``maxsize`` events
    (module docstring). An :class:`~btmission.runtime.events.Observer` itself; a context manager
    (``close()`` on exit)."""

    def __init__(
        self, observer: Observer, maxsize: int = 1000, *, name: str = "", batch_s: float = 0.0
    ) -> None:
        """``batch_s`` > 0: the thread wakes at most every ``batch_s`` s and delivers what has
        arrived since, instead of waking for each event (fewer thread switches taking the GIL
        from the run; an observer that only needs to keep up, like a viewer)."""
        if maxsize < 1:
            raise ValueError(f"maxsize must be at least 1 (got {maxsize})")
        if not batch_s >= 0:
            raise ValueError(f"batch_s must be >= 0 (got {batch_s})")
        self.observer = observer
        self.maxsize = maxsize
        self.batch_s = batch_s
        self._queue: deque[_Slot] = deque()
        self._size = 0  # events in the queue (not dropped)
        self._by_key: dict[Key, deque[_Slot]] = {}  # queued droppable events, oldest first
        self._several: dict[str, set[Key]] = {kind: set() for kind in DROPPABLE}
        """Per droppable kind, the keys with more than one event queued (superseded ones)."""
        self._cond = threading.Condition()
        self._closed = False
        self._busy = False  # the thread is delivering an event taken off the queue
        self.dropped: Counter[str] = Counter()
        """Events dropped (never delivered), by kind."""
        self.delivered = 0
        self.errors = 0
        """Exceptions the wrapped observer raised (each event is delivered once)."""
        self.error: BaseException | None = None
        """The first of them."""
        self._thread = threading.Thread(
            target=self._deliver,
            name=name or f"QueuedObserver({type(observer).__name__})",
            daemon=True,
        )
        self._thread.start()

    # ---------------------------------------------------------------- the run's side
    def on_event(self, event: Event) -> None:
        with self._cond:
            if self._closed:
                self.dropped[event.kind] += 1
                return
            key = (event.kind, event.get("agent")) if event.kind in DROPPABLE else None
            if self._size >= self.maxsize:
                self._make_room(key)
            slot = _Slot(event)
            self._queue.append(slot)
            self._size += 1
            if len(self._queue) > 2 * max(self._size, self.maxsize):  # mostly dropped slots
                self._queue = deque(s for s in self._queue if s.event is not None)
            if key is not None:
                same = self._by_key.setdefault(key, deque())
                same.append(slot)
                if len(same) == 2:
                    self._several[key[0]].add(key)
            if not self.batch_s or self._size >= self.maxsize:
                self._cond.notify()

    def _make_room(self, incoming: Key | None) -> None:
        """Drop the oldest pose superseded by a later pose of its agent — ``incoming``'s agent
        first — else such a route (module docstring). None of them: the queue grows."""
        for kind in DROPPABLE:
            if incoming is not None and incoming[0] == kind and incoming in self._by_key:
                self._drop_oldest(incoming)
                return
            if self._several[kind]:
                self._drop_oldest(next(iter(self._several[kind])))
                return

    def _drop_oldest(self, key: Key) -> None:
        slot = self._forget(key)
        assert slot.event is not None
        self.dropped[slot.event.kind] += 1
        slot.event = None
        self._size -= 1

    def _forget(self, key: Key) -> _Slot:
        """Take the oldest queued event of ``key`` off its index."""
        same = self._by_key[key]
        slot = same.popleft()
        if len(same) == 1:
            self._several[key[0]].discard(key)
        elif not same:
            del self._by_key[key]
        return slot

    @property
    def queued(self) -> int:
        """Events waiting to be delivered."""
        with self._cond:
            return self._size

    # ---------------------------------------------------------------- the observer's side
    def _deliver(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait(self.batch_s or None)
                if not self._queue:  # closed and drained
                    self._cond.notify_all()
                    return
                ev = self._queue.popleft().event
                if ev is None:  # dropped
                    continue
                self._size -= 1
                if ev.kind in DROPPABLE:
                    self._forget((ev.kind, ev.get("agent")))
                self._busy = True
            try:
                self.observer.on_event(ev)
            except Exception as exc:  # the observer's problem: it must not stop delivery
                with self._cond:
                    self.errors += 1
                    if self.error is None:
                        self.error = exc
            finally:
                with self._cond:
                    self._busy = False
                    self.delivered += 1
                    self._cond.notify_all()

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every queued event has been delivered (False: ``timeout`` s passed)."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._size and not self._busy, timeout)

    def close(self, timeout: float | None = None) -> None:
        """Deliver what is queued, then stop the thread (events published later are dropped
        and counted). Waits at most ``timeout`` s for the observer (None: as long as it takes)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout)

    def __enter__(self) -> QueuedObserver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
