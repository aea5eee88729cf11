#!/usr/bin/env python3
"""Console benchmark: ``python benchmarks/bench_console.py [options]``.

The same command as ``btmission bench console`` (see :mod:`btmission.bench.console` for what is
measured; ``--help`` for the options); results go to ``benchmarks/results/console.md``, ``.csv``
next to this file unless ``--out`` says otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence

from btmission.cli.bench_cmds import script_main


def main(argv: Sequence[str] | None = None) -> int:
    return script_main("console", __file__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
