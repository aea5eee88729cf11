"""MAVLink benchmark: many vehicles from one ground station process, btmission beside MAVSDK-Python
(``btmission bench mavlink``).

For each fleet size N, N simulated PX4 vehicles (``btmission mavsim --count N --arrivals``: its
own process, real time, UDP on loopback, noting when each setpoint reaches a vehicle's socket,
:meth:`~btmission.mavsim.MavSim.stamp_arrivals`) are driven by one client process
(:mod:`btmission.bench.mavlink_client`) doing the same work with either library:

* ``btmission``: the :class:`~btmission.backends.mavlink.MavlinkProvider` (one I/O thread for
  every vehicle);
* ``mavsdk``: MAVSDK-Python 4 (``pip install 'btmission[bench]'``; the MAVSDK C++ library in the
  client's process, no server), when it is installed — otherwise the benchmark says how to
  install it and measures btmission alone.

The work: connect all N at once, ask each for five telemetry streams at ``telemetry_hz``, then
renew every vehicle's position setpoint ``setpoint_hz`` times a second (one second of warm-up,
then ``seconds`` measured). Both clients run on fresh vehicles of the same simulator, one after
the other, their order alternating from one fleet size to the next, and beside the same
``stress`` CPU burners (:mod:`btmission.bench.stress`, running from before the first client's
vehicles start until the last client ends). Measured, per client:

* at the vehicle (the kernel's arrival stamps): the setpoint rate per vehicle, the jitter
  |interval between two setpoints arriving at one vehicle − 1/``setpoint_hz``| (p50, p99 over all
  vehicles) and the worst gap between two arrivals at one vehicle;
* LOCAL_POSITION_NED received by the client per vehicle per second;
* CPU per vehicle: the client process's CPU time over the window (all its threads) per wall
  second per vehicle, and the simulator process's;
* the connect: from opening the links until every vehicle is connected with its telemetry flowing
  (issue #36's goal for btmission: 10 vehicles in ≤ 1 s and 30 in ≤ 3 s on a quiet machine,
  ≤ 10 s beside eight burners), and when the last vehicle was first heard (the vehicles send a
  HEARTBEAT once a second, as autopilots do: up to a second of any connect waits for it);
* the machine's 1-minute load average at the end of the window.

Goals (issue #36): quiet, 30 vehicles at full rate with p99 jitter < 10 ms; beside burners
≥ 97.5 % of the rate, no gap over 200 ms, p99 ≤ 50 ms, and no more CPU per vehicle than
MAVSDK-Python doing the same work in the same run.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

from btmission.bench.stress import cpu_burners
from btmission.bench.synth import environment, header_lines, write_page

GOAL_VEHICLES = 30
GOAL_P99_MS = 10.0
STRESS_GOAL_RATE = 0.975
STRESS_GOAL_GAP_MS = 200.0
STRESS_GOAL_P99_MS = 50.0
CLIENTS = ("btmission", "mavsdk")
MAVSDK_MIN = "4"
"""MAVSDK-Python's first major version with this API (3.x and earlier: the gRPC package with a
``mavsdk_server``, now ``mavsdk-grpc``)."""
INSTALL_NOTE = (
    "MAVSDK-Python 4 is not installed: measuring btmission alone (no peer). To measure it side "
    "by side in the same run: pip install 'btmission[bench]' (or pip install 'mavsdk>=4')."
)
CLIENT_TIMEOUT_S = 120.0
"""A client that has not finished this long after its window should have ended is stopped."""


@dataclass(frozen=True)
class MavlinkPoint:
    vehicles: int
    seconds: float
    setpoint_hz: float
    telemetry_hz: float
    connect_s: float
    setpoint_rate: float
    """Setpoints that arrived per vehicle per second (mean over the vehicles)."""
    telemetry_rate: float
    """LOCAL_POSITION_NED the client received per vehicle per second (mean)."""
    jitter_p50_ms: float
    jitter_p99_ms: float
    cpu_ms_per_vehicle: float
    """The client process's CPU ms per vehicle per wall second."""
    sim_cpu_ms_per_vehicle: float
    worst_gap_ms: float = 0.0
    """The longest interval between two setpoints arriving at one vehicle."""
    stress: int = 0
    """CPU-burning processes running meanwhile."""
    load: float = 0.0
    """The machine's 1-minute load average at the end of the measurement."""
    heard_s: float = 0.0
    """When the last vehicle was first heard (of ``connect_s``: mavsim's vehicles, like
    autopilots, send HEARTBEAT at 1 Hz, so up to a second of any connect is waiting for it)."""
    client: str = "btmission"
    """``btmission`` or ``mavsdk`` (MAVSDK-Python)."""

    @property
    def met(self) -> bool | None:
        if self.stress:  # issue #36's goal under load, at any fleet size
            return (
                self.setpoint_rate >= STRESS_GOAL_RATE * self.setpoint_hz
                and self.worst_gap_ms <= STRESS_GOAL_GAP_MS
                and self.jitter_p99_ms <= STRESS_GOAL_P99_MS
            )
        if self.vehicles < GOAL_VEHICLES:
            return None
        full = self.setpoint_rate >= 0.98 * self.setpoint_hz
        full = full and self.telemetry_rate >= 0.95 * self.telemetry_hz
        return full and self.jitter_p99_ms < GOAL_P99_MS


@dataclass(frozen=True)
class ArrivalStats:
    rate: float
    """Arrivals per vehicle per second (mean over the vehicles)."""
    jitter_p50_ms: float
    jitter_p99_ms: float
    worst_gap_ms: float


def arrival_stats(
    arrivals: Sequence[Sequence[float]], t0: float, t1: float, period: float
) -> ArrivalStats:
    """The setpoint stream as the vehicles saw it: ``arrivals`` holds each vehicle's arrival
    times (seconds); only those in ``[t0, t1]`` count. Jitter = |interval − ``period``| over
    every vehicle's intervals; the worst gap also counts the window's edges (from ``t0`` to the
    first arrival, from the last to ``t1``), so a vehicle that hears nothing has a gap of the
    whole window."""
    if not arrivals or t1 <= t0:
        raise ValueError("arrival_stats needs at least one vehicle and t1 > t0")
    counts, jitters, worst = [], [], 0.0
    for times in arrivals:
        ts = np.sort(np.asarray([t for t in times if t0 <= t <= t1], dtype=float))
        counts.append(ts.size)
        edges = np.concatenate(([t0], ts, [t1]))
        worst = max(worst, float(np.diff(edges).max()))
        if ts.size > 1:
            jitters.append(np.abs(np.diff(ts) - period))
    jitter = np.concatenate(jitters) if jitters else np.asarray([period])
    return ArrivalStats(
        rate=float(np.mean(counts)) / (t1 - t0),
        jitter_p50_ms=1000 * float(np.percentile(jitter, 50)),
        jitter_p99_ms=1000 * float(np.percentile(jitter, 99)),
        worst_gap_ms=1000 * worst,
    )


def mavsdk_version() -> str | None:
    """The installed MAVSDK-Python's version if it is 4 or later (the API the peer drives)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("mavsdk")
    except PackageNotFoundError:
        return None
    major = v.split(".", 1)[0]
    return v if major.isdigit() and int(major) >= int(MAVSDK_MIN) else None


def _free_udp_base(count: int) -> int:
    """A first port with ``count`` free UDP ports after it (loopback)."""
    for base in range(24540, 60000, 211):
        socks: list[socket.socket] = []
        try:
            for i in range(count):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(s)
                s.bind(("127.0.0.1", base + i))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError(f"no {count} consecutive free UDP ports on 127.0.0.1")


def _proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _end(proc: subprocess.Popen[str]) -> None:
    """End a process this benchmark started (by its own handle), however it is."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()


@contextmanager
def _vehicles(count: int) -> Iterator[tuple[subprocess.Popen[str], list[tuple[str, str]]]]:
    """``count`` fresh simulated vehicles in their own process; yields it and (agent, url)s."""
    base = _free_udp_base(count)
    sim = subprocess.Popen(
        [sys.executable, "-m", "btmission", "mavsim", "--count", str(count), "--port", str(base),
         "--arrivals"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert sim.stdout is not None
        urls = []
        for _ in range(count):
            parts = sim.stdout.readline().split()
            if len(parts) < 2:
                raise RuntimeError(f"the simulated vehicles did not start: {' '.join(parts)}")
            urls.append((parts[0], parts[1]))
        if not sim.stdout.readline().startswith("ready"):
            raise RuntimeError("the simulated vehicles did not start")
        yield sim, urls
    finally:
        _end(sim)


def _line(stream: IO[str], client: str, err: IO[str]) -> dict[str, object]:
    line = stream.readline()
    if not line:
        err.seek(0)
        tail = "\n".join(err.read().strip().splitlines()[-5:])
        raise RuntimeError(f"the {client} client stopped: {tail or 'no output'}")
    message: dict[str, object] = json.loads(line)
    return message


def measure_client(
    client: str, count: int, seconds: float, setpoint_hz: float, telemetry_hz: float,
    note: Callable[[str], None] = print,
) -> MavlinkPoint:  # fmt: skip
    """One client (``btmission`` or ``mavsdk``) on ``count`` fresh vehicles (module docstring)."""
    with _vehicles(count) as (sim, urls), tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "btmission.bench.mavlink_client", client,
             "--urls", json.dumps(urls), "--seconds", repr(seconds),
             "--setpoint-hz", repr(setpoint_hz), "--telemetry-hz", repr(telemetry_hz)],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=err, text=True,
        )  # fmt: skip
        try:
            assert proc.stdout is not None
            connected = _line(proc.stdout, client, err)
            connect_s, heard_s = float(connected["connect_s"]), float(connected["heard_s"])  # type: ignore[arg-type]
            note(
                f"  {client}: {count} vehicle(s) connected in {connect_s:.2f} s (the last first "
                f"heard after {heard_s:.2f} s); measuring {seconds:g} s"
            )
            _line(proc.stdout, client, err)  # measuring
            sim_cpu0 = _proc_cpu_s(sim.pid)
            done = _line(proc.stdout, client, err)
            sim_cpu = _proc_cpu_s(sim.pid) - sim_cpu0
            load = os.getloadavg()[0]
            proc.wait(timeout=CLIENT_TIMEOUT_S)
        finally:
            _end(proc)
        assert sim.stdin is not None and sim.stdout is not None
        t0, t1 = float(done["t0"]), float(done["t1"])  # type: ignore[arg-type]
        sim.stdin.write(f"arrivals {t0!r} {t1!r}\n")
        sim.stdin.flush()
        arrivals: dict[str, list[float]] = json.loads(sim.stdout.readline())
    wall, cpu = float(done["wall_s"]), float(done["cpu_s"])  # type: ignore[arg-type]
    telemetry: list[int] = done["telemetry"]  # type: ignore[assignment]
    stats = arrival_stats([arrivals[agent] for agent, _ in urls], t0, t1, 1.0 / setpoint_hz)
    return MavlinkPoint(
        vehicles=count,
        seconds=wall,
        setpoint_hz=setpoint_hz,
        telemetry_hz=telemetry_hz,
        connect_s=connect_s,
        setpoint_rate=stats.rate,
        telemetry_rate=float(np.mean(telemetry)) / wall,
        jitter_p50_ms=stats.jitter_p50_ms,
        jitter_p99_ms=stats.jitter_p99_ms,
        cpu_ms_per_vehicle=1000 * cpu / wall / count,
        sim_cpu_ms_per_vehicle=1000 * sim_cpu / wall / count,
        worst_gap_ms=stats.worst_gap_ms,
        load=load,
        heard_s=heard_s,
        client=client,
    )


def measure(
    count: int, seconds: float, setpoint_hz: float, telemetry_hz: float,
    note: Callable[[str], None] = print, stress: int = 0,
    clients: Sequence[str] = ("btmission",),
) -> list[MavlinkPoint]:  # fmt: skip
    """One fleet size, each client in turn (in the order given) beside the same ``stress`` CPU
    burners."""
    points = []
    with cpu_burners(stress):
        for client in clients:
            point = measure_client(client, count, seconds, setpoint_hz, telemetry_hz, note)
            points.append(dataclasses.replace(point, stress=stress))
            _summary(points[-1], note)
    return points


def _summary(p: MavlinkPoint, note: Callable[[str], None]) -> None:
    note(
        f"  {p.client}: setpoints {p.setpoint_rate:.1f} Hz at the vehicle, telemetry "
        f"{p.telemetry_rate:.1f} Hz, jitter p50 {p.jitter_p50_ms:.2f} ms p99 "
        f"{p.jitter_p99_ms:.2f} ms, worst gap {p.worst_gap_ms:.0f} ms, CPU "
        f"{p.cpu_ms_per_vehicle:.1f} + {p.sim_cpu_ms_per_vehicle:.1f} ms/s per vehicle "
        f"(load {p.load:.1f})"
    )


COLUMNS = (
    "vehicles", "seconds", "setpoint_hz", "telemetry_hz", "connect_s", "setpoint_rate",
    "telemetry_rate", "jitter_p50_ms", "jitter_p99_ms", "cpu_ms_per_vehicle",
    "sim_cpu_ms_per_vehicle", "worst_gap_ms", "stress", "load", "heard_s", "client",
)  # fmt: skip

CLIENT_NAMES = {"btmission": "btmission", "mavsdk": "MAVSDK-Python"}


def side_by_side(points: Sequence[MavlinkPoint]) -> list[str]:
    """The comparison table: one row per fleet size and stress where both clients ran, each
    figure as btmission / MAVSDK-Python; the last column says whether btmission used no more CPU
    per vehicle than MAVSDK-Python (issue #36). Empty when no MAVSDK point is there."""
    pairs: dict[tuple[int, int], dict[str, MavlinkPoint]] = {}
    for p in points:
        pairs.setdefault((p.vehicles, p.stress), {})[p.client] = p
    rows = [(key, pair) for key, pair in pairs.items() if set(CLIENTS) <= pair.keys()]
    if not rows:
        return []
    lines = [
        "| vehicles | burners | load | setpoints at the vehicle [Hz] | worst gap [ms] | "
        "jitter p99 [ms] | CPU [ms/s per vehicle] | connect [s] | btmission CPU ≤ MAVSDK |",
        "|---:|---:|---|---|---|---|---|---|---|",
    ]
    for (vehicles, stress), pair in rows:
        b, m = pair["btmission"], pair["mavsdk"]
        lines.append(
            f"| {vehicles} | {stress} | {b.load:.1f} / {m.load:.1f} | "
            f"{b.setpoint_rate:.1f} / {m.setpoint_rate:.1f} | "
            f"{b.worst_gap_ms:.0f} / {m.worst_gap_ms:.0f} | "
            f"{b.jitter_p99_ms:.1f} / {m.jitter_p99_ms:.1f} | "
            f"{b.cpu_ms_per_vehicle:.1f} / {m.cpu_ms_per_vehicle:.1f} | "
            f"{b.connect_s:.2f} / {m.connect_s:.2f} | "
            f"{'yes' if b.cpu_ms_per_vehicle <= m.cpu_ms_per_vehicle else '**no**'} |"
        )
    return lines


def markdown(points: Sequence[MavlinkPoint], env: dict[str, str], peer_note: str = "") -> str:
    lines = [
        "# MAVLink benchmark",
        "",
        *header_lines(env),
        "",
        "One ground station process drives N simulated PX4 vehicles (`btmission mavsim`'s "
        "simulator in its own process, real time, UDP on loopback): it connects them all at "
        "once, asks each for five telemetry streams at the telemetry rate (LOCAL_POSITION_NED "
        "counted) and renews every vehicle's position setpoint at the setpoint rate. Client "
        "btmission = the MAVLink provider (one I/O thread); MAVSDK-Python = MAVSDK-Python 4 "
        "(`pip install 'btmission[bench]'`; the MAVSDK C++ library in the client's process), "
        "doing the same work on fresh vehicles in the same run, beside the same burners. "
        "Setpoints are counted where they arrive (the kernel's arrival stamps on the vehicles' "
        "sockets). Jitter = |interval between two setpoints arriving at one vehicle − period|; "
        "worst gap = the longest such interval. CPU = the client process's (or the "
        "simulator's) CPU ms per wall second per vehicle (100 = 10 % of one core). Stress = "
        "CPU-burning processes running meanwhile; load = the 1-minute load average at the end "
        "of the client's window. Connect = from opening the links until every vehicle is "
        "connected with its telemetry flowing; heard = when the last vehicle was first heard "
        "(the vehicles send HEARTBEAT once a second, as autopilots do). Goals (issue #36): "
        f"quiet, {GOAL_VEHICLES} vehicles at full rate with p99 jitter < {GOAL_P99_MS:g} ms; "
        f"under stress, ≥ {100 * STRESS_GOAL_RATE:g} % of the rate, no gap over "
        f"{STRESS_GOAL_GAP_MS:g} ms, p99 ≤ {STRESS_GOAL_P99_MS:g} ms, and no more CPU per "
        "vehicle than MAVSDK-Python; connect, 10 vehicles in ≤ 1 s and 30 in ≤ 3 s quiet, "
        "≤ 10 s under 8 burners.",
    ]
    if peer_note:
        lines += ["", peer_note]
    lines += [
        "",
        "| client | vehicles | stress | load | setpoints [Hz/vehicle] | telemetry [Hz/vehicle] | "
        "jitter p50 [ms] | jitter p99 [ms] | worst gap [ms] | CPU client [ms/s/vehicle] | "
        "CPU mavsim [ms/s/vehicle] | connect [s] | heard [s] | goal |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for p in points:
        goal = {None: "—", True: "met", False: "missed"}[p.met]
        lines.append(
            f"| {CLIENT_NAMES.get(p.client, p.client)} | {p.vehicles} | {p.stress} | "
            f"{p.load:.1f} | {p.setpoint_rate:.1f} of {p.setpoint_hz:g} | "
            f"{p.telemetry_rate:.1f} of {p.telemetry_hz:g} | "
            f"{p.jitter_p50_ms:.2f} | {p.jitter_p99_ms:.2f} | {p.worst_gap_ms:.0f} | "
            f"{p.cpu_ms_per_vehicle:.1f} | {p.sim_cpu_ms_per_vehicle:.1f} | {p.connect_s:.2f} | "
            f"{p.heard_s:.2f} | {goal} |"
        )
    table = side_by_side(points)
    if table:
        lines += [
            "",
            "Side by side (btmission / MAVSDK-Python, the same fleet beside the same burners):",
            "",
            *table,
        ]
    return "\n".join(lines) + "\n"


def run_mavlink_benchmark(
    counts: Sequence[int], seconds: float, setpoint_hz: float, telemetry_hz: float, out: Path,
    note: Callable[[str], None] = print, stress: int = 0, peer: bool = True,
) -> list[MavlinkPoint]:  # fmt: skip
    """Every fleet size in ``counts``; with ``peer`` and MAVSDK-Python 4 installed, both
    clients, their order alternating from one fleet size to the next."""
    env = environment()
    version = mavsdk_version() if peer else None
    peer_note = ""
    if peer and version is None:
        peer_note = INSTALL_NOTE
        note(INSTALL_NOTE)
    elif version is not None:
        peer_note = f"Peer: MAVSDK-Python {version} (PyPI `mavsdk`)."
    points: list[MavlinkPoint] = []
    for k, n in enumerate(counts):
        clients = list(CLIENTS) if version is not None else ["btmission"]
        if k % 2:
            clients.reverse()
        note(f"{n} vehicle(s)" + (f", {stress} CPU burner(s)" if stress else ""))
        points += measure(n, seconds, setpoint_hz, telemetry_hz, note, stress, clients)
    out.mkdir(parents=True, exist_ok=True)
    write_page(out / "mavlink.md", markdown(points, env, peer_note))
    with (out / "mavlink.csv").open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for p in points:
            w.writerow([getattr(p, c) for c in COLUMNS])
    note(f"wrote {out / 'mavlink.md'} and {out / 'mavlink.csv'}")
    return points
