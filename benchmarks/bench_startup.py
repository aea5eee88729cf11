#!/usr/bin/env python3
"""Start-up benchmark: ``python benchmarks/bench_startup.py [--repeat 10]``.

The same command as ``btmission bench startup`` (see :mod:`btmission.bench.startup` for what is
timed); results go to ``benchmarks/results/startup.md`` and ``startup.csv`` next to this file
unless ``--out`` says otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence

from btmission.cli.bench_cmds import script_main


def main(argv: Sequence[str] | None = None) -> int:
    return script_main("startup", __file__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
