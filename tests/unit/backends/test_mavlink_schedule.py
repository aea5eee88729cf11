"""The MAVLink streams' schedule and health, with made-up wake-up times (no sockets, no sleep):
sends stay on the absolute grid however late the thread wakes, a late tick goes at once, a stall
resynchronises without a burst, and a stream that falls short is reported (issue #36)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from btmission.backends.mavlink_schedule import Deadlines, StreamHealth

P = 0.05  # 20 Hz


def run(schedule: Deadlines, wakes: list[float]) -> list[float]:
    """The times at which the thread sends, waking at ``wakes`` (and at every deadline it is
    given in between: a thread that sleeps until ``next`` and wakes exactly then)."""
    sent = []
    for t in wakes:
        if schedule.due(t):
            sent.append(t)
    return sent


def test_a_late_tick_goes_at_once_and_the_next_stays_on_the_grid() -> None:
    s = Deadlines(P, first=0.0)
    assert s.due(0.0) and s.next == pytest.approx(P)
    assert not s.due(0.049)
    assert s.due(0.085)  # 35 ms late: sent at once...
    assert s.next == pytest.approx(2 * P)  # ...and the next one is still due at 100 ms
    assert not s.due(0.099) and s.due(0.1)
    assert s.next == pytest.approx(3 * P) and s.skipped == 0 and s.sent == 3


def test_late_wake_ups_lose_no_rate() -> None:
    """A thread that wakes up to 0.9 period late at every deadline still sends once per
    period on average: sends == elapsed / period ± 1, and none are skipped."""
    rng = np.random.default_rng(7)
    s = Deadlines(P, first=0.0)
    t, sent = 0.0, []
    while t < 10.0:
        t = max(t, s.next) + float(rng.uniform(0.0, 0.9 * P))  # woken late for the deadline
        if s.due(t):
            sent.append(t)
    assert abs(len(sent) - t / P) <= 1
    assert s.skipped == 0
    # every send is within a period of its grid point: the schedule has not drifted
    grid = np.arange(len(sent)) * P
    assert np.all(np.asarray(sent) - grid < P) and np.all(np.asarray(sent) >= grid)


def test_scheduling_from_the_last_send_would_have_lost_a_third() -> None:
    """The old rule (next = last send + period) on the same wake-ups: what the grid fixes."""
    rng = np.random.default_rng(7)
    t, nxt, sent = 0.0, 0.0, 0
    while t < 10.0:
        t = max(t, nxt) + float(rng.uniform(0.0, 0.9 * P))
        if t >= nxt:
            sent += 1
            nxt = t + P
    assert sent < 0.75 * t / P


def test_a_long_stall_sends_one_then_resumes_on_the_grid() -> None:
    s = Deadlines(P, first=0.0)
    assert run(s, [0.0, 0.05, 0.10]) == [0.0, 0.05, 0.10]
    # stalled from 0.10 to 0.43: one send at 0.43, no burst, next on the grid at 0.45
    assert run(s, [0.43, 0.43, 0.431, 0.44]) == [0.43]
    assert s.next == pytest.approx(0.45)
    assert s.skipped == 5  # the send at 0.43 is the 0.15 tick's, late; 0.20 ... 0.40 passed
    assert run(s, [0.45, 0.50, 0.55]) == [0.45, 0.50, 0.55]
    elapsed_slots = round(0.55 / P) + 1
    assert s.sent + s.skipped == elapsed_slots


def test_exactly_one_period_late_is_a_stall_of_one_slot() -> None:
    s = Deadlines(P, first=0.0)
    s.due(0.0)
    assert s.due(0.1)  # the 0.05 tick woke at 0.10: one send for it, the 0.10 slot passes
    assert s.next == pytest.approx(0.15) and s.skipped == 1


def test_restart_re_anchors_the_grid_where_the_mission_asked() -> None:
    s = Deadlines(P, first=0.0)
    s.due(0.0)
    s.restart(0.072)  # a new setpoint handed over at 72 ms, sent by a thread woken at 80 ms
    assert s.due(0.080)
    assert s.next == pytest.approx(0.122)  # anchored at 72 ms, not at the late wake-up


def test_the_first_look_anchors_an_unset_schedule() -> None:
    s = Deadlines(1.0)
    assert s.next == -math.inf
    assert s.due(12.5) and s.next == pytest.approx(13.5) and s.skipped == 0


def test_bad_periods_are_refused() -> None:
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="positive number"):
            Deadlines(bad)


# ------------------------------------------------------------------ health
def feed(h: StreamHealth, times: list[float] | np.ndarray) -> list[str]:
    return [w for t in times if (w := h.sent(float(t))) is not None]


def test_a_steady_stream_says_nothing() -> None:
    h = StreamHealth(20.0)
    assert feed(h, np.arange(0.0, 5.0, P)) == []
    assert h.last_rate_hz == pytest.approx(20.0, rel=0.03)
    assert h.worst_gap_s == pytest.approx(P) and h.long_gaps == 0 and h.low_windows == 0


def test_a_gap_over_200_ms_is_reported_once_then_throttled() -> None:
    h = StreamHealth(20.0)
    times = [*np.arange(0.0, 1.0, P), 1.3, *np.arange(1.35, 3.0, P), 3.4]
    said = feed(h, times)
    assert len(said) == 1  # the second long gap, 2 s later, is counted, not said again
    assert "a gap of 0.35 s" in said[0] and "OFFBOARD" in said[0]
    assert h.long_gaps == 2 and h.worst_gap_s == pytest.approx(0.45)
    said = feed(h, [*np.arange(3.45, 14.0, P), 14.5])  # 10 s later: said again, with counts
    assert len(said) == 1 and "3 long gaps" in said[0]


def test_a_slow_stream_is_reported_by_its_rate_over_a_window() -> None:
    h = StreamHealth(20.0)
    said = feed(h, np.arange(0.0, 2.0, 1 / 15))  # 15 Hz: 75 % of 20, gaps of 67 ms only
    assert said and "15.0 Hz of 20 over the last 1 s" in said[0]
    assert h.long_gaps == 0 and h.low_windows >= 1


def test_gaps_and_rates_are_in_the_vehicles_time() -> None:
    """At time_scale 10, 30 ms of wall time is 0.3 s on the vehicle's (PX4 SITL's) clock."""
    h = StreamHealth(20.0, time_scale=10.0)
    wall = [*np.arange(0.0, 0.5, P / 10), 0.525]
    said = feed(h, wall)
    assert said and "a gap of 0.30 s" in said[0]


def test_a_stream_stopped_on_purpose_is_no_gap() -> None:
    h = StreamHealth(20.0)
    feed(h, np.arange(0.0, 1.0, P))
    h.pause()  # the mission stopped renewing its setpoint
    assert feed(h, np.arange(5.0, 7.0, P)) == []
    assert h.long_gaps == 0 and h.worst_gap_s == pytest.approx(P)
