"""Simulator benchmark: how much faster than real time missions run, and the auction at scale.

``btmission bench sim`` (or ``python benchmarks/bench_sim.py``) measures

* **the seed 000 field mission** (``missions/mine_inspection.yaml``: 3 drones, 7 inspections,
  T7 added at 116 s) run to its end with each path-following controller — the lightweight
  tracking controller and the seed 002 NMPC on every agent — as simulated time over wall time.
  Targets (issue 19; issue 6's were ≥ 50× and ≥ 5×): ≥ 100× with the tracking controller,
  ≥ 20× with NMPC. Building the run (map generation, risk layer, rock-face cells, NMPC
  set-up, loading the loop's compiled kernels) is timed separately;
* **the seed 003 scaling point**: 50 ground robots and 400 inspection tasks open at once on a
  100 m × 100 m floor (Fig. 4/5's instance size), run for ``duration`` simulated seconds with the
  tracking controller: the auction round rate (every round announces, collects all 50 agents'
  bids computed from D*+ cost-to-goal fields, allocates and publishes), the bidding stage's time,
  and the total wall time. The first round, which runs the 400 backward searches the bids read,
  is reported on its own.

Times are wall-clock (``time.perf_counter``); the results say when and where they were measured
and, from the load average, whether other work shared the machine.
"""

from __future__ import annotations

import csv
import os
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from btmission.bench.synth import environment, header_lines, write_page

TARGETS = {"track": 100.0, "nmpc": 20.0}
"""Speed-up over real time the mine mission must reach with each controller."""

MINE = Path(__file__).resolve().parents[2] / "missions" / "mine_inspection.yaml"


@dataclass(frozen=True)
class MissionPoint:
    controller: str
    build_s: float
    sim_s: float
    wall_s: float
    done: int
    tasks: int
    collisions: int
    end: str
    solver_cpu_s: float = 0.0
    """CPU time of every agent's NMPC solver calls (0: no NMPC)."""
    cpus: int = 1

    @property
    def speedup(self) -> float:
        return self.sim_s / self.wall_s if self.wall_s > 0 else float("inf")

    @property
    def solver_ceiling(self) -> float:
        """The speed-up the solver calls alone allow with every CPU solving all the time
        (simulated s / (solver CPU s / CPUs)): no run of this machine can be faster."""
        if self.solver_cpu_s <= 0:
            return float("inf")
        return self.sim_s / (self.solver_cpu_s / self.cpus)

    @property
    def target(self) -> float:
        return TARGETS[self.controller]

    @property
    def met(self) -> bool:
        return self.speedup >= self.target and self.done == self.tasks


@dataclass(frozen=True)
class ScalePoint:
    agents: int
    tasks: int
    participation: float
    build_s: float
    sim_s: float
    wall_s: float
    first_round_s: float
    rounds: int
    round_ms: float
    round_p90_ms: float
    round_cpu_ms: float
    """Median CPU time of a round (the coordinator's thread; what the load does not change)."""
    bid_ms: float
    searches: int
    done: int
    repeated_pct: float
    """Share of the bids (one per agent per round) that repeated the agent's previous costs
    (not moved to another voxel, same announcement: :mod:`btmission.allocation.bidder`)."""

    @property
    def round_hz(self) -> float:
        return 1000.0 / self.round_ms if self.round_ms > 0 else float("inf")

    @property
    def bid_ms_per_agent(self) -> float:
        return self.bid_ms / self.agents

    @property
    def speedup(self) -> float:
        return self.sim_s / self.wall_s if self.wall_s > 0 else float("inf")


def run_mission(path: Path, controller: str) -> MissionPoint:
    """Run ``path`` to its end with ``controller``; build and run timed apart."""
    from btmission.missions import load_mission
    from btmission.runtime.runner import MissionRun

    m = load_mission(path)
    t0 = time.perf_counter()
    run = MissionRun(m, controller=controller)
    build = time.perf_counter() - t0
    res = run.run()
    solver_cpu = sum(a.navigator.solve_cpu_s for a in run.agents.values())
    run.close()
    return MissionPoint(
        controller,
        build,
        res.time_s,
        res.wall_s,
        len(res.done),
        len(res.done) + len(res.open) + len(res.pending),
        res.collisions,
        res.reason,
        solver_cpu,
        os.cpu_count() or 1,
    )


def scale_mission_text(agents: int, tasks: int, participation: float, seed: int) -> str:
    """A 100 m × 100 m floor, ``agents`` ground robots and ``tasks`` inspections, all at 0 s."""
    rng = np.random.default_rng(seed)
    size = 100.0
    pts = rng.uniform(1.0, size - 1.0, (agents + tasks, 2)).round(1)
    lines = [
        "mission: scale",
        "version: 1",
        f"description: seed 003 scaling point, {agents} agents x {tasks} tasks",
        "world:",
        f"  map: {{generate: empty, size: [{size:g}, {size:g}, 1]}}",
        "  resolution: 1.0",
        "agents:",
        *(
            f"  - {{id: A{i}, library: ground, start: [{x:g}, {y:g}, 0]}}"
            for i, (x, y) in enumerate(pts[:agents])
        ),
        "tasks:",
        *(
            f"  - {{id: T{i}, type: inspect, location: [{x:g}, {y:g}, 0]}}"
            for i, (x, y) in enumerate(pts[agents:])
        ),
        "task_types:",
        "  inspect: {goal: at_goal(location), cost: path_cost(location)}",
        f"coordination: {{auction_rate_hz: 10, participation: {participation:g}}}",
        "runtime: {controller: track, settings: {clearance_m: 0}}",
        "",
    ]
    return "\n".join(lines)


def run_scale(
    agents: int = 50,
    tasks: int = 400,
    participation: float = 0.3,
    duration_s: float = 30.0,
    seed: int = 0,
) -> ScalePoint:
    """Run the scaling mission for ``duration_s`` simulated seconds."""
    from btmission.missions import load_mission_text
    from btmission.runtime.runner import MissionRun

    m = load_mission_text(scale_mission_text(agents, tasks, participation, seed), "scale.yaml")
    t0 = time.perf_counter()
    run = MissionRun(m)
    build = time.perf_counter() - t0
    res = run.run(until=duration_s)
    rounds = run.coordinator.rounds
    later = rounds[1:] or rounds
    repeated = sum(a.bidder.repeated for a in run.agents.values())
    return ScalePoint(
        agents,
        tasks,
        participation,
        build,
        res.time_s,
        res.wall_s,
        rounds[0] if rounds else 0.0,
        len(rounds),
        1000 * statistics.median(later),
        1000 * float(np.percentile(later, 90)),
        1000 * statistics.median(run.coordinator.round_cpu[1:] or run.coordinator.round_cpu or [0]),
        1000 * statistics.median(run.coordinator.bid_times[1:] or run.coordinator.bid_times),
        run.paths.searches,
        len(res.done),
        100.0 * repeated / max(1, len(rounds) * agents),
    )


# ------------------------------------------------------------------------------- output
def _row(cells: Sequence[object]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


MISSION_HEAD = (
    "controller",
    "build s",
    "simulated s",
    "wall s",
    "speed-up",
    "target",
    "met",
    "tasks done",
    "collisions",
    "ended",
    "solver CPU s",
    "solver ceiling",
)
SCALE_HEAD = (
    "agents × tasks",
    "participation",
    "build s",
    "first round s",
    "rounds",
    "round ms (median)",
    "round ms (p90)",
    "round CPU ms",
    "round rate Hz",
    "bidding ms (all agents)",
    "bid ms per agent",
    "bids repeated",
    "D*+ searches",
    "simulated s",
    "wall s",
    "speed-up",
)


def _mission_cells(p: MissionPoint) -> list[str]:
    return [
        p.controller,
        f"{p.build_s:.2f}",
        f"{p.sim_s:.1f}",
        f"{p.wall_s:.1f}",
        f"{p.speedup:.1f}×",
        f"≥ {p.target:g}×",
        "yes" if p.met else "no",
        f"{p.done}/{p.tasks}",
        str(p.collisions),
        p.end,
        f"{p.solver_cpu_s:.1f}" if p.solver_cpu_s > 0 else "–",
        f"{p.solver_ceiling:.1f}×" if p.solver_cpu_s > 0 else "–",
    ]


def _scale_cells(p: ScalePoint) -> list[str]:
    return [
        f"{p.agents} × {p.tasks}",
        f"{p.participation:g}",
        f"{p.build_s:.2f}",
        f"{p.first_round_s:.2f}",
        str(p.rounds),
        f"{p.round_ms:.1f}",
        f"{p.round_p90_ms:.1f}",
        f"{p.round_cpu_ms:.1f}",
        f"{p.round_hz:.1f}",
        f"{p.bid_ms:.1f}",
        f"{p.bid_ms_per_agent:.2f}",
        f"{p.repeated_pct:.0f} %",
        str(p.searches),
        f"{p.sim_s:.1f}",
        f"{p.wall_s:.1f}",
        f"{p.speedup:.1f}×",
    ]


def _table(head: Sequence[str], rows: Sequence[Sequence[str]], flag: str) -> list[str]:
    """A table, or a line saying it was not measured this time (``flag`` left it out)."""
    if not rows:
        return [f"Not measured in this run ({flag}); see Earlier runs for the last numbers."]
    return [_row(head), _row(["---"] * len(head)), *(_row(r) for r in rows)]


def markdown(
    missions: Sequence[MissionPoint],
    scale: Sequence[ScalePoint],
    env: dict[str, str],
) -> str:
    """The results page (the previous runs are kept below it by :func:`write_page`)."""
    lines = [
        "# Simulator benchmark",
        "",
        *header_lines(env),
        "",
        "## mine_inspection (seed 000 §VI) to its end",
        "",
        "Speed-up = simulated time / wall time of the run (the build — map, risk layer, "
        "rock-face cells, controllers, the loop's compiled kernels — is timed apart). "
        "*Solver CPU s*: the CPU time of every NMPC solver call (the threads that solved); "
        "*solver ceiling*: simulated s / (solver CPU s / CPUs), the speed-up the solves alone "
        "would allow with every core solving all the time — no run on this machine is faster, "
        "whatever the rest of the loop costs.",
        "",
        *_table(MISSION_HEAD, [_mission_cells(p) for p in missions], "`--controllers ''`"),
        "",
        "## Scaling point (seed 003 Fig. 4/5: 50 agents × 400 tasks)",
        "",
        "Ground robots with the tracking controller on a 100 m × 100 m floor (1 m voxels), every "
        "task open from 0 s. A round = announce, every agent's bid (D*+ cost-to-goal lookups "
        "for its participation share of the tasks), allocation, publication. The first round "
        "also runs one backward D*+ search per task. *Round CPU ms*: the median CPU time the "
        "coordinator's thread spent on a round (the wall-clock medians grow when other work "
        "shares the machine; this one far less). *Bids repeated*: the share of bids that "
        "sent the agent's previous costs again (it had not moved to another voxel and the "
        "announced tasks and the map were unchanged).",
        "",
        *_table(SCALE_HEAD, [_scale_cells(p) for p in scale], "`--scale ''`"),
        "",
        "Regenerate with `btmission bench sim` or `python benchmarks/bench_sim.py`; "
        "`--controllers ''` measures the scaling point alone, `--scale ''` the mission alone.",
        "",
    ]
    return "\n".join(lines)


def run_sim_benchmark(
    controllers: Sequence[str] = ("track", "nmpc"),
    scale: Sequence[tuple[int, int, float]] = ((50, 400, 0.3),),
    duration_s: float = 30.0,
    out_dir: Path | str = Path("benchmarks/results"),
    echo: Callable[[str], object] = print,
    mission: Path = MINE,
) -> tuple[list[MissionPoint], list[ScalePoint]]:
    """Measure, echo the tables as they fill, and write ``sim.md`` (the previous page kept
    under "Earlier runs") and ``sim.csv``."""
    env = environment()
    echo(f"simulator benchmark; {env['machine']}, {env['cpus']} CPU(s), {env['python']}")
    echo("")
    echo(_row(MISSION_HEAD))
    echo(_row(["---"] * len(MISSION_HEAD)))
    missions = []
    for c in controllers:
        p = run_mission(mission, c)
        missions.append(p)
        echo(_row(_mission_cells(p)))
    echo("")
    echo(_row(SCALE_HEAD))
    echo(_row(["---"] * len(SCALE_HEAD)))
    points = []
    for agents, tasks, part in scale:
        q = run_scale(agents, tasks, part, duration_s)
        points.append(q)
        echo(_row(_scale_cells(q)))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    page = out / "sim.md"
    write_page(page, markdown(missions, points, env))
    with (out / "sim.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "kind",
                "controller_or_size",
                "speedup",
                "target",
                "met",
                "build_s",
                "sim_s",
                "wall_s",
                "round_ms",
                "round_hz",
                "bid_ms",
                "bid_ms_per_agent",
                "solver_cpu_s",
                "solver_ceiling",
            ]
        )
        for p in missions:
            w.writerow(
                [
                    "mission",
                    p.controller,
                    f"{p.speedup:.2f}",
                    p.target,
                    p.met,
                    f"{p.build_s:.3f}",
                    f"{p.sim_s:.2f}",
                    f"{p.wall_s:.2f}",
                    "",
                    "",
                    "",
                    "",
                    f"{p.solver_cpu_s:.2f}" if p.solver_cpu_s > 0 else "",
                    f"{p.solver_ceiling:.2f}" if p.solver_cpu_s > 0 else "",
                ]
            )
        for q in points:
            w.writerow(
                [
                    "scale",
                    f"{q.agents}x{q.tasks}@{q.participation:g}",
                    f"{q.speedup:.2f}",
                    "",
                    "",
                    f"{q.build_s:.3f}",
                    f"{q.sim_s:.2f}",
                    f"{q.wall_s:.2f}",
                    f"{q.round_ms:.2f}",
                    f"{q.round_hz:.2f}",
                    f"{q.bid_ms:.2f}",
                    f"{q.bid_ms_per_agent:.3f}",
                    "",
                    "",
                ]
            )
    echo("")
    for p in missions:
        ceiling = (
            f" (the solver calls alone allow at most {p.solver_ceiling:.1f}× on {p.cpus} CPU(s))"
            if p.solver_cpu_s > 0
            else ""
        )
        echo(
            f"target {p.controller}: {p.speedup:.1f}× ≥ {p.target:g}× — "
            f"{'met' if p.met else 'NOT met'}{ceiling}"
        )
    echo(f"wrote {out / 'sim.md'} and {out / 'sim.csv'}")
    return missions, points
