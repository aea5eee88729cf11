"""Reactive-navigation benchmark: NMPC solve times, APF on a LiDAR scan, DPHR on a depth image.

``btmission bench control`` (or ``python benchmarks/bench_control.py``) measures, on synthetic but
geometric inputs (:mod:`btmission.control.scenes`):

* **nmpc** — the MAV NMPC (seed 002 eq. 1-2, 20 Hz, N = 20) in a closed loop of ``steps`` control
  steps (default 200 = 10 s) against the numpy model integrated with RK4 at a finer step: from
  hover at (0, 0, 1) through four set-points changed every quarter of the run (2 m moves in x, y
  and z), warm-started as in flight. Every solve's wall time (the CasADi call, perf_counter) is
  kept; median, p99 and max are reported for **fatrop** and **ipopt** on the *same* NLP, side by
  side. Issue target: median ≤ 3 ms and p99 ≤ 15 ms. A third row times fatrop as the runtime
  configures it (``compiled=True``, ``warm_mu_init=1e-3``, tol 1e-4: gcc-compiled NLP functions
  and a warm barrier start, :mod:`~btmission.control.ocp`); its build time includes a compile
  unless the library is already cached. Also timed: the ground-robot NMPC (seed 003,
  N = 50, one other agent) in the head-on scenario of the tests, and (fatrop) the same pair
  meeting in a 1.6 m aisle between two shelves, with the safe corridor on (report only, no
  target).
* **apf** — :meth:`PotentialField.step` (eq. 3 + Alg. 1) on a 30,000-point VLP-16-like scan
  (16 rings × 1,875 azimuths) taken 0.5 m off the centre of a 3 m corridor, ``repeat`` times.
  Target: median ≤ 1 ms.
* **dphr** — :func:`deepest_point_heading` on a 640×480 depth image of a tunnel bending left
  (with depth noise and 5 % dropout), ``repeat`` times. Target: median ≤ 10 ms.

Solver set-up time (building the CasADi functions) is excluded and printed separately.
"""

from __future__ import annotations

import csv
import gc
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from btmission.bench.synth import environment, header_lines, own_heap, write_page

__all__ = [
    "CSV_HEADER",
    "PARTS",
    "TimingRow",
    "run_control_benchmark",
    "time_apf",
    "time_dphr",
    "time_nmpc",
    "time_unicycle",
]

PARTS = ("nmpc", "apf", "dphr")
"""What ``--only`` can pick."""

NMPC_MEDIAN_MS = 3.0
NMPC_P99_MS = 15.0
APF_MEDIAN_MS = 1.0
DPHR_MEDIAN_MS = 10.0


@dataclass(frozen=True)
class TimingRow:
    """One benchmark line: per-call wall times summarised (ms)."""

    component: str
    case: str
    runs: int
    median_ms: float
    p99_ms: float
    max_ms: float
    target: str
    met: bool | None
    note: str = ""


def _summary(
    component: str,
    case: str,
    times_s: Sequence[float],
    median_target: float | None,
    p99_target: float | None = None,
    note: str = "",
) -> TimingRow:
    ms = np.asarray(times_s) * 1000.0
    med, p99 = float(np.median(ms)), float(np.percentile(ms, 99))
    parts, met = [], None
    if median_target is not None:
        parts.append(f"median ≤ {median_target:g}")
        met = med <= median_target
    if p99_target is not None:
        parts.append(f"p99 ≤ {p99_target:g}")
        met = bool(met) and p99 <= p99_target
    return TimingRow(
        component, case, len(ms), med, p99, float(ms.max()), ", ".join(parts) or "—", met, note
    )


# ----------------------------------------------------------------------------------------------
RUNTIME_NMPC = {"compiled": True, "warm_mu_init": 1e-3, "tol": 1e-4}
"""The MAV NMPC options the runtime uses (``btmission/runtime/navigation.py``)."""


def time_nmpc(
    solver: str, steps: int = 200, **options: Any
) -> tuple[list[float], int, float, float]:
    """Closed-loop MAV NMPC: (per-step solve times s, failures, build s, final error m).

    ``options`` go to :class:`~btmission.control.nmpc.NmpcConfig` (e.g. :data:`RUNTIME_NMPC`).
    """
    from btmission.control.mav_model import simulate
    from btmission.control.nmpc import MavNmpc, NmpcConfig

    cfg = NmpcConfig(solver=solver, **options)
    t0 = time.perf_counter()
    nmpc = MavNmpc(cfg)
    build = time.perf_counter() - t0
    setpoints = [(2.0, 0.0, 1.0), (2.0, 2.0, 1.0), (2.0, 2.0, 3.0), (0.0, 0.0, 2.0)]
    x = np.zeros(8)
    x[2] = 1.0
    times: list[float] = []
    failures = 0
    goal = np.asarray(setpoints[0])
    gc.collect()
    for k in range(steps):
        goal = np.asarray(setpoints[min(4 * k // steps, 3)])
        res = nmpc.solve(x, goal)
        times.append(res.solve_time_s)
        failures += not res.success
        x = simulate(x, res.u, cfg.dt_s, cfg.model)
    return times, failures, build, float(np.linalg.norm(x[:3] - goal))


AISLE_SHELVES = ((-1.0, 5.0, -1.8, -0.8), (-1.0, 5.0, 0.8, 1.8))
"""Two shelves (x0, x1, y0, y1) with a 1.6 m aisle between them along y = 0."""


def time_unicycle(
    solver: str, steps: int = 100, shelves: bool = False
) -> tuple[list[float], int, float]:
    """Two ground robots head-on (seed 003): (per-solve times s, failures, closest distance m).

    ``shelves``: they meet in the aisle between :data:`AISLE_SHELVES`, whose outlines (points
    every 5 cm) are the obstacle points of the safe corridor."""
    from btmission.control.scenes import shelf_outline
    from btmission.control.unicycle_nmpc import (
        UnicycleConfig,
        UnicycleNmpc,
        shift_prediction,
        unicycle_step,
    )

    cfg = UnicycleConfig(solver=solver)
    a, b = UnicycleNmpc(cfg), UnicycleNmpc(cfg)
    n = cfg.horizon
    xa, xb = np.array([0.0, 0.05, 0.0]), np.array([4.0, 0.0, math.pi])
    pa, pb = np.tile(xa[:2], (n + 1, 1)), np.tile(xb[:2], (n + 1, 1))
    points = np.vstack([shelf_outline(*box) for box in AISLE_SHELVES]) if shelves else None
    times: list[float] = []
    failures = 0
    closest = math.inf
    for _ in range(steps):
        ra = a.solve(xa, [4.0, 0.05], [shift_prediction(pb)], obstacles=points)
        rb = b.solve(xb, [0.0, 0.0], [shift_prediction(pa)], obstacles=points)
        times += [ra.solve_time_s, rb.solve_time_s]
        failures += (not ra.success) + (not rb.success)
        pa, pb = ra.predicted_positions, rb.predicted_positions
        xa, xb = unicycle_step(xa, ra.u, cfg.dt_s), unicycle_step(xb, rb.u, cfg.dt_s)
        closest = min(closest, float(np.linalg.norm(xa[:2] - xb[:2])))
    return times, failures, closest


def _repeat(fn: Callable[[], object], repeat: int) -> list[float]:
    fn()  # warm-up (imports, caches)
    gc.collect()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def time_apf(repeat: int = 200) -> tuple[list[float], int]:
    """APF step on a 30,000-point scan: (times s, number of points)."""
    from btmission.control.apf import PotentialField
    from btmission.control.scenes import lidar_scan, straight_corridor

    points = lidar_scan(straight_corridor(3.0, 3.0), [0.0, 0.5, 1.5], noise_m=0.01)
    apf = PotentialField()
    return _repeat(lambda: apf.step(points, [1.0, 0.0, 0.0]), repeat), len(points)


def time_dphr(repeat: int = 50) -> tuple[list[float], tuple[int, int]]:
    """DPHR on a 640×480 depth image: (times s, image shape)."""
    from btmission.control.dphr import deepest_point_heading
    from btmission.control.scenes import bending_tunnel, depth_image

    img = depth_image(bending_tunnel("left"), [0.0, 0.0, 1.5], noise_m=0.02, dropout=0.05)
    return _repeat(lambda: deepest_point_heading(img), repeat), (img.shape[0], img.shape[1])


# ----------------------------------------------------------------------------------------------
CSV_HEADER = (
    "component",
    "case",
    "runs",
    "median_ms",
    "p99_ms",
    "max_ms",
    "target_ms",
    "met",
    "note",
)
_MD_HEADER = ("component", "case", "runs", "median ms", "p99 ms", "max ms", "target (ms)", "met")


def _row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _md_cells(r: TimingRow) -> list[str]:
    met = "—" if r.met is None else ("yes" if r.met else "**no**")
    return [
        r.component,
        r.case,
        str(r.runs),
        f"{r.median_ms:.3f}",
        f"{r.p99_ms:.3f}",
        f"{r.max_ms:.3f}",
        r.target,
        met,
    ]


def _table_head() -> list[str]:
    return [
        _row(list(_MD_HEADER)),
        _row(["---", "---", "---:", "---:", "---:", "---:", "---", "---"]),
    ]


@own_heap()
def run_control_benchmark(
    parts: Sequence[str] = PARTS,
    *,
    steps: int = 200,
    repeat: int = 200,
    out_dir: Path | str = Path("benchmarks/results"),
    echo: Callable[[str], object] = print,
) -> list[TimingRow]:
    """Run the chosen parts, echo a Markdown table as rows arrive, write ``control.md``/``.csv``."""
    unknown = [p for p in parts if p not in PARTS]
    if unknown or not parts:
        raise ValueError(
            f"unknown part(s) {', '.join(unknown) or '(none)'} (known: {', '.join(PARTS)})"
        )
    if steps < 1 or repeat < 1:
        raise ValueError("steps and repeat must be at least 1")
    env = environment()
    echo(
        f"control benchmark: {', '.join(parts)}; {env['machine']}, {env['cpus']} CPU(s), "
        f"{env['python']}"
    )
    rows: list[TimingRow] = []
    notes: list[str] = []

    def emit(row: TimingRow) -> None:
        rows.append(row)
        echo(_row(_md_cells(row)))

    if "nmpc" in parts:
        echo(f"  … MAV NMPC: {steps}-step closed loop with fatrop, then ipopt (same NLP)")
        for line in _table_head():
            echo(line)
        for solver in ("fatrop", "ipopt"):
            times, failures, build, err = time_nmpc(solver, steps)
            hold_s = (steps - 3 * steps // 4) * 0.05
            note = (
                f"build {build * 1000:.0f} ms, {failures} failed, {err:.2f} m from the last "
                f"set-point {hold_s:.1f} s after it was given"
            )
            emit(_summary("nmpc (MAV, N=20)", solver, times, NMPC_MEDIAN_MS, NMPC_P99_MS, note))
            notes.append(f"nmpc {solver}: {note}")
        times, failures, build, err = time_nmpc("fatrop", steps, **RUNTIME_NMPC)
        case = "fatrop, compiled, warm μ (runtime)"
        note = (
            f"build {build * 1000:.0f} ms, {failures} failed, {err:.2f} m from the last set-point"
        )
        emit(_summary("nmpc (MAV, N=20)", case, times, NMPC_MEDIAN_MS, NMPC_P99_MS, note))
        notes.append(f"nmpc {case}: {note}")
        for solver in ("fatrop", "ipopt"):
            utimes, ufail, closest = time_unicycle(solver, max(steps // 2, 1))
            note = f"{ufail} failed, closest approach {closest:.3f} m (r_obs 0.3 m)"
            emit(_summary("nmpc (unicycle, N=50)", solver, utimes, None, None, note))
            notes.append(f"unicycle {solver}: {note}")
        utimes, ufail, closest = time_unicycle("fatrop", max(steps // 2, 1), shelves=True)
        note = f"{ufail} failed, closest approach {closest:.3f} m (r_obs 0.3 m)"
        emit(_summary("nmpc (unicycle, N=50, shelves)", "fatrop", utimes, None, None, note))
        notes.append(f"unicycle fatrop in an aisle between shelves: {note}")
    else:
        for line in _table_head():
            echo(line)
    if "apf" in parts:
        times, n_points = time_apf(repeat)
        emit(_summary("apf", f"{n_points:,}-point scan", times, APF_MEDIAN_MS))
    if "dphr" in parts:
        times, shape = time_dphr(max(repeat // 4, 1))
        emit(_summary("dphr", f"{shape[1]}×{shape[0]} depth image", times, DPHR_MEDIAN_MS))

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md_path, csv_path = out / "control.md", out / "control.csv"
    write_page(md_path, _markdown(rows, notes, env, steps))
    with csv_path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_HEADER)
        for r in rows:
            writer.writerow(
                [
                    r.component,
                    r.case,
                    r.runs,
                    f"{r.median_ms:.4f}",
                    f"{r.p99_ms:.4f}",
                    f"{r.max_ms:.4f}",
                    r.target,
                    "" if r.met is None else str(r.met).lower(),
                    r.note,
                ]
            )
    echo("")
    for note in notes:
        echo(f"  {note}")
    for r in rows:
        if r.met is not None:
            echo(
                f"target {r.component} [{r.case}]: {r.target} ms — {'met' if r.met else 'NOT met'}"
            )
    echo(f"wrote {md_path} and {csv_path}")
    return rows


def _markdown(
    rows: Sequence[TimingRow], notes: Sequence[str], env: dict[str, str], steps: int
) -> str:
    lines = [
        "# Control benchmark",
        "",
        *header_lines(env),
        "",
        f"Per-call wall time (ms). *nmpc*: every solve of a {steps}-step closed loop (MAV, 20 Hz, "
        "N = 20, warm-started), fatrop and ipopt on the same NLP, and fatrop as the runtime "
        "runs it (gcc-compiled NLP functions, warm barrier start, tol 1e-4); the unicycle rows are the "
        "seed 003 NMPC (N = 50) of two robots passing head-on (*shelves*: in a 1.6 m aisle "
        "between two shelves, with the safe corridor). *apf*: eq. 3 + Alg. 1 on a "
        "VLP-16-like scan. *dphr*: close + k-means + centroid on a 640×480 depth image. "
        "See `btmission/bench/control.py` for the exact scenarios.",
        "",
        *_table_head(),
        *(_row(_md_cells(r)) for r in rows),
        "",
        *(f"- {n}" for n in notes),
        "",
        "Regenerate with `btmission bench control` or `python benchmarks/bench_control.py`. "
        "The load line at the top says whether other work shared the machine; if it did, compare "
        "ratios (fatrop vs ipopt) first.",
        "",
    ]
    return "\n".join(lines)
