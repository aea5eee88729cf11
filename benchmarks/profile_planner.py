#!/usr/bin/env python3
"""Profile D*+ one-to-all on the benchmark mine: ``python benchmarks/profile_planner.py [--calls 20]``.

Builds the planner benchmark's mine (seed 7, 400 × 240 × 20 voxels at 0.5 m), warms the compiled
search up, then runs ``Planner.one_to_all`` from the launch area ``--calls`` times under cProfile,
twice: once dropping each field (nothing to copy before the next search) and once keeping the
previous field until the next one replaces it (the planner copies the kept field out first).
Prints, per case, the wall time per call and the functions that took the time (ms per call).
py-spy sees the same split (``py-spy record -r 1000 -f raw -- python
benchmarks/profile_planner.py``); neither looks inside the numba kernel, which is one frame.
``benchmarks/results/profiles/planner_one_to_all.md`` has the summaries before and after #19.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time
from collections.abc import Sequence

import numpy as np


def _rows(prof: cProfile.Profile, calls: int, top: int) -> list[str]:
    stats = pstats.Stats(prof)
    rows = []
    for (path, line, name), (_cc, _nc, tt, ct, _callers) in stats.stats.items():  # type: ignore[attr-defined]
        if "btmission" not in path and "numpy" not in path and path != "~":
            continue
        rows.append((tt, ct, f"{path.rsplit('/', 1)[-1]}:{line}({name})"))
    rows.sort(reverse=True)
    out = ["| function | own ms/call | with callees ms/call |", "|---|---:|---:|"]
    out += [
        f"| `{n}` | {tt / calls * 1e3:.2f} | {ct / calls * 1e3:.2f} |" for tt, ct, n in rows[:top]
    ]
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=20, help="one_to_all calls per case")
    ap.add_argument("--top", type=int, default=8, help="functions listed per case")
    a = ap.parse_args(argv)
    from btmission.bench.planner import SEED, SIZE
    from btmission.planning.dstar import Planner
    from btmission.planning.risk import CostMap
    from btmission.world.minegen import generate_mine

    mine = generate_mine(SEED, SIZE, 0.5)
    planner = Planner(CostMap(mine.map))
    start = np.array([mine.launch[0], mine.launch[1], 2.0])
    planner.one_to_all(start)  # compile or load the cache
    for kept in (False, True):
        prof = cProfile.Profile()
        field = None
        t0 = time.perf_counter()
        prof.enable()
        for _ in range(a.calls):
            if kept:
                field = planner.one_to_all(start)
            else:
                planner.one_to_all(start)
        prof.disable()
        wall = (time.perf_counter() - t0) / a.calls * 1e3
        print(f"### one_to_all, the caller {'keeps' if kept else 'drops'} the previous field")
        print()
        print(f"{a.calls} calls, {wall:.1f} ms per call (wall, under the profiler)")
        print()
        print("\n".join(_rows(prof, a.calls, a.top)))
        print()
        del field
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
