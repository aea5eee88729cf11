# mypy: allow-untyped-defs
"""Compiled range check of a bid's costs (:meth:`btmission.allocation.auction.Bid.problem`):
every bid of every round is checked, and numpy's per-call cost of the half-dozen array
operations the check takes was most of it.

numba in nopython mode (typed by numba, not annotated, like the planner's kernels); imported
lazily, ``cache=True`` stores the machine code next to this file.
"""

from __future__ import annotations

import math

from numba import njit


@njit(cache=True)
def first_bad_cost(costs, max_cost):  # pragma: no cover - jit
    """Index of the first cost below 0 (−inf too) or finite above ``max_cost``; −1 if none
    (NaN: no bid, and inf: unreachable, are fine)."""
    for i in range(costs.shape[0]):
        c = costs[i]
        if c < 0 or (c > max_cost and math.isfinite(c)):
            return i
    return -1
