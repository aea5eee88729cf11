"""What the viewer page is fed: a run's events as compact records, live or from a log.

The page draws everything from one list of records in time order — the log's own JSON form of
the events (``{"t", "ev", ...}``) a viewer needs — whether it watches a live run or replays a
log: the 3D scene, the behaviour trees, the task table and the timeline at any time *T* are
folded from the records up to *T* (``viewer.js``). This module makes that list:

* :func:`view_record` — one event as the viewer's record (None for kinds it does not draw:
  auction rounds that changed nothing, ...); poses keep only what is drawn;
* :func:`replay_records` — a finished run's records from its log, poses thinned so that a long
  run stays within a budget (:data:`REPLAY_POSE_BUDGET`);
* :class:`LiveFeed` — an :class:`~btmission.runtime.events.Observer` of a running mission (put
  it behind a :class:`~btmission.runtime.observers.QueuedObserver`: the run never waits for it)
  that keeps the records so far for pages that connect late, and samples the agents' poses
  from the run's immutable snapshots at :attr:`LiveFeed.pose_hz` (the log's ``pose`` events
  come at ``runtime.status_hz``, 2 Hz by default: too coarse to watch). A page reads it with a
  cursor (:meth:`LiveFeed.read`): the records it has not seen, and every agent's latest pose.
  A page that reads slowly gets bigger batches, never a backlog: poses between two reads are
  kept in the history only every :attr:`LiveFeed.pose_history_s`, the latest pose always, and
  task events never dropped.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from btmission.runtime.eventkinds import (
    AgentLostEvent,
    AgentTaskEvent,
    BuiltEvent,
    CollisionEvent,
    CommandEvent,
    CommittedEvent,
    EndEvent,
    HeaderEvent,
    LeafErrorEvent,
    LinkEvent,
    ObjectsEvent,
    PoseEvent,
    ProgressEvent,
    RelocalizedEvent,
    RoundEvent,
    RouteEvent,
    SignalEvent,
    StageEvent,
    TaskAddedEvent,
    TaskStateEvent,
    TreeEvent,
    VehicleLinkEvent,
    WarningEvent,
    WithdrawnEvent,
)
from btmission.runtime.events import (
    Event,
    TypedEvent,
    event_class,
)

Record = dict[str, Any]
"""An event in its JSON form: ``{"t": ..., "ev": kind, **fields}``."""

VIEW_CLASSES: tuple[type[TypedEvent], ...] = (
    HeaderEvent, BuiltEvent, TaskAddedEvent, TaskStateEvent, AgentTaskEvent, StageEvent,
    CommittedEvent, ProgressEvent, RouteEvent, TreeEvent, PoseEvent, CollisionEvent,
    AgentLostEvent, LinkEvent, VehicleLinkEvent, SignalEvent, CommandEvent, WithdrawnEvent,
    ObjectsEvent, RelocalizedEvent, WarningEvent, LeafErrorEvent, EndEvent, RoundEvent,
)  # fmt: skip
"""The events the page draws (a ``round`` only when its assignments changed)."""

VIEW_KINDS = frozenset(cls.KIND for cls in VIEW_CLASSES)
"""Their kinds."""

POSE_FIELDS = ("agent", "p", "yaw", "mode", "flying")
"""What a pose record keeps (the velocity, odometer and clearance are the report's)."""

REPLAY_POSE_BUDGET = 250_000
"""At most this many pose records in a replay (poses are thinned evenly past it): 30 agents
at 2 Hz for over an hour; about 20 MB of JSON."""

MAX_HISTORY = 2_000_000
"""A live feed stops keeping poses in its history past this many records (the latest pose of
each agent is still sent): a page that connects then sees the past more coarsely."""


def draws(event: Event) -> bool:
    """The page draws this event: one of :data:`VIEW_CLASSES` (an auction round only when its
    assignments changed), with fields of its kind's types."""
    if not issubclass(event_class(event.kind), VIEW_CLASSES):  # (cheap: nothing typed yet)
        return False
    typed = event.typed_or_none()
    return typed is not None and (not isinstance(typed, RoundEvent) or bool(typed.assignments))


def view_record(event: Event) -> Record | None:
    """``event`` as the viewer's record, or None if the page does not draw it (:func:`draws`)."""
    if not draws(event):
        return None
    typed = event.typed()
    data: Mapping[str, Any]
    match typed:
        case PoseEvent():
            full = typed.to_data()
            data = {k: full[k] for k in POSE_FIELDS if k in full}
        case LeafErrorEvent():
            data = {k: v for k, v in typed.to_data().items() if k != "traceback"}
        case RoundEvent():
            data = {"round": typed.round, "assignments": typed.assignments}
        case _:
            data = typed.to_data()
    rec: Record = {"t": round(event.t, 4), "ev": typed.kind}
    rec.update(data)
    return rec


def thin_poses(records: Iterable[Record], min_dt: float) -> list[Record]:
    """``records`` with each agent's poses at least ``min_dt`` s apart (its first and last kept;
    every other record kept)."""
    recs = list(records)
    last_index: dict[Any, int] = {}
    for i, r in enumerate(recs):
        if r["ev"] == "pose":
            last_index[r.get("agent")] = i
    kept_t: dict[Any, float] = {}
    out = []
    for i, r in enumerate(recs):
        if r["ev"] == "pose":
            agent = r.get("agent")
            if i != last_index[agent] and r["t"] < kept_t.get(agent, -math.inf) + min_dt:
                continue
            kept_t[agent] = r["t"]
        out.append(r)
    return out


def replay_records(events: Iterable[Event], pose_budget: int = REPLAY_POSE_BUDGET) -> list[Record]:
    """A finished run's records (from its log's events), with no more than about
    ``pose_budget`` poses: past it, each agent's poses are thinned to an even spacing."""
    recs = [r for r in (view_record(e) for e in events) if r is not None]
    poses = [r for r in recs if r["ev"] == "pose"]
    if len(poses) <= pose_budget or not poses:
        return recs
    span = max(r["t"] for r in poses) - min(r["t"] for r in poses)
    agents = len({r.get("agent") for r in poses})
    min_dt = span * agents / max(pose_budget - agents, 1)
    return thin_poses(recs, min_dt)


def snapshot_poses(snapshot: Any) -> list[Record]:
    """Pose records of every agent in a :class:`~btmission.runtime.snapshot.RunSnapshot`."""
    t = round(float(snapshot.time_s), 4)
    return [
        {
            "t": t,
            "ev": "pose",
            "agent": a.id,
            "p": [round(float(c), 4) for c in a.position],
            "yaw": round(float(a.yaw), 4),
            "mode": a.mode,
            "alive": a.alive,
        }
        for a in snapshot.agents
    ]


class LiveFeed:
    """A running mission's records for the viewer (module docstring). ``snapshot()`` gives the
    run's latest :class:`~btmission.runtime.snapshot.RunSnapshot` (or None before it is built);
    :meth:`start` samples it ``pose_hz`` times a second on a thread of its own."""

    def __init__(
        self,
        snapshot: Callable[[], Any] | None = None,
        *,
        pose_hz: float = 10.0,
        pose_history_s: float = 0.5,
        max_history: int = MAX_HISTORY,
    ) -> None:
        if pose_hz <= 0 or pose_history_s < 0:
            raise ValueError("pose_hz must be > 0 and pose_history_s >= 0")
        self._snapshot = snapshot
        self.pose_hz = pose_hz
        self.pose_history_s = pose_history_s
        self.max_history = max_history
        self._records: list[Record] = []
        self._latest: dict[str, Record] = {}
        self._latest_seq = 0
        self._kept_t: dict[str, float] = {}
        self._lock = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_time = -math.inf
        self.ended = False
        """The run's ``end`` event has arrived."""
        self.samples = 0

    @classmethod
    def of_records(cls, records: Iterable[Record]) -> LiveFeed:
        """A feed of a finished run: ``records`` are all there is (it has ended)."""
        feed = cls()
        feed._records = list(records)
        feed.ended = True
        return feed

    # ---------------------------------------------------------------- the run's side
    def on_event(self, event: Event) -> None:
        """An event of the run (Observer). Its ``pose`` events are left out: the poses come
        from the snapshots, more often."""
        if event.kind == PoseEvent.KIND:
            return
        rec = view_record(event)
        if rec is None:
            return
        with self._lock:
            self._records.append(rec)
            if event.kind == EndEvent.KIND:
                self.ended = True
            self._lock.notify_all()

    def add_poses(self, poses: Iterable[Record]) -> None:
        """Poses (sampled from a snapshot): each becomes its agent's latest; the history keeps
        one every ``pose_history_s`` per agent (module docstring)."""
        with self._lock:
            for rec in poses:
                agent = str(rec["agent"])
                self._latest[agent] = rec
                room = len(self._records) < self.max_history
                if room and rec["t"] >= self._kept_t.get(agent, -math.inf) + self.pose_history_s:
                    self._kept_t[agent] = rec["t"]
                    self._records.append(rec)
            self._latest_seq += 1
            self._lock.notify_all()

    def sample(self) -> bool:
        """Take the run's latest snapshot's poses if its time moved on (True if it did)."""
        snap = self._snapshot() if self._snapshot is not None else None
        if snap is None or snap.time_s <= self._last_time:
            return False
        self._last_time = snap.time_s
        self.samples += 1
        self.add_poses(snapshot_poses(snap))
        return True

    def start(self) -> LiveFeed:
        """Sample the snapshots on a daemon thread until :meth:`close`."""
        if self._thread is None and self._snapshot is not None:
            self._thread = threading.Thread(target=self._sampler, name="viewer-poses", daemon=True)
            self._thread.start()
        return self

    def _sampler(self) -> None:
        period = 1.0 / self.pose_hz
        while not self._stop.wait(period):
            self.sample()

    def close(self) -> None:
        """Stop sampling (a last sample first, so the final poses are in)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.sample()
        with self._lock:
            self._lock.notify_all()

    # ---------------------------------------------------------------- the pages' side
    def read(self, cursor: int, seen: int = -1) -> tuple[list[Record], int, list[Record], int]:
        """The records from index ``cursor`` on, the next cursor, every agent's latest pose if
        they changed since ``seen`` (a value this returned before), and the new ``seen``."""
        with self._lock:
            new = self._records[cursor:]
            latest = list(self._latest.values()) if self._latest_seq != seen else []
            return new, len(self._records), latest, self._latest_seq

    def wait(self, cursor: int, seen: int, timeout: float) -> bool:
        """Wait up to ``timeout`` s for something newer than (``cursor``, ``seen``)."""
        with self._lock:
            return self._lock.wait_for(
                lambda: len(self._records) > cursor or self._latest_seq != seen, timeout
            )

    def complete(self, cursor: int) -> bool:
        """The run has ended and a reader at ``cursor`` has every record."""
        with self._lock:
            return self.ended and cursor >= len(self._records)

    def __len__(self) -> int:
        with self._lock:
            return len(self._records)
