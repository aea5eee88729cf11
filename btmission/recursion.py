"""A bounded, scoped raise of the interpreter's recursion limit for very deep trees.

btmission's own tree code is iterative. Third-party code that recurses once per tree level
(py_trees' ``tick``/``stop``/``iterate``, :mod:`json`'s C decoder) is run inside
:func:`recursion_limit`, which raises the limit only for the duration of the call and never past
:data:`MAX_RECURSION_LIMIT`, so a deep (1,000-action chain) tree works while a runaway recursion
still stops with :class:`RecursionError` long before the C stack is at risk.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

MAX_RECURSION_LIMIT = 60_000
"""The highest limit :func:`recursion_limit` sets. Python-to-Python calls use no C stack on
3.11+, but generator resumption (py_trees' nested ``tick`` generators) does, a few hundred bytes
a level: 60,000 levels stay well inside the 8 MiB main-thread stack."""


@contextmanager
def recursion_limit(limit: int, *, cap: int | None = MAX_RECURSION_LIMIT) -> Iterator[None]:
    """Temporarily raise (never lower) the recursion limit to ``limit``, at most ``cap``.

    ``cap=None`` is for pure-Python recursion only (no C stack used per level).
    """
    previous = sys.getrecursionlimit()
    wanted = limit if cap is None else min(limit, cap)
    if wanted > previous:
        sys.setrecursionlimit(wanted)
    try:
        yield
    finally:
        sys.setrecursionlimit(previous)


def recursion_for_depth(depth: int, *, frames_per_level: int = 3) -> int:
    """A recursion limit enough for code recursing ``frames_per_level`` frames per tree level."""
    return sys.getrecursionlimit() + frames_per_level * depth
