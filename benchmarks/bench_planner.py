#!/usr/bin/env python3
"""Planner benchmark: ``python benchmarks/bench_planner.py [--size 200 120 10] [--repeat 5]``.

The same runner as ``btmission bench planner`` (see :mod:`btmission.bench.planner` for what is
timed); results go to ``benchmarks/results/planner.md`` and ``planner.csv`` next to this file
unless ``--out`` says otherwise.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from btmission.bench.planner import SIZE, run_planner_benchmark

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="D*+ planner benchmark (btmission bench planner).")
    parser.add_argument("--size", type=float, nargs=3, default=list(SIZE), metavar=("X", "Y", "Z"))
    parser.add_argument("--resolution", type=float, default=0.5)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--queries", type=int, default=20)
    parser.add_argument("--no-peers", action="store_true", help="skip skimage and networkx")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.repeat < 1 or args.queries < 1 or min(args.size) <= 0 or args.resolution <= 0:
        parser.error("--repeat and --queries must be ≥ 1, --size and --resolution > 0")
    run_planner_benchmark(
        args.size,
        args.resolution,
        args.repeat,
        args.queries,
        out_dir=args.out,
        echo=print,
        peers=not args.no_peers,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
