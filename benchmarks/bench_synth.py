#!/usr/bin/env python3
"""Synthesis benchmark: ``python benchmarks/bench_synth.py [--sizes 10,100,1000] [--repeat 5]``.

The same command as ``btmission bench synth`` (see :mod:`btmission.bench.synth` for the shapes
and what is timed; ``--help`` for the options, e.g. ``--shapes chain,fanin,diamond``); results go
to ``benchmarks/results/synth.md`` and ``synth.csv`` next to this file unless ``--out`` says
otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence

from btmission.cli.bench_cmds import script_main


def main(argv: Sequence[str] | None = None) -> int:
    return script_main("synth", __file__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
