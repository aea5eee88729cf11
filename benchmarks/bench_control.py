#!/usr/bin/env python3
"""Control benchmark: ``python benchmarks/bench_control.py [--only nmpc,apf,dphr] [--steps 200]``.

The same command as ``btmission bench control`` (see :mod:`btmission.bench.control` for the
scenarios and what is timed; ``--help`` for the options); results go to
``benchmarks/results/control.md`` and ``control.csv`` next to this file unless ``--out`` says
otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence

from btmission.cli.bench_cmds import script_main


def main(argv: Sequence[str] | None = None) -> int:
    return script_main("control", __file__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
