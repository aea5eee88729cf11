#!/usr/bin/env python3
"""Control benchmark: ``python benchmarks/bench_control.py [--only nmpc,apf,dphr] [--steps 200]``.

The same runner as ``btmission bench control`` (see :mod:`btmission.bench.control` for the
scenarios and what is timed); results go to ``benchmarks/results/control.md`` and ``control.csv``
next to this file unless ``--out`` says otherwise.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from btmission.bench.control import PARTS, run_control_benchmark

RESULTS = Path(__file__).resolve().parent / "results"


def _parts(text: str) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names or any(n not in PARTS for n in names):
        raise argparse.ArgumentTypeError(f"unknown part(s) in '{text}' (known: {', '.join(PARTS)})")
    return names


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got '{text}'") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got '{text}'")
    return value


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="NMPC (fatrop vs ipopt), APF and DPHR timings (btmission bench control)."
    )
    parser.add_argument("--only", type=_parts, default=list(PARTS), help="parts: nmpc,apf,dphr")
    parser.add_argument("--steps", type=_positive, default=200, help="closed-loop NMPC steps")
    parser.add_argument("--repeat", type=_positive, default=200, help="timed APF calls")
    parser.add_argument("--out", type=Path, default=RESULTS, help=f"output dir (default {RESULTS})")
    args = parser.parse_args(argv)
    run_control_benchmark(args.only, steps=args.steps, repeat=args.repeat, out_dir=args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
