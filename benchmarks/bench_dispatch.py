#!/usr/bin/env python3
"""GA dispatch benchmark: ``python benchmarks/bench_dispatch.py [--vehicles 2,4,6,8,10] [--runs 5]``.

The same runner as ``btmission bench dispatch`` (see :mod:`btmission.bench.dispatch`); results go
to ``benchmarks/results/dispatch.md`` and ``dispatch.csv`` next to this file unless ``--out`` says
otherwise.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from btmission.bench.dispatch import run_dispatch_benchmark

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Static GA batch vs push and swap (seed 004).")
    parser.add_argument(
        "--vehicles", default="2,4,6,8,10", help="even fleet sizes, comma-separated"
    )
    parser.add_argument(
        "--runs", type=int, default=5, help="instances per size and map (default 5)"
    )
    parser.add_argument("--tau", type=float, default=0.3, help="GA budget per vehicle in s")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--out", type=Path, default=RESULTS, help=f"results directory ({RESULTS})")
    args = parser.parse_args(argv)
    try:
        sizes = [int(s) for s in args.vehicles.split(",") if s.strip()]
    except ValueError:
        parser.error(f"--vehicles: expected comma-separated integers, got '{args.vehicles}'")
    if args.runs < 1 or args.tau <= 0:
        parser.error("--runs must be >= 1 and --tau > 0")
    run_dispatch_benchmark(sizes, args.runs, args.tau, args.seed, args.out, echo=print)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
