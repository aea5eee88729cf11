"""MAVLink benchmark: many vehicles from one process (``btmission bench mavlink``).

For each fleet size N, ``btmission mavsim --count N`` serves N simulated PX4 vehicles (UDP, real
time) in its own process, and this process attaches all N through one
:class:`~btmission.backends.mavlink.MavlinkProvider` — one I/O thread — asks each for telemetry at
``telemetry_hz`` (LOCAL_POSITION_NED, ATTITUDE, EXTENDED_SYS_STATE, SYS_STATUS, DISTANCE_SENSOR)
and, like a run's control loop, renews every vehicle's position setpoint ``setpoint_hz`` times a
second for ``seconds``. Measured:

* the achieved setpoint rate and telemetry (LOCAL_POSITION_NED) rate per vehicle;
* the setpoint interval jitter: |interval between two sends to one vehicle − 1/``setpoint_hz``|,
  its median and 99th percentile over all vehicles (goal: p99 < 10 ms with 30 vehicles), and
  the worst gap between two sends to one vehicle;
* CPU per vehicle: this process's CPU time (the I/O thread and the control loop) and the
  simulator process's, over the wall time, divided by N;
* the connect: from opening the links to every vehicle connected, all at once as a run connects
  them (``attach_all``; issue #36's goal: 10 vehicles in ≤ 1 s and 30 in ≤ 3 s on a quiet
  machine, ≤ 10 s beside eight burners), and when the last vehicle's first HEARTBEAT came (the
  vehicles send it once a second: up to a second of any connect waits for it).

Setpoints are timed where the provider sends them (on loopback UDP the vehicle hears them a few
microseconds later). ``stress`` CPU-burning processes (:mod:`btmission.bench.stress`) run from
before mavsim starts until the measurement ends: a ground station's computer is never idle
(issue #36: goal under eight burners ≥ 97.5 % of the rate, no gap over 200 ms, p99 ≤ 50 ms).
The machine's 1-minute load average is recorded with each point.

No peer runs side by side: MAVSDK is not installed here.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from btmission.bench.stress import cpu_burners
from btmission.bench.synth import environment, header_lines, write_page
from btmission.spec.vehicleref import VehicleRef

GOAL_VEHICLES = 30
GOAL_P99_MS = 10.0
STRESS_GOAL_RATE = 0.975
STRESS_GOAL_GAP_MS = 200.0
STRESS_GOAL_P99_MS = 50.0


@dataclass(frozen=True)
class MavlinkPoint:
    vehicles: int
    seconds: float
    setpoint_hz: float
    telemetry_hz: float
    connect_s: float
    setpoint_rate: float
    """Setpoints sent per vehicle per second (mean)."""
    telemetry_rate: float
    """LOCAL_POSITION_NED received per vehicle per second (mean)."""
    jitter_p50_ms: float
    jitter_p99_ms: float
    cpu_ms_per_vehicle: float
    """This process's CPU ms per vehicle per wall second."""
    sim_cpu_ms_per_vehicle: float
    worst_gap_ms: float = 0.0
    """The longest interval between two setpoints sent to one vehicle."""
    stress: int = 0
    """CPU-burning processes running meanwhile."""
    load: float = 0.0
    """The machine's 1-minute load average at the end of the measurement."""
    heard_s: float = 0.0
    """When the last vehicle's first HEARTBEAT was heard (of ``connect_s``: mavsim's vehicles,
    like autopilots, send it at 1 Hz, so up to a second of any connect is waiting for it)."""

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


def measure(
    count: int, seconds: float, setpoint_hz: float, telemetry_hz: float,
    note: Callable[[str], None] = print, stress: int = 0,
) -> MavlinkPoint:  # fmt: skip
    """One fleet size (module docstring), beside ``stress`` CPU burners."""
    with cpu_burners(stress):
        point = _measure(count, seconds, setpoint_hz, telemetry_hz, note)
        load = os.getloadavg()[0]
    return dataclasses.replace(point, stress=stress, load=load)


def _measure(
    count: int, seconds: float, setpoint_hz: float, telemetry_hz: float,
    note: Callable[[str], None],
) -> MavlinkPoint:  # fmt: skip
    from btmission.backends.mavlink import MavlinkOptions, MavlinkProvider
    from btmission.vehicles.base import VehicleKind
    from btmission.vehicles.provider import AttachRequest

    base = _free_udp_base(count)
    sim = subprocess.Popen(
        [sys.executable, "-m", "btmission", "mavsim", "--count", str(count), "--port", str(base)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    provider = MavlinkProvider(
        MavlinkOptions(setpoint_hz=setpoint_hz, telemetry_hz=telemetry_hz, connect_timeout_s=60)
    )
    try:
        assert sim.stdout is not None
        urls = []
        for _ in range(count):
            parts = sim.stdout.readline().split()
            if len(parts) < 2:
                raise RuntimeError(f"mavsim did not start: {parts}")
            urls.append((parts[0], parts[1]))
        sim.stdout.readline()  # ready
        requests = [
            AttachRequest(agent, VehicleKind.MULTIROTOR, (5.0 + 3.0 * i, 5.0, 0.0), VehicleRef.parse(url))
            for i, (agent, url) in enumerate(urls)
        ]  # fmt: skip
        t0 = time.perf_counter()
        provider.prepare([r.ref for r in requests])  # as a run connects: all at once
        vehicles = [v.backend for v in provider.attach_all(requests)]
        connect_s = time.perf_counter() - t0
        heard_s = max(t.heard_s for t in provider.connect_times.values())
        note(
            f"  {count} vehicle(s) connected in {connect_s:.2f} s (the last first heard after "
            f"{heard_s:.2f} s); measuring {seconds:g} s"
        )
        targets = [np.asarray(v.telemetry().position, dtype=float) for v in vehicles]
        period = 1.0 / setpoint_hz

        def control_for(duration: float) -> None:
            end = time.perf_counter() + duration
            due = time.perf_counter()
            while due < end:
                for v, p in zip(vehicles, targets, strict=True):
                    v.set_position_setpoint(p)
                due += period
                delay = due - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)

        control_for(1.0)  # warm-up: streams running
        states = [v.state for v in vehicles]  # type: ignore[attr-defined]
        for st in states:
            st.send_times = []
        pos0 = [st.positions for st in states]
        cpu0, sim_cpu0, wall0 = time.process_time(), _proc_cpu_s(sim.pid), time.perf_counter()
        control_for(seconds)
        wall = time.perf_counter() - wall0
        cpu = time.process_time() - cpu0
        sim_cpu = _proc_cpu_s(sim.pid) - sim_cpu0
        sent = [len(st.send_times or []) for st in states]
        received = [st.positions - p0 for st, p0 in zip(states, pos0, strict=True)]
        intervals = [np.diff(np.asarray(st.send_times)) for st in states]
        jitter = np.concatenate([np.abs(iv - period) for iv in intervals])
        worst_gap = max((float(iv.max()) for iv in intervals if iv.size), default=0.0)
        for st in states:
            st.send_times = None
    finally:
        provider.close()
        sim.send_signal(signal.SIGTERM)
        try:
            sim.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.communicate()
    return MavlinkPoint(
        vehicles=count,
        seconds=wall,
        setpoint_hz=setpoint_hz,
        telemetry_hz=telemetry_hz,
        connect_s=connect_s,
        setpoint_rate=float(np.mean(sent)) / wall,
        telemetry_rate=float(np.mean(received)) / wall,
        jitter_p50_ms=1000 * float(np.percentile(jitter, 50)),
        jitter_p99_ms=1000 * float(np.percentile(jitter, 99)),
        cpu_ms_per_vehicle=1000 * cpu / wall / count,
        sim_cpu_ms_per_vehicle=1000 * sim_cpu / wall / count,
        worst_gap_ms=1000 * worst_gap,
        heard_s=heard_s,
    )


COLUMNS = (
    "vehicles", "seconds", "setpoint_hz", "telemetry_hz", "connect_s", "setpoint_rate",
    "telemetry_rate", "jitter_p50_ms", "jitter_p99_ms", "cpu_ms_per_vehicle",
    "sim_cpu_ms_per_vehicle", "worst_gap_ms", "stress", "load", "heard_s",
)  # fmt: skip


def markdown(points: Sequence[MavlinkPoint], env: dict[str, str]) -> str:
    lines = [
        "# MAVLink benchmark",
        "",
        *header_lines(env),
        "",
        "One btmission process drives N simulated PX4 vehicles (`btmission mavsim --count N`, its "
        "own process, real time, UDP on loopback) through the MAVLink provider's single I/O "
        "thread: telemetry asked at the given rate per message (LOCAL_POSITION_NED counted), "
        "each vehicle's setpoint renewed by a control loop at the setpoint rate. Jitter = "
        "|interval between two setpoints to one vehicle − period|. CPU = CPU ms per wall second "
        "per vehicle (100 = 10 % of one core). Worst gap = the longest interval between two "
        "setpoints to one vehicle. Stress = CPU-burning processes running meanwhile; load = the "
        "1-minute load average at the end. Goal: quiet, "
        f"{GOAL_VEHICLES} vehicles at full rate with p99 jitter < {GOAL_P99_MS:g} ms; under "
        f"stress, ≥ {100 * STRESS_GOAL_RATE:g} % of the rate, no gap over "
        f"{STRESS_GOAL_GAP_MS:g} ms, p99 ≤ {STRESS_GOAL_P99_MS:g} ms. Connect = from opening "
        "the links to every vehicle connected (all at once, as a run does); heard = when the "
        "last vehicle's first HEARTBEAT came (mavsim's vehicles send it once a second, as "
        "autopilots do). Connect goal (issue #36): quiet, 10 vehicles in ≤ 1 s and 30 in "
        "≤ 3 s; under 8 burners, ≤ 10 s. No peer (MAVSDK is not installed here).",
        "",
        "| vehicles | stress | load | setpoints [Hz/vehicle] | telemetry [Hz/vehicle] | "
        "jitter p50 [ms] | jitter p99 [ms] | worst gap [ms] | CPU btmission [ms/s/vehicle] | "
        "CPU mavsim [ms/s/vehicle] | connect [s] | heard [s] | goal |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for p in points:
        goal = {None: "—", True: "met", False: "missed"}[p.met]
        lines.append(
            f"| {p.vehicles} | {p.stress} | {p.load:.1f} | {p.setpoint_rate:.1f} of "
            f"{p.setpoint_hz:g} | {p.telemetry_rate:.1f} of {p.telemetry_hz:g} | "
            f"{p.jitter_p50_ms:.2f} | {p.jitter_p99_ms:.2f} | {p.worst_gap_ms:.0f} | "
            f"{p.cpu_ms_per_vehicle:.1f} | {p.sim_cpu_ms_per_vehicle:.1f} | {p.connect_s:.2f} | "
            f"{p.heard_s:.2f} | {goal} |"
        )
    return "\n".join(lines) + "\n"


def run_mavlink_benchmark(
    counts: Sequence[int], seconds: float, setpoint_hz: float, telemetry_hz: float, out: Path,
    note: Callable[[str], None] = print, stress: int = 0,
) -> list[MavlinkPoint]:  # fmt: skip
    env = environment()
    points = []
    for n in counts:
        note(f"{n} vehicle(s)" + (f", {stress} CPU burner(s)" if stress else ""))
        points.append(measure(n, seconds, setpoint_hz, telemetry_hz, note, stress))
        p = points[-1]
        note(
            f"  setpoints {p.setpoint_rate:.1f} Hz, telemetry {p.telemetry_rate:.1f} Hz, "
            f"jitter p50 {p.jitter_p50_ms:.2f} ms p99 {p.jitter_p99_ms:.2f} ms, worst gap "
            f"{p.worst_gap_ms:.0f} ms, CPU {p.cpu_ms_per_vehicle:.1f} + "
            f"{p.sim_cpu_ms_per_vehicle:.1f} ms/s per vehicle (load {p.load:.1f})"
        )
    out.mkdir(parents=True, exist_ok=True)
    write_page(out / "mavlink.md", markdown(points, env))
    with (out / "mavlink.csv").open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for p in points:
            w.writerow([getattr(p, c) for c in COLUMNS])
    note(f"wrote {out / 'mavlink.md'} and {out / 'mavlink.csv'}")
    return points
