"""Transport benchmark: auction rounds over Zenoh on loopback, side by side with the in-process bus.

``btmission bench transport`` (or ``python benchmarks/bench_transport.py``) runs, for each size
(agents × tasks; 10×40 and 50×400 by default), whole coordination rounds over two transports in
the same run:

* **in-memory** — :class:`~btmission.links.bus.InMemoryBus`: messages are Python objects
  handed over synchronously (no encoding);
* **zenoh** — :class:`~btmission.transport.zenoh_link.ZenohCoordinatorLink` in this process
  and one :class:`~btmission.transport.zenoh_link.ZenohAgentLink` per agent, each with its own
  Zenoh session (as on separate robots), in a separate process by default (the agents' side of
  a fleet), connected over ``tcp/127.0.0.1``: every message is encoded
  (:mod:`btmission.links.wire`), sent and decoded.

One **round** is: announce the open tasks → every agent computes its bid (straight-line costs
from where it is to each announced task, its ``⌈p·n⌉`` cheapest kept; every agent moves 0.1 m
per round, so bids change) and sends it → the coordinator waits for all of them → solves
(:func:`~btmission.allocation.auction.auction_round`) → sends the assignment → every agent
confirms it with a status report. Rounds run back to back; the *rate* is rounds per second of
wall time, the *latency* of a round is from the announcement to the last confirmation (p50,
p99), split into bids (announce → last bid in), solve, and assign (→ last confirmation).
Message sizes are the wire sizes (bytes of JSON, format version 2: a bid's costs in base64,
an assignment naming an unchanged announcement by serial) of that size's messages.

Zenoh's shared-memory transport (same-host sessions hand large payloads over in shared memory)
is off by default, so the numbers are for bytes through TCP, as between machines. Every wait is
bounded (``timeout_s``); a round that does not complete in time ends the benchmark with an error.
"""

from __future__ import annotations

import argparse
import csv
import gc
import math
import re
import resource
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from btmission.allocation.auction import (
    Announcement,
    AuctionConfig,
    AuctionState,
    Bid,
    announce,
    auction_round,
    participation_k,
)
from btmission.allocation.tasks import TaskInfo, TaskPool
from btmission.bench.auction import AREA_M, keep_cheapest
from btmission.bench.synth import _load1, describe_load, environment
from btmission.errors import BtmissionError
from btmission.links import wire
from btmission.links.bus import (
    AgentLink,
    AgentStatus,
    Assignment,
    CoordinatorInbox,
    CoordinatorLink,
    InMemoryBus,
    ProgressAck,
)

TARGET_HZ = 50.0
"""A round over Zenoh at 50 agents × 400 tasks at this rate or faster (issue #17)."""
TARGET_SIZE = (50, 400)
STEP_M = 0.1
"""How far every agent moves between two rounds (so its bids change)."""
TRANSPORTS = ("in-memory", "zenoh")


class BenchError(BtmissionError, RuntimeError):
    """The benchmark could not run (a round timed out, the agents' process failed ...)."""


@dataclass(frozen=True)
class Layout:
    """Where the agents' Zenoh links run: in ``processes`` child processes (0: a thread of the
    coordinator's process), each agent with a session of its own or one shared per process."""

    processes: int = 1
    shared_session: bool = False

    def __post_init__(self) -> None:
        if self.processes < 0:
            raise ValueError("processes must be ≥ 0")

    @property
    def label(self) -> str:
        """``1:each``, ``2:shared``, ``thread:each`` ... (the ``--layouts`` syntax)."""
        where = "thread" if self.processes == 0 else str(self.processes)
        return f"{where}:{'shared' if self.shared_session else 'each'}"

    def describe(self, n_agents: int) -> str:
        where = (
            "a thread of the coordinator's process"
            if self.processes == 0
            else f"{min(self.processes, n_agents)} process(es)"
        )
        sessions = "one session per process" if self.shared_session else "a session each"
        return f"agents in {where}, {sessions}"

    @classmethod
    def parse(cls, text: str) -> Layout:
        """``P:S`` with P a number of processes or ``thread``, S ``each`` or ``shared``."""
        where, _, sessions = text.strip().partition(":")
        try:
            processes = 0 if where == "thread" else int(where)
        except ValueError:
            processes = -1
        if (
            processes < 0
            or (processes == 0 and where != "thread")
            or sessions not in ("each", "shared")
        ):
            raise ValueError(
                f"'{text}' is not a layout (PROCESSES:each|shared, e.g. 1:each, 2:shared, thread:each)"
            )
        return cls(processes, sessions == "shared")


DEFAULT_LAYOUTS = (Layout(1, False), Layout(2, True))
"""One agents' process with a Zenoh session per agent (the fleet's topology: 50 sessions,
50 connections), and two processes with one session each (less of the agents' CPU)."""


@dataclass(frozen=True)
class TransportBenchConfig:
    """What to measure (the defaults are the full run; :meth:`quick` a short one)."""

    sizes: tuple[tuple[int, int], ...] = ((10, 40), (50, 400))
    rounds: int = 300
    warmup: int = 10
    participation: float = 0.9
    layouts: tuple[Layout, ...] = DEFAULT_LAYOUTS
    """The agents' sides measured over Zenoh (a row each)."""
    shared_memory: bool = False
    """Let Zenoh pass large payloads between the processes through shared memory."""
    timeout_s: float = 20.0
    """Bound of every wait (a round that takes longer is an error)."""
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.sizes:
            raise ValueError("give at least one size")
        for na, nt in self.sizes:
            if na < 1 or nt < 1:
                raise ValueError(f"bad size {na}x{nt}")
        if not self.layouts:
            raise ValueError("give at least one layout")
        if self.rounds < 1 or self.warmup < 0:
            raise ValueError("rounds must be ≥ 1 and warmup ≥ 0")
        if not 0 < self.participation <= 1:
            raise ValueError(f"participation must be in (0, 1], got {self.participation}")
        if not (math.isfinite(self.timeout_s) and self.timeout_s > 0):
            raise ValueError("timeout_s must be a finite number of seconds > 0")

    @classmethod
    def quick(cls, **overrides: Any) -> TransportBenchConfig:
        return replace(cls(rounds=60, warmup=5), **overrides)


# --------------------------------------------------------------------------------------------
# The instance: tasks and agents, the same in every process for a seed
# --------------------------------------------------------------------------------------------
def mission_name(n_agents: int, n_tasks: int) -> str:
    return f"bench-{n_agents}x{n_tasks}"


def agent_ids(n_agents: int) -> list[str]:
    return [f"R{i:04d}" for i in range(n_agents)]


def task_pool(n_agents: int, n_tasks: int, seed: int) -> TaskPool:
    rng = np.random.default_rng([seed, n_agents, n_tasks, 1])
    xy = rng.uniform(0, AREA_M, (n_tasks, 2))
    return TaskPool().add_all(
        TaskInfo(f"T{j:05d}", "inspect", {"location": [float(x), float(y), 0.0]})
        for j, (x, y) in enumerate(xy)
    )


def agent_motion(n_agents: int, n_tasks: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Every agent's start (n, 2) and step per round (n, 2)."""
    rng = np.random.default_rng([seed, n_agents, n_tasks, 2])
    start = rng.uniform(0, AREA_M, (n_agents, 2))
    heading = rng.uniform(0, 2 * np.pi, n_agents)
    return start, STEP_M * np.stack([np.cos(heading), np.sin(heading)], axis=1)


_XY_CACHE: dict[int, tuple[Announcement, np.ndarray]] = {}
_XY_LOCK = threading.Lock()


def task_xy(ann: Announcement) -> np.ndarray:
    """The announced tasks' (x, y), computed once per announcement object (agents sharing a
    process share the decoded announcement)."""
    with _XY_LOCK:
        hit = _XY_CACHE.get(id(ann))
        if hit is not None and hit[0] is ann:
            return hit[1]
    xy = np.array([t.fields["location"][:2] for t in ann.tasks], dtype=np.float64).reshape(-1, 2)
    with _XY_LOCK:
        _XY_CACHE.clear()
        _XY_CACHE[id(ann)] = (ann, xy)
    return xy


class BenchAgent:
    """An agent of the benchmark: it bids its straight-line costs on every announcement and
    confirms every assignment with a status report (``action = "round <k>"``)."""

    def __init__(
        self, link: AgentLink, start: np.ndarray, step: np.ndarray, participation: float
    ) -> None:
        self.link = link
        self.id = link.agent
        self.pos = np.asarray(start, dtype=np.float64).copy()
        self.step = np.asarray(step, dtype=np.float64)
        self.participation = participation
        self.rounds = 0
        link.connect(self.on_announcement, self.on_assignment, self.on_ack)

    def on_announcement(self, ann: Announcement) -> None:
        self.rounds += 1
        self.pos = self.pos + self.step
        xy = task_xy(ann)
        costs = np.sqrt(((xy - self.pos) ** 2).sum(axis=1))[None, :]
        k = participation_k(self.participation, len(ann))
        row = keep_cheapest(costs, k)[0] if len(ann) else costs[0]
        self.link.send_bid(Bid.aligned(self.id, self.rounds * 0.1, ann, row))

    def on_assignment(self, a: Assignment) -> None:
        p = self.pos
        status = AgentStatus(
            self.id, a.time_s, (float(p[0]), float(p[1]), 0.0), "HOLD", True, 1.0,
            a.tasks.get(self.id), f"round {a.round}",
        )  # fmt: skip
        self.link.send_status(status)

    def on_ack(self, ack: ProgressAck) -> None:
        pass


# --------------------------------------------------------------------------------------------
# The coordinator's rounds
# --------------------------------------------------------------------------------------------
@dataclass
class RoundTimes:
    total_ms: list[float] = field(default_factory=list)
    bids_ms: list[float] = field(default_factory=list)
    solve_ms: list[float] = field(default_factory=list)
    assign_ms: list[float] = field(default_factory=list)
    wall_s: float = 0.0
    cpu_s: float = 0.0
    """This process's CPU time (all its threads) over the timed rounds."""
    changes: int = 0
    assignments: list[dict[str, str | None]] = field(default_factory=list)


Waiter = Callable[[Callable[[CoordinatorInbox], bool]], bool]


def run_rounds(
    link: CoordinatorLink,
    wait: Waiter | None,
    n_agents: int,
    n_tasks: int,
    cfg: TransportBenchConfig,
) -> RoundTimes:
    """``warmup + rounds`` rounds through ``link`` (module docstring); ``wait(predicate)`` waits
    (bounded) until the pending inbox satisfies it (None: the link is synchronous)."""
    state = AuctionState(
        AuctionConfig(participation=cfg.participation, agent_timeout_s=1e6),
        task_pool(n_agents, n_tasks, cfg.seed),
    )
    times = RoundTimes()
    statuses: list[AgentStatus] = []
    gc.collect()
    t_start = cpu_start = 0.0
    for k in range(cfg.warmup + cfg.rounds):
        if k == cfg.warmup:
            t_start, cpu_start = time.perf_counter(), time.process_time()
        now = k * 0.1
        t0 = time.perf_counter()
        state = announce(state, now)
        ann = state.announcement
        link.announce(ann)
        if wait is not None:
            serial = ann.serial

            def all_bids(inbox: CoordinatorInbox, serial: int = serial) -> bool:
                return len({b.agent for b in inbox.bids if b.serial == serial}) >= n_agents

            if not wait(all_bids):
                raise BenchError(f"round {k}: the bids of {n_agents} agents did not all arrive")
        inbox = link.drain()
        t1 = time.perf_counter()
        assignments, state, report = auction_round(state, inbox.bids, now)
        t2 = time.perf_counter()
        tag = f"round {report.round}"
        link.assign(Assignment(now, report.round, assignments, ann))
        if wait is not None:

            def confirmed(inbox: CoordinatorInbox, tag: str = tag) -> bool:
                return sum(s.action == tag for s in inbox.statuses) >= n_agents

            if not wait(confirmed):
                raise BenchError(f"round {k}: not every agent confirmed its assignment")
        statuses = link.drain().statuses
        t3 = time.perf_counter()
        if sum(s.action == tag for s in statuses) < n_agents:
            raise BenchError(f"round {k}: {len(statuses)} confirmations for {n_agents} agents")
        if k >= cfg.warmup:
            times.total_ms.append((t3 - t0) * 1e3)
            times.bids_ms.append((t1 - t0) * 1e3)
            times.solve_ms.append((t2 - t1) * 1e3)
            times.assign_ms.append((t3 - t2) * 1e3)
            times.changes += len(report.changes)
            if len(times.assignments) < 3:
                times.assignments.append(dict(assignments))
    times.wall_s = time.perf_counter() - t_start
    times.cpu_s = time.process_time() - cpu_start
    return times


@dataclass(frozen=True)
class Sizes:
    """Wire sizes (bytes) of one size's messages."""

    announcement: int
    bid: int
    assignment: int
    """With its announcement inside."""
    assignment_named: int
    """Naming its announcement by serial (wire format 2), as most rounds send it."""
    status: int


def message_sizes(n_agents: int, n_tasks: int, cfg: TransportBenchConfig) -> Sizes:
    pool = task_pool(n_agents, n_tasks, cfg.seed)
    state = announce(AuctionState(AuctionConfig(participation=cfg.participation), pool), 0.0)
    ann = state.announcement
    bus = InMemoryBus()
    start, step = agent_motion(n_agents, n_tasks, cfg.seed)
    agent = BenchAgent(bus.agent_link(agent_ids(n_agents)[0]), start[0], step[0], cfg.participation)
    agent.on_announcement(ann)
    (bid,) = bus.drain().bids
    ids = agent_ids(n_agents)
    tasks: dict[str, str | None] = {
        a: (ann.ids[i] if i < len(ann) else None) for i, a in enumerate(ids)
    }
    assignment = Assignment(0.0, 1, tasks, ann)
    agent.on_assignment(assignment)
    (status,) = bus.drain().statuses
    return Sizes(
        len(wire.encode(ann)),
        len(wire.encode(bid)),
        len(wire.encode(assignment)),
        len(wire.encode(assignment, embed=False)),
        len(wire.encode(status)),
    )


@dataclass(frozen=True)
class Point:
    """One transport at one size."""

    transport: str
    layout: str
    """Where the agents ran (:attr:`Layout.label`; ``—`` in memory)."""
    agents: int
    tasks: int
    rounds: int
    rate_hz: float
    p50_ms: float
    p99_ms: float
    bids_ms: float
    solve_ms: float
    assign_ms: float
    sizes: Sizes
    bytes_per_round: float
    """Bytes the coordinator sent and received per round (Zenoh; 0 in memory)."""
    coordinator_cpu_ms: float
    """CPU per round of the coordinator's process (in memory: everything, agents included)."""
    agents_cpu_ms: float | None
    """CPU per round of the agents' processes (None: they ran in the coordinator's)."""
    same_assignments: bool | None = None
    """The first rounds assigned as the in-memory bus did (Zenoh rows)."""


def _pct(xs: Sequence[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, max(0, math.ceil(q * len(s)) - 1))]


def _point(transport: str, layout: str, na: int, nt: int, t: RoundTimes, sizes: Sizes,
           nbytes: float, agents_cpu_s: float | None = None, same: bool | None = None) -> Point:  # fmt: skip
    n = max(1, len(t.total_ms))
    return Point(
        transport,
        layout,
        na,
        nt,
        len(t.total_ms),
        len(t.total_ms) / t.wall_s if t.wall_s > 0 else math.inf,
        statistics.median(t.total_ms),
        _pct(t.total_ms, 0.99),
        statistics.median(t.bids_ms),
        statistics.median(t.solve_ms),
        statistics.median(t.assign_ms),
        sizes,
        nbytes,
        t.cpu_s / n * 1e3,
        None if agents_cpu_s is None else agents_cpu_s / n * 1e3,
        same,
    )


def measure_in_memory(na: int, nt: int, cfg: TransportBenchConfig) -> tuple[Point, RoundTimes]:
    bus = InMemoryBus()
    start, step = agent_motion(na, nt, cfg.seed)
    for i, a in enumerate(agent_ids(na)):
        BenchAgent(bus.agent_link(a), start[i], step[i], cfg.participation)
    t = run_rounds(bus, None, na, nt, cfg)
    return _point("in-memory", "—", na, nt, t, message_sizes(na, nt, cfg), 0.0), t


class _Agents:
    """The agents' side over Zenoh: child processes (default) or a thread here."""

    def __init__(
        self, na: int, nt: int, endpoint: str, cfg: TransportBenchConfig, layout: Layout
    ) -> None:
        self.procs: list[subprocess.Popen[str]] = []
        self.thread: threading.Thread | None = None
        self.stop = threading.Event()
        self.error: BaseException | None = None
        if layout.processes > 0:
            n = min(layout.processes, na)
            for i in range(n):
                lo, hi = i * na // n, (i + 1) * na // n
                args = _agent_args(na, nt, endpoint, cfg, layout, lo, hi)
                self.procs.append(
                    subprocess.Popen(
                        [sys.executable, "-m", "btmission.bench.transport", "agents", *args],
                        stdin=subprocess.PIPE,
                        stdout=subprocess.PIPE,
                        stderr=subprocess.PIPE,
                        text=True,
                    )
                )
        else:
            args = _agent_args(na, nt, endpoint, cfg, layout, 0, na)

            def run() -> None:
                try:
                    agents_main(args, self.stop)
                except BaseException as exc:  # reported by close()
                    self.error = exc

            self.thread = threading.Thread(target=run, name="bench-agents", daemon=True)
            self.thread.start()

    def alive(self) -> bool:
        if self.procs:
            return all(p.poll() is None for p in self.procs)
        return self.thread is not None and self.thread.is_alive()

    def close(self, timeout_s: float) -> str:
        """Stop the agents (bounded); what a failed one said. Sets :attr:`cpu_s` (the agents'
        processes' CPU over the timed rounds, summed; None in a thread)."""
        said: list[str] = []
        self.cpu_s: float | None = 0.0 if self.procs else None
        for proc in self.procs:
            try:  # closes the child's stdin: at its end the child stops
                out, err = proc.communicate(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, err = proc.communicate(timeout=timeout_s)
            if proc.returncode != 0:
                said.append((err or "").strip() or f"exit status {proc.returncode}")
            for line in (out or "").splitlines():
                if line.startswith("cpu ") and self.cpu_s is not None:
                    self.cpu_s += float(line.split()[1])
        if self.thread is not None:
            self.stop.set()
            self.thread.join(timeout_s)
            if self.error is not None:
                said.append(f"{type(self.error).__name__}: {self.error}")
        return "; ".join(said)


def _agent_args(
    na: int, nt: int, endpoint: str, cfg: TransportBenchConfig, layout: Layout, lo: int, hi: int
) -> list[str]:
    args = ["--agents", str(na), "--tasks", str(nt), "--endpoint", endpoint,
            "--participation", repr(cfg.participation), "--seed", str(cfg.seed),
            "--first", str(lo), "--last", str(hi), "--warmup", str(cfg.warmup)]  # fmt: skip
    if layout.shared_session:
        args.append("--shared-session")
    if cfg.shared_memory:
        args.append("--shm")
    return args


def measure_zenoh(
    na: int,
    nt: int,
    cfg: TransportBenchConfig,
    layout: Layout = DEFAULT_LAYOUTS[0],
    reference: RoundTimes | None = None,
) -> Point:
    from btmission.transport.zenoh_link import ZenohCoordinatorLink
    from btmission.transport.zenoh_session import ZenohSettings, locators, loopback

    settings = ZenohSettings.coordinator(
        [loopback(0)], admin_space=True, shared_memory=cfg.shared_memory
    )
    ids = agent_ids(na)
    with ZenohCoordinatorLink(mission_name(na, nt), settings=settings) as link:
        (endpoint,) = locators(link.session)
        agents = _Agents(na, nt, endpoint, cfg, layout)

        def wait(pred: Callable[[CoordinatorInbox], bool]) -> bool:
            deadline = time.monotonic() + cfg.timeout_s
            while True:
                left = deadline - time.monotonic()
                if link.wait(pred, max(0.0, min(0.5, left))):
                    return True
                if not agents.alive():
                    raise BenchError("the agents' process ended")
                if left <= 0:
                    return False

        try:
            if not link.wait_for_agents(ids, cfg.timeout_s):
                missing = len(set(ids) - link.agents)
                raise BenchError(f"{missing} of {na} agents did not connect in {cfg.timeout_s:g} s")
            sent0, got0 = link.stats.sent_bytes, link.stats.received_bytes
            t = run_rounds(link, wait, na, nt, cfg)
            total = cfg.warmup + cfg.rounds
            nbytes = (link.stats.sent_bytes - sent0 + link.stats.received_bytes - got0) / total
            if link.stats.dropped:
                raise BenchError(f"the coordinator dropped messages: {link.stats.snapshot()}")
        except BenchError as exc:
            said = agents.close(cfg.timeout_s)
            raise BenchError(
                f"{exc}" + (f"; the agents said: {said[-2000:]}" if said else "")
            ) from None
        said = agents.close(cfg.timeout_s)
        if said:
            raise BenchError(f"the agents' side failed: {said[-2000:]}")
    same = None if reference is None else t.assignments == reference.assignments
    sizes = message_sizes(na, nt, cfg)
    return _point("zenoh", layout.label, na, nt, t, sizes, nbytes, agents.cpu_s, same)


def agents_main(argv: Sequence[str], stop: threading.Event | None = None) -> int:
    """The agents' side of a size (``python -m btmission.bench.transport agents ...``): one
    Zenoh agent link per agent, served by one loop, until stdin ends (or ``stop`` is set)."""
    from btmission.transport.zenoh_link import ZenohAgentLink, agent_links, close_all
    from btmission.transport.zenoh_session import ZenohSettings

    p = argparse.ArgumentParser(prog="btmission.bench.transport agents")
    p.add_argument("--agents", type=int, required=True)
    p.add_argument("--tasks", type=int, required=True)
    p.add_argument("--endpoint", required=True)
    p.add_argument("--participation", type=float, default=0.9)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--first", type=int, default=0, help="the first agent (index) served here")
    p.add_argument("--last", type=int, default=None, help="the agent after the last served here")
    p.add_argument("--warmup", type=int, default=0, help="rounds before the CPU is counted")
    p.add_argument("--shared-session", action="store_true")
    p.add_argument("--shm", action="store_true")
    a = p.parse_args(list(argv))
    own_stop = stop if stop is not None else threading.Event()
    if stop is None:  # a child process: stop at the end of stdin (the parent closes it)

        def watch_stdin() -> None:
            sys.stdin.read()
            own_stop.set()

        threading.Thread(target=watch_stdin, name="stdin", daemon=True).start()
    settings = ZenohSettings.agent([a.endpoint], shared_memory=a.shm, connect_timeout_s=20.0)
    last = a.agents if a.last is None else a.last
    links: list[ZenohAgentLink] = agent_links(
        mission_name(a.agents, a.tasks),
        agent_ids(a.agents)[a.first : last],
        settings,
        shared_session=a.shared_session,
    )
    try:
        start, step = agent_motion(a.agents, a.tasks, a.seed)
        agents = [
            BenchAgent(link, start[i], step[i], a.participation)
            for i, link in enumerate(links, start=a.first)
        ]
        mailbox = links[0].mailbox
        cpu_start: float | None = None
        deadline = time.monotonic() + 3600.0  # never outlive a forgotten parent for long
        while not own_stop.is_set() and time.monotonic() < deadline:
            mailbox.dispatch(0.05)
            if cpu_start is None and agents and agents[0].rounds > a.warmup:
                cpu_start = time.process_time()  # the first timed round has begun
        if cpu_start is not None and stop is None:  # a child's CPU over the timed rounds
            print(f"cpu {time.process_time() - cpu_start!r} {agents[0].rounds - a.warmup}")
    finally:
        close_all(links)
    return 0


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------
COLS = (
    "transport",
    "agents' side",
    "agents",
    "tasks",
    "rounds",
    "rate Hz",
    "p50 ms",
    "p99 ms",
    "bids ms",
    "solve ms",
    "assign ms",
    "coordinator CPU ms",
    "agents CPU ms",
    "same assignments",
)
SIZE_COLS = (
    "agents",
    "tasks",
    "announcement B",
    "bid B",
    "assignment B",
    "by serial B",
    "status B",
    "kB per round (Zenoh)",
)
CSV_HEADER = (
    "transport", "layout", "agents", "tasks", "rounds", "rate_hz", "p50_ms", "p99_ms",
    "bids_ms", "solve_ms", "assign_ms", "coordinator_cpu_ms", "agents_cpu_ms",
    "announcement_bytes", "bid_bytes", "assignment_bytes", "assignment_named_bytes",
    "status_bytes", "bytes_per_round",
    "same_assignments",
)  # fmt: skip


def _opt(v: float | None, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def _cells(p: Point) -> list[str]:
    same = "—" if p.same_assignments is None else ("yes" if p.same_assignments else "no")
    return [
        p.transport,
        p.layout,
        f"{p.agents:,}",
        f"{p.tasks:,}",
        f"{p.rounds:,}",
        f"{p.rate_hz:,.0f}",
        f"{p.p50_ms:.2f}",
        f"{p.p99_ms:.2f}",
        f"{p.bids_ms:.2f}",
        f"{p.solve_ms:.2f}",
        f"{p.assign_ms:.2f}",
        f"{p.coordinator_cpu_ms:.1f}",
        _opt(p.agents_cpu_ms, ".1f"),
        same,
    ]


def _size_cells(p: Point, zenoh: Point | None) -> list[str]:
    s = p.sizes
    return [
        f"{p.agents:,}",
        f"{p.tasks:,}",
        f"{s.announcement:,}",
        f"{s.bid:,}",
        f"{s.assignment:,}",
        f"{s.assignment_named:,}",
        f"{s.status:,}",
        "—" if zenoh is None else f"{zenoh.bytes_per_round / 1e3:,.0f}",
    ]


def _csv(p: Point) -> list[object]:
    s = p.sizes
    return [p.transport, p.layout, p.agents, p.tasks, p.rounds, round(p.rate_hz, 2),
            round(p.p50_ms, 4), round(p.p99_ms, 4), round(p.bids_ms, 4), round(p.solve_ms, 4),
            round(p.assign_ms, 4), round(p.coordinator_cpu_ms, 3),
            "" if p.agents_cpu_ms is None else round(p.agents_cpu_ms, 3),
            s.announcement, s.bid, s.assignment, s.assignment_named, s.status,
            round(p.bytes_per_round),
            "" if p.same_assignments is None else p.same_assignments]  # fmt: skip


def _row(cells: Sequence[object]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _head(cols: Sequence[str], text: int = 2) -> list[str]:
    return [_row(cols), _row(["---"] * text + ["---:"] * (len(cols) - text))]


@dataclass
class TransportBench:
    cfg: TransportBenchConfig
    env: dict[str, str]
    points: list[Point] = field(default_factory=list)
    load: str = ""

    def target(self) -> Point | None:
        """The fastest Zenoh row at the target size."""
        rows = [
            p for p in self.points if p.transport == "zenoh" and (p.agents, p.tasks) == TARGET_SIZE
        ]
        return max(rows, key=lambda p: p.rate_hz) if rows else None


def _load_note(env: dict[str, str]) -> str:
    """The machine's load during the run; the benchmark's own CPU includes its agents' processes."""
    end = _load1()
    if not env.get("load_start") or end is None:
        return "load average not available on this OS: quiet or shared is unknown"
    wall = time.perf_counter() - float(env["wall_s_start"])
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = time.process_time() - float(env["cpu_s_start"]) + children.ru_utime + children.ru_stime
    cpu -= float(env.get("children_cpu_s_start", "0"))
    return describe_load(float(env["load_start"]), end, cpu / wall if wall > 0 else 0.0)


def markdown(b: TransportBench) -> str:
    cfg = b.cfg
    layouts = "; ".join(
        f"`{lay.label}` = {lay.describe(max(a for a, _ in cfg.sizes))}" for lay in cfg.layouts
    )
    lines = [
        "# Transport benchmark: auction rounds over Zenoh vs the in-process bus",
        "",
        f"- date: {b.env['date']}",
        f"- machine: {b.env['machine']}, {b.env['cpus']} CPU(s)",
        f"- load: {b.load}",
        f"- Python: {b.env['python']}",
        f"- btmission: {b.env['btmission']}; eclipse-zenoh: {b.env.get('zenoh', '?')}",
        "",
        "One round: announce the open tasks → every agent bids (straight-line costs from where it "
        f"is, its ⌈p·n⌉ cheapest, p = {cfg.participation:g}; agents move {STEP_M:g} m per round) "
        "→ the coordinator waits for every bid → solves (`auction_round`) → sends the assignment "
        "→ every agent confirms with a status report. Rounds back to back: *rate* = rounds per "
        "second; *p50*/*p99* = a round's latency from the announcement to the last confirmation, "
        "split (medians) into *bids* (announce → last bid in), *solve* and *assign* (→ last "
        f"confirmation). {cfg.rounds} timed rounds after {cfg.warmup} warm-up rounds, seed "
        f"{cfg.seed}. *CPU ms*: CPU time per round of the coordinator's process (all its threads) "
        "and of the agents' processes together.",
        "",
        "*in-memory*: `InMemoryBus`, the objects handed over synchronously, nothing encoded (its "
        "CPU column is the agents' and the coordinator's work together). *zenoh*: the "
        "coordinator's `ZenohCoordinatorLink` in this process, listening on `tcp/127.0.0.1`; the "
        "agents' `ZenohAgentLink`s are Zenoh clients of it, their side laid out as "
        + layouts
        + ". "
        f"Every message is JSON-encoded (`btmission.links.wire`, v{wire.WIRE_VERSION}), sent "
        f"and decoded; Zenoh's shared memory is {'on' if cfg.shared_memory else 'off'} (bytes go "
        "through TCP, as between machines). *same assignments*: the first timed rounds assigned "
        "exactly as in memory.",
        "",
        *_head(COLS),
        *(_row(_cells(p)) for p in b.points),
        "",
        "## Message sizes",
        "",
        "Bytes of one message on the wire (JSON); *assignment B* with its announcement inside, "
        "*by serial B* naming it (the coordinator's link embeds it when it changed and in every "
        "10th assignment); *kB per round*: what the coordinator published and received per "
        "round over Zenoh (its announcement and assignment counted once, though Zenoh sends "
        "each agent a copy; every agent's bid and status).",
        "",
        *_head(SIZE_COLS, 0),
    ]
    for na, nt in cfg.sizes:
        rows = [p for p in b.points if (p.agents, p.tasks) == (na, nt)]
        if rows:
            net = [p for p in rows if p.transport == "zenoh"]
            lines.append(_row(_size_cells(rows[0], net[0] if net else None)))
    lines += ["", "## Target", "", "| target | measured | met |", "| --- | --- | ---: |"]
    t = b.target()
    what = f"a round over Zenoh at {TARGET_SIZE[0]}×{TARGET_SIZE[1]} ≥ {TARGET_HZ:g} Hz"
    if t is not None:
        lines.append(
            f"| {what} | {t.rate_hz:,.0f} Hz ({t.layout}; p50 {t.p50_ms:.1f} ms, p99 "
            f"{t.p99_ms:.1f} ms) | {'yes' if t.rate_hz >= TARGET_HZ else 'no'} |"
        )
    else:
        lines.append(f"| {what} | not measured in this run | — |")
    lines += [
        "",
        "Regenerate with `btmission bench transport` or `python benchmarks/bench_transport.py`.",
        "",
    ]
    return "\n".join(lines)


EARLIER = "## Earlier runs"
_EARLIER_INTRO = (
    "The main tables of earlier runs of this benchmark, newest first (kept when it writes this "
    "file)."
)


def with_earlier_runs(new: str, previous: str | None) -> str:
    """``new`` (this run's page) followed by the earlier runs' main tables: the previous page's
    own (its date, load, wire format version and main table) first, then the ones it kept."""
    if not previous or "| transport |" not in previous:
        return new
    main, _, kept = previous.partition(EARLIER)
    date = re.search(r"^- date: (.*)$", main, re.M)
    load = re.search(r"^- load: (.*)$", main, re.M)
    version = re.search(
        r"`btmission\.(?:runtime|links)\.wire`, v(\d+)", main
    )  # (pages before 2026-12)
    lines = main.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| transport |"))
    table = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        table.append(line)
    title = date.group(1) if date else "an earlier run"
    if version:
        title += f" (wire format {version.group(1)})"
    older = kept.strip()
    if older.startswith(_EARLIER_INTRO):
        older = older[len(_EARLIER_INTRO) :].strip()
    parts = [new.rstrip(), "", EARLIER, "", _EARLIER_INTRO, "", f"### {title}", ""]
    if load:
        parts += [f"- load: {load.group(1)}", ""]
    parts += [*table, ""]
    if older:
        parts += [older, ""]
    return "\n".join(parts)


def run_transport_benchmark(
    cfg: TransportBenchConfig,
    out_dir: Path | str = Path("benchmarks/results"),
    echo: Callable[[str], object] = print,
) -> TransportBench:
    """Measure every size over the in-memory bus and every layout over Zenoh, echoing rows as
    they come; write ``transport.md`` and ``transport.csv``. Needs eclipse-zenoh
    (:class:`~btmission.transport.zenoh_session.ZenohMissing` otherwise)."""
    from btmission.transport.zenoh_session import import_zenoh

    import_zenoh()  # ZenohMissing (how to install it) before anything runs
    env = environment()
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    env["children_cpu_s_start"] = repr(children.ru_utime + children.ru_stime)
    env["zenoh"] = _zenoh_version()
    b = TransportBench(cfg, env)
    echo(
        f"transport benchmark: sizes {', '.join(f'{a}x{t}' for a, t in cfg.sizes)}, {cfg.rounds} "
        f"rounds each over the in-memory bus and Zenoh ({', '.join(lay.label for lay in cfg.layouts)}); "
        f"{env['machine']}, {env['cpus']} CPU(s)"
    )
    echo("")
    for line in _head(COLS):
        echo(line)
    for na, nt in cfg.sizes:
        mem, ref = measure_in_memory(na, nt, cfg)
        b.points.append(mem)
        echo(_row(_cells(mem)))
        for layout in cfg.layouts:
            net = measure_zenoh(na, nt, cfg, layout, ref)
            b.points.append(net)
            echo(_row(_cells(net)))
    b.load = _load_note(env)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    page = out / "transport.md"
    previous = page.read_text(encoding="utf-8") if page.is_file() else None
    page.write_text(with_earlier_runs(markdown(b), previous), encoding="utf-8")
    with (out / "transport.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_HEADER)
        w.writerows(_csv(p) for p in b.points)
    echo("")
    echo(f"load: {b.load}")
    t = b.target()
    if t is not None:
        verdict = "met" if t.rate_hz >= TARGET_HZ else "NOT met"
        echo(f"target {TARGET_SIZE[0]}x{TARGET_SIZE[1]} over Zenoh >= {TARGET_HZ:g} Hz: "
             f"{t.rate_hz:,.0f} Hz ({t.layout}), {verdict}")  # fmt: skip
    echo(f"wrote {out / 'transport.md'} and {out / 'transport.csv'}")
    return b


def _zenoh_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("eclipse-zenoh")
    except PackageNotFoundError:
        return "?"


if __name__ == "__main__":
    if sys.argv[1:2] != ["agents"]:
        sys.exit(
            "usage: python -m btmission.bench.transport agents --agents N --tasks M --endpoint E"
        )
    raise SystemExit(agents_main(sys.argv[2:]))
