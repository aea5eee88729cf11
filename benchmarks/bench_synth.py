#!/usr/bin/env python3
"""Synthesis benchmark: ``python benchmarks/bench_synth.py [--sizes 10,100,1000] [--repeat 5]``.

The same runner as ``btmission bench synth`` (see :mod:`btmission.bench.synth` for the shapes and
what is timed); results go to ``benchmarks/results/synth.md`` and ``synth.csv`` next to this file
unless ``--out`` says otherwise.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from btmission.bench.synth import DEFAULT_SHAPES, SHAPES, run_synth_benchmark

RESULTS = Path(__file__).resolve().parent / "results"


def _ints(text: str) -> list[int]:
    try:
        values = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got '{text}'"
        ) from None
    if not values or any(v < 1 for v in values):
        raise argparse.ArgumentTypeError(f"expected positive integers, got '{text}'")
    return values


def _shapes(text: str) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [s for s in names if s not in SHAPES]
    if not names or unknown:
        known = ", ".join(SHAPES)
        raise argparse.ArgumentTypeError(f"unknown shape(s) in '{text}' (known: {known})")
    return names


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Synthesis + checks on generated libraries (btmission bench synth)."
    )
    parser.add_argument(
        "--sizes",
        type=_ints,
        default=[10, 100, 1000, 5000],
        help="comma-separated library sizes (default: 10,100,1000,5000)",
    )
    parser.add_argument(
        "--repeat",
        type=int,
        default=5,
        help="timed repetitions per case; the median is reported (default: 5)",
    )
    parser.add_argument(
        "--shapes",
        type=_shapes,
        default=list(DEFAULT_SHAPES),
        help=f"comma-separated shapes among {', '.join(SHAPES)} "
        f"(default: {','.join(DEFAULT_SHAPES)})",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=RESULTS,
        help=f"directory for synth.md and synth.csv (default: {RESULTS})",
    )
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    run_synth_benchmark(
        args.sizes, repeat=args.repeat, out_dir=args.out, echo=print, shapes=args.shapes
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
