"""Relocalization benchmark: one scan, no initial guess, generated ~200 m mines (seed 000 §IV-C1).

``btmission bench reloc`` (or ``python benchmarks/bench_reloc.py``) generates the mines of
``seeds`` at ``size`` (default 200 × 120 × 12 m at 0.5 m), builds each one's place database
(places every metre at 2 m above the floors; its build time is reported), and draws ``poses``
random sensor poses in all (split evenly over the mines): uniform over the floor area of every
level, 1-3 m above the floor, any heading. At each pose the simulated OS1-32 (3 cm range noise)
scans the mine, and every method localises the same scan:

* **ours** — :meth:`~btmission.localization.relocalize.Relocalizer.localize`: descriptors →
  40 candidate poses → coarse GICP → fine GICP on the best two → best fit, confidence, "not
  localised". A success must be *localised* and within the tolerance; a localised pose outside
  it is counted as a wrong answer.
* **descriptor guess only** — the best initial guess ``T_0`` of the descriptors, no ICP.
* **ours, nearest guess only** — our coarse-then-fine GICP from that single ``T_0``.
* **plain ICP from the nearest guess** — point-to-point ICP (small_gicp ``"ICP"``), coarse then
  fine, from that single ``T_0``.
* **plain ICP from the identity** — the same ICP from ``T_0`` = identity (the map's origin,
  heading 0): what registration alone does with no initial guess.

The peers have no "not localised" answer: their success is the error alone. Success means
translation error < 0.3 m and yaw error < 3° (the issue's tolerance). Times are wall-clock per
scan, descriptor and preparation steps included (the peers that start from the nearest guess
include computing it); the map-side preparation (:class:`Relocalizer` construction) is done once
per mine and not timed per scan.

Then, on ``robustness`` more poses per case: **ours with 5 % dust** (returns replaced by dust
short of the wall), **ours with an occluding object** (a 2 × 2 × 3 m box the map does not know,
2-4 m away in a random direction) and **scans from another mine** (each mine's scans localised in
the next mine's database: the right answer is "not localised").

Results go to ``reloc.md`` and ``reloc.csv`` under ``out_dir``; the Markdown also has the success
rate of ours by confidence. Its header says, from the load average, whether other work shared the
machine (times are noisy if it did).
"""

from __future__ import annotations

import csv
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from btmission.bench.planner import _md_row
from btmission.bench.synth import environment, header_lines, write_page

SIZE = (200.0, 120.0, 12.0)
SEEDS = (7, 11)
TOL_M = 0.3
TOL_DEG = 3.0
TARGET_SUCCESS = 0.95
TARGET_MS = 200.0


@dataclass
class Tally:
    """Outcomes and times of one method."""

    method: str
    success: int = 0
    wrong: int = 0
    """A pose outside the tolerance was given (the peers always give one)."""
    not_localised: int = 0
    times_ms: list[float] = field(default_factory=list)
    errors: list[tuple[float, float]] = field(default_factory=list)
    note: str = ""

    @property
    def n(self) -> int:
        return self.success + self.wrong + self.not_localised

    @property
    def rate(self) -> float:
        return self.success / self.n if self.n else float("nan")

    def median_ms(self) -> float:
        return statistics.median(self.times_ms) if self.times_ms else float("nan")

    def p90_ms(self) -> float:
        return float(np.percentile(self.times_ms, 90)) if self.times_ms else float("nan")


HEADER = (
    "method",
    "scans",
    "success",
    "wrong pose",
    "not localised",
    "median ms",
    "p90 ms",
    "target",
    "met",
    "note",
)
CSV_HEADER = (
    "method",
    "scans",
    "success",
    "success_rate",
    "wrong",
    "not_localised",
    "median_ms",
    "p90_ms",
    "target",
    "target_met",
    "note",
)


def _target(t: Tally) -> tuple[str, bool | None]:
    if t.method == "ours":
        met = t.rate >= TARGET_SUCCESS and t.median_ms() < TARGET_MS
        return f"≥ {TARGET_SUCCESS:.0%} and median < {TARGET_MS:g} ms", met
    return "", None


def _cells(t: Tally) -> list[str]:
    target, met = _target(t)
    return [
        t.method,
        str(t.n),
        f"{t.success} ({t.rate:.1%})",
        str(t.wrong),
        str(t.not_localised),
        f"{t.median_ms():.1f}",
        f"{t.p90_ms():.1f}",
        target or "—",
        "—" if met is None else ("yes" if met else "**no**"),
        t.note,
    ]


def _score(t: Tally, ok: bool, localised: bool, err: tuple[float, float], ms: float) -> None:
    t.times_ms.append(ms)
    t.errors.append(err)
    if ok:
        t.success += 1
    elif localised:
        t.wrong += 1
    else:
        t.not_localised += 1


def _within(err: tuple[float, float]) -> bool:
    return err[0] < TOL_M and err[1] < TOL_DEG


def run_reloc_benchmark(
    seeds: Sequence[int] = SEEDS,
    poses: int = 200,
    size: Sequence[float] = SIZE,
    resolution: float = 0.5,
    robustness: int = 50,
    out_dir: Path | str = Path("benchmarks/results"),
    echo: Callable[[str], object] = print,
    *,
    peers: bool = True,
) -> list[Tally]:
    """Run every measurement (see the module docstring), echo the table, write reloc.md/.csv."""
    from btmission.localization.database import build_database, random_poses
    from btmission.localization.relocalize import Relocalizer, RelocConfig, pose_error
    from btmission.localization.scan import add_dust, simulate_scan, with_obstacle
    from btmission.world.minegen import generate_mine

    if poses < 1 or robustness < 0 or not seeds:
        raise ValueError("need at least one mine and one pose, and robustness ≥ 0")
    env = environment()
    echo(
        f"relocalization benchmark: mines {', '.join(map(str, seeds))} at "
        f"{' × '.join(f'{v:g}' for v in size)} m, {resolution:g} m voxels, {poses} poses; "
        f"{env['machine']}, {env['cpus']} CPU(s), {env['python']}"
    )
    names = ["ours"]
    if peers:
        names += [
            "descriptor guess only",
            "ours, nearest guess only",
            "plain ICP from the nearest guess",
            "plain ICP from the identity",
        ]
    tallies = {n: Tally(n) for n in names}
    robust = {
        n: Tally(n)
        for n in ("ours, 5 % dust", "ours, occluding object", "ours, scan from another mine")
    }
    conf_hits: list[tuple[float, bool]] = []
    stage_ms: dict[str, list[float]] = {}
    mines: list[dict[str, Any]] = []
    per_mine = [
        poses // len(seeds) + (1 if i < poses % len(seeds) else 0) for i in range(len(seeds))
    ]
    for seed in seeds:
        mine = generate_mine(seed, size, resolution)
        t0 = time.perf_counter()
        db = build_database(mine.map)
        build_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        reloc = Relocalizer(db)
        prep_s = time.perf_counter() - t0
        mines.append(
            {
                "seed": seed,
                "map": mine.map,
                "db": db,
                "reloc": reloc,
                "build_s": build_s,
                "prep_s": prep_s,
            }
        )
        echo(
            f"  mine {seed}: {len(db):,} places, {len(db.cloud):,} map points; database built in "
            f"{build_s:.1f} s, map prepared for ICP in {prep_s * 1000:.0f} ms"
        )
    icp_cfg = replace(RelocConfig(), registration="ICP")
    for m, n_poses in zip(mines, per_mine):
        vm, reloc = m["map"], m["reloc"]
        plain = Relocalizer(m["db"], icp_cfg) if peers else None
        for k, truth in enumerate(random_poses(vm, n_poses, rng=1000 + m["seed"])):
            scan = simulate_scan(vm, truth, rng=k)
            t0 = time.perf_counter()
            r = reloc.localize(scan)
            ms = (time.perf_counter() - t0) * 1000
            for key, v in r.timings_ms.items():
                stage_ms.setdefault(key, []).append(v)
            err = pose_error(r.pose, truth) if r.pose is not None else (np.inf, np.inf)
            _score(tallies["ours"], r.localized and _within(err), r.localized, err, ms)
            if r.localized:
                conf_hits.append((r.confidence, _within(err)))
            if plain is None:
                continue
            t0 = time.perf_counter()
            guesses = reloc.initial_guesses(reloc.clean(scan))
            guess_ms = (time.perf_counter() - t0) * 1000
            best_t0 = guesses[0][2]
            err = pose_error(best_t0, truth)
            _score(tallies["descriptor guess only"], _within(err), True, err, guess_ms)
            for name, who, init in (
                ("ours, nearest guess only", reloc, best_t0),
                ("plain ICP from the nearest guess", plain, best_t0),
                ("plain ICP from the identity", plain, np.eye(4)),
            ):
                t0 = time.perf_counter()
                c = who.register(scan, init)
                ms = (time.perf_counter() - t0) * 1000
                if init is best_t0:
                    ms += guess_ms
                err = pose_error(c.pose, truth)
                _score(tallies[name], _within(err), True, err, ms)
        if robustness:
            g = np.random.default_rng(m["seed"])
            for k, truth in enumerate(random_poses(vm, robustness, rng=2000 + m["seed"])):
                dusty = add_dust(simulate_scan(vm, truth, rng=k), 0.05, rng=k)
                blocked = simulate_scan(
                    with_obstacle(
                        vm, truth, distance_m=g.uniform(2.0, 4.0), bearing=g.uniform(-np.pi, np.pi)
                    ),
                    truth,
                    rng=k,
                )
                for name, scan in (("ours, 5 % dust", dusty), ("ours, occluding object", blocked)):
                    t0 = time.perf_counter()
                    r = reloc.localize(scan)
                    ms = (time.perf_counter() - t0) * 1000
                    err = pose_error(r.pose, truth) if r.pose is not None else (np.inf, np.inf)
                    _score(robust[name], r.localized and _within(err), r.localized, err, ms)
    if robustness and len(mines) > 1:
        t = robust["ours, scan from another mine"]
        for i, m in enumerate(mines):
            other = mines[(i + 1) % len(mines)]
            for k, pose in enumerate(random_poses(m["map"], robustness, rng=3000 + m["seed"])):
                scan = simulate_scan(m["map"], pose, rng=k)
                t0 = time.perf_counter()
                r = other["reloc"].localize(scan)
                ms = (time.perf_counter() - t0) * 1000
                # the right answer is "not localised": count it as the success
                _score(t, not r.localized, r.localized, (np.inf, np.inf), ms)
        t.note = "success = correctly not localised; wrong = a pose was given"
    ours = tallies["ours"]
    ok = np.array([x for x in ours.errors if _within(x)])
    if len(ok):
        ours.note = (
            f"errors of successes: median {np.median(ok[:, 0]) * 100:.1f} cm, "
            f"{np.median(ok[:, 1]):.2f}°; p95 {np.percentile(ok[:, 0], 95) * 100:.1f} cm"
        )
    rows = list(tallies.values()) + [t for t in robust.values() if t.n]
    echo("")
    echo(_md_row(HEADER))
    echo(_md_row(["---"] * len(HEADER)))
    for t in rows:
        echo(_md_row(_cells(t)))
    stages = {k: statistics.median(v) for k, v in stage_ms.items()}
    calib = _calibration(conf_hits)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md_path, csv_path = out / "reloc.md", out / "reloc.csv"
    write_page(
        md_path,
        _markdown(rows, env, seeds, size, resolution, poses, robustness, mines, stages, calib),
    )
    with csv_path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_HEADER)
        for t in rows:
            target, met = _target(t)
            w.writerow(
                [
                    t.method,
                    t.n,
                    t.success,
                    f"{t.rate:.4f}",
                    t.wrong,
                    t.not_localised,
                    f"{t.median_ms():.2f}",
                    f"{t.p90_ms():.2f}",
                    target,
                    "" if met is None else str(met).lower(),
                    t.note,
                ]
            )
    echo("")
    echo(f"wrote {md_path} and {csv_path}")
    return rows


def _calibration(hits: list[tuple[float, bool]]) -> list[tuple[str, int, float]]:
    """(confidence bin, localised scans in it, fraction correct) for ours."""
    bins = [(0.0, 0.5), (0.5, 0.7), (0.7, 0.85), (0.85, 1.01)]
    out = []
    for lo, hi in bins:
        sel = [ok for c, ok in hits if lo <= c < hi]
        label = f"{lo:.2f}–{min(hi, 1.0):.2f}"
        out.append((label, len(sel), sum(sel) / len(sel) if sel else float("nan")))
    return out


def _markdown(
    rows: Sequence[Tally],
    env: dict[str, str],
    seeds: Sequence[int],
    size: Sequence[float],
    resolution: float,
    poses: int,
    robustness: int,
    mines: Sequence[dict[str, Any]],
    stages: dict[str, float],
    calib: Sequence[tuple[str, int, float]],
) -> str:
    mine_lines = [
        f"- mine {m['seed']}: {len(m['db']):,} places, {len(m['db'].cloud):,} map points; "
        f"database built in {m['build_s']:.1f} s; map prepared for ICP in {m['prep_s'] * 1000:.0f} ms"
        for m in mines
    ]
    stage_txt = ", ".join(f"{k} {v:.1f} ms" for k, v in stages.items())
    lines = [
        "# Relocalization benchmark",
        "",
        *header_lines(env),
        "",
        f"Generated mines {', '.join(map(str, seeds))} at {' × '.join(f'{v:g}' for v in size)} m "
        f"({resolution:g} m voxels); {poses} random poses in all (uniform over the floors, 1-3 m "
        "up, any heading), one simulated OS1-32 scan each (3 cm noise). Success = translation error "
        f"< {TOL_M:g} m and yaw error < {TOL_DEG:g}°; for ours it must also be *localised*. "
        f"Robustness rows: {robustness} more poses per mine. `btmission/bench/reloc.py` says "
        "exactly what is timed.",
        "",
        *mine_lines,
        "",
        _md_row(HEADER),
        _md_row(["---"] * len(HEADER)),
        *(_md_row(_cells(t)) for t in rows),
        "",
        f"Median time per stage of ours: {stage_txt}.",
        "",
        "Ours, localised scans by confidence:",
        "",
        "| confidence | localised scans | correct |",
        "| --- | --- | --- |",
        *(f"| {label} | {n} | {'—' if n == 0 else f'{frac:.1%}'} |" for label, n, frac in calib),
        "",
        "Regenerate with `btmission bench reloc` or `python benchmarks/bench_reloc.py`.",
        "",
    ]
    return "\n".join(lines)
