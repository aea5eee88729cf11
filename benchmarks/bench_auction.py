#!/usr/bin/env python3
"""Auction benchmark: ``python benchmarks/bench_auction.py [--quick] [options]``.

The same command as ``btmission bench auction`` (see :mod:`btmission.bench.auction` for what is
measured; ``--help`` for the options); results go to ``benchmarks/results/auction.md``, ``.csv``
and ``.png`` next to this file unless ``--out`` says otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence

from btmission.cli.bench_cmds import script_main


def main(argv: Sequence[str] | None = None) -> int:
    return script_main("auction", __file__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
