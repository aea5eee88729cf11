"""Console benchmark: what the operator console costs a running mission (issue #16).

``btmission bench console`` (or ``python benchmarks/bench_console.py``) runs one mission —
``missions/mine_inspection.yaml`` with the tracking controller by default (``--mission``: any
mission file; without one, ``bench viewer``'s scaling floor) — for ``duration`` simulated
seconds, as fast as the machine goes (``realtime=False``), with the same seed every time, in
alternating variants (V I F R, R F I V, …, so that whatever else loads the machine, and its
drift, hits each alike). Every variant serves the run as ``btmission run`` does, through the
command's own :class:`~btmission.viz.live.LiveViewer` on 127.0.0.1 (a free port), read by one
reader of ``GET /api/stream`` in a process of its own (as ``bench viewer`` reads it):

* **V, viewer only** (``viewer``): ``run --view``; the baseline;
* **I, console idle** (``idle``): ``run --console`` (``LiveViewer(console=True)``) and, in a
  second process, a page's status poll: ``GET /api/status`` every second (``poll_hz``), as an
  open viewer page asks;
* **F, flood** (``flood``): I plus a third process that sends bursts of ``burst`` requests —
  ``burst - adds`` ``GET /api/status`` and ``adds`` ``POST /api/tasks``, shuffled — from a pool
  of ``threads`` threads (each on a keep-alive connection), a burst every ``every_s`` wall
  seconds (or as soon as the previous one ends) while the run goes. The adds are valid: a copy
  of the mission's first task (its type and fields, the id left to the console), so every
  accepted one is a new task for the auction, which costs the run too;
* **R, refused flood** (``refused``): F with adds the console refuses (422): the same task
  moved into rock next to it (its nearest occupied voxel) or, on a map without rock, outside
  the map. No task reaches the run (a refusal is only logged), so this is the server's cost.

The speed is simulated seconds per wall second of the run loop (:attr:`RunResult.speedup
<btmission.runtime.runner.RunResult.speedup>`; building the run, starting the server and the
client processes are not timed). The drop of a variant is ``1 - speed / speed_V`` for the V run
of the same repeat (a pair); the table gives the median of the pairs with their range, and the
ratio of the mean speeds. The run's process's threads' CPU time is read as ``bench viewer`` does
(:func:`btmission.bench.viewer.thread_cpu`, Linux): the server's (uvicorn's event loop and the
worker threads that run its routes) and the viewer's other threads (queue, pose sampler), as a
share of the run loop's wall time: work the run loses the GIL to.

The clients time every request (``time.perf_counter``, from sending it to the end of the
answer) and count the answers by status. Each run is checked, and the benchmark fails
(:class:`ConsoleBenchError`) otherwise:

* every add answered 201 is a ``task_added`` event of the run's log, by the flood's client,
  and the log has no flood add that was not answered 201 or 202 (or lost on the way);
* no request was answered 5xx, and the adds of R were all refused (422; 409 when the pool is full; or 429 before any work);
* the stream reader received every record of the log other than poses and routes, in order
  (:func:`btmission.bench.viewer.check_run`);
* the runs that add nothing (I, R) did the same tasks as V of the same repeat.

Results go to ``console.md`` and ``console.csv`` with the machine and its load
(:func:`btmission.bench.synth.header_lines`) and the command line.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
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
from btmission.bench.viewer import (
    DRAIN_S,
    LOSSY_KINDS,
    READ_TIMEOUT_S,
    ClientStats,
    ReaderProcess,
    ViewerBenchError,
    check_run,
    log_records,
    start_process,
    thread_cpu,
)
from btmission.errors import BtmissionError

DEFAULT_MISSION = "missions/mine_inspection.yaml"
TOKEN = "bench-console-token"
"""The run's console token (a benchmark on loopback: no secret to keep)."""
FLOOD_CLIENT = "bench-flood"
"""The flood's ``X-Btmission-Client``: its adds are logged ``by`` ``bench-flood@127.0.0.1``."""
PAGE_CLIENT = "page"
REQUEST_TIMEOUT_S = 30.0
"""A request not answered in this long counts as an error (status 0)."""
SERVER_THREADS = ("viewer-server", "AnyIO worker thread")
"""The names of the server's threads: uvicorn's event loop and the threads running routes."""

VARIANTS = {
    "viewer": "viewer only",
    "idle": "console, idle",
    "flood": "console, flood (valid adds)",
    "refused": "console, flood (refused adds)",
}
FLOODS = ("flood", "refused")


class ConsoleBenchError(BtmissionError):
    """A console run broke a promise: an accepted add not in the log, a 5xx, a lost record."""


# ------------------------------------------------------------------------------ the clients
@dataclass(frozen=True)
class Request:
    """One request as its client saw it."""

    kind: str
    """``poll`` (the page's status), ``status`` (the flood's) or ``add``."""
    burst: int
    """The flood's burst (-1 for the page's polls)."""
    t0: float
    """When it was sent (``time.perf_counter``: the same clock in every process of the host)."""
    latency_s: float
    status: int
    """The HTTP status; 0 when no answer came (``error``)."""
    task: str = ""
    """An add's task id, from its answer."""
    error: str = ""


@dataclass
class LoadLog:
    """What a client process did: its requests and, for a flood, its bursts."""

    requests: list[Request] = field(default_factory=list)
    bursts: list[tuple[float, float, int]] = field(default_factory=list)
    """Per burst: its start and end (``time.perf_counter``) and the requests it sent."""
    reconnects: int = 0
    """Keep-alive connections found closed by the server and opened again."""


@dataclass(frozen=True)
class FloodSpec:
    """A flood's shape (module docstring)."""

    burst: int = 1000
    adds: int = 200
    threads: int = 16
    every_s: float = 2.0
    add_body: dict[str, Any] = field(default_factory=dict)
    seed: int = 0


class _Http:
    """One keep-alive HTTP/1.1 connection to the console, as a page or a script keeps one."""

    def __init__(self, host: str, port: int, client: str, log: LoadLog) -> None:
        self.host, self.port = host, port
        self.headers = {"X-Btmission-Client": client, "Accept": "application/json"}
        self.log = log
        self.conn: Any = None

    def call(self, method: str, path: str, body: Any = None) -> tuple[int, bytes]:
        import http.client

        headers = dict(self.headers)
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            headers["Content-Type"] = "application/json"
            headers["Authorization"] = f"Bearer {TOKEN}"
        for attempt in range(2):
            fresh = self.conn is None
            if fresh:
                self.conn = http.client.HTTPConnection(
                    self.host, self.port, timeout=REQUEST_TIMEOUT_S
                )
            try:
                self.conn.request(method, path, body=data, headers=headers)
                resp = self.conn.getresponse()
                raw = resp.read()
                if resp.will_close:
                    self.close()
                return resp.status, raw
            except (http.client.RemoteDisconnected, BrokenPipeError, ConnectionResetError):
                self.close()  # a kept-alive connection the server had closed: once more
                if fresh or attempt:
                    raise
                self.log.reconnects += 1
            except BaseException:
                self.close()
                raise
        raise AssertionError("unreachable")

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None


def _timed(http: _Http, kind: str, burst: int, method: str, path: str, body: Any = None) -> Request:
    t0 = time.perf_counter()
    try:
        status, raw = http.call(method, path, body)
    except (OSError, ValueError) as exc:  # (http.client's errors are OSError or ValueError)
        return Request(kind, burst, t0, time.perf_counter() - t0, 0, error=type(exc).__name__)
    latency = time.perf_counter() - t0
    task = ""
    if kind == "add" and status in (201, 202):
        try:
            task = str(json.loads(raw).get("task") or "")
        except (ValueError, AttributeError):
            pass
    return Request(kind, burst, t0, latency, status, task)


def _poll(host: str, port: int, hz: float, go: Any, stop: Any) -> LoadLog:
    """The page's status poll: ``GET /api/status`` every ``1 / hz`` s until ``stop``."""
    log = LoadLog()
    http = _Http(host, port, PAGE_CLIENT, log)
    go.wait()
    period = 1.0 / hz
    next_t = time.perf_counter()
    while not stop.is_set():
        log.requests.append(_timed(http, "poll", -1, "GET", "/api/status"))
        next_t += period
        stop.wait(max(next_t - time.perf_counter(), 0.0))
    http.close()
    return log


def _flood(host: str, port: int, spec: FloodSpec, go: Any, stop: Any) -> LoadLog:
    """Bursts of requests (module docstring) from ``spec.threads`` threads until ``stop``."""
    import queue
    import random

    log = LoadLog()
    jobs: queue.Queue[tuple[int, str] | None] = queue.Queue()
    lock = threading.Lock()

    def worker() -> None:
        http = _Http(host, port, FLOOD_CLIENT, log)
        while (job := jobs.get()) is not None:
            try:
                burst, kind = job
                if stop.is_set():
                    continue  # (dropped: the run has ended)
                if kind == "add":
                    req = _timed(http, "add", burst, "POST", "/api/tasks", spec.add_body)
                else:
                    req = _timed(http, "status", burst, "GET", "/api/status")
                with lock:
                    log.requests.append(req)
            finally:
                jobs.task_done()
        http.close()

    workers = [
        threading.Thread(target=worker, name=f"flood-{i}", daemon=True) for i in range(spec.threads)
    ]
    for w in workers:
        w.start()
    go.wait()
    start = time.perf_counter()
    burst = 0
    while not stop.is_set():
        kinds = ["add"] * spec.adds + ["status"] * (spec.burst - spec.adds)
        random.Random(spec.seed * 100_003 + burst).shuffle(kinds)
        t0 = time.perf_counter()
        for kind in kinds:
            jobs.put((burst, kind))
        jobs.join()
        with lock:
            sent = sum(1 for r in log.requests if r.burst == burst)
        log.bursts.append((t0, time.perf_counter(), sent))
        burst += 1
        stop.wait(max(start + burst * spec.every_s - time.perf_counter(), 0.0))
    for _ in workers:
        jobs.put(None)
    for w in workers:
        w.join(REQUEST_TIMEOUT_S)
    return log


def _load_main(
    role: str, host: str, port: int, spec: FloodSpec, hz: float, pipe: Any, go: Any, stop: Any
) -> None:
    """A :class:`LoadProcess`'s process: poll or flood, then report its :class:`LoadLog`."""
    pipe.send(("ready", ""))  # (SIGINT ignored since the start: the parent ends us)
    log = _poll(host, port, hz, go, stop) if role == "poll" else _flood(host, port, spec, go, stop)
    pipe.send(("log", log))


class LoadProcess:
    """A client of the console in a process of its own (a page or a script is one): the
    page's status poll (``role`` ``poll``, ``hz`` a second) or a flood (``flood``, ``spec``).
    It waits for :meth:`go`, runs until :meth:`stop`, and :meth:`join` returns its log."""

    def __init__(
        self, role: str, host: str, port: int, *, spec: FloodSpec | None = None, hz: float = 1.0
    ) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")  # (no fork of a process with threads)
        self.role = role
        self._pipe, child = ctx.Pipe()
        self._go = ctx.Event()
        self._stop = ctx.Event()
        self._proc = ctx.Process(
            target=_load_main,
            args=(role, host, port, spec or FloodSpec(), hz, child, self._go, self._stop),
            name=f"bench-console-{role}",
            daemon=True,
        )
        self.log: LoadLog | None = None

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def start(self) -> LoadProcess:
        start_process(self._proc)
        if not self._pipe.poll(READ_TIMEOUT_S + 30.0):  # (a new interpreter imports first)
            raise ConsoleBenchError(f"the {self.role} client's process did not start")
        self._pipe.recv()
        return self

    def go(self) -> None:
        self._go.set()

    def stop(self) -> None:
        self._stop.set()
        self._go.set()

    def join(self, timeout: float) -> LoadLog | None:
        """Wait up to ``timeout`` s for the log; end the process (by its handle) either way."""
        if self.log is None and self._proc.pid is not None:
            try:
                if self._pipe.poll(max(timeout, 0.0)):
                    kind, value = self._pipe.recv()
                    if kind == "log":
                        self.log = value
            except (EOFError, OSError):
                pass
        if self._proc.pid is not None:
            self._proc.join(5.0 if self.log is not None else 0.0)
            if self._proc.is_alive():
                self._proc.kill()  # ours, by its pid
                self._proc.join(5.0)
        return self.log


# ------------------------------------------------------------------------------ the mission
def load_bench_mission(path: str | Path | None, agents: int = 30, tasks: int = 60) -> Any:
    """The mission file at ``path``; None: ``bench viewer``'s floor of ``agents`` robots."""
    if path is None:
        from btmission.bench.viewer import bench_mission

        return bench_mission(agents, tasks)
    from btmission.missions import load_mission

    return load_mission(path)


def add_bodies(
    mission: Any, vmap: Any, refused: str = "rock"
) -> tuple[dict[str, Any], dict[str, Any], str]:
    """The flood's add bodies: a valid one (the mission's first task with a position field:
    its type and fields, no id) and one the console refuses: its positions moved to the
    nearest occupied voxel (``refused`` ``rock``; the console then looks for the nearest free
    voxel to name in its answer) or outside the map (``outside``, and on a map without rock);
    and what the refused one is (``inside rock`` / ``outside the map``)."""
    import numpy as np

    from btmission.world.voxel import OCCUPIED

    for task in mission.tasks:
        positions = {
            k: v for k, v in task.fields.items() if isinstance(v, (list, tuple)) and len(v) == 3
        }
        if positions:
            break
    else:
        raise ConsoleBenchError("the mission has no task with a position field to add copies of")

    def plain(v: Any) -> Any:
        return [float(x) for x in v] if isinstance(v, (list, tuple)) else v

    good = {"type": task.type, **{k: plain(v) for k, v in task.fields.items()}}
    bad = dict(good)
    rock: Any = np.empty((0, 3), dtype=np.int64)
    if refused == "rock" and vmap is not None:
        rock = np.argwhere(vmap.state == OCCUPIED)
    what = "inside rock" if len(rock) else "outside the map"
    for name, p in positions.items():
        if len(rock):
            centres = vmap.index_to_world(rock)
            k = int(np.argmin(np.sum((centres - np.asarray(p, dtype=float)) ** 2, axis=1)))
            bad[name] = [round(float(x), 3) for x in centres[k]]
        else:
            hi = vmap.bounds[1] if vmap is not None else (1e6, 1e6, 1e6)
            bad[name] = [float(hi[0]) + 10.0, float(p[1]), float(p[2])]
    return good, bad, what


# ------------------------------------------------------------------------------ one run
@dataclass
class RunPoint:
    """One measured run."""

    variant: str
    repeat: int
    sim_s: float
    wall_s: float
    build_s: float
    done: tuple[str, ...]
    tasks: int
    """Tasks in the pool at the end (the mission's and the added ones)."""
    reader: ClientStats | None = None
    dropped: dict[str, int] = field(default_factory=dict)
    poll: LoadLog | None = None
    flood: LoadLog | None = None
    logged_adds: int = 0
    """``task_added`` events of the log by the flood's client."""
    cpu_s: dict[str, float] = field(default_factory=dict)
    """CPU seconds during the run loop: the run's thread (``run``), the server's threads
    (``server``), the viewer's others (``viewer``); empty where the OS does not tell."""
    clock: list[tuple[float, float]] = field(default_factory=list)
    """``(simulated s, time.perf_counter)`` every simulated second of the run loop."""

    @property
    def speed(self) -> float:
        return self.sim_s / self.wall_s if self.wall_s > 0 else math.inf

    def cpu_share(self, role: str) -> float | None:
        return self.cpu_s[role] / self.wall_s if role in self.cpu_s and self.wall_s > 0 else None

    def flood_requests(self) -> list[Request]:
        return self.flood.requests if self.flood is not None else []

    def statuses(self, kind: str | None = None) -> Counter[int]:
        return Counter(r.status for r in self.flood_requests() if kind in (None, r.kind))

    def burst_s(self) -> float:
        return sum(end - start for start, end, _ in self.flood.bursts) if self.flood else 0.0

    def burst_speed(self) -> float | None:
        """Simulated s per wall s while bursts were being answered (None: no burst)."""
        if self.flood is None or not self.flood.bursts or len(self.clock) < 2:
            return None
        sim = wall = 0.0
        for start, end, _ in self.flood.bursts:
            a, b = sim_at(self.clock, start), sim_at(self.clock, end)
            lo, hi = max(start, self.clock[0][1]), min(end, self.clock[-1][1])
            if hi > lo:
                sim += b - a
                wall += hi - lo
        return sim / wall if wall > 0 else None


def sim_at(clock: Sequence[tuple[float, float]], wall: float) -> float:
    """The simulated time the run had reached at ``wall`` (``time.perf_counter``),
    interpolated in ``clock`` (``(simulated s, wall)`` pairs in time order)."""
    if wall <= clock[0][1]:
        return clock[0][0]
    for (t0, w0), (t1, w1) in itertools.pairwise(clock):
        if w0 <= wall <= w1:
            return t0 + (t1 - t0) * (wall - w0) / (w1 - w0) if w1 > w0 else t1
    return clock[-1][0]


def cpu_roles(
    before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]]
) -> dict[str, float]:
    """CPU seconds threads used between two :func:`thread_cpu` readings: ``run`` (the main
    thread), ``server`` (:data:`SERVER_THREADS`) and ``viewer`` (every other)."""
    if not after:
        return {}
    roles = {"run": 0.0, "server": 0.0, "viewer": 0.0}
    for tid, (name, cpu) in after.items():
        used = cpu - before.get(tid, (name, 0.0))[1]
        roles[
            "run" if name == "MainThread" else "server" if name in SERVER_THREADS else "viewer"
        ] += used
    return roles


def run_once(
    mission: Any,
    variant: str,
    duration_s: float,
    *,
    repeat: int = 0,
    seed: int = 0,
    controller: str | None = None,
    spec: FloodSpec | None = None,
    poll_hz: float = 1.0,
    log_dir: Path,
) -> RunPoint:
    """Run ``mission`` for ``duration_s`` simulated seconds as fast as it goes in ``variant``
    (module docstring; ``spec``: the flood, its add body included). The log goes to
    ``log_dir``."""
    from btmission.runtime.session import RunSession
    from btmission.viz.live import LiveViewer

    console = variant != "viewer"
    live = LiveViewer("127.0.0.1", 0, console=console, token=TOKEN)  # a free loopback port
    session = RunSession(
        mission,
        seed=seed,
        controller=controller,
        realtime=False,
        log_dir=log_dir,
        observers=[live.observer],
    )
    readers: list[ReaderProcess] = []
    loads: list[LoadProcess] = []
    clock: list[tuple[float, float]] = []
    cpu: dict[str, float] = {}
    result: Any = None
    tasks = 0
    try:
        with session:
            run = session.start()
            if run is None:
                raise ConsoleBenchError("the run was stopped while being built")
            live.attach(session, run)
            host, port = live.server.address[:2]
            readers.append(ReaderProcess(host, port))
            if console:
                loads.append(LoadProcess("poll", host, port, hz=poll_hz))
            if variant in FLOODS:
                loads.append(LoadProcess("flood", host, port, spec=spec))
            clients: list[ReaderProcess | LoadProcess] = [*readers, *loads]
            for client in clients:  # (listed first: ended below even if one fails)
                client.start()
            cpu0 = thread_cpu()
            clock.append((run.now(), time.perf_counter()))
            for load in loads:
                load.go()
            try:
                result = session.run(
                    duration_s, progress=lambda r: clock.append((r.now(), time.perf_counter()))
                )
            except BaseException:  # Ctrl-C: end the run, so that no request waits for a step
                if not session.ended:
                    session.end(run.result("interrupted"))
                raise
            clock.append((result.time_s, time.perf_counter()))
            for load in loads:
                load.stop()
            cpu = cpu_roles(cpu0, thread_cpu())
            tasks = len(run.coordinator.state.pool)
            t_end = time.perf_counter()
            for load in loads:  # before the end of the server: requests still going
                load.join(REQUEST_TIMEOUT_S + 10.0)
            live.finish()
            for r in readers:
                r.join(max(DRAIN_S - (time.perf_counter() - t_end), 0.0))
    finally:
        for load in loads:
            load.stop()
        for r in readers:
            r.stop()
        live.close()
        for load in loads:
            load.join(5.0)
        for r in readers:
            r.join(READ_TIMEOUT_S)
            r.end()
    assert session.log_path is not None and result is not None
    point = RunPoint(
        variant,
        repeat,
        result.time_s,
        result.wall_s,
        session.build_s,
        tuple(sorted(result.done)),
        tasks,
        readers[0].stats,
        dict(live.queue.dropped),
        next((ld.log for ld in loads if ld.role == "poll"), None),
        next((ld.log for ld in loads if ld.role == "flood"), None),
        cpu_s=cpu,
        clock=clock,
    )
    if console and point.poll is None:
        raise ConsoleBenchError("the page's status poll did not report")
    if variant in FLOODS and point.flood is None:
        raise ConsoleBenchError("the flood did not report")
    recs = log_records(session.log_path)
    try:
        check_run(_as_viewer_point(point), [r for r in recs if r["ev"] not in LOSSY_KINDS])
    except ViewerBenchError as exc:
        raise ConsoleBenchError(str(exc)) from None
    flood_adds = [
        str(r.get("task"))
        for r in recs
        if r["ev"] == "task_added" and str(r.get("by", "")).startswith(f"{FLOOD_CLIENT}@")
    ]
    point.logged_adds = len(flood_adds)
    check_adds(point, flood_adds)
    return point


def _as_viewer_point(p: RunPoint) -> Any:
    """The part of ``p`` :func:`btmission.bench.viewer.check_run` reads."""
    from btmission.bench.viewer import RunPoint as ViewerPoint

    return ViewerPoint(
        p.variant, p.repeat, 0, p.sim_s, p.wall_s, p.build_s, p.done, 0, 0, 0,
        [p.reader] if p.reader is not None else [], dict(p.dropped),
    )  # fmt: skip


def check_adds(point: RunPoint, logged: Sequence[str]) -> None:
    """:class:`ConsoleBenchError` unless every add answered 201 is in ``logged`` (the log's
    adds by the flood's client), every logged one was answered 201 or 202 (or got no answer),
    nothing was answered 5xx, and a refused flood's adds were all refused."""
    reqs = point.flood_requests() + (point.poll.requests if point.poll is not None else [])
    server_errors = Counter(r.status for r in reqs if r.status >= 500)
    if server_errors:
        raise ConsoleBenchError(f"{point.variant}: answers 5xx: {dict(server_errors)}")
    adds = [r for r in point.flood_requests() if r.kind == "add"]
    accepted = {r.task for r in adds if r.status == 201}
    missing = accepted - set(logged)
    if missing:
        raise ConsoleBenchError(
            f"{point.variant}: {len(missing)} add(s) answered 201 are not in the log: "
            f"{', '.join(sorted(missing)[:5])}"
        )
    queued = {r.task for r in adds if r.status == 202}
    lost = sum(1 for r in adds if r.status == 0)
    extra = set(logged) - accepted - queued
    if len(extra) > lost:
        raise ConsoleBenchError(
            f"{point.variant}: {len(extra)} add(s) in the log were not answered 201 or 202: "
            f"{', '.join(sorted(extra)[:5])}"
        )
    if point.variant == "refused":
        wrong = Counter(r.status for r in adds if r.status not in (409, 422, 429, 0))
        if wrong or logged:
            raise ConsoleBenchError(
                f"refused: adds the console should refuse were answered {dict(wrong)}, "
                f"{len(logged)} in the log"
            )


# ------------------------------------------------------------------------------ the benchmark
@dataclass
class Summary:
    """The runs of one variant, against the viewer-only runs of the same repeats."""

    variant: str
    runs: list[RunPoint]
    drops: list[float]
    """Per repeat, 1 - speed / speed of the viewer-only run (empty for ``viewer``)."""
    mean_drop: float | None
    """1 - mean speed / mean speed of the viewer-only runs of the same repeats."""

    @property
    def speed(self) -> float:
        return statistics.median(p.speed for p in self.runs)

    @property
    def drop(self) -> float | None:
        return statistics.median(self.drops) if self.drops else None


def summarize(points: Sequence[RunPoint]) -> list[Summary]:
    base = {p.repeat: p for p in points if p.variant == "viewer"}
    out = []
    for variant in VARIANTS:
        runs = [p for p in points if p.variant == variant]
        if not runs:
            continue
        paired = [p for p in runs if p.repeat in base] if variant != "viewer" else []
        drops = [1.0 - p.speed / base[p.repeat].speed for p in paired]
        mean_drop = (
            1.0
            - statistics.mean(p.speed for p in paired)
            / statistics.mean(base[p.repeat].speed for p in paired)
            if paired
            else None
        )
        out.append(Summary(variant, runs, drops, mean_drop))
    return out


def percentiles(xs: Sequence[float]) -> tuple[float, float] | None:
    """The median and the 99th percentile (nearest rank) of ``xs``; None if empty."""
    if not xs:
        return None
    s = sorted(xs)
    return statistics.median(s), s[min(math.ceil(0.99 * len(s)) - 1, len(s) - 1)]


def _ms(reqs: Sequence[Request], statuses: Sequence[int]) -> str:
    """p50, p99 latency in ms of the requests answered with one of ``statuses``."""
    pair = percentiles([r.latency_s for r in reqs if r.status in statuses])
    return f"{1000 * pair[0]:.1f}, {1000 * pair[1]:.1f}" if pair else "—"


def _pct(x: float | None, sign: bool = True) -> str:
    if x is None:
        return "—"
    return f"{100 * x:+.1f} %" if sign else f"{100 * x:.1f} %"


ANSWERED = (200, 201, 202, 409, 422)
"""Statuses after the console did the work (429 is refused before any)."""


def flood_stats(runs: Sequence[RunPoint]) -> dict[str, Any]:
    """The floods of ``runs`` pooled: requests, answered per burst second, 429 share, adds."""
    reqs = [r for p in runs for r in p.flood_requests()]
    burst_s = sum(p.burst_s() for p in runs)
    codes = Counter(r.status for r in reqs)
    adds = Counter(r.status for r in reqs if r.kind == "add")
    return {
        "requests": len(reqs),
        "bursts": sum(len(p.flood.bursts) for p in runs if p.flood is not None),
        "per_s": len(reqs) / burst_s if burst_s else 0.0,
        "answered_per_s": sum(codes[c] for c in ANSWERED) / burst_s if burst_s else 0.0,
        "share_429": codes[429] / len(reqs) if reqs else 0.0,
        "codes": codes,
        "adds": adds,
        "errors": codes[0],
    }


def _codes(codes: Counter[int]) -> str:
    return ", ".join(f"{c or 'none'}: {n:,}" for c, n in sorted(codes.items())) or "—"


SUMMARY_HEAD = (
    "variant",
    "runs",
    "speed × real time (median)",
    "drop vs viewer only (median of pairs, range)",
    "drop (ratio of means)",
    "speed during bursts (median)",
    "server threads' CPU, % of wall (median)",
    "viewer's other threads' CPU, %",
    "flood: answered / s in bursts (all, not 429)",
    "flood: 429 share",
    "status GET ms (p50, p99)",
    "add POST ms (p50, p99)",
    "adds: accepted / refused 422 / 429 (per run, median)",
    "page polls: 200 of sent, ms (p50, p99)",
    "same tasks done as viewer only",
)


def _median(xs: Sequence[float | None]) -> float | None:
    vals = [x for x in xs if x is not None]
    return statistics.median(vals) if vals else None


def summary_cells(s: Summary, base: dict[int, RunPoint]) -> list[str]:
    runs = s.runs
    server = _median([p.cpu_share("server") for p in runs])
    viewer = _median([p.cpu_share("viewer") for p in runs])
    first = [
        VARIANTS[s.variant],
        str(len(runs)),
        f"{s.speed:.2f}",
        f"{_pct(s.drop)} ({_pct(min(s.drops))} … {_pct(max(s.drops))})" if s.drops else "—",
        _pct(s.mean_drop),
    ]
    burst_speed = _median([p.burst_speed() for p in runs])
    cpu = [_pct(server, False), _pct(viewer, False)]
    polls = [r for p in runs if p.poll is not None for r in p.poll.requests]
    page = (
        f"{sum(r.status == 200 for r in polls)} of {len(polls)}; {_ms(polls, (200,))}"
        if polls
        else "—"
    )
    if s.variant == "viewer":
        same = "—"
    elif s.variant == "flood":
        same = "— (tasks added)"
    else:
        same = (
            "yes"
            if all(p.done == base[p.repeat].done for p in runs if p.repeat in base)
            else "**no**"
        )
    if s.variant not in FLOODS:
        status = [r for p in runs if p.poll is not None for r in p.poll.requests]
        return [
            *first, "—", *cpu, "—", "—", _ms(status, (200,)) if status else "—", "—", "—",
            page, same,
        ]  # fmt: skip
    f = flood_stats(runs)
    reqs = [r for p in runs for r in p.flood_requests()]
    per_run = [p.statuses("add") for p in runs]
    adds = " / ".join(
        f"{statistics.median(sum(c[x] for x in codes) for c in per_run):,.0f}"
        for codes in ((201, 202), (422,), (429,))
    )
    return [
        *first,
        f"{burst_speed:.2f}" if burst_speed is not None else "—",
        *cpu,
        f"{f['per_s']:,.0f}, {f['answered_per_s']:,.0f}",
        _pct(f["share_429"], False),
        _ms([r for r in reqs if r.kind == "status"], (200,)),
        _ms([r for r in reqs if r.kind == "add"], (201, 202, 422)),
        adds,
        page,
        same,
    ]


RUNS_HEAD = (
    "#",
    "variant",
    "simulated s",
    "wall s",
    "speed ×",
    "drop %",
    "speed in bursts",
    "server CPU %",
    "viewer CPU %",
    "tasks done / in pool",
    "bursts",
    "flood answers by status",
    "status GET ms (p50, p99)",
    "add POST ms (p50, p99)",
    "flood adds in the log",
    "page polls 200 / sent",
    "reader complete",
)


def run_cells(i: int, p: RunPoint, base: dict[int, RunPoint]) -> list[str]:
    b = base.get(p.repeat)
    drop = 1.0 - p.speed / b.speed if b is not None and p.variant != "viewer" else None
    reqs = p.flood_requests()
    burst_speed = p.burst_speed()
    server, viewer = p.cpu_share("server"), p.cpu_share("viewer")
    polls = p.poll.requests if p.poll is not None else []
    flooded = p.variant in FLOODS
    status_reqs = [r for r in reqs if r.kind == "status"] if flooded else polls
    return [
        str(i),
        VARIANTS[p.variant],
        f"{p.sim_s:.1f}",
        f"{p.wall_s:.2f}",
        f"{p.speed:.2f}",
        f"{100 * drop:+.1f}" if drop is not None else "—",
        f"{burst_speed:.2f}" if burst_speed is not None else "—",
        f"{100 * server:.1f}" if server is not None else "—",
        f"{100 * viewer:.1f}" if viewer is not None else "—",
        f"{len(p.done)} / {p.tasks}",
        str(len(p.flood.bursts)) if p.flood is not None else "—",
        _codes(p.statuses()) if flooded else "—",
        _ms(status_reqs, (200,)) if status_reqs else "—",
        _ms([r for r in reqs if r.kind == "add"], (201, 202, 422)) if flooded else "—",
        str(p.logged_adds) if flooded else "—",
        f"{sum(r.status == 200 for r in polls)} / {len(polls)}" if p.poll is not None else "—",
        "yes" if p.reader is not None and p.reader.complete else "no",
    ]


@dataclass(frozen=True)
class ConsoleConfig:
    """What ``btmission bench console`` measures (module docstring)."""

    mission: str | None = DEFAULT_MISSION
    """A mission file; None: ``bench viewer``'s floor of ``agents`` robots and ``tasks``."""
    agents: int = 30
    tasks: int = 60
    duration_s: float = 80.0
    pairs: int = 5
    variants: tuple[str, ...] = tuple(VARIANTS)
    controller: str | None = "track"
    seed: int = 0
    burst: int = 1000
    adds: int = 200
    threads: int = 16
    every_s: float = 2.0
    poll_hz: float = 1.0
    refused: str = "rock"
    """Where the refused adds go: ``rock`` (next to the valid one) or ``outside`` the map."""
    warmup_s: float = 30.0
    """Simulated seconds of one unmeasured flood run first (caches, imports)."""

    def mission_name(self) -> str:
        if self.mission is None:
            return (
                f"`bench viewer`'s scaling floor: {self.agents} ground robots and {self.tasks} "
                "inspection tasks on 100 m × 100 m"
            )
        return f"`{self.mission}`"


def markdown(
    cfg: ConsoleConfig,
    points: Sequence[RunPoint],
    env: dict[str, str],
    command: str,
    refused_what: str = "",
) -> str:
    base = {p.repeat: p for p in points if p.variant == "viewer"}
    sums = summarize(points)
    variants = [v for v in VARIANTS if any(p.variant == v for p in points)]
    flood = [p for p in points if p.variant in FLOODS]
    accepted = sum(p.statuses("add")[201] + p.statuses("add")[202] for p in flood)
    logged = sum(p.logged_adds for p in flood)
    checks = [
        "**Checked in every run:** no answer was 5xx; every add answered 201 or 202 is a "
        f"`task_added` event of the run's log ({accepted:,} such answers, {logged:,} flood adds "
        "in the logs); the refused flood's adds were all answered 422 or 429 and none reached "
        "the run; the stream reader received every record of the log other than poses and "
        "routes, in order; the runs that add nothing did the same tasks as the viewer-only run "
        "of their pair.",
        "",
    ]
    lines = [
        "# Console benchmark",
        "",
        *header_lines(env),
        f"- command: `{command}`",
        "",
        f"The mission {cfg.mission_name()}, controller {cfg.controller or 'the mission’s'}, "
        f"seed {cfg.seed}, run for {cfg.duration_s:g} simulated seconds as fast as it goes (no "
        f"pacing), with its event log, in alternating runs ({', '.join(variants)}, then the "
        f"other way round, …; {cfg.pairs} repeat(s) after one unmeasured {cfg.warmup_s:g} s "
        "flood run). Every run is served as `btmission run` serves it (`LiveViewer` on "
        "127.0.0.1) with one reader of `/api/stream` in a process of its own. *viewer only*: "
        "`run --view`, the baseline. *console, idle*: `run --console` "
        "(`LiveViewer(console=True)`) and one open page's status poll, `GET /api/status` every "
        f"{1 / cfg.poll_hz:g} s from a second process. *flood*: the same plus a third process "
        f"sending a burst of {cfg.burst:,} requests ({cfg.burst - cfg.adds:,} `GET /api/status`, "
        f"{cfg.adds:,} `POST /api/tasks`, shuffled) from {cfg.threads} threads on keep-alive "
        f"connections, every {cfg.every_s:g} s (or as soon as the last one was answered). "
        "*valid adds*: copies of the mission's first task (a new task each, for the auction); "
        f"*refused adds*: the same moved {refused_what or 'where the console refuses it'} (422).",
        "",
        "Speed = simulated s / wall s of the run loop; drop = 1 − speed / speed of the viewer-only "
        "run of the same repeat (median of the pairs and their range), and 1 − the ratio of the "
        "mean speeds. Speed during bursts: simulated seconds the run advanced while a burst was "
        "being answered, per wall second. CPU: the threads of the run's process, as a share of "
        "the run loop's wall time: the server (uvicorn's event loop and the threads running its "
        "routes) and the viewer's others (its queue and pose sampler). Latency: from sending a "
        "request to the end of its answer, as the client measured it (answered ones: a status "
        "200, an add 201/202/422); answered / s: the flood's answers per second of its bursts "
        "(all, and those not refused 429); adds accepted: answered 201 (or 202, queued).",
        "",
        *checks,
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
        "Regenerate with `btmission bench console` or `python benchmarks/bench_console.py`.",
        "",
    ]
    return "\n".join(lines)


CSV_HEAD = (
    "repeat", "variant", "sim_s", "wall_s", "speed", "drop", "burst_speed", "build_s",
    "tasks_done", "tasks_in_pool", "run_cpu_s", "server_cpu_s", "viewer_cpu_s", "bursts",
    "burst_s", "flood_requests", "flood_200", "flood_201", "flood_202", "flood_409",
    "flood_422", "flood_429", "flood_other", "flood_errors", "status_ms_p50", "status_ms_p99",
    "add_ms_p50", "add_ms_p99", "adds_logged", "polls", "polls_200", "poll_ms_p50",
    "poll_ms_p99", "reader_complete", "reader_records", "reconnects",
)  # fmt: skip


def _ms_pair(reqs: Sequence[Request], statuses: Sequence[int]) -> list[str]:
    pair = percentiles([r.latency_s for r in reqs if r.status in statuses])
    return [f"{1000 * pair[0]:.2f}", f"{1000 * pair[1]:.2f}"] if pair else ["", ""]


def write_csv(path: Path, points: Sequence[RunPoint]) -> None:
    base = {p.repeat: p for p in points if p.variant == "viewer"}
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_HEAD)
        for p in points:
            b = base.get(p.repeat)
            drop = (
                f"{1.0 - p.speed / b.speed:.4f}" if b is not None and p.variant != "viewer" else ""
            )
            reqs = p.flood_requests()
            codes = p.statuses()
            polls = p.poll.requests if p.poll is not None else []
            bs = p.burst_speed()
            known = (200, 201, 202, 409, 422, 429, 0)
            w.writerow(
                [
                    p.repeat, p.variant, f"{p.sim_s:.2f}", f"{p.wall_s:.3f}", f"{p.speed:.3f}",
                    drop, f"{bs:.3f}" if bs is not None else "", f"{p.build_s:.3f}",
                    len(p.done), p.tasks,
                    *(f"{p.cpu_s[k]:.2f}" if k in p.cpu_s else "" for k in ("run", "server", "viewer")),
                    len(p.flood.bursts) if p.flood is not None else "", f"{p.burst_s():.3f}",
                    len(reqs), *(codes[c] for c in (200, 201, 202, 409, 422, 429)),
                    sum(n for c, n in codes.items() if c not in known), codes[0],
                    *_ms_pair([r for r in reqs if r.kind == "status"], (200,)),
                    *_ms_pair([r for r in reqs if r.kind == "add"], (201, 202, 422)),
                    p.logged_adds, len(polls), sum(r.status == 200 for r in polls),
                    *_ms_pair(polls, (200,)),
                    p.reader.complete if p.reader is not None else "",
                    p.reader.records if p.reader is not None else "",
                    sum(x.reconnects for x in (p.flood, p.poll) if x is not None),
                ]
            )  # fmt: skip


def run_console_benchmark(
    cfg: ConsoleConfig,
    out_dir: Path | str | None = Path("benchmarks/results"),
    echo: Callable[[str], object] = print,
    progress: Callable[[str], object] | None = None,
    command: str = "btmission bench console",
) -> list[RunPoint]:
    """Measure (module docstring): each run is told to ``progress`` (default ``echo``) as it
    ends, the summary to ``echo``; write ``console.md`` and ``console.csv`` to ``out_dir``
    (None: write nothing)."""
    say = progress if progress is not None else echo
    env = environment()
    mission = load_bench_mission(cfg.mission, cfg.agents, cfg.tasks)
    variants = [v for v in VARIANTS if v in cfg.variants]
    if "viewer" not in variants:
        raise ConsoleBenchError("the viewer-only runs are the baseline: keep the variant 'viewer'")
    say(
        f"console benchmark: {mission.name}, {len(mission.agents)} agent(s), "
        f"{cfg.duration_s:g} simulated s, {cfg.pairs} × ({', '.join(variants)}); "
        f"{env['machine']}, {env['cpus']} CPU(s)"
    )
    points: list[RunPoint] = []
    refused_what = ""
    with tempfile.TemporaryDirectory(prefix="btmission-bench-console-") as tmp:
        logs = Path(tmp)
        good, bad, refused_what = add_bodies(mission, mission_map(mission), cfg.refused)
        specs = {
            v: FloodSpec(
                cfg.burst,
                cfg.adds,
                cfg.threads,
                cfg.every_s,
                good if v == "flood" else bad,
                cfg.seed,
            )
            for v in FLOODS
        }
        warm = next((v for v in ("flood", "refused", "idle") if v in variants), "viewer")
        if cfg.warmup_s > 0:
            say(f"warm-up: one {cfg.warmup_s:g} s {warm} run (not measured)")
            run_once(mission, warm, cfg.warmup_s, seed=cfg.seed, controller=cfg.controller,
                     spec=specs.get(warm), poll_hz=cfg.poll_hz, log_dir=logs / "warmup")  # fmt: skip
        say("")
        say(_row(RUNS_HEAD))
        say(_row(["---"] * len(RUNS_HEAD)))
        for rep in range(cfg.pairs):
            order = variants if rep % 2 == 0 else variants[::-1]  # V I F R, R F I V: drift cancels
            for variant in order:
                p = run_once(
                    mission,
                    variant,
                    cfg.duration_s,
                    repeat=rep,
                    seed=cfg.seed,
                    controller=cfg.controller,
                    spec=specs.get(variant),
                    poll_hz=cfg.poll_hz,
                    log_dir=logs / f"{rep}-{variant}",
                )
                points.append(p)  # (its drop is "—" here until its pair's baseline ran)
                base = {q.repeat: q for q in points if q.variant == "viewer"}
                say(_row(run_cells(len(points), p, base)))
    base = {p.repeat: p for p in points if p.variant == "viewer"}
    echo("")
    echo(_row(SUMMARY_HEAD))
    echo(_row(["---"] * len(SUMMARY_HEAD)))
    for s in summarize(points):
        echo(_row(summary_cells(s, base)))
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_page(out / "console.md", markdown(cfg, points, env, command, refused_what))
        write_csv(out / "console.csv", points)
        say(f"wrote {out / 'console.md'} and {out / 'console.csv'}")
    return points


def mission_map(mission: Any) -> Any:
    """The mission's voxel map, as a run builds it (to place the refused adds)."""
    from btmission.world.build import world_from_spec

    return world_from_spec(mission.spec.world, mission.base_dir)
