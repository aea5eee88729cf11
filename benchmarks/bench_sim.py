#!/usr/bin/env python3
"""Simulator benchmark: ``python benchmarks/bench_sim.py [options]``.

The same command as ``btmission bench sim`` (see :mod:`btmission.bench.sim` for what is
measured; ``--help`` for the options); results go to ``benchmarks/results/sim.md``, ``.csv``
next to this file unless ``--out`` says otherwise.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from btmission.cli.bench_cmds import sim_bench

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not any(a in ("-o", "--out") or a.startswith("--out=") for a in args):
        args += ["--out", str(RESULTS)]
    try:
        sim_bench.main(args, prog_name="bench_sim.py")  # exits with click's status
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
