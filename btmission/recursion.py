"""Running third-party code that recurses once per tree level on very deep trees.

btmission's own tree code is iterative. Code that recurses once per tree level (py_trees'
``tick``/``stop``/``iterate``, :mod:`json`'s C decoder) is run with the recursion limit raised
for the call only (:func:`recursion_limit`), never past :data:`MAX_RECURSION_LIMIT`, so a deep
(1,000-action chain) tree works while a runaway recursion still ends in :class:`RecursionError`.
Nested generators (py_trees' ticks) also use C stack on every level, so :func:`call_deep` runs
such a call in a thread whose stack is sized for the recursion limit it sets: an overflow of the
8 MiB main-thread stack would kill the process (SIGSEGV) instead of raising.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")

MAX_RECURSION_LIMIT = 60_000
"""The highest limit :func:`recursion_limit` sets by default."""

_STACK_PER_FRAME = 4096
"""C stack reserved per Python frame in :func:`call_deep` (a generator resume on 3.11 takes
well under 1 KiB; the rest is margin). Only touched pages are committed."""
_MAIN_THREAD_FRAMES = 2_000
"""Up to this recursion limit a call runs in the calling thread."""


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


def call_deep(fn: Callable[[], T], limit: int) -> T:
    """``fn()`` with the recursion limit raised to ``limit`` (capped at
    :data:`MAX_RECURSION_LIMIT`), in a thread with a C stack big enough for that many frames when
    the limit is high. Exceptions (including :class:`RecursionError`) propagate to the caller."""
    wanted = min(limit, MAX_RECURSION_LIMIT)
    if wanted <= _MAIN_THREAD_FRAMES:
        with recursion_limit(wanted):
            return fn()
    result: list[T] = []
    error: list[BaseException] = []

    def work() -> None:
        try:
            with recursion_limit(wanted):
                result.append(fn())
        except BaseException as exc:  # handed to the caller
            error.append(exc)

    stack = (16 << 20) + wanted * _STACK_PER_FRAME
    previous = threading.stack_size(stack)
    try:
        worker = threading.Thread(target=work, name="btmission-deep", daemon=True)
        worker.start()
    finally:
        threading.stack_size(previous)
    worker.join()
    if error:
        raise error[0]
    return result[0]


_MAIN_STACK_BYTES_PER_FRAME = 256
"""Main-thread C stack a recursion level may take (measured here: a 6,000-action chain's run,
about 49,000 frames, fit in the default 8 MiB; 15,000 actions crashed with SIGSEGV)."""


def main_thread_limit() -> int:
    """The deepest recursion the main thread's C stack can take safely (from ``ulimit -s``),
    at most :data:`MAX_RECURSION_LIMIT`."""
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_STACK)
    if soft == resource.RLIM_INFINITY:
        return MAX_RECURSION_LIMIT
    return min(
        MAX_RECURSION_LIMIT, max(sys.getrecursionlimit(), soft // _MAIN_STACK_BYTES_PER_FRAME)
    )
