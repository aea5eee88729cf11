"""QueuedObserver: a slow observer never slows the run; under back-pressure it loses poses (and
superseded routes), counted, never a task, assignment, round, progress or end event."""

from __future__ import annotations

import threading
import time

import pytest

from btmission.runtime.events import Event, EventStream, Recorder
from btmission.runtime.observers import QueuedObserver

WAIT_S = 10.0
"""Upper bound of any wait in these tests (they take milliseconds when all is well)."""


class Gated(Recorder):
    """An observer stuck on its first event until the test opens the gate (a viewer that froze),
    then as fast as a Recorder."""

    def __init__(self) -> None:
        super().__init__()
        self.gate = threading.Event()
        self.entered = threading.Event()
        self.thread: threading.Thread | None = None

    def on_event(self, event: Event) -> None:
        self.thread = threading.current_thread()
        self.entered.set()
        assert self.gate.wait(WAIT_S), "the test never opened the gate"
        super().on_event(event)


ESSENTIAL = ("task", "round", "progress", "agent_task", "stage", "tree")


def publish(stream: EventStream, n: int) -> list[Event]:
    """n steps of a run: 3 agents' poses every step, an auction round every step, a task,
    progress, assignment... event every 10th, a route every 25th; then the end."""
    out = []
    for k in range(n):
        t = k * 0.05
        for agent in ("G1", "G2", "G3"):
            out.append(stream.emit(t, "pose", agent=agent, p=[k, 0, 0]))
        out.append(stream.emit(t, "round", round=k, announced=1, agents=3))
        if k % 10 == 0:
            kind = ESSENTIAL[(k // 10) % len(ESSENTIAL)]
            out.append(stream.emit(t, kind, agent="G1", task=f"T{k}", state="assigned"))
        if k % 25 == 0:
            out.append(stream.emit(t, "route", agent="G2", points=[[k, 0, 0]], length_m=1.0))
    out.append(stream.emit(n * 0.05, "end", reason="completed"))
    return out


def test_a_stuck_observer_does_not_hold_the_run_and_loses_only_poses_and_old_routes() -> None:
    slow = Gated()
    queued = QueuedObserver(slow, maxsize=50)
    stream = EventStream([queued])
    first = stream.emit(0.0, "header", format="btmission-log", version=2)
    assert slow.entered.wait(WAIT_S)  # the observer holds the header; nothing else is delivered
    t0 = time.perf_counter()
    sent = [first, *publish(stream, 2000)]  # ~8,000 events while the observer is stuck
    publish_s = time.perf_counter() - t0
    assert publish_s < 5.0  # it would wait forever if on_event blocked (the gate is shut)
    assert slow.events == [] and queued.delivered == 0
    slow.gate.set()
    queued.close(timeout=WAIT_S)
    assert slow.thread is not None and slow.thread is not threading.main_thread()

    got = slow.events
    kept = [e for e in sent if e.kind not in ("pose", "route")]
    assert [e for e in got if e.kind not in ("pose", "route")] == kept  # all, in order
    poses = [e for e in sent if e.kind == "pose"]
    got_poses = [e for e in got if e.kind == "pose"]
    assert queued.dropped["pose"] > 5000
    assert queued.dropped["pose"] + len(got_poses) == len(poses)
    delivered = {id(e) for e in got}
    newest = {e.get("agent"): e for e in poses}
    assert all(id(e) in delivered for e in newest.values())  # each agent's last pose
    routes = [e for e in sent if e.kind == "route"]
    got_routes = [e for e in got if e.kind == "route"]
    assert got_routes[-1] == routes[-1]  # superseded ones dropped, never the newest
    assert queued.dropped["route"] + len(got_routes) == len(routes)
    assert set(queued.dropped) == {"pose", "route"}
    assert got == [e for e in sent if id(e) in delivered]  # in publication order
    assert got[-1].kind == "end" and queued.delivered == len(got)


def test_a_stuck_observer_does_not_make_the_queue_grow_with_dropped_poses() -> None:
    """Memory stays bounded: dropped events do not stay behind in the queue."""
    slow = Gated()
    queued = QueuedObserver(slow, maxsize=10)
    stream = EventStream([queued])
    stream.emit(0.0, "header", format="btmission-log", version=2)
    assert slow.entered.wait(WAIT_S)
    for k in range(50_000):
        stream.emit(k * 0.05, "pose", agent=f"G{k % 3}", p=[k, 0, 0])
    assert queued.queued <= 10 and len(queued._queue) <= 2 * 10 + 1
    slow.gate.set()
    queued.close(timeout=WAIT_S)
    last = {e.get("agent"): e.get("p")[0] for e in slow.events if e.kind == "pose"}
    assert last == {"G0": 49_998, "G1": 49_999, "G2": 49_997}  # each agent's newest pose
    assert queued.dropped["pose"] + len(slow.events) - 1 == 50_000


def test_a_fast_observer_gets_everything_in_order() -> None:
    rec = Recorder()
    with QueuedObserver(rec, maxsize=10_000) as queued:
        sent = publish(EventStream([queued]), 300)
        assert queued.flush(WAIT_S)
        assert rec.events == sent and queued.queued == 0
    assert not queued.dropped


def test_a_full_queue_of_events_that_matter_grows_rather_than_drop_one() -> None:
    slow = Gated()
    queued = QueuedObserver(slow, maxsize=4)
    stream = EventStream([queued])
    stream.emit(0.0, "header")
    assert slow.entered.wait(WAIT_S)
    sent = [stream.emit(1.0, "task", task=f"T{i}", state="open") for i in range(20)]
    sent.append(stream.emit(1.0, "pose", agent="G1", p=[0, 0, 0]))  # the agent's latest: kept
    sent.append(stream.emit(1.0, "round", round=1))
    sent.append(stream.emit(1.5, "pose", agent="G2", p=[1, 0, 0]))
    sent.append(stream.emit(1.5, "pose", agent="G1", p=[2, 0, 0]))  # supersedes G1's at 1.0
    sent.append(stream.emit(2.0, "pose", agent="G1", p=[3, 0, 0]))  # supersedes G1's at 1.5
    assert queued.queued == 23 and queued.dropped == {"pose": 2}
    slow.gate.set()
    queued.close(timeout=WAIT_S)
    assert slow.events[1:] == [sent[i] for i in (*range(20), 21, 22, 24)]


def test_close_delivers_what_is_queued_then_drops_and_counts() -> None:
    slow = Gated()
    queued = QueuedObserver(slow, maxsize=100)
    stream = EventStream([queued])
    sent = [stream.emit(float(i), "task", task="T1", state="open") for i in range(5)]
    slow.gate.set()
    queued.close(timeout=WAIT_S)
    assert slow.events == sent
    stream.emit(9.0, "end", reason="completed")
    assert queued.dropped == {"end": 1} and len(slow.events) == 5


def test_an_observer_that_raises_does_not_stop_delivery() -> None:
    class Picky(Recorder):
        def on_event(self, event: Event) -> None:
            if event.kind == "pose":
                raise ValueError("no poses, thanks")
            super().on_event(event)

    picky = Picky()
    with QueuedObserver(picky) as queued:
        stream = EventStream([queued])
        stream.emit(0.0, "pose", agent="G1")
        stream.emit(0.1, "task", task="T1", state="open")
        stream.emit(0.2, "pose", agent="G1")
        stream.emit(0.3, "end", reason="completed")
    assert [e.kind for e in picky.events] == ["task", "end"]
    assert queued.errors == 2 and isinstance(queued.error, ValueError)
    assert queued.delivered == 4


def test_maxsize_must_be_positive() -> None:
    with pytest.raises(ValueError, match="maxsize must be at least 1"):
        QueuedObserver(Recorder(), maxsize=0)


def test_batched_delivery_wakes_per_batch_and_loses_nothing() -> None:
    """With ``batch_s`` the thread delivers what arrived since its last wake, in order, and
    flush/close still deliver everything."""
    rec = Recorder()
    with QueuedObserver(rec, maxsize=1000, batch_s=0.05) as queued:
        for i in range(300):
            queued.on_event(Event(i * 0.01, "task", {"task": f"T{i}"}))
        assert queued.flush(timeout=5.0)
        assert [e.get("task") for e in rec.events] == [f"T{i}" for i in range(300)]
        queued.on_event(Event(9.0, "end", {"reason": "completed"}))
    assert rec.events[-1].kind == "end"
    with pytest.raises(ValueError, match="batch_s"):
        QueuedObserver(Recorder(), batch_s=-1)
