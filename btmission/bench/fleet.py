"""Fleet scaling benchmark: how the simulator's speed falls as the fleet grows.

``btmission bench fleet`` (or ``python benchmarks/bench_fleet.py``) flies 3, 10, 30 and 100
drones (:data:`FLEET_SIZES`) in the seed 000 mine, each fleet with the field mission's ratio of
7 inspections per 3 drones (:func:`fleet_mission_text`), and reports simulated time over wall
time. Every run is the whole system in one process, as ``btmission run`` runs it: the simulator,
every agent's tree ticks, D*+ bids and path following (APF on the LiDAR), and the coordinator's
auction rounds.

A run is timed in two parts: the *warm-up* (the first ``warmup_s`` simulated seconds: the first
auction round, which runs one D*+ search per task, and the take-off) and the *window* after it
(``duration_s`` simulated seconds of the fleet flying its tasks), whose speed-up is the one the
targets apply to (issue 19: 3 drones ≥ 100×, 30 drones ≥ 25× with the tracking controller).

Times are wall-clock (``time.perf_counter``); the results say when and where they were measured
and, from the load average, whether other work shared the machine; each run keeps the previous
page's numbers below its own (:func:`~btmission.bench.synth.earlier_runs`).

A shared host's speed swings by 2-3× from minute to minute, so one run per size can mislead:
``repeat`` builds and flies each fleet that many times (a fresh ``MissionRun`` each time, the same
mission), the table reports the median run's speed-up with the min and max over the repeats
(:func:`summarise`), and every run is timed after the host speed reference
(:func:`~btmission.bench.synth.host_speed_ms`), which shows when the host itself was slow.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from btmission.bench.synth import environment, header_lines, host_speed_ms, write_page

FLEET_SIZES = (3, 10, 30, 100)
"""Fleet sizes of the scaling table."""

TARGETS = {3: 100.0, 30: 25.0}
"""Speed-up the window must reach, by fleet size (issue 19)."""

WARMUP_S = 10.0
DURATION_S = 60.0


def fleet_mission_text(drones: int, seed: int = 0, controller: str = "track") -> str:
    """The seed 000 mine (seed 7, 200 m × 120 m × 12 m) with ``drones`` aerial agents and
    ⌈7·drones/3⌉ inspections (the field mission's ratio: 7 tasks for 3 drones).

    Starts and tasks are points every 2 m along the mine's drift centrelines, nearest drifts to
    the launch area first: the drones stand on the floor at the first ``drones`` of them (none
    closer than 2 m to another), the tasks are drawn (generator ``seed``) from the rest, 2 m
    above the local floor. Deterministic for a seed.
    """
    from btmission.runtime.paths import field_bytes
    from btmission.world.minegen import generate_mine
    from btmission.world.voxel import OCCUPIED

    if drones < 1:
        raise ValueError(f"a fleet needs at least one drone, got {drones}")
    mine = generate_mine(seed=7, size=(200.0, 120.0, 12.0), resolution=0.5)
    vm = mine.map
    tunnels = sorted(mine.tunnels, key=lambda t: (math.dist(t.a, mine.launch), t.a, t.b))
    floor: list[tuple[float, float, float]] = []
    for t in tunnels:
        a, b = np.asarray(t.a, dtype=float), np.asarray(t.b, dtype=float)
        k = max(int(float(np.linalg.norm(b - a)) // 2.0), 1)
        for i in range(k + 1):
            x, y, z = a + (b - a) * i / k
            gz = vm.ground_z((x, y, z + 0.3))
            above = vm.state_at((x, y, gz + 2.0))
            if above is None or above == OCCUPIED:
                continue
            q = (round(float(x), 1), round(float(y), 1), round(float(gz), 2))
            if all(math.dist(q, other) >= 2.0 for other in floor):
                floor.append(q)
    n_tasks = math.ceil(7 * drones / 3)
    if drones + n_tasks > len(floor):
        raise ValueError(
            f"the mine has room for {len(floor)} starts and tasks, not {drones} drones "
            f"and {n_tasks} tasks"
        )
    # one D*+ cost-to-goal field per task goal and per home (float32 over the padded map): a
    # large fleet needs more than the default budget, or evicted fields are searched again
    field_mb = field_bytes(vm.shape) / 2**20
    need_mb = math.ceil(1.1 * (n_tasks + drones) * field_mb)
    fields = f", path_fields_mb: {need_mb}" if need_mb > 1024 else ""
    rng = np.random.default_rng(seed)
    picks = sorted(int(i) for i in rng.choice(np.arange(drones, len(floor)), n_tasks, False))
    lines = [
        f"mission: fleet{drones}",
        "version: 1",
        f"description: {drones} drones, {n_tasks} inspections in the seed 000 mine",
        "world:",
        "  map: {generate: mine, seed: 7, size: [200, 120, 12]}",
        "  resolution: 0.5",
        "agents:",
        *(
            f"  - {{id: R{i + 1}, library: aerial, start: [{x:g}, {y:g}, {z:g}], backend: sim}}"
            for i, (x, y, z) in enumerate(floor[:drones])
        ),
        "tasks:",
        *(
            f"  - {{id: T{j + 1}, type: inspect, location: "
            f"[{floor[i][0]:g}, {floor[i][1]:g}, {floor[i][2] + 2.0:g}]}}"
            for j, i in enumerate(picks)
        ),
        "task_types:",
        "  inspect: {goal: at_goal(location), cost: path_cost(location)}",
        "coordination: {auction_rate_hz: 10, participation: 1.0, priority_scale: 1000, "
        "switch_cost: 5}",
        f"runtime: {{controller: {controller}{fields}}}",
        "",
    ]
    return "\n".join(lines)


@dataclass(frozen=True)
class FleetPoint:
    """One build and flight of a fleet; ``repeat`` counts from 1, ``host_ms`` is the host speed
    reference timed just before the build (NaN when not measured)."""

    drones: int
    tasks: int
    controller: str
    build_s: float
    warmup_sim_s: float
    warmup_wall_s: float
    sim_s: float
    wall_s: float
    done: int
    collisions: int
    repeat: int = 1
    host_ms: float = math.nan

    @property
    def speedup(self) -> float:
        return self.sim_s / self.wall_s if self.wall_s > 0 else math.inf

    @property
    def target(self) -> float | None:
        return TARGETS.get(self.drones) if self.controller == "track" else None

    @property
    def met(self) -> bool | None:
        return None if self.target is None else self.speedup >= self.target


def run_fleet(
    drones: int,
    controller: str = "track",
    warmup_s: float = WARMUP_S,
    duration_s: float = DURATION_S,
    repeat: int = 1,
) -> FleetPoint:
    """Build and fly a fleet of ``drones``: warm-up and window timed apart (module docstring),
    the host speed reference timed just before the build; ``repeat`` numbers the run."""
    from btmission.missions import load_mission_text
    from btmission.runtime.runner import MissionRun

    m = load_mission_text(fleet_mission_text(drones, controller=controller), "fleet.yaml")
    host_ms = host_speed_ms()
    t0 = time.perf_counter()
    run = MissionRun(m, controller=controller)
    build = time.perf_counter() - t0
    try:
        warm = run.run(until=warmup_s)
        res = run.run(until=warmup_s + duration_s)
    finally:
        run.close()
    return FleetPoint(
        drones,
        len(m.spec.tasks),
        controller,
        build,
        warm.time_s,
        warm.wall_s,
        res.time_s - warm.time_s,
        res.wall_s - warm.wall_s,  # (a run's wall time adds up over its run() calls)
        len(res.done),
        res.collisions,
        repeat,
        host_ms,
    )


@dataclass(frozen=True)
class FleetSummary:
    """The repeats of one fleet size and controller: ``median`` is the median run (by window
    speed-up; for an even number of runs the slower of the two middle ones, so the row is one
    real, self-consistent run and the target check errs on the slow side), ``runs`` all of
    them in the order flown."""

    median: FleetPoint
    runs: tuple[FleetPoint, ...]

    @property
    def speedup(self) -> float:
        return self.median.speedup

    @property
    def min_speedup(self) -> float:
        return min(p.speedup for p in self.runs)

    @property
    def max_speedup(self) -> float:
        return max(p.speedup for p in self.runs)

    @property
    def met(self) -> bool | None:
        """The target check, on the median run."""
        return self.median.met


def summarise(points: Sequence[FleetPoint]) -> list[FleetSummary]:
    """Group ``points`` by controller and fleet size (first-flown order) into their median run
    and the min and max speed-up (:class:`FleetSummary`)."""
    groups: dict[tuple[str, int], list[FleetPoint]] = {}
    for p in points:
        groups.setdefault((p.controller, p.drones), []).append(p)
    out = []
    for runs in groups.values():
        ranked = sorted(runs, key=lambda p: p.speedup)
        out.append(FleetSummary(ranked[(len(ranked) - 1) // 2], tuple(runs)))
    return out


HEAD = (
    "drones",
    "tasks",
    "controller",
    "build s",
    "warm-up: simulated s",
    "warm-up: wall s",
    "window: simulated s",
    "window: wall s",
    "speed-up",
    "target",
    "met",
    "tasks done",
    "collisions",
    "runs",
    "speed-up min-max",
    "host ms",
)


def _row(cells: Sequence[object]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _cells(s: FleetSummary) -> list[str]:
    p = s.median
    return [
        str(p.drones),
        str(p.tasks),
        p.controller,
        f"{p.build_s:.2f}",
        f"{p.warmup_sim_s:.1f}",
        f"{p.warmup_wall_s:.1f}",
        f"{p.sim_s:.1f}",
        f"{p.wall_s:.1f}",
        f"{p.speedup:.1f}×",
        "—" if p.target is None else f"≥ {p.target:g}×",
        "—" if p.met is None else ("yes" if p.met else "**no**"),
        f"{p.done}/{p.tasks}",
        str(p.collisions),
        str(len(s.runs)),
        f"{s.min_speedup:.1f}-{s.max_speedup:.1f}×",
        _ms(p.host_ms),
    ]


def _ms(ms: float) -> str:
    return "—" if math.isnan(ms) else f"{ms:.0f}"


CSV_HEAD = (
    "drones",
    "tasks",
    "controller",
    "build_s",
    "warmup_wall_s",
    "sim_s",
    "wall_s",
    "speedup",
    "done",
    "collisions",
    "repeat",
    "host_ms",
)
"""``fleet.csv``'s columns: one row per run (``repeat`` numbers the runs of a size from 1)."""


def _csv_cells(p: FleetPoint) -> list[object]:
    return [
        p.drones,
        p.tasks,
        p.controller,
        f"{p.build_s:.3f}",
        f"{p.warmup_wall_s:.3f}",
        f"{p.sim_s:.2f}",
        f"{p.wall_s:.3f}",
        f"{p.speedup:.2f}",
        p.done,
        p.collisions,
        p.repeat,
        "" if math.isnan(p.host_ms) else f"{p.host_ms:.1f}",
    ]


def markdown(
    rows: Sequence[FleetSummary],
    env: dict[str, str],
    warmup_s: float,
    duration_s: float,
    plot: str | None = None,
) -> str:
    lines = [
        "# Fleet scaling benchmark",
        "",
        *header_lines(env),
        "",
        f"Drones in the seed 000 mine, 7 inspections per 3 drones (`fleet_mission_text`), the "
        f"whole system in one process. *Warm-up* = the first {warmup_s:g} simulated s (the "
        f"first auction round runs one D*+ search per task; take-off); *window* = the next "
        f"{duration_s:g} s, whose simulated time over wall time is the speed-up. Each size is "
        "built and flown *runs* times; its row is the median run (by speed-up; of an even "
        "number, the slower middle one), which the target check uses, beside the min-max "
        "speed-up over the runs (every run in `fleet.csv`). *Host ms*: the median run's host "
        "speed reference (`host_speed_ms`, a fixed pure-Python workload timed just before the "
        "build; higher = the host was slower then).",
        "",
        _row(HEAD),
        _row(["---"] * len(HEAD)),
        *(_row(_cells(r)) for r in rows),
        "",
    ]
    if plot:
        lines += [f"![speed-up against fleet size]({plot})", ""]
    lines += ["Regenerate with `btmission bench fleet` or `python benchmarks/bench_fleet.py`.", ""]
    return "\n".join(lines)


def plot_scaling(rows: Sequence[FleetSummary], path: Path) -> Path | None:
    """Median speed-up against fleet size (log-log), bars from the min to the max over the
    repeats, with the targets; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        return None
    fig, ax = plt.subplots(figsize=(6, 4))
    for ctrl in sorted({r.median.controller for r in rows}):
        pts = sorted(
            (r for r in rows if r.median.controller == ctrl), key=lambda r: r.median.drones
        )
        mid = [r.speedup for r in pts]
        bars = [
            [m - r.min_speedup for m, r in zip(mid, pts)],
            [r.max_speedup - m for m, r in zip(mid, pts)],
        ]
        ax.errorbar([r.median.drones for r in pts], mid, yerr=bars, fmt="o-", capsize=3, label=ctrl)
    for n, target in TARGETS.items():
        ax.plot([n], [target], "r_", markersize=18, mew=2)
    ax.axhline(1.0, color="0.6", lw=0.8, ls="--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    sizes = sorted({r.median.drones for r in rows} | set(TARGETS))
    ax.set_xticks(sizes, [str(n) for n in sizes])
    ax.minorticks_off()
    ax.set_xlabel("drones")
    ax.set_ylabel("simulated time / wall time")
    ax.set_title("Speed-up against fleet size\n(median run, bars: min-max; red: targets)")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run_fleet_benchmark(
    sizes: Sequence[int] = FLEET_SIZES,
    controllers: Sequence[str] = ("track",),
    warmup_s: float = WARMUP_S,
    duration_s: float = DURATION_S,
    out_dir: Path | str = Path("benchmarks/results"),
    echo: Callable[[str], object] = print,
    repeat: int = 1,
) -> list[FleetSummary]:
    """Measure every size ``repeat`` times, echo each run as it ends and then the table (one
    median row per size); write ``fleet.md``, ``fleet.csv`` (every run) and ``fleet.png``."""
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    env = environment()
    echo(
        f"fleet scaling benchmark, {repeat} run(s) per size (the median reported); "
        f"{env['machine']}, {env['cpus']} CPU(s), {env['python']}"
    )
    points = []
    for ctrl in controllers:
        for n in sizes:
            for k in range(1, repeat + 1):
                p = run_fleet(n, ctrl, warmup_s, duration_s, repeat=k)
                points.append(p)
                echo(
                    f"  {n} drones, {ctrl}, run {k}/{repeat}: host speed reference "
                    f"{_ms(p.host_ms)} ms; build {p.build_s:.2f} s; window {p.sim_s:.1f} s "
                    f"simulated in {p.wall_s:.2f} s wall: {p.speedup:.1f}×"
                )
    rows = summarise(points)
    echo(_row(HEAD))
    echo(_row(["---"] * len(HEAD)))
    for r in rows:
        echo(_row(_cells(r)))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    page = out / "fleet.md"
    png = plot_scaling(rows, out / "fleet.png")
    write_page(page, markdown(rows, env, warmup_s, duration_s, png.name if png else None))
    with (out / "fleet.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_HEAD)
        w.writerows(_csv_cells(p) for p in points)
    for r in rows:
        p = r.median
        if p.met is not None:
            echo(
                f"target {p.drones} drones: {p.speedup:.1f}× (median of {len(r.runs)}) "
                f"≥ {p.target:g}× — {'met' if p.met else 'NOT met'}"
            )
    echo(f"wrote {page}, {out / 'fleet.csv'}" + (f" and {png}" if png else ""))
    return rows
