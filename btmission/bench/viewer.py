"""Viewer benchmark: what watching a run live costs the simulator (issue #15).

``btmission bench viewer`` (or ``python benchmarks/bench_viewer.py``) runs one mission — the
seed 003 scaling floor of :func:`btmission.bench.sim.scale_mission_text`: ``agents`` ground
robots and ``tasks`` inspections on a 100 m × 100 m floor, the tracking controller — for
``duration`` simulated seconds, as fast as the machine goes (``realtime=False``), with the same
seed every time, in alternating variants (A B S, S B A, A B S …, so that whatever else loads the
machine, and its drift, hits each alike):

* **A, no viewer**: the run and its event log (as ``btmission run`` writes it);
* **B, viewer**: the same plus the viewer exactly as ``btmission run --view`` wires it — the
  command's own :class:`~btmission.viz.live.LiveViewer`: a
  :class:`~btmission.viz.feed.LiveFeed` (poses sampled from the run's snapshots at 10 Hz on its
  own thread) behind a :class:`~btmission.runtime.observers.QueuedObserver`, served by a
  :class:`~btmission.viz.server.ViewerServer` (FastAPI on uvicorn, on a thread) on 127.0.0.1, a
  free port — with ``clients`` readers of ``GET /api/stream`` over loopback HTTP for the whole
  run (:class:`ReaderProcess`: a process each, as a browser is, reading with a plain socket,
  HTTP/1.1 chunked Server-Sent Events, as a page's ``EventSource`` reads them);
* **S, slow client** (unless ``slow=False``): B with one reader that pauses ``slow_pause_s``
  after each message, so the server's writes back up.

The speed is simulated seconds per wall second of the run loop (:attr:`RunResult.speedup
<btmission.runtime.runner.RunResult.speedup>`; building the run is not timed, nor is starting
the server). The drop of B (and S) is ``1 - speed_B / speed_A`` for each A/B pair of a repeat;
the table gives the median of the pairs and their range, and the median speeds. On a shared
machine single runs move by 10-20 % either way, more than the viewer costs, so the benchmark also
reads each thread's CPU time (Linux: :func:`thread_cpu`): what the viewer's threads used while
the run went, as a share of its wall time, is the work the viewer takes from the run's core
(its threads and the run share the GIL), and does not depend on other work on the machine.

What reached each reader is counted: messages, bytes, records by kind, and *pose updates* — the
distinct (agent, time) poses it saw, in the records or in the ``latest`` poses of a message —
per agent per simulated second and per wall second. Each viewer run is checked, and the
benchmark fails (:class:`ViewerBenchError`) otherwise:

* the :class:`QueuedObserver` dropped nothing but superseded ``pose`` and ``route`` events
  (:data:`btmission.runtime.observers.DROPPABLE`): no task event;
* every reader that saw the stream to its end received every record of the run's log the page
  draws, other than poses and routes, in the log's order (:func:`log_records`): the same task
  events as the log, none lost;
* the run did the same tasks as the run without a viewer of the same repeat.

Results go to ``viewer.md`` and ``viewer.csv`` with the machine and its load
(:func:`btmission.bench.synth.header_lines`) and the command line.
"""

from __future__ import annotations

import bisect
import csv
import json
import math
import socket
import statistics
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from btmission.bench.sim import _row
from btmission.bench.synth import environment, header_lines, write_page
from btmission.errors import BtmissionError

POSE_HZ = 10.0
"""The live feed's pose sampling rate (``run --view``'s)."""

TASK_KINDS = frozenset({"task_added", "task", "agent_task", "stage", "committed", "progress"})
"""The record kinds about tasks (arrival, state, assignment, stage, commitment, progress)."""

LOSSY_KINDS = frozenset({"pose", "route"})
"""Record kinds a viewer may thin (superseded states); every other record must arrive."""

READ_TIMEOUT_S = 10.0
"""A reader that hears nothing for this long gives up (the stream sends every 0.1 s while the
run moves)."""

READER_THREAD = "bench-stream-reader"

DRAIN_S = 60.0
"""After the run, how long the readers get to receive the rest of the stream."""


class ViewerBenchError(BtmissionError):
    """A viewer run broke a promise: a task event dropped or lost, or a different outcome."""


# ------------------------------------------------------------------------------ the reader
@dataclass
class ClientStats:
    """What one reader of ``/api/stream`` received."""

    pause_s: float = 0.0
    messages: int = 0
    bytes: int = 0
    records: int = 0
    kinds: Counter[str] = field(default_factory=Counter)
    latest_poses: int = 0
    """Pose records received in messages' ``latest`` lists."""
    pose_times: dict[str, set[float]] = field(default_factory=dict)
    """Per agent, the times of the poses seen (records and ``latest``)."""
    kept: list[dict[str, Any]] = field(default_factory=list)
    """The records received that are not poses or routes, in order."""
    receipts: list[tuple[float, float]] = field(default_factory=list)
    """Per message with poses: when it arrived (``time.perf_counter``) and its newest pose's
    simulated time."""
    complete: bool = False
    """The stream's ``complete`` event arrived (the reader saw everything)."""
    error: str = ""
    lags: list[float] = field(default_factory=list)
    """Per message with poses, how long after the run reached its newest pose it arrived (s;
    filled by :func:`run_once`)."""

    @property
    def pose_updates(self) -> int:
        """Distinct (agent, time) poses seen."""
        return sum(len(ts) for ts in self.pose_times.values())

    def task_events(self) -> int:
        return sum(self.kinds[k] for k in TASK_KINDS)


class _Stoppable:
    """hurry / stop through two events (a thread's or a process's)."""

    _hurry: Any
    _stop: Any

    def hurry(self) -> None:
        """Pause no more: read the rest of the stream as fast as it comes."""
        self._hurry.set()

    def stop(self) -> None:
        """Stop reading (at the next message or within :data:`READ_TIMEOUT_S`)."""
        self._stop.set()
        self._hurry.set()


class StreamClient(_Stoppable):
    """Reads ``GET /api/stream?cursor=0`` of a viewer at ``host``:``port`` on a thread of its
    own, over a plain socket (HTTP/1.1, chunked, Server-Sent Events), until the stream's
    ``complete`` event, the end of the connection, :data:`READ_TIMEOUT_S` of silence, or
    :meth:`stop`. ``pause_s`` > 0: sleeps that long after each message (a slow page);
    ``recv_buffer`` > 0: the socket's receive buffer in bytes (the OS's autotuned one
    otherwise), so that a slow reader's backlog stays small and the server's writes wait."""

    def __init__(self, host: str, port: int, *, pause_s: float = 0.0, recv_buffer: int = 0) -> None:
        self.address = (host, port)
        self.recv_buffer = recv_buffer
        self.stats = ClientStats(pause_s=pause_s)
        self._stop = threading.Event()
        self._hurry = threading.Event()
        self._thread = threading.Thread(target=self._main, name=READER_THREAD, daemon=True)
        self.connected = threading.Event()

    def start(self) -> StreamClient:
        self._thread.start()
        if not self.connected.wait(READ_TIMEOUT_S):
            raise ViewerBenchError(f"the stream reader could not connect: {self.stats.error}")
        return self

    def join(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the reader to end (True if it has)."""
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _main(self) -> None:
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
                if self.recv_buffer > 0:  # before connecting: it sets the window offered
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.recv_buffer)
                sock.settimeout(READ_TIMEOUT_S)
                sock.connect(self.address)
                host, port = self.address
                sock.sendall(
                    f"GET /api/stream?cursor=0 HTTP/1.1\r\nHost: {host}:{port}\r\n"
                    "Accept: text/event-stream\r\nCache-Control: no-cache\r\n\r\n".encode()
                )
                with sock.makefile("rb") as f:
                    self._read(f)
        except (OSError, ValueError) as exc:
            self.stats.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.connected.set()

    def _read(self, f: Any) -> None:
        status = f.readline(1024)
        if b" 200 " not in status:
            raise ValueError(f"unexpected response {status!r}")
        headers = {}
        for _ in range(100):
            line = f.readline(8192).strip()
            if not line:
                break
            name, _, value = line.decode("latin-1").partition(":")
            headers[name.strip().lower()] = value.strip().lower()
        if headers.get("transfer-encoding") != "chunked":
            raise ValueError(f"expected a chunked stream, got headers {headers}")
        self.connected.set()
        buf = b""
        while not self._stop.is_set():
            size_line = f.readline(1024)
            if not size_line:
                return  # the server closed the connection
            size = int(size_line.split(b";")[0].strip() or b"0", 16)
            if size == 0:
                return  # the response's end
            data = f.read(size)
            f.read(2)
            self.stats.bytes += len(data)
            buf += data
            while b"\n\n" in buf and not self._stop.is_set():
                message, buf = buf.split(b"\n\n", 1)
                if self._message(message):
                    return
                if self.stats.pause_s > 0 and not self._hurry.is_set():
                    self._hurry.wait(self.stats.pause_s)

    def _message(self, message: bytes) -> bool:
        """Count one Server-Sent Events message; True at the stream's ``complete``."""
        event, data = "message", []
        for line in message.decode("utf-8").split("\n"):
            name, _, value = line.partition(":")
            if name == "event":
                event = value.strip()
            elif name == "data":
                data.append(value[1:] if value.startswith(" ") else value)
        if event == "complete":
            self.stats.complete = True
            return True
        if not data:
            return False  # retry:, comments
        body = json.loads("\n".join(data))
        s = self.stats
        s.messages += 1
        newest = -math.inf
        for rec in body.get("records", ()):
            s.records += 1
            kind = rec.get("ev")
            s.kinds[kind] += 1
            if kind == "pose":
                s.pose_times.setdefault(str(rec.get("agent")), set()).add(rec["t"])
                newest = max(newest, rec["t"])
            elif kind != "route":
                s.kept.append(rec)
        for rec in body.get("latest", ()):
            s.latest_poses += 1
            s.pose_times.setdefault(str(rec.get("agent")), set()).add(rec["t"])
            newest = max(newest, rec["t"])
        if newest > -math.inf:
            s.receipts.append((time.perf_counter(), newest))
        return False


def start_process(proc: Any) -> None:
    """Start ``proc`` (a multiprocessing process) with SIGINT blocked in it from its first
    instruction: a Ctrl-C at the terminal reaches the whole process group, and the parent,
    which ends its children itself, must not have them print tracebacks while they import.
    (Blocked, not ignored, here meanwhile: a Ctrl-C in that instant waits for us, not lost.)"""
    import signal

    if not hasattr(signal, "pthread_sigmask"):
        proc.start()
        return
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})  # (inherited by the child)
    try:
        proc.start()
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


class ReaderProcess(_Stoppable):
    """A :class:`StreamClient` in a process of its own, as a browser is: its reading and JSON
    decoding do not compete with the run for this process's GIL. The same interface as a
    :class:`StreamClient`; :attr:`stats` arrive when it ends (:meth:`join`)."""

    def __init__(self, host: str, port: int, *, pause_s: float = 0.0, recv_buffer: int = 0) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")  # (no fork of a process with threads)
        self.stats = ClientStats(pause_s=pause_s)
        self._pipe, child = ctx.Pipe()
        self._hurry = ctx.Event()
        self._stop = ctx.Event()
        self._proc = ctx.Process(
            target=_reader_main,
            args=(host, port, pause_s, recv_buffer, child, self._hurry, self._stop),
            name=READER_THREAD,
            daemon=True,
        )
        self._done = False

    def start(self) -> ReaderProcess:
        start_process(self._proc)
        if not self._pipe.poll(READ_TIMEOUT_S + 30.0):  # (a new interpreter imports first)
            raise ViewerBenchError("the stream reader's process did not start")
        kind, value = self._pipe.recv()
        if kind != "connected":
            raise ViewerBenchError(f"the stream reader could not connect: {value}")
        return self

    def join(self, timeout: float) -> bool:
        if not self._done and self._pipe.poll(max(timeout, 0.0)):
            kind, value = self._pipe.recv()
            if kind == "stats":
                self.stats = value
                self._done = True
        if self._done:
            self._proc.join(5.0)
        elif not self._proc.is_alive():
            self._done = True
        if self._done and self._proc.is_alive():
            self._proc.kill()  # ours, by its handle
            self._proc.join(5.0)
        return self._done

    def end(self) -> None:
        """End the process now if it still runs (ours, by its handle): after an error or a
        Ctrl-C, when it would not report."""
        if self._proc.pid is not None and self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5.0)


def _reader_main(
    host: str, port: int, pause_s: float, recv_buffer: int, pipe: Any, hurry: Any, stop: Any
) -> None:
    """A :class:`ReaderProcess`'s process: read the stream, report the stats."""
    client = StreamClient(host, port, pause_s=pause_s, recv_buffer=recv_buffer)
    client._thread.start()
    client.connected.wait(READ_TIMEOUT_S)
    pipe.send(("connected", "") if not client.stats.error else ("error", client.stats.error))
    while client._thread.is_alive():
        if stop.is_set():
            client.stop()
        elif hurry.is_set():
            client.hurry()
        client._thread.join(0.05)
    pipe.send(("stats", client.stats))


# ------------------------------------------------------------------------------ one run
@dataclass
class RunPoint:
    """One measured run."""

    variant: str
    """``none``, ``viewer`` or ``slow``."""
    repeat: int
    agents: int
    sim_s: float
    wall_s: float
    build_s: float
    done: tuple[str, ...]
    log_task_events: int
    log_kept: int
    """Records of the log a page draws, other than poses and routes."""
    log_routes: int
    clients: list[ClientStats] = field(default_factory=list)
    dropped: dict[str, int] = field(default_factory=dict)
    """The QueuedObserver's dropped events, by kind."""
    delivered: int = 0
    feed_records: int = 0
    samples: int = 0
    """Pose samples the live feed took."""
    drain_s: float = 0.0
    """Wall time from the run's end until every reader had the whole stream."""
    cpu_s: dict[str, float] = field(default_factory=dict)
    """CPU seconds used during the run loop by the run's thread (``run``), the viewer's threads
    (``viewer``: its queue, pose sampler and server) and the readers (``readers``); empty where
    the OS does not tell (:func:`thread_cpu`)."""

    @property
    def viewer_cpu(self) -> float | None:
        """The viewer threads' CPU time as a share of the run loop's wall time."""
        return self.cpu_s["viewer"] / self.wall_s if "viewer" in self.cpu_s else None

    @property
    def speed(self) -> float:
        return self.sim_s / self.wall_s if self.wall_s > 0 else math.inf


def thread_cpu() -> dict[int, tuple[str, float]]:
    """CPU seconds (user + system) each thread of this process has used, by native thread id,
    with the thread's name: from Linux's ``/proc/self/task``; empty elsewhere."""
    import os

    names = {t.native_id: t.name for t in threading.enumerate()}
    main = threading.main_thread().native_id
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    out = {}
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return {}
    for tid in tids:
        try:
            with open(f"/proc/self/task/{tid}/stat", encoding="ascii") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # the thread ended meanwhile
        name = "MainThread" if int(tid) == main else names.get(int(tid), "?")
        out[int(tid)] = (name, (int(fields[11]) + int(fields[12])) / tick)
    return out


def cpu_by_role(
    before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]]
) -> dict[str, float]:
    """The CPU seconds threads used between two :func:`thread_cpu` readings, as ``run`` (the
    main thread), ``readers`` (:class:`StreamClient` threads) and ``viewer`` (every other)."""
    if not after:
        return {}
    roles = {"run": 0.0, "viewer": 0.0, "readers": 0.0}
    for tid, (name, cpu) in after.items():
        used = cpu - before.get(tid, (name, 0.0))[1]
        role = "run" if name == "MainThread" else "readers" if name == READER_THREAD else "viewer"
        roles[role] += used
    return roles


def bench_mission(agents: int, tasks: int, participation: float = 0.3, seed: int = 0) -> Any:
    """The scaling floor of ``btmission bench sim`` with ``agents`` robots and ``tasks`` tasks."""
    from btmission.bench.sim import scale_mission_text
    from btmission.missions import load_mission_text

    return load_mission_text(
        scale_mission_text(agents, tasks, participation, seed), "viewer-bench.yaml"
    )


def log_records(path: Path) -> list[dict[str, Any]]:
    """The viewer records of a run's log (:func:`~btmission.viz.feed.view_record`), poses
    left out (the live feed samples its own)."""
    from btmission.runtime.events import read_events
    from btmission.viz.feed import view_record

    out = []
    for ev in read_events(path).events:
        rec = view_record(ev)
        if rec is not None and rec["ev"] != "pose":
            out.append(rec)
    return out


def run_once(
    mission: Any,
    variant: str,
    duration_s: float,
    *,
    repeat: int = 0,
    seed: int = 0,
    controller: str | None = None,
    clients: int = 1,
    pause_s: float = 0.0,
    recv_buffer: int = 0,
    log_dir: Path,
) -> RunPoint:
    """Run ``mission`` for ``duration_s`` simulated seconds as fast as it goes: without a viewer
    (``variant`` ``none``), or with ``run --view``'s viewer read by ``clients`` readers, each
    pausing ``pause_s`` after every message with a ``recv_buffer``-byte receive buffer
    (:class:`StreamClient`). The log goes to ``log_dir``."""
    from btmission.runtime.session import RunSession
    from btmission.viz.live import LiveViewer

    live: LiveViewer | None = None
    readers: list[ReaderProcess] = []
    if variant != "none":
        live = LiveViewer("127.0.0.1", 0)  # binds a free loopback port now, as run --view does
    session = RunSession(
        mission,
        seed=seed,
        controller=controller,
        realtime=False,
        log_dir=log_dir,
        observers=[live.observer] if live is not None else [],
    )
    drain = 0.0
    clock: list[tuple[float, float]] = []  # (simulated s, wall) every simulated second
    cpu: dict[str, float] = {}
    try:
        with session:
            run = session.start()
            if run is None:
                raise ViewerBenchError("the run was stopped while being built")
            if live is not None:
                live.attach(session, run)
                host, port = live.server.address[:2]
                readers = [
                    ReaderProcess(host, port, pause_s=pause_s, recv_buffer=recv_buffer).start()
                    for _ in range(clients)
                ]
            clock.append((run.now(), time.perf_counter()))
            cpu0 = thread_cpu()
            result = session.run(
                duration_s, progress=lambda r: clock.append((r.now(), time.perf_counter()))
            )
            cpu = cpu_by_role(cpu0, thread_cpu())
            if result is None:
                raise ViewerBenchError("the run did not run")
            clock.append((result.time_s, time.perf_counter()))
            if live is not None:  # run --view's finish (no linger), the readers given time first
                t_end = time.perf_counter()
                live.finish()
                for r in readers:  # a slow one reads the rest at once (its delay is measured)
                    r.hurry()
                    r.join(max(DRAIN_S - (time.perf_counter() - t_end), 0.0))
                drain = time.perf_counter() - t_end
    finally:
        for r in readers:
            r.stop()
        if live is not None:
            live.close()
        for r in readers:
            r.join(READ_TIMEOUT_S)
            r.end()
    assert session.log_path is not None
    recs = log_records(session.log_path)
    point = RunPoint(
        variant,
        repeat,
        len(mission.agents),
        result.time_s,
        result.wall_s,
        session.build_s,
        tuple(sorted(result.done)),
        sum(1 for r in recs if r["ev"] in TASK_KINDS),
        sum(1 for r in recs if r["ev"] not in LOSSY_KINDS),
        sum(1 for r in recs if r["ev"] == "route"),
        [r.stats for r in readers],
        drain_s=drain,
        cpu_s=cpu,
    )
    for c in point.clients:
        c.lags = [wall - wall_at(clock, t) for wall, t in c.receipts]
    if live is not None:
        point.dropped = dict(live.queue.dropped)
        point.delivered = live.queue.delivered
        point.feed_records = len(live.feed)
        point.samples = live.feed.samples
        check_run(point, [r for r in recs if r["ev"] not in LOSSY_KINDS])
    return point


def wall_at(clock: Sequence[tuple[float, float]], t: float) -> float:
    """When (``time.perf_counter``) the run reached simulated time ``t``, interpolated in
    ``clock`` (``(simulated s, wall)`` pairs in time order; at its ends, the end's wall)."""
    i = bisect.bisect_left(clock, (t, -math.inf))
    if i <= 0:
        return clock[0][1]
    if i >= len(clock):
        return clock[-1][1]
    (t0, w0), (t1, w1) = clock[i - 1], clock[i]
    return w0 + (w1 - w0) * (t - t0) / (t1 - t0) if t1 > t0 else w1


def check_run(point: RunPoint, kept: list[dict[str, Any]]) -> None:
    """:class:`ViewerBenchError` unless only poses and routes were dropped and every reader
    that saw the whole stream received ``kept`` (the log's other records), in order."""
    lost = {k: n for k, n in point.dropped.items() if k not in LOSSY_KINDS and n}
    if lost:
        raise ViewerBenchError(f"the viewer's queue dropped events that must arrive: {lost}")
    for i, c in enumerate(point.clients):
        if c.error:
            raise ViewerBenchError(f"stream reader {i}: {c.error}")
        if c.complete and c.kept != kept:
            missing = len(kept) - len(c.kept)
            raise ViewerBenchError(
                f"stream reader {i} received {len(c.kept)} records other than poses and routes, "
                f"the log has {len(kept)} ({missing} missing or different)"
            )


# ------------------------------------------------------------------------------ the benchmark
VARIANTS = {"none": "no viewer", "viewer": "viewer", "slow": "viewer, slow reader"}


@dataclass
class Summary:
    """The runs of one variant, against the no-viewer runs of the same repeats."""

    variant: str
    runs: list[RunPoint]
    drops: list[float]
    """Per repeat, 1 - speed / speed without the viewer (empty for ``none``)."""

    @property
    def speed(self) -> float:
        return statistics.median(p.speed for p in self.runs)

    @property
    def drop(self) -> float | None:
        return statistics.median(self.drops) if self.drops else None

    def per_agent(self, wall: bool) -> float | None:
        """Median pose updates a reader got per agent per simulated (or wall) second."""
        rates = [
            c.pose_updates / p.agents / (p.wall_s if wall else p.sim_s)
            for p in self.runs
            for c in p.clients
        ]
        return statistics.median(rates) if rates else None

    def client_total(self, what: Callable[[ClientStats], float]) -> float:
        return statistics.median(what(c) for p in self.runs for c in p.clients)


def summarize(points: Sequence[RunPoint]) -> list[Summary]:
    base = {p.repeat: p for p in points if p.variant == "none"}
    out = []
    for variant in VARIANTS:
        runs = [p for p in points if p.variant == variant]
        if not runs:
            continue
        drops = [
            1.0 - p.speed / base[p.repeat].speed
            for p in runs
            if variant != "none" and p.repeat in base
        ]
        out.append(Summary(variant, runs, drops))
    return out


SUMMARY_HEAD = (
    "variant",
    "runs",
    "speed × real time (median)",
    "drop vs no viewer (median, range)",
    "viewer threads' CPU, % of wall (median)",
    "pose updates / agent / sim s",
    "pose updates / agent / wall s",
    "pose delay s (median, p99)",
    "records / reader",
    "messages / reader",
    "MB / reader",
    "task events: log / reader",
    "queue dropped (by kind)",
    "same tasks done",
)

RUNS_HEAD = (
    "#",
    "variant",
    "simulated s",
    "wall s",
    "speed ×",
    "drop %",
    "viewer CPU %",
    "tasks done",
    "readers complete",
    "pose updates / agent / wall s",
    "pose delay s (median, p99)",
    "records / reader",
    "feed samples",
    "queue delivered",
    "queue dropped",
)


def _dropped(runs: Sequence[RunPoint]) -> str:
    total: Counter[str] = Counter()
    for p in runs:
        total.update(p.dropped)
    return ", ".join(f"{k} {n}" for k, n in sorted(total.items())) or "none"


def _delay_pair(clients: Sequence[ClientStats]) -> tuple[str, str]:
    """The median and 99th percentile of the readers' pose delays (s; all their messages)."""
    lags = sorted(x for c in clients for x in c.lags)
    if not lags:
        return "", ""
    p99 = lags[min(int(0.99 * len(lags)), len(lags) - 1)]
    return f"{statistics.median(lags):.2f}", f"{p99:.2f}"


def _delays(clients: Sequence[ClientStats]) -> str:
    median, p99 = _delay_pair(clients)
    return f"{median}, {p99}" if median else "—"


def _pct(x: float) -> str:
    return f"{100 * x:+.1f} %"


def summary_cells(s: Summary, base: dict[int, RunPoint]) -> list[str]:
    if s.variant == "none":
        return [VARIANTS[s.variant], str(len(s.runs)), f"{s.speed:.2f}", *["—"] * 11]
    drop = s.drop
    per_sim, per_wall = s.per_agent(False), s.per_agent(True)
    task_log = statistics.median(p.log_task_events for p in s.runs)
    task_got = s.client_total(ClientStats.task_events)
    same = all(p.done == base[p.repeat].done for p in s.runs if p.repeat in base)
    shares = [x for x in (p.viewer_cpu for p in s.runs) if x is not None]
    return [
        VARIANTS[s.variant],
        str(len(s.runs)),
        f"{s.speed:.2f}",
        f"{_pct(drop or 0.0)} ({_pct(min(s.drops))} … {_pct(max(s.drops))})" if s.drops else "—",
        f"{100 * statistics.median(shares):.1f} %" if shares else "—",
        f"{per_sim:.2f}" if per_sim is not None else "—",
        f"{per_wall:.2f}" if per_wall is not None else "—",
        _delays([c for p in s.runs for c in p.clients]),
        f"{s.client_total(lambda c: c.records):,.0f}",
        f"{s.client_total(lambda c: c.messages):,.0f}",
        f"{s.client_total(lambda c: c.bytes) / 1e6:.2f}",
        f"{task_log:,.0f} / {task_got:,.0f}",
        _dropped(s.runs),
        "yes" if same else "**no**",
    ]


def run_cells(i: int, p: RunPoint, base: dict[int, RunPoint]) -> list[str]:
    b = base.get(p.repeat)
    drop = 1.0 - p.speed / b.speed if b is not None and p.variant != "none" else None
    rates = [c.pose_updates / p.agents / p.wall_s for c in p.clients]
    return [
        str(i),
        VARIANTS[p.variant],
        f"{p.sim_s:.1f}",
        f"{p.wall_s:.2f}",
        f"{p.speed:.2f}",
        f"{100 * drop:+.1f}" if drop is not None else "—",
        f"{100 * p.viewer_cpu:.1f}" if p.viewer_cpu is not None and p.variant != "none" else "—",
        str(len(p.done)),
        f"{sum(c.complete for c in p.clients)}/{len(p.clients)}" if p.clients else "—",
        ", ".join(f"{r:.2f}" for r in rates) or "—",
        _delays(p.clients),
        ", ".join(f"{c.records:,}" for c in p.clients) or "—",
        str(p.samples) if p.variant != "none" else "—",
        str(p.delivered) if p.variant != "none" else "—",
        _dropped([p]) if p.variant != "none" else "—",
    ]


@dataclass(frozen=True)
class ViewerConfig:
    """What ``btmission bench viewer`` measures (module docstring)."""

    agents: int = 30
    tasks: int = 60
    duration_s: float = 20.0
    repeats: int = 8
    clients: int = 1
    slow: bool = True
    slow_pause_s: float = 0.5
    slow_buffer: int = 0
    """The slow reader's socket receive buffer (bytes; 0: the OS's, autotuned)."""
    controller: str | None = None
    seed: int = 0
    participation: float = 0.3
    warmup_s: float = 5.0
    """Simulated seconds of one unmeasured run with the viewer first (caches, imports)."""


def markdown(
    cfg: ViewerConfig, points: Sequence[RunPoint], env: dict[str, str], command: str
) -> str:
    base = {p.repeat: p for p in points if p.variant == "none"}
    sums = summarize(points)
    viewer = next((s for s in sums if s.variant == "viewer"), None)
    viewed = [p for p in points if p.variant != "none"]
    verdict = []
    if viewer is not None and viewer.drop is not None:
        ok = viewer.drop <= 0.10
        pairs = f"{len(viewer.drops)} pair{'s' if len(viewer.drops) != 1 else ''}"
        verdict = [
            f"**Target: the simulator at most 10 % slower with the viewer ({cfg.agents} agents, "
            f"{POSE_HZ:g} Hz poses): {_pct(viewer.drop)} (median of {pairs}) — "
            f"{'met' if ok else 'NOT met'}.** No task event was dropped: the viewer's queue "
            f"dropped {_dropped(viewed)}, and every reader that saw the stream to its end "
            "received every record of the log other than poses and routes, in order (checked "
            "in each run).",
            "",
        ]
    variants = [v for v in VARIANTS if any(p.variant == v for p in points)]
    slow = (
        f" *viewer, slow reader*: the same with one reader that pauses {cfg.slow_pause_s:g} s "
        "after each message (socket receive buffer "
        f"{f'{cfg.slow_buffer:,} bytes' if cfg.slow_buffer else 'the OS default'}) while the "
        "run goes, and reads the rest at once when it has ended."
        if "slow" in variants
        else ""
    )
    lines = [
        "# Viewer benchmark",
        "",
        *header_lines(env),
        f"- command: `{command}`",
        "",
        f"The seed 003 scaling floor (`btmission bench sim`'s): {cfg.agents} ground robots and "
        f"{cfg.tasks} inspection tasks on 100 m × 100 m (participation {cfg.participation:g}), "
        f"controller {cfg.controller or 'track'}, seed {cfg.seed}, run for {cfg.duration_s:g} "
        "simulated seconds as fast as it goes (no pacing), with its event log, in alternating "
        f"runs ({', '.join(variants)}, then the other way round, …; {cfg.repeats} repeat(s) "
        "after one unmeasured "
        f"{cfg.warmup_s:g} s run with the viewer). *viewer*: `btmission run --view`'s own "
        f"wiring (`LiveViewer`: a LiveFeed sampling poses at {POSE_HZ:g} Hz behind a "
        "QueuedObserver, served by uvicorn on 127.0.0.1) with "
        f"{cfg.clients} reader(s) of `/api/stream` over loopback HTTP for the whole run." + slow,
        "",
        "Speed = simulated s / wall s of the run loop; drop = 1 − speed / speed of the no-viewer "
        "run of the same repeat. Pose updates = distinct (agent, time) poses a reader received "
        "(history records and each message's latest poses). Pose delay = how long after the "
        "run reached a message's newest pose the reader had the message.",
        "",
        *verdict,
        _row(SUMMARY_HEAD),
        _row(["---"] * len(SUMMARY_HEAD)),
        *(_row(summary_cells(s, base)) for s in sums),
        "",
        "## Every run, in order",
        "",
        _row(RUNS_HEAD),
        _row(["---"] * len(RUNS_HEAD)),
        *(_row(run_cells(i + 1, p, base)) for i, p in enumerate(points)),
        "",
        "Regenerate with `btmission bench viewer` or `python benchmarks/bench_viewer.py`.",
        "",
    ]
    return "\n".join(lines)


def write_csv(path: Path, points: Sequence[RunPoint]) -> None:
    base = {p.repeat: p for p in points if p.variant == "none"}
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "repeat", "variant", "agents", "sim_s", "wall_s", "speed", "drop", "build_s",
                "tasks_done", "log_task_events", "run_cpu_s", "viewer_cpu_s", "readers_cpu_s",
                "reader", "reader_pause_s", "complete",
                "messages", "bytes", "records", "task_events", "pose_updates",
                "pose_updates_per_agent_sim_s", "pose_updates_per_agent_wall_s",
                "pose_delay_median_s", "pose_delay_p99_s", "feed_samples",
                "queue_delivered", "queue_dropped_pose", "queue_dropped_route",
                "queue_dropped_other", "drain_s",
            ]
        )  # fmt: skip
        for p in points:
            b = base.get(p.repeat)
            drop = f"{1.0 - p.speed / b.speed:.4f}" if b is not None and p.variant != "none" else ""
            other = sum(n for k, n in p.dropped.items() if k not in LOSSY_KINDS)
            common = [
                p.repeat, p.variant, p.agents, f"{p.sim_s:.2f}", f"{p.wall_s:.3f}",
                f"{p.speed:.3f}", drop, f"{p.build_s:.3f}", len(p.done), p.log_task_events,
                *(f"{p.cpu_s[k]:.2f}" if k in p.cpu_s else "" for k in ("run", "viewer", "readers")),
            ]  # fmt: skip
            queue = [
                p.samples, p.delivered, p.dropped.get("pose", 0), p.dropped.get("route", 0),
                other, f"{p.drain_s:.2f}",
            ]  # fmt: skip
            if not p.clients:
                w.writerow([*common, *[""] * 12, *queue])
            for i, c in enumerate(p.clients):
                w.writerow(
                    [
                        *common, i, c.pause_s, c.complete, c.messages, c.bytes, c.records,
                        c.task_events(), c.pose_updates,
                        f"{c.pose_updates / p.agents / p.sim_s:.3f}",
                        f"{c.pose_updates / p.agents / p.wall_s:.3f}", *_delay_pair([c]),
                        *queue,
                    ]
                )  # fmt: skip


def run_viewer_benchmark(
    cfg: ViewerConfig,
    out_dir: Path | str | None = Path("benchmarks/results"),
    echo: Callable[[str], object] = print,
    command: str = "btmission bench viewer",
) -> list[RunPoint]:
    """Measure (module docstring), echo each run and the summary, and write ``viewer.md`` and
    ``viewer.csv`` to ``out_dir`` (None: write nothing)."""
    env = environment()
    mission = bench_mission(cfg.agents, cfg.tasks, cfg.participation, cfg.seed)
    variants = ["none", "viewer", *(["slow"] if cfg.slow else [])]
    echo(
        f"viewer benchmark: {cfg.agents} agents, {cfg.tasks} tasks, {cfg.duration_s:g} simulated s, "
        f"{cfg.repeats} × ({', '.join(variants)}); {env['machine']}, {env['cpus']} CPU(s)"
    )
    points: list[RunPoint] = []
    with tempfile.TemporaryDirectory(prefix="btmission-bench-viewer-") as tmp:
        logs = Path(tmp)
        if cfg.warmup_s > 0:
            run_once(mission, "viewer", cfg.warmup_s, seed=cfg.seed, controller=cfg.controller,
                     clients=1, log_dir=logs / "warmup")  # fmt: skip
        echo("")
        echo(_row(RUNS_HEAD))
        echo(_row(["---"] * len(RUNS_HEAD)))
        for rep in range(cfg.repeats):
            order = variants if rep % 2 == 0 else variants[::-1]  # A B S, S B A: drift cancels
            for variant in order:
                p = run_once(
                    mission,
                    variant,
                    cfg.duration_s,
                    repeat=rep,
                    seed=cfg.seed,
                    controller=cfg.controller,
                    clients=1 if variant == "slow" else cfg.clients,
                    pause_s=cfg.slow_pause_s if variant == "slow" else 0.0,
                    recv_buffer=cfg.slow_buffer if variant == "slow" else 0,
                    log_dir=logs / f"{rep}-{variant}",
                )
                points.append(p)
            base = {q.repeat: q for q in points if q.variant == "none"}
            for i in range(len(points) - len(order), len(points)):
                echo(_row(run_cells(i + 1, points[i], base)))
    base = {p.repeat: p for p in points if p.variant == "none"}
    echo("")
    echo(_row(SUMMARY_HEAD))
    echo(_row(["---"] * len(SUMMARY_HEAD)))
    for s in summarize(points):
        echo(_row(summary_cells(s, base)))
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_page(out / "viewer.md", markdown(cfg, points, env, command))
        write_csv(out / "viewer.csv", points)
        echo(f"wrote {out / 'viewer.md'} and {out / 'viewer.csv'}")
    return points
