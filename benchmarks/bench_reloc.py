#!/usr/bin/env python3
"""Relocalization benchmark: ``python benchmarks/bench_reloc.py [--poses 200] [--seeds 7,11]``.

The same command as ``btmission bench reloc`` (see :mod:`btmission.bench.reloc` for what is
timed; ``--help`` for the options); results go to ``benchmarks/results/reloc.md`` and
``reloc.csv`` next to this file unless ``--out`` says otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence

from btmission.cli.bench_cmds import script_main


def main(argv: Sequence[str] | None = None) -> int:
    return script_main("reloc", __file__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
