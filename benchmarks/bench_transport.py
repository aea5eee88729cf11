#!/usr/bin/env python3
"""Transport benchmark: ``python benchmarks/bench_transport.py [--quick] [options]``.

The same command as ``btmission bench transport`` (see :mod:`btmission.bench.transport` for what
is measured; ``--help`` for the options); results go to ``benchmarks/results/transport.md`` and
``.csv`` next to this file unless ``--out`` says otherwise. Needs the net extra (eclipse-zenoh).
"""

from __future__ import annotations

from collections.abc import Sequence

from btmission.cli.bench_cmds import script_main


def main(argv: Sequence[str] | None = None) -> int:
    return script_main("transport", __file__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
