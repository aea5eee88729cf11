"""Pacing a run's steps against the wall clock.

A simulated run goes as fast as the machine allows, unless asked to go ``realtime`` (the
simulator paced to the wall clock, ``speed`` times faster than real time). A run against real
vehicles always goes at their clock: one step per ``step_s`` of the provider's time. A step that
comes late (a slow step) is not caught up with a burst of steps: the schedule moves on.

Falling behind is judged in the vehicles' time, not in steps: each :data:`BEHIND_WINDOW_S` of
it is a window, and a window in which the run made fewer than :data:`BEHIND_FRACTION` of the
steps due (``window / step_s``) means the control loop cannot keep up. The first such window
gives one ``warning`` event (the command line prints it on stderr), with the advice; a run that
makes one step per vehicle-second warns after its first window, as one that makes half the
steps it should. A simulated run never warns: its clock is its steps.
"""

from __future__ import annotations

import time

from btmission.runtime.eventkinds import WarningEvent
from btmission.runtime.events import EmitEvent
from btmission.vehicles.clock import Clock

BEHIND_WINDOW_S = 5.0
"""Vehicle time over which a run against a real provider's clock counts its steps (module
docstring): long enough that one slow step (an auction round's path searches, the first NMPC
solves) does not read as falling behind, short enough that a run making a step a second says so
within seconds."""
BEHIND_FRACTION = 0.5
"""A window in which the run made fewer than this share of its due steps falls behind."""


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
        """Steps that came more than a step late (the schedule moved on after each)."""
        self.behind_warned = False
        self._wall0 = time.perf_counter()
        self._steps0 = 0
        self._clock0 = 0.0
        self._window_t = 0.0
        self._window_steps = 0

    def start(self, steps: int) -> None:
        """The loop starts (again) after ``steps`` steps, or the clock was set (an agent
        process follows its coordinator's): the schedule, and the window that judges falling
        behind, count from now."""
        self._wall0 = time.perf_counter()
        self._steps0 = self._window_steps = steps
        self._clock0 = self._window_t = self.clock.now()

    def after_step(self, steps: int) -> None:
        """Step ``steps`` is done: wait until the next one is due."""
        if self.vehicles_realtime:  # real vehicles: one step per ``dt`` of their time
            now = self.clock.now()
            due = self._clock0 + (steps - self._steps0) * self.dt
            if now > due + self.dt:  # late (a slow step): no catch-up burst
                self._clock0 += now - due
                self.late_steps += 1
            else:
                self.clock.sleep_until(due)
            if now - self._window_t >= BEHIND_WINDOW_S:
                self._judge_window(steps, now)
        elif self.realtime:  # the simulator, paced: one step per dt / speed of wall time
            ahead = (
                self._wall0 + (steps - self._steps0) * self.dt / self.speed - time.perf_counter()
            )
            if ahead > 0:
                time.sleep(ahead)  # (at most about one step: a stop waits that long)

    def _judge_window(self, steps: int, now: float) -> None:
        """A window of vehicle time is over: warn (once) if it made too few of its due steps."""
        span = now - self._window_t
        made, due = steps - self._window_steps, round(span / self.dt)
        self._window_t, self._window_steps = now, steps
        if self.behind_warned or made >= BEHIND_FRACTION * due:
            return
        self.behind_warned = True
        self.emit(
            WarningEvent(
                message=f"the run falls behind its vehicles' clock ({made} of {due} steps made "
                f"in {span:.1f} s of their time): the control loop cannot keep up; lower "
                "runtime.mavlink.time_scale, use the track controller or fly fewer vehicles "
                "from this computer",
            )
        )
