#!/usr/bin/env python3
"""Relocalization benchmark: ``python benchmarks/bench_reloc.py [--poses 200] [--seeds 7,11]``.

The same runner as ``btmission bench reloc`` (see :mod:`btmission.bench.reloc` for what is
timed); results go to ``benchmarks/results/reloc.md`` and ``reloc.csv`` next to this file unless
``--out`` says otherwise.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from btmission.bench.reloc import SEEDS, SIZE, run_reloc_benchmark

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Relocalization benchmark (btmission bench reloc)."
    )
    parser.add_argument("--seeds", default=",".join(map(str, SEEDS)))
    parser.add_argument("--size", type=float, nargs=3, default=list(SIZE), metavar=("X", "Y", "Z"))
    parser.add_argument("--resolution", type=float, default=0.5)
    parser.add_argument("--poses", type=int, default=200)
    parser.add_argument("--robustness", type=int, default=50)
    parser.add_argument("--no-peers", action="store_true", help="only ours")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        parser.error("--seeds takes comma-separated integers")
    if not seeds or args.poses < 1 or args.robustness < 0 or min(args.size) <= 0:
        parser.error("need a seed, --poses ≥ 1, --robustness ≥ 0 and a positive --size")
    run_reloc_benchmark(
        seeds,
        args.poses,
        args.size,
        args.resolution,
        args.robustness,
        out_dir=args.out,
        echo=print,
        peers=not args.no_peers,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
