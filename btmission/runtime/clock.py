"""The clock the runtime reads: simulated time in the simulator, the wall clock on real robots.

Agents, leaves and the coordinator never call ``time.time()``: they read
:meth:`Clock.now` (seconds since the mission started). The auction loop's clocks are reused —
:class:`~btmission.allocation.loop.WallClock` (real time) and
:class:`~btmission.allocation.loop.ManualClock` (set by hand) — and :class:`SimClock` reads the
embedded simulator's fixed-step time, so the same agent and coordinator code drives simulated and
(later) real vehicles.
"""

from __future__ import annotations

from typing import Protocol

from btmission.allocation.loop import Clock, ManualClock, WallClock

__all__ = ["Clock", "ManualClock", "SimClock", "TimeSource", "WallClock"]


class TimeSource(Protocol):
    time_s: float


class SimClock:
    """The simulator's time. ``sleep_until`` does nothing: the runner steps time itself."""

    def __init__(self, sim: TimeSource) -> None:
        self._sim = sim

    def now(self) -> float:
        return self._sim.time_s

    def sleep_until(self, t: float) -> None:
        pass
