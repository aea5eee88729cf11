#!/usr/bin/env python3
"""Fleet scaling benchmark: ``python benchmarks/bench_fleet.py [--sizes 3,10,30,100]``.

The same command as ``btmission bench fleet`` (see :mod:`btmission.bench.fleet` for what is
timed); results go to ``benchmarks/results/fleet.md``, ``fleet.csv`` and ``fleet.png`` next to
this file unless ``--out`` says otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence

from btmission.cli.bench_cmds import script_main


def main(argv: Sequence[str] | None = None) -> int:
    return script_main("fleet", __file__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
