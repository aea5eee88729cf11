"""Telling a vehicle that stood still from a lost link, by the vehicle's own clock.

A SITL (ArduCopter's, PX4's) runs in lockstep with its simulation: stopped (``kill -STOP``, a
debugger, a starved machine), its clock stops too, it takes no failsafe and flies on where it
was once it runs again. The link looks lost meanwhile, and the mission's clock — wall time ×
``time_scale`` — runs on: on ArduCopter SITL an 8 s stop put 33 s on a task's time with no word
of it. When a vehicle is heard again after a loss, its clock (``time_boot_ms``) says what
happened: it advanced as much as the mission's (the link was lost, the vehicle flew on), much
less (it stood still: the run's times include that), or went back (it restarted).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

PAUSE_MIN_S = 2.0
"""A vehicle whose clock fell behind the mission's by less than this (its time), or by less
than half the outage, is taken as having run on (latency, a late first message)."""


@dataclass
class _Outage:
    before: tuple[float, float] | None
    """The vehicle's clock (s) and the wall time it was read, last before the loss."""
    back_wall: float | None = None
    """When its link came back (wall)."""


class VehicleClockWatch:
    """Per vehicle: after a link loss, the first reading of the vehicle's clock once it is heard
    again is compared with the wall time between the two readings × ``time_scale``."""

    def __init__(self, time_scale: float) -> None:
        self.time_scale = time_scale
        self._outages: dict[str, _Outage] = {}

    def check(
        self, agent: str, link_ok: bool, boot: tuple[float, float] | None, wall: float | None = None
    ) -> str | None:
        """Follow ``agent``'s link (``link_ok``) and clock (``boot``: its clock in s and the wall
        time it was read); returns what to warn of once, when its clock is read after a loss."""
        outage = self._outages.get(agent)
        if not link_ok:
            if outage is None:
                self._outages[agent] = _Outage(boot)
            else:
                outage.back_wall = None  # lost again before its clock was read
            return None
        if outage is None:
            return None
        if outage.back_wall is None:
            outage.back_wall = time.monotonic() if wall is None else wall
        if outage.before is None or boot is None:
            if outage.before is None:
                del self._outages[agent]  # nothing to compare with
            return None
        if boot[1] < outage.back_wall:
            return None  # not read since it came back
        del self._outages[agent]
        (v0, w0), (v1, w1) = outage.before, boot
        if v1 < v0:
            return (
                f"its autopilot's clock went back from {v0:.1f} s to {v1:.1f} s while the link "
                "was down: it restarted (its mode, arming and home may have changed)"
            )
        expected = (w1 - w0) * self.time_scale
        stood = expected - (v1 - v0)
        if stood < max(PAUSE_MIN_S, 0.5 * expected):
            return None
        return (
            f"its autopilot's clock stood still for {stood:.1f} s of the {expected:.1f} s its "
            "link was down (a stopped or paused vehicle: a frozen SITL, a debugger); the "
            f"mission's clock ran on, so this run's times include {stood:.1f} s of it standing "
            "still"
        )
