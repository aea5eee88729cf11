"""Pacing a run's steps against the wall clock.

A simulated run goes as fast as the machine allows, unless asked to go ``realtime`` (the
simulator paced to the wall clock, ``speed`` times faster than real time). A run against real
vehicles always goes at their clock: one step per ``step_s`` of the provider's time. A step that
comes late (a slow step) is not caught up with a burst of steps: the schedule moves on, and once
more than 5 % of at least :data:`LATE_STEPS_WARNING` steps were late, a ``warning`` event says
the control loop cannot keep up.
"""

from __future__ import annotations

import time

from btmission.runtime.eventkinds import WarningEvent
from btmission.runtime.events import EmitEvent
from btmission.vehicles.clock import Clock

LATE_STEPS_WARNING = 400
"""Steps a run against a real provider's clock makes before it may warn that it falls behind
(more than 5 % of its steps late by more than a step: the start's first NMPC solves are slow)."""


class Pacer:
    """Waits between a run's steps as its clock asks (module docstring)."""

    def __init__(
        self,
        clock: Clock,
        dt: float,
        *,
        vehicles_realtime: bool,
        realtime: bool,
        speed: float,
        emit: EmitEvent,
    ) -> None:
        """``vehicles_realtime``: the provider's time passes on its own (real vehicles);
        ``realtime``: pace a simulator to the wall clock, ``speed`` times faster."""
        self.clock = clock
        self.dt = dt
        self.vehicles_realtime = vehicles_realtime
        self.realtime = realtime
        self.speed = speed
        self.emit = emit
        self.late_steps = 0
        self.late_warned = False
        self._wall0 = time.perf_counter()
        self._steps0 = 0
        self._clock0 = 0.0

    def start(self, steps: int) -> None:
        """The loop starts (again) after ``steps`` steps: the schedule counts from now."""
        self._wall0 = time.perf_counter()
        self._steps0 = steps
        self._clock0 = self.clock.now()

    def after_step(self, steps: int) -> None:
        """Step ``steps`` is done: wait until the next one is due."""
        if self.vehicles_realtime:  # real vehicles: one step per ``dt`` of their time
            due = self._clock0 + (steps - self._steps0) * self.dt
            if self.clock.now() > due + self.dt:  # late (a slow step): no catch-up burst
                self._clock0 += self.clock.now() - due
                self.late_steps += 1
                late, made = self.late_steps, steps - self._steps0
                if not self.late_warned and made >= LATE_STEPS_WARNING and late > 0.05 * made:
                    self.late_warned = True
                    self.emit(
                        WarningEvent(
                            message=f"the run falls behind its vehicles' clock ({late} of "
                            f"{made} steps late by more than {self.dt:g} s): the control loop "
                            "cannot keep up; lower runtime.mavlink.time_scale or use the track "
                            "controller",
                        )
                    )
            else:
                self.clock.sleep_until(due)
        elif self.realtime:  # the simulator, paced: one step per dt / speed of wall time
            ahead = (
                self._wall0 + (steps - self._steps0) * self.dt / self.speed - time.perf_counter()
            )
            if ahead > 0:
                time.sleep(ahead)  # (at most about one step: a stop waits that long)
