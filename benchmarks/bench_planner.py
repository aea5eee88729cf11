#!/usr/bin/env python3
"""Planner benchmark: ``python benchmarks/bench_planner.py [--size 200 120 10] [--repeat 5]``.

The same command as ``btmission bench planner`` (see :mod:`btmission.bench.planner` for what is
timed; ``--help`` for the options); results go to ``benchmarks/results/planner.md`` and
``planner.csv`` next to this file unless ``--out`` says otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence

from btmission.cli.bench_cmds import script_main


def main(argv: Sequence[str] | None = None) -> int:
    return script_main("planner", __file__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
