"""Seed 003 section of ``btmission bench paper``: the ground robots' distributed NMPC (eq. 11-12)
in the warehouse, over several seeds, and the numbers around it.

What seed 003 reports and btmission reproduces (paper vs btmission, in one table each):

* **Scenario 2, Fig. 9**: TurtleBots picking and delivering in a lab warehouse under the
  distributed NMPC with set-exclusion constraints (eq. 12), r_obs = 0.3 m: no collision, the
  smallest distance between two robots 0.3 m less at most 0.04 m ("a maximum violation of 0.04 m
  at one instant"). btmission: ``missions/warehouse.yaml`` under ``--controller nmpc`` for every
  seed of :data:`SEEDS`, the robots' true distance taken at every 0.05 s simulator step, the
  collisions (robot-shelf, robot-robot) and the smallest shelf clearance from the simulator, the
  tasks done. The mission's noise (``runtime.sim``: velocity tracking error, pose-estimate error)
  makes each seed a different run.
* **The NMPC's parameters** (§VI): T_s = 0.1 s, N = 50, r_obs = 0.3 m; and its solve times in the
  same runs (the paper gives none: its solver is PANOC in OpEn, ours fatrop through CasADi).
* **Reactivity** (§VII-B, scenario 3): the auction at 9 Hz takes a new task into the allocation
  within 1/9 s; a robot that holds an object is never taken off its task (k_bt = 0, eq. 8-10),
  the high-priority inspections (t = 28 s, Fig. 11) take a robot off a task it has not committed
  to. Measured from the same runs' events.
* **Fig. 4** at its named point, 50 agents × 400 tasks: SCIP solved the ILP (eq. 6-7) in 1,450 ms
  at 90 % participation and 180 ms at 30 %; btmission's SCIP (the same ILP through OR-Tools) and
  its default assignment solver on the instances of ``btmission bench auction``.

Quick mode (about a minute): two seeds of the warehouse cut at ``QUICK_UNTIL_S`` of mission time
(the first deliveries and the first high-priority inspection), and the head-on pair of
:func:`btmission.control.examples.head_on`.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from btmission.bench.paper import SectionResult, pct, table

KEY = "seed003"
TITLE = "Seed 003 ground robots: distributed NMPC in the warehouse (eq. 11-12, Fig. 9, Fig. 4)"

SEEDS: tuple[int, ...] = (0, 1, 2, 3)
QUICK_SEEDS: tuple[int, ...] = (0, 1)
QUICK_UNTIL_S = 45.0
"""Mission time of a quick warehouse run (the first pick-ups, H1 at 28 s)."""

MISSION = Path(__file__).resolve().parents[2] / "missions" / "warehouse.yaml"

R_OBS_M = 0.3
PAPER_VIOLATION_M = 0.04
"""Seed 003 §VII-B: r_obs = 0.3 m "maintained, with a maximum violation of 0.04 m at one
instant"; the issue's bar: every seed's smallest distance ≥ r_obs − this."""
PAPER_FIG4_MS = {0.9: 1450.0, 0.3: 180.0}
"""Seed 003 §IV-B, Fig. 4: 50 agents, 400 tasks, SCIP solve time by participation."""
PAPER_AUCTION_HZ = 9.0


@dataclass
class WarehouseRun:
    """One warehouse run under a controller, as measured by :func:`warehouse_run`."""

    seed: int
    controller: str
    reason: str
    time_s: float
    wall_s: float
    tasks_done: int
    tasks_total: int
    shelf_collisions: int
    robot_collisions: int
    """Robot-robot contacts (each pair once)."""
    min_robot_m: float
    """Smallest distance between two robots' centres at any simulator step."""
    min_robot_at: tuple[float, str, str]
    """When (mission s) and between whom."""
    below_r_obs_s: float
    """Mission time during which some pair was closer than r_obs."""
    min_clearance_m: float | None
    """Smallest gap between a robot's body (0.15 m sphere) and a shelf or wall face."""
    solves: int
    solve_median_ms: float
    solve_p99_ms: float
    solve_max_ms: float
    new_task_latency_s: float | None
    """Largest delay from a task's arrival to the first auction round after it (the round that
    announces it and takes its bids)."""
    rounds: int
    round_median_ms: float
    reassigned_after_commit: int
    """Tasks taken off a robot after it committed to them (picked the object): 0 by eq. 8-10."""
    preempted_by_priority: int
    """Tasks a robot left for a high-priority task (Fig. 11)."""
    distance_m: dict[str, float] = field(default_factory=dict)
    """Each robot's odometer (true path length): with the mission time, what tells runs apart
    (the robots end at home in every run)."""


def warehouse_run(
    seed: int,
    *,
    controller: str = "nmpc",
    until: float | None = None,
    mission_path: Path = MISSION,
) -> WarehouseRun:
    """Run ``missions/warehouse.yaml`` for ``seed`` (until ``until`` s of mission time, or its
    end) and measure it (:class:`WarehouseRun`); the robots' distance is checked at every
    simulator step on their true positions (the pose-estimate noise left out)."""
    from btmission.missions import load_mission
    from btmission.runtime.events import Recorder
    from btmission.runtime.runner import MissionRun

    mission = load_mission(mission_path)
    rec = Recorder()
    run = MissionRun(mission, controller=controller, seed=seed, observers=[rec])
    sim = run.provider.sim  # type: ignore[attr-defined]
    ids = sorted(run.vehicles)
    pairs = [(i, j) for i in range(len(ids)) for j in range(i + 1, len(ids))]
    closest: dict[str, Any] = {"d": math.inf, "at": (0.0, "", ""), "below": 0}

    def watch(r: MissionRun) -> None:
        p = np.array([sim.vehicle(a).x[:2] for a in ids])
        for i, j in pairs:
            d = float(math.hypot(*(p[i] - p[j])))
            if d < closest["d"]:
                closest["d"], closest["at"] = d, (round(r.now(), 3), ids[i], ids[j])
        d_all = [math.hypot(*(p[i] - p[j])) for i, j in pairs]
        if d_all and min(d_all) < R_OBS_M:
            closest["below"] += 1

    result = run.run(until, progress=watch, progress_every_s=run.dt)
    run.end(result)
    events = rec.events
    collisions = [e for e in events if e.kind == "collision"]
    shelf = sum(1 for e in collisions if e.get("other") == "rock")
    robot_pairs = {
        (round(e.t, 3), *sorted((str(e.get("agent")), str(e.get("other")))))
        for e in collisions
        if e.get("other") in ids
    }
    clearances = [
        float(e.get("clearance_m"))
        for e in events
        if e.kind == "pose" and e.get("clearance_m") is not None
    ]
    times = sorted(t * 1e3 for a in run.agents.values() for t in a.navigator.solve_times)
    added = [e.t for e in events if e.kind == "task_added"]
    round_t = np.array([e.t for e in events if e.kind == "round"])
    latency = []  # arrival → the first auction round after it (which announces the task)
    for t in added:
        later = round_t[round_t >= t - 1e-9]
        if len(later):
            latency.append(float(later[0]) - t)
    rounds = [float(e.get("step_ms")) for e in events if e.kind == "round"]
    committed: dict[str, str] = {}
    after_commit = 0
    preempted = 0
    priority = {
        str(e.get("task"))
        for e in events
        if e.kind == "task_added" and (e.get("priority") or 1.0) > 1.0
    }
    for e in events:
        if e.kind != "task":
            continue
        task, state, agent = str(e.get("task")), e.get("state"), e.get("agent")
        if state == "committed":
            committed[task] = str(agent)
        elif task in committed and (
            state == "open" or (state == "assigned" and agent != committed[task])
        ):
            after_commit += 1
        if state == "open" and any(
            str(e.get("reason", "")).endswith(f"reassigned to {p}") for p in priority
        ):
            preempted += 1
    total = len(mission.spec.tasks)
    return WarehouseRun(
        seed=seed,
        controller=controller,
        reason=result.reason,
        time_s=round(result.time_s, 2),
        wall_s=round(result.wall_s, 1),
        tasks_done=len(result.done),
        tasks_total=total,
        shelf_collisions=shelf,
        robot_collisions=len(robot_pairs),
        min_robot_m=round(closest["d"], 4),
        min_robot_at=closest["at"],
        below_r_obs_s=round(closest["below"] * run.dt, 2),
        min_clearance_m=round(min(clearances), 4) if clearances else None,
        solves=len(times),
        solve_median_ms=round(statistics.median(times), 2) if times else math.nan,
        solve_p99_ms=round(times[min(len(times) - 1, int(0.99 * len(times)))], 1)
        if times
        else math.nan,
        solve_max_ms=round(times[-1], 1) if times else math.nan,
        new_task_latency_s=round(max(latency), 3) if latency else None,
        rounds=len(rounds),
        round_median_ms=round(statistics.median(rounds), 3) if rounds else math.nan,
        reassigned_after_commit=after_commit,
        preempted_by_priority=preempted,
        distance_m={a: round(float(sim.vehicle(a).odometer_m), 3) for a in ids},
    )


@dataclass
class HeadOn:
    """:func:`btmission.control.examples.head_on`: two robots 4 m apart driving at each other."""

    closest_m: float
    closest_without_m: float
    """The same robots without the shared predictions (no eq. 12)."""
    failures: int


def head_on_pair() -> HeadOn:
    from btmission.control.examples import head_on

    with_ = head_on()
    without = head_on(avoid=False)
    return HeadOn(
        round(float(with_.distance.min()), 4),
        round(float(without.distance.min()), 4),
        int((~with_.success).sum()),
    )


@dataclass
class Fig4Point:
    participation: float
    bids: int
    scip_ms: float | None
    assignment_ms: float
    same_optimum: bool | None


def fig4_points() -> list[Fig4Point]:
    """Fig. 4's named point, 50 agents × 400 tasks, at 90 % and 30 % participation."""
    from btmission.bench.auction import BenchConfig, measure_point

    cfg = BenchConfig(agents=(50,), tasks=(400,), participation=(0.9, 0.3), repeat=5)
    out = []
    for p in (0.9, 0.3):
        pt = measure_point("fig4", 50, 400, p, cfg)
        out.append(
            Fig4Point(
                p,
                pt.bids,
                None if pt.scip_solve_ms is None else round(pt.scip_solve_ms, 1),
                round(pt.assignment_ms, 3),
                pt.same_optimum,
            )
        )
    return out


def _m(v: float | None, digits: int = 3) -> str:
    return "—" if v is None or not math.isfinite(v) else f"{v:.{digits}f} m"


def _ms(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{v:.1f} ms" if v >= 10 else f"{v:.2f} ms"


def run(quick: bool, echo: Callable[[str], None]) -> SectionResult:
    """The section (module docstring): the warehouse for each seed, one after the other (each
    run uses one core, ~2.5 min on a free one), then the head-on pair and Fig. 4's point."""
    seeds = QUICK_SEEDS if quick else SEEDS
    until = QUICK_UNTIL_S if quick else None
    runs: list[WarehouseRun] = []
    for seed in seeds:
        t0 = time.perf_counter()
        r = warehouse_run(seed, until=until)
        echo(
            f"   warehouse seed {seed}: {r.tasks_done}/{r.tasks_total} tasks in {r.time_s:g} s, "
            f"collisions {r.shelf_collisions} shelf / {r.robot_collisions} robot, closest "
            f"{r.min_robot_m:.3f} m ({time.perf_counter() - t0:.0f} s wall)"
        )
        runs.append(r)
    pair = head_on_pair()
    echo(
        f"   head-on pair: closest {pair.closest_m:.3f} m (without eq. 12: {pair.closest_without_m:.3f} m)"
    )
    fig4 = fig4_points()
    echo(
        "   Fig. 4 point: " + ", ".join(f"{p.participation:.0%} SCIP {p.scip_ms} ms" for p in fig4)
    )
    markdown = section_markdown(runs, pair, fig4, quick=quick, until=until)
    data = {
        "warehouse": [asdict(r) for r in runs],
        "head_on": asdict(pair),
        "fig4": [asdict(p) for p in fig4],
        "paper": {
            "r_obs_m": R_OBS_M,
            "max_violation_m": PAPER_VIOLATION_M,
            "fig4_ms": PAPER_FIG4_MS,
            "auction_hz": PAPER_AUCTION_HZ,
        },
    }
    return SectionResult(markdown=markdown, data=data)


def markdown_from_data(data: dict[str, Any], *, quick: bool = False) -> str:
    """:func:`section_markdown` again from a stored section's ``data`` (its JSON record): the
    page's wording can change without re-running the experiment."""
    runs = [
        WarehouseRun(**{**r, "min_robot_at": tuple(r["min_robot_at"])}) for r in data["warehouse"]
    ]
    until = next((r.time_s for r in runs if r.reason == "until"), None)
    return section_markdown(
        runs,
        HeadOn(**data["head_on"]),
        [Fig4Point(**p) for p in data["fig4"]],
        quick=quick,
        until=until,
    )


def section_markdown(
    runs: Sequence[WarehouseRun],
    pair: HeadOn,
    fig4: Sequence[Fig4Point],
    *,
    quick: bool = False,
    until: float | None = None,
) -> str:
    """The section's Markdown from its measurements (kept apart from :func:`run` so the page can
    be rebuilt from stored numbers)."""
    seeds = ",".join(str(r.seed) for r in runs)
    cut = f" --until {until:g}" if until is not None else ""
    out: list[str] = []
    out.append(
        "Scenario 2 of seed 003 (§VII-B, Fig. 9): TurtleBots pick objects off shelves and deliver "
        "them to a shared drop-off area, tasks arriving at random times, each robot running the "
        "distributed NMPC of §VI (eq. 11: unicycle; eq. 12: a set-exclusion constraint of radius "
        "r_obs = 0.3 m around every other robot's shared predicted trajectory). The paper: no "
        'collision, and the robots kept r_obs "with a maximum violation of 0.04 m at one instant". '
        "btmission: `missions/warehouse.yaml` (4 robots, 8 pick-and-deliver tasks at random times, "
        "4 inspections and 2 high-priority ones added at 28 s and 45 s) under `--controller nmpc`, "
        "one run per seed. The mission's noise makes each seed another run: each robot drives its "
        "command with a 5 % error correlated over 1 s and reports its pose with a 2 mm / 0.01 rad "
        "error (`runtime.sim`; the paper's robots drove real motors and were located by Vicon). "
        "The robots' distance is taken between their true centres at every 0.05 s simulator step."
    )
    out.append(
        "```sh\n"
        f"btmission bench paper --only seed003{' --quick' if quick else ''}\n"
        f"# one seed by hand (its report; the distance above is sampled more finely than the log's poses):\n"
        f"btmission run missions/warehouse.yaml --controller nmpc --seed 0{cut} --log runs\n"
        "```"
    )
    rows: list[list[object]] = [
        ["paper (lab, TurtleBot3)", "all", "—", 0, 0, "≈ 0.26 m", "", "0.04 m", "one instant", "—"],
    ]
    for r in runs:
        rows.append(
            [
                f"seed {r.seed}" + (f" (until {until:g} s)" if until is not None else ""),
                f"{r.tasks_done} of {r.tasks_total}",
                f"{r.time_s:g} s",
                r.shelf_collisions,
                r.robot_collisions,
                _m(r.min_robot_m),
                pct(r.min_robot_m, R_OBS_M - PAPER_VIOLATION_M),
                _m(max(0.0, R_OBS_M - r.min_robot_m)),
                f"{r.below_r_obs_s:g} s",
                _m(r.min_clearance_m),
            ]
        )
    out.append(
        table(
            [
                "run",
                "tasks done",
                "mission time",
                "robot-shelf collisions",
                "robot-robot collisions",
                "closest robots",
                "vs paper",
                "violation of r_obs",
                "time below r_obs",
                "closest to a shelf",
            ],
            rows,
        )
    )
    ok = all(
        r.shelf_collisions == 0
        and r.robot_collisions == 0
        and r.min_robot_m >= R_OBS_M - PAPER_VIOLATION_M
        for r in runs
    )
    worst = max((R_OBS_M - r.min_robot_m for r in runs), default=0.0)
    closest = min((r.min_robot_m for r in runs), default=math.nan)
    distinct = len({(r.time_s, *sorted(r.distance_m.items())) for r in runs}) == len(runs)
    out.append(
        ("Every seed" if ok else "**Not every seed**")
        + " meets the paper's result (no collision, r_obs kept to within 0.04 m): "
        + (
            f"no seed of {seeds} came closer than r_obs (closest {closest:.3f} m). "
            if worst <= 0
            else f"the largest violation over seeds {seeds} is {worst * 100:.1f} cm. "
        )
        + (
            "The seeds are different runs (each its own mission time and path lengths)."
            if distinct
            else "**Some seeds gave the same run.**"
        )
        + " The last column is the gap between a robot's 0.15 m body and the nearest shelf or "
        "wall face (its centre is 0.15 m farther): seed 003's NMPC constrains only the other "
        "robots, btmission's also keeps its centre 0.3 m off the shelves through a safe "
        "corridor built from the LiDAR ([Reactive navigation](control.md))."
    )
    # --- the NMPC
    solves = sum(r.solves for r in runs)
    medians = [r.solve_median_ms for r in runs]
    p99 = max((r.solve_p99_ms for r in runs), default=math.nan)
    mx = max((r.solve_max_ms for r in runs), default=math.nan)
    spread = f"{min(medians):.2f}-{max(medians):.2f} ms" if medians else "—"
    out.append("**The NMPC** (§VI) and the head-on pair of `btmission control plot unicycle`:")
    out.append(
        table(
            ["", "paper", "btmission"],
            [
                [
                    "model",
                    "unicycle (eq. 11), TurtleBot3",
                    "unicycle (eq. 11); the simulator's "
                    "plant the same model, driven with the velocity error above",
                ],
                ["sampling time, horizon", "0.1 s, N = 50 (5 s)", "0.1 s, N = 50 (5 s)"],
                ["r_obs", "0.3 m", "0.3 m (+ 0.02 m inside the optimiser)"],
                [
                    "constraint, solver",
                    "eq. 12 by a quadratic penalty method, PANOC (OpEn)",
                    "eq. 12 by a quadratic penalty method (ρ × 10 while violated), fatrop (CasADi)",
                ],
                ["state", "Vicon motion capture", "the simulator's pose + 2 mm, 0.01 rad noise"],
                [
                    "solve time",
                    "not reported",
                    f"median {spread} (by run), p99 ≤ {_ms(p99)}, max {_ms(mx)}, over {solves:,} "
                    "control steps (the solver's time in each, every penalty update included)",
                ],
                [
                    "head-on pair, 4 m apart (Fig. 8's situation)",
                    "collision avoided",
                    f"closest {pair.closest_m:.3f} m (without eq. 12: {pair.closest_without_m:.3f} m)",
                ],
            ],
        )
    )
    # --- reactivity
    latency = max((r.new_task_latency_s or 0.0 for r in runs), default=math.nan)
    rounds = sum(r.rounds for r in runs)
    mission_s = sum(r.time_s for r in runs)
    after = sum(r.reassigned_after_commit for r in runs)
    pre = [r.preempted_by_priority for r in runs]
    round_ms = statistics.median([r.round_median_ms for r in runs]) if runs else math.nan
    out.append("**Reactivity** (§IV, §VII-B and C), from the same runs' events:")
    out.append(
        table(
            ["", "paper", "btmission"],
            [
                [
                    "auction rate",
                    "9 Hz (a 100 ms delay per round)",
                    f"{rounds / mission_s:.2f} rounds per mission second ({round_ms:.2f} ms of "
                    "computation each, median)"
                    if mission_s
                    else "—",
                ],
                [
                    "a new task in the allocation",
                    "within 1/9 s of its arrival",
                    f"within {latency:.3f} s (the largest over every task and seed)",
                ],
                [
                    "a robot holding an object reassigned (k_bt = 0, eq. 8-10)",
                    "never",
                    f"{after} times",
                ],
                [
                    "high-priority inspection (t = 28 s, Fig. 11)",
                    "takes a robot off its task",
                    "robots taken off a task when one arrived, by seed: "
                    + ", ".join(str(p) for p in pre),
                ],
            ],
        )
    )
    # --- Fig. 4
    rows4 = []
    for p in fig4:
        paper = PAPER_FIG4_MS.get(p.participation)
        scip = "—" if p.scip_ms is None else f"{p.scip_ms:,.0f} ms"
        rows4.append(
            [
                f"{p.participation:.0%} ({p.bids:,} bids)",
                f"{paper:,.0f} ms" if paper else "—",
                scip,
                pct(p.scip_ms, paper) if paper and p.scip_ms is not None else "—",
                f"{p.assignment_ms:.2f} ms",
                {True: "yes", False: "**no**", None: "—"}[p.same_optimum],
            ]
        )
    out.append(
        "**Fig. 4** at the point the text names, 50 agents × 400 tasks (instances of "
        "`btmission bench auction`: random positions, straight-line costs, each agent bidding on "
        "its cheapest ⌈p·400⌉ tasks):"
    )
    out.append(
        table(
            [
                "participation",
                "paper: SCIP",
                "btmission: SCIP (same ILP)",
                "vs paper",
                "btmission: assignment solver",
                "same optimum",
            ],
            rows4,
        )
    )
    closest_txt = (
        f"its closest pair was {closest:.3f} m apart, {pct(closest, R_OBS_M - PAPER_VIOLATION_M)} "
        "from the paper's 0.26 m"
        if math.isfinite(closest)
        else "no run to compare"
    )
    if worst > 0:
        closest_txt += f" (a violation of {worst * 100:.1f} cm)"
    by_p = {p.participation: p for p in fig4}
    hi, lo = by_p.get(0.9), by_p.get(0.3)
    if hi and lo and hi.scip_ms and lo.scip_ms:
        scaling = (
            f"SCIP took {hi.scip_ms:,.0f} ms at 90 % and {lo.scip_ms:,.0f} ms at 30 % here, "
            f"{hi.scip_ms / lo.scip_ms:.1f} times less at 30 % where the paper measured "
            f"{PAPER_FIG4_MS[0.9] / PAPER_FIG4_MS[0.3]:.1f} times; its times differ with the "
            "machine, the instance and the SCIP version (the paper's costs came from its planner "
            "on a real map, ours are straight lines)."
        )
    else:
        scaling = "SCIP was not run."
    out.append(
        "**Why the numbers differ.** The warehouse is a reconstruction: seed 003 gives neither "
        "its lab's layout nor its tasks' places and times, so `missions/warehouse.yaml` draws "
        "them (numpy `default_rng(3)`) in a generated 24 × 16 m warehouse with 2 m aisles, and its "
        "robots are 0.15 m spheres on the unicycle model at up to 0.4 m/s (a TurtleBot3 Burger "
        "tops out at 0.22 m/s). The paper's 0.04 m violation came from real robots: motor "
        "dynamics, latency and slip. btmission's noise stands in for the slip and the pose "
        "estimate, but its plant has no acceleration limit and no latency beyond the one-step-old "
        f"shared predictions both have, and its optimiser keeps a 0.02 m margin: {closest_txt}. "
        "The solve times are of a different solver on a shared 2-core machine; the paper gives "
        f"none to compare. {scaling} btmission allocates with an exact assignment solver instead "
        "of SCIP (the same optimum, checked above), which is why its rounds take "
        f"{round_ms:.2f} ms (median)."
    )
    return "\n\n".join(out)
