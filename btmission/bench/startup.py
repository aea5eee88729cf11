"""``btmission bench startup``: how long the command line takes before it does anything useful.

Each case runs a fresh interpreter (``python -m btmission ARGS``) ``repeat`` times, alternating
the cases so that a passing load spike hits them alike, and reports the median and the fastest
wall time. The peer row is the interpreter alone (``python -c pass``), the floor no command can
go below. Targets (issue 19): ``--help`` ≤ 0.15 s, ``validate`` on the mine mission ≤ 0.5 s.

Bytecode: an installed btmission runs from cached bytecode (pip compiles it at install time; an
editable install writes ``__pycache__`` on its first run). The cases run so, with a bytecode
cache of their own in a temporary directory (``PYTHONPYCACHEPREFIX``) that the warm-up run fills,
whatever the environment says: a sandbox with ``PYTHONDONTWRITEBYTECODE=1`` would otherwise
compile btmission's sources in every run. One case keeps that condition (``bytecode=False``),
to show its cost and to compare with runs measured before the cases had a cache.
"""

from __future__ import annotations

import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from btmission.bench.synth import environment, header_lines, write_page

MINE = Path(__file__).resolve().parents[2] / "missions" / "mine_inspection.yaml"


@dataclass(frozen=True)
class Case:
    name: str
    argv: tuple[str, ...]
    """Arguments after the interpreter."""
    target_s: float | None = None
    bytecode: bool = True
    """Run with a bytecode cache (see the module's docstring); ``False``: with
    ``PYTHONDONTWRITEBYTECODE=1`` and no cache of the case's own, so sources without an existing
    ``__pycache__`` are compiled in every run."""


VALIDATE = ("-m", "btmission", "validate", str(MINE))

CASES: tuple[Case, ...] = (
    Case("python -c pass (the interpreter alone)", ("-c", "pass")),
    Case("btmission --version", ("-m", "btmission", "--version")),
    Case("btmission --help", ("-m", "btmission", "--help"), 0.15),
    Case("btmission validate missions/mine_inspection.yaml", VALIDATE, 0.5),
    Case("btmission validate missions/mine_inspection.yaml, PYTHONDONTWRITEBYTECODE=1", VALIDATE, bytecode=False),
)  # fmt: skip


def case_env(case: Case, cache_dir: Path, base: Mapping[str, str] = os.environ) -> dict[str, str]:
    """The environment of ``case``'s runs: ``base`` with a bytecode cache in ``cache_dir``, or
    with bytecode writing turned off (``case.bytecode`` False)."""
    env = dict(base)
    if case.bytecode:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = str(cache_dir)
    else:
        env["PYTHONDONTWRITEBYTECODE"] = "1"
        env.pop("PYTHONPYCACHEPREFIX", None)
    return env


@dataclass(frozen=True)
class Sample:
    """One run of a case."""

    wall_s: float
    cpu_s: float
    """User + system CPU time of the process (all its threads): what the run cost, which a busy
    machine inflates far less than the wall time."""


@dataclass(frozen=True)
class Timing:
    case: Case
    times_s: tuple[float, ...]
    """Wall times."""
    cpu_s: tuple[float, ...]

    @property
    def median_s(self) -> float:
        return statistics.median(self.times_s)

    @property
    def cpu_median_s(self) -> float:
        return statistics.median(self.cpu_s)

    @property
    def best_s(self) -> float:
        return min(self.times_s)

    @property
    def met(self) -> str:
        if self.case.target_s is None:
            return "—"
        return "yes" if self.median_s <= self.case.target_s else "no"


Clock = Callable[[Sequence[str], Mapping[str, str]], Sample]
"""One timed run: (arguments after the interpreter, environment) → its times."""


def time_once(argv: Sequence[str], env: Mapping[str, str]) -> Sample:
    """Times of one ``python ARGV`` run in ``env`` (its output discarded); raises if it fails."""
    import resource  # POSIX; the children's CPU time is counted once they are waited for

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, *argv],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=dict(env),
        check=True,
        timeout=120,
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return Sample(wall, cpu)


def measure(
    cases: Sequence[Case], repeat: int, clock: Clock = time_once, cache_dir: Path | None = None
) -> list[Timing]:
    """Each case ``repeat`` times, round-robin, after one untimed warm-up run of each.

    The bytecode cache is ``cache_dir``, or a temporary directory removed afterwards."""
    if cache_dir is None:
        with tempfile.TemporaryDirectory(prefix="btmission-startup-") as tmp:
            return measure(cases, repeat, clock, Path(tmp))
    envs = {c.name: case_env(c, cache_dir) for c in cases}
    for c in cases:
        clock(c.argv, envs[c.name])  # warm the OS file cache and the bytecode cache
    samples: dict[str, list[Sample]] = {c.name: [] for c in cases}
    for _ in range(repeat):
        for c in cases:
            samples[c.name].append(clock(c.argv, envs[c.name]))
    return [
        Timing(
            c,
            tuple(x.wall_s for x in samples[c.name]),
            tuple(x.cpu_s for x in samples[c.name]),
        )
        for c in cases
    ]


HEAD = ["command", "median s", "fastest s", "target s", "met", "CPU s (median)"]


def rows(timings: Sequence[Timing]) -> list[list[str]]:
    return [
        [
            t.case.name,
            f"{t.median_s:.3f}",
            f"{t.best_s:.3f}",
            "—" if t.case.target_s is None else f"≤ {t.case.target_s:g}",
            t.met,
            f"{t.cpu_median_s:.3f}",
        ]
        for t in timings
    ]


def markdown(timings: Sequence[Timing], repeat: int, env: dict[str, str]) -> str:
    lines = ["# Start-up benchmark", "", *header_lines(env), ""]
    lines.append(
        f"Wall time of a fresh `python -m btmission ...` ({repeat} runs each, cases alternated, "
        "after one warm-up run each). The first row is the interpreter alone: the floor. "
        "Every row but the last runs from a bytecode cache (a temporary `PYTHONPYCACHEPREFIX` "
        "the warm-up run fills), as an installed package does; the last runs with "
        "`PYTHONDONTWRITEBYTECODE=1`, so btmission's sources are compiled in every run unless "
        "the checkout already has `__pycache__` (runs before 2026-11-28 measured every row so). "
        "Targets judge the median wall time; the CPU column (user + system time of the process, "
        "all threads) is what a run costs, which other work on the machine inflates far less."
    )
    lines += ["", "| " + " | ".join(HEAD) + " |", "|" + "---|" * len(HEAD)]
    lines += ["| " + " | ".join(r) + " |" for r in rows(timings)]
    lines += ["", "Regenerate with `btmission bench startup`.", ""]
    return "\n".join(lines)


def run_startup_benchmark(
    repeat: int = 10,
    out_dir: Path = Path("benchmarks/results"),
    echo: Callable[[str], object] = print,
    cases: Sequence[Case] = CASES,
) -> list[Timing]:
    """Measure, echo the table and write ``startup.md`` (the previous page's tables kept under
    "Earlier runs") and ``startup.csv`` under ``out_dir``."""
    env = environment()
    timings = measure(cases, repeat)
    echo("| " + " | ".join(HEAD) + " |")
    for r in rows(timings):
        echo("| " + " | ".join(r) + " |")
    out_dir.mkdir(parents=True, exist_ok=True)
    page = out_dir / "startup.md"
    write_page(page, markdown(timings, repeat, env))
    with (out_dir / "startup.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "command",
                "median_s",
                "best_s",
                "target_s",
                "cpu_median_s",
                *(f"run{i}" for i in range(repeat)),
            ]
        )
        for t in timings:
            w.writerow(
                [
                    t.case.name,
                    t.median_s,
                    t.best_s,
                    t.case.target_s or "",
                    t.cpu_median_s,
                    *t.times_s,
                ]
            )
    echo(f"wrote {out_dir / 'startup.md'} and {out_dir / 'startup.csv'}")
    return timings
