"""The clock the runtime reads: simulated time in the simulator, the wall clock on real robots.

Agents, leaves and the coordinator never call ``time.time()``: they read
:meth:`Clock.now` (seconds since the mission started). The auction loop's clocks are reused —
:class:`~btmission.allocation.loop.WallClock` (real time) and
:class:`~btmission.allocation.loop.ManualClock` (set by hand) — and :class:`SimClock` reads the
embedded simulator's fixed-step time, so the same agent and coordinator code drives simulated and
(later) real vehicles.
"""

from __future__ import annotations

import time
from typing import Protocol

from btmission.allocation.loop import Clock, ManualClock, WallClock

__all__ = ["Clock", "ManualClock", "ScaledWallClock", "SimClock", "TimeSource", "WallClock"]


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


class ScaledWallClock:
    """The wall clock (monotonic, zero when made or at ``now_s``), running ``scale`` times
    faster: real vehicles' time (a simulator's speed-up), and a distributed run's processes'
    (a restarted coordinator continues its mission's time; an agent process follows its
    coordinator's: :meth:`set_now`)."""

    def __init__(self, scale: float = 1.0, *, now_s: float = 0.0) -> None:
        self.scale = scale
        self._t0 = time.monotonic() - now_s / scale

    def now(self) -> float:
        return (time.monotonic() - self._t0) * self.scale

    def sleep_until(self, t: float) -> None:
        delay = (t - self.now()) / self.scale
        if delay > 0:
            time.sleep(delay)

    def restart(self) -> None:
        """Zero now (times read before are then negative)."""
        self._t0 = time.monotonic()

    def set_now(self, t: float) -> None:
        """It is mission time ``t`` now."""
        self._t0 = time.monotonic() - t / self.scale
