"""When the MAVLink I/O thread sends a periodic message, and how well a stream keeps its rate.

Pure logic, no sockets and no sleeping, so that both are tested with made-up wake-up times.

**Deadlines** (:class:`Deadlines`): a stream (a vehicle's setpoints, a link's GCS heartbeat) is
due on an absolute grid — deadline *k* is ``anchor + k · period`` — not "a period after the last
send". Scheduling from the last send lets every late wake-up of the thread lower the rate (the
next send moves back by the lateness) and never makes up what was lost; on a loaded machine that
cost btmission 25-65 % of a 20 Hz stream (issue #36). The rule:

* woken at or after a deadline, the thread sends **at once**, and the next deadline is the next
  point of the grid: a tick late by less than a period is followed by the next one on time (so
  sooner than a period later), and the schedule never drifts;
* woken a whole period or more late (a stall), it sends **one** message now and resumes at the
  first grid point after now: the missed slots are counted (:attr:`Deadlines.skipped`), not
  sent in a burst. A setpoint is a state, not an increment: ten copies of the latest one sent
  together tell the autopilot nothing more than one, and would only load the link;
* the grid is re-anchored only when the stream (re)starts or the mission hands a new setpoint
  over at once (:meth:`Deadlines.restart`, at the time the mission asked, never at the
  thread's late wake-up).

So over any interval without a stall, sends = elapsed / period ± 1; with stalls,
sends + skipped does.

**Health** (:class:`StreamHealth`): the achieved rate over windows of ``window_s`` and the gaps
between sends, in the *vehicle's* time (a simulator running ``time_scale`` times faster judges a
gap on its own clock, as PX4 SITL's ``COM_OF_LOSS_T`` does). PX4 refuses OFFBOARD below 2 Hz and
leaves it after ``COM_OF_LOSS_T`` (1 s) without a setpoint; the warning comes well before: when
a window's rate drops below ``min_fraction`` (80 %) of the asked rate or one gap exceeds
``max_gap_s`` (0.2 s). A warning is returned at the first problem and then at most once per
``warn_every_s``, counting what happened meanwhile, so a machine that stays overloaded says so
regularly without flooding the log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

LOW_RATE_FRACTION = 0.8
"""A stream whose rate over a window falls below this fraction of the asked rate is reported."""
MAX_GAP_S = 0.2
"""A gap between two sends longer than this (vehicle time) is reported."""
RATE_WINDOW_S = 1.0
"""The window (vehicle time) over which the achieved rate is measured."""
WARN_EVERY_S = 10.0
"""At most one warning per stream per this much vehicle time (the others are counted)."""


class Deadlines:
    """A periodic stream's absolute schedule (module docstring). Times are the caller's
    (``time.monotonic()`` in the I/O thread); ``next`` is the deadline of the next send."""

    __slots__ = ("next", "period", "sent", "skipped")

    def __init__(self, period: float, first: float = -math.inf) -> None:
        if not (math.isfinite(period) and period > 0):
            raise ValueError(f"a stream's period must be a positive number, got {period!r}")
        self.period = period
        self.next = first
        """The next deadline; ``-inf``: due at the first look (then anchored there)."""
        self.sent = 0
        self.skipped = 0
        """Grid slots that passed unsent during stalls (a period or more late)."""

    def restart(self, at: float) -> None:
        """Re-anchor the grid: the next send is due at ``at`` (a new stream, or a new setpoint
        the mission hands over at once), the following ones a period apart from it."""
        self.next = at

    def due(self, now: float) -> bool:
        """Whether a send is due at ``now``; if so it counts as made and the schedule moves to
        the next grid point after ``now`` (missed slots skipped and counted)."""
        nxt = self.next
        if now < nxt:
            return False
        self.sent += 1
        if nxt == -math.inf:  # the first look anchors the grid
            self.next = now + self.period
            return True
        nxt += self.period
        if nxt <= now:  # a stall: resume on the grid, no burst
            missed = math.floor((now - nxt) / self.period) + 1
            nxt += missed * self.period
            if nxt <= now:  # rounding
                nxt += self.period
                missed += 1
            self.skipped += missed
        self.next = nxt
        return True


@dataclass(frozen=True)
class StreamStats:
    """What a setpoint stream achieved so far (vehicle time)."""

    sent: int
    skipped: int
    """Grid slots skipped after stalls of the I/O thread (:class:`Deadlines`)."""
    worst_gap_s: float
    """The longest time between two consecutive sends of a continuous stream."""
    last_rate_hz: float | None
    """The rate over the last complete window (None: no window completed yet)."""
    lowest_rate_hz: float | None
    """The lowest rate over any complete window."""
    low_windows: int
    """Windows whose rate was below :data:`LOW_RATE_FRACTION` of the asked rate."""
    long_gaps: int
    """Gaps longer than :data:`MAX_GAP_S`."""
    warnings: int


class StreamHealth:
    """Rate and gaps of one stream (module docstring). Call :meth:`sent` with the wall time
    of every send, :meth:`pause` when the stream stops on purpose (the mission stopped renewing
    its setpoint: that silence is not a gap)."""

    __slots__ = (
        "_last",
        "_next_warning",
        "_win_sends",
        "_win_start",
        "hz",
        "last_rate_hz",
        "long_gaps",
        "low_windows",
        "lowest_rate_hz",
        "max_gap_s",
        "min_fraction",
        "time_scale",
        "warn_every_s",
        "warnings",
        "window_s",
        "worst_gap_s",
        "worst_since_warning",
    )

    def __init__(
        self,
        hz: float,
        time_scale: float = 1.0,
        *,
        window_s: float = RATE_WINDOW_S,
        min_fraction: float = LOW_RATE_FRACTION,
        max_gap_s: float = MAX_GAP_S,
        warn_every_s: float = WARN_EVERY_S,
    ) -> None:
        self.hz = hz
        self.time_scale = time_scale
        self.window_s = window_s
        self.min_fraction = min_fraction
        self.max_gap_s = max_gap_s
        self.warn_every_s = warn_every_s
        self._last: float | None = None
        self._win_start = 0.0
        self._win_sends = 0
        self._next_warning = -math.inf
        self.worst_since_warning = 0.0
        self.worst_gap_s = 0.0
        self.last_rate_hz: float | None = None
        self.lowest_rate_hz: float | None = None
        self.low_windows = 0
        self.long_gaps = 0
        self.warnings = 0

    def pause(self) -> None:
        """The stream stopped on purpose: the next send starts it again (no gap, new window)."""
        self._last = None

    def sent(self, wall: float) -> str | None:
        """A send at ``wall`` (seconds, the I/O thread's clock). Returns a warning's text (what
        fell short, in vehicle time) when one is due, else None."""
        last = self._last
        self._last = wall
        if last is None:
            self._win_start, self._win_sends = wall, 0
            return None
        scale = self.time_scale
        gap = (wall - last) * scale
        problem = False
        if gap > self.worst_gap_s:
            self.worst_gap_s = gap
        if gap > self.worst_since_warning:
            self.worst_since_warning = gap
        if gap > self.max_gap_s:
            self.long_gaps += 1
            problem = True
        self._win_sends += 1
        span = (wall - self._win_start) * scale
        rate = None
        if span >= self.window_s:
            rate = self._win_sends / span
            self.last_rate_hz = rate
            if self.lowest_rate_hz is None or rate < self.lowest_rate_hz:
                self.lowest_rate_hz = rate
            self._win_start, self._win_sends = wall, 0
            if rate < self.min_fraction * self.hz:
                self.low_windows += 1
                problem = True
        if not problem:
            return None
        now = wall * scale
        if now < self._next_warning:
            return None
        self._next_warning = now + self.warn_every_s
        self.warnings += 1
        text = self._text(rate)
        self.worst_since_warning = 0.0
        return text

    def _text(self, rate: float | None) -> str:
        what = []
        if rate is not None and rate < self.min_fraction * self.hz:
            what.append(f"{rate:.1f} Hz of {self.hz:g} over the last {self.window_s:g} s")
        if self.worst_since_warning > self.max_gap_s:
            what.append(f"a gap of {self.worst_since_warning:.2f} s")
        more = ""
        if self.warnings > 1:
            more = f" ({self.long_gaps} long gaps and {self.low_windows} slow windows so far)"
        return (
            f"setpoints fell short: {' and '.join(what)}{more}. PX4 leaves OFFBOARD after "
            "COM_OF_LOSS_T without one and refuses it below 2 Hz; the machine or btmission's "
            "MAVLink thread is too busy"
        )

    def stats(self, deadlines: Deadlines | None = None) -> StreamStats:
        return StreamStats(
            sent=deadlines.sent if deadlines is not None else 0,
            skipped=deadlines.skipped if deadlines is not None else 0,
            worst_gap_s=self.worst_gap_s,
            last_rate_hz=self.last_rate_hz,
            lowest_rate_hz=self.lowest_rate_hz,
            low_windows=self.low_windows,
            long_gaps=self.long_gaps,
            warnings=self.warnings,
        )
