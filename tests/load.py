"""The machine's load, for tests paced by the wall clock (issue #35).

A busy machine (a CI runner, two test workers beside a browser, a field laptop) stretches every
wall-clock wait. Tests that wait for something over the network or for a vehicle scale their
bounds by :func:`margin` — the 1-minute load per CPU, at least 1 and at most :data:`MAX_MARGIN` —
so that a waited-for event still comes in time under load; a wait ends as soon as its condition
holds, so a larger bound only costs time when something is broken. When a test fails on a loaded
machine, ``tests/conftest.py`` adds a ``machine load`` section to its report (:func:`note`), so a
failure that looks like load says so.
"""

from __future__ import annotations

import os

MAX_MARGIN = 8.0
"""The most a bound is stretched (a load of 8 per CPU: the machine is mostly elsewhere)."""

BUSY_PER_CPU = 1.5
"""A 1-minute load per CPU above this is reported with a failure."""


def load_per_cpu() -> float:
    """The 1-minute load average per CPU (0 where the system does not tell)."""
    try:
        return os.getloadavg()[0] / (os.cpu_count() or 1)
    except OSError:
        return 0.0


def margin() -> float:
    """How much to stretch a wall-clock bound now (module docstring)."""
    return min(MAX_MARGIN, max(1.0, load_per_cpu()))


def note(at_start: float | None = None) -> str | None:
    """The ``machine load`` section of a failed test's report, or None on a quiet machine.
    ``at_start``: the load per CPU when the test started."""
    now = load_per_cpu()
    worst = max(now, at_start or 0.0)
    if worst <= BUSY_PER_CPU:
        return None
    cpus = os.cpu_count() or 1
    start = f" ({at_start * cpus:.1f} when it started)" if at_start is not None else ""
    return (
        f"the machine was busy: 1-minute load average {now * cpus:.1f} on {cpus} CPUs{start}. "
        "A timeout or a late message here may be the load, not the code: run the test alone "
        "(pytest -p no:xdist -k NAME) to tell."
    )
