"""The coordinator behind an asynchronous link: bid window, late and stale bids, progress
acknowledgement and deduplication (issue #13 §4-5)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Progress
from btmission.links.bus import (
    AgentLink,
    AgentStatus,
    Assignment,
    CoordinatorInbox,
    CoordinatorLink,
    InMemoryBus,
    ProgressAck,
)
from btmission.runtime.coordinator import Coordinator
from btmission.runtime.events import Recorder, TypedEvent
from btmission.runtime.runner import MissionRun
from btmission.spec.mission import Mission
from tests.system.test_runtime import ROBOTS, mission_text

MISSION = ROBOTS.replace(
    "  - {id: A, type: inspect, location: [12, 2, 0]}",
    "  - {id: A, type: inspect, location: [12, 2, 0]}\n  - {id: B, type: inspect, location: [12, 6, 0]}",
).replace(
    "coordination: {auction_rate_hz: 10, agent_timeout_s: 1.0}",
    "coordination: {auction_rate_hz: 2, agent_timeout_s: 1.0, bid_window_s: WINDOW}",
)


def mission(tmp_path: Path, window: float) -> Mission:
    return mission_text(MISSION.replace("WINDOW", str(window)), tmp_path)


class FakeLink:
    """A coordinator link whose messages arrive when the test says (an asynchronous transport)."""

    def __init__(self) -> None:
        self.inbox = CoordinatorInbox()
        self.announced: list[Announcement] = []
        self.assigned: list[Assignment] = []
        self.acks: list[ProgressAck] = []
        self.on_announce: Any = None

    def announce(self, announcement: Announcement) -> None:
        self.announced.append(announcement)
        if self.on_announce is not None:
            self.on_announce(announcement)

    def assign(self, assignment: Assignment) -> None:
        self.assigned.append(assignment)

    def acknowledge(self, ack: ProgressAck) -> None:
        self.acks.append(ack)

    def drain(self) -> CoordinatorInbox:
        inbox, self.inbox = self.inbox, CoordinatorInbox()
        return inbox


class Events:
    def __init__(self) -> None:
        self.events: list[tuple[float | None, str, dict[str, Any]]] = []

    def __call__(self, event: TypedEvent) -> None:
        self.events.append((None if math.isnan(event.t) else event.t, event.kind, event.to_data()))

    def of(self, kind: str) -> list[dict[str, Any]]:
        return [d for _, k, d in self.events if k == kind]


def bid(agent: str, t: float, serial: int, a: float, b: float) -> Bid:
    return Bid.of(agent, t, {"A": a, "B": b}, serial=serial)


def coordinator(tmp_path: Path, window: float) -> tuple[Coordinator, FakeLink, Events, list[float]]:
    link = FakeLink()
    ev = Events()
    clock = [0.0]
    c = Coordinator(mission(tmp_path, window), link, lambda: clock[0], ev)
    return c, link, ev, clock


def test_the_in_memory_bus_is_both_links() -> None:
    bus = InMemoryBus()
    coordinator_side: CoordinatorLink = bus
    agent_side: AgentLink = bus.agent_link("G1")
    got: list[object] = []
    agent_side.connect(got.append, got.append, got.append)
    coordinator_side.announce(Announcement(1, 0.0, ()))
    agent_side.send_progress(Progress("G1", "A", "done", 1.0))
    coordinator_side.acknowledge(ProgressAck("G1", (("A", "done", 1.0),)))
    assert [type(m).__name__ for m in got] == ["Announcement", "ProgressAck"]
    assert coordinator_side.drain().progress == [Progress("G1", "A", "done", 1.0)]
    bus.set_link("G1", False)
    assert not agent_side.up
    agent_side.send_status(AgentStatus("G1", 1.0, (0, 0, 0), "HOLD", False, 1.0, None, ""))
    coordinator_side.acknowledge(ProgressAck("G1", ()))
    assert coordinator_side.drain().statuses == [] and bus.dropped == 2 and len(got) == 2


def test_window_zero_allocates_in_the_announcing_step(tmp_path: Path) -> None:
    c, link, ev, _ = coordinator(tmp_path, 0)

    def answer(ann: Announcement) -> None:  # agents that answer at once (the in-memory bus)
        link.inbox.bids += [bid("G1", 0.0, ann.serial, 1, 5), bid("G2", 0.0, ann.serial, 5, 1)]

    link.on_announce = answer
    result = c.step(0.0)
    assert result is not None and result.assignments == {"G1": "A", "G2": "B"}
    assert (
        ev.of("round")[0].get("late_bids") is None and ev.of("round")[0].get("stale_bids") is None
    )


def test_a_round_collects_bids_for_its_window(tmp_path: Path) -> None:
    c, link, ev, _ = coordinator(tmp_path, 0.2)
    assert c.step(0.0) is None  # announced; collecting
    assert [a.serial for a in link.announced] == [1] and link.assigned == []
    link.inbox.bids.append(bid("G1", 0.05, 1, 1, 5))
    assert c.step(0.1) is None
    link.inbox.bids.append(bid("G2", 0.15, 1, 5, 1))
    link.inbox.bids.append(bid("G2", 0.15, 0, 1, 1))  # answers an older announcement
    result = c.step(0.2)  # the window closes: allocate with what arrived
    assert result is not None and result.assignments == {"G1": "A", "G2": "B"}
    assert result.report.stale_bids == 1 and result.report.late_bids == 0
    assert ev.of("round")[-1]["stale_bids"] == 1
    assert link.assigned[-1].tasks == {"G1": "A", "G2": "B"}
    # a bid arriving after the round closed is late: ignored, counted in the next round
    link.inbox.bids.append(bid("G2", 0.3, 1, 0.5, 0.5))
    assert c.step(0.3) is None and c.step(0.5) is None  # round 2 opens at 0.5
    result = c.step(0.7)
    assert result is not None and result.report.late_bids == 1
    assert ev.of("round")[-1]["late_bids"] == 1
    # the board of latest bids is still the heartbeat: no new bids, but nobody is dropped yet
    assert result.assignments == {"G1": "A", "G2": "B"} and result.report.dropped == ()


def test_an_agent_whose_bids_never_arrive_in_time_times_out(tmp_path: Path) -> None:
    c, link, _, _ = coordinator(tmp_path, 0.2)
    c.step(0.0)
    link.inbox.bids += [bid("G1", 0.1, 1, 1, 5), bid("G2", 0.1, 1, 5, 1)]
    c.step(0.2)
    t = 0.5
    result = None
    while t < 2.0 and (result is None or not result.report.dropped):
        c.step(t)  # opens
        link.inbox.bids.append(bid("G1", t + 0.1, 1, 1, 5))  # G1 answers in time, G2 never
        result = c.step(t + 0.2)
        t += 0.5
    assert result is not None
    dropped = result.report.dropped
    # dropped at the first round closing more than agent_timeout_s (1 s) after its last bid
    assert dropped == ("G2",) and result.report.time_s == pytest.approx(1.2)
    assert result.assignments == {"G1": "A"}


def test_progress_is_acknowledged_and_copies_are_ignored(tmp_path: Path) -> None:
    c, link, ev, _ = coordinator(tmp_path, 0)

    def answer(ann: Announcement) -> None:
        link.inbox.bids += [bid("G1", 0.0, ann.serial, 1, 5), bid("G2", 0.0, ann.serial, 5, 1)]

    link.on_announce = answer
    c.step(0.0)
    done = Progress("G1", "A", "done", 0.3)
    link.inbox.progress.append(done)
    c.step(0.5)
    assert c.state.pool["A"].state.value == "done"
    assert link.acks[-1] == ProgressAck("G1", (("A", "done", 0.3),))
    link.inbox.progress.append(done)  # the ack was lost: the agent sends it again
    c.step(1.0)
    assert link.acks[-1] == ProgressAck("G1", (("A", "done", 0.3),))
    assert ev.of("warning") == []  # a copy is not a problem
    assert [d["state"] for d in ev.of("task") if d["task"] == "A"] == ["assigned", "done"]


def test_a_run_with_a_bid_window_allocates_after_it(tmp_path: Path) -> None:
    """The in-memory bus answers at once; with a 0.15 s window each round still waits for it."""
    m = mission_text(
        ROBOTS.replace("agent_timeout_s: 1.0}", "agent_timeout_s: 1.0, bid_window_s: 0.15}"),
        tmp_path,
    )
    rec = Recorder()
    run = MissionRun(m, observers=[rec])
    result = run.run(until=35)
    assert result.done == ["A"]
    first = rec.of("task")[0]
    assert (first.get("state"), first.get("agent"), first.t) == ("assigned", "G1", 0.15)
    rounds = rec.of("round")
    assert [r.t for r in rounds[:3]] == pytest.approx([0.15, 0.35, 0.55])  # window + 1 step
    assert not [r for r in rounds if r.get("late_bids") or r.get("stale_bids")]


def test_a_bid_window_as_long_as_the_agent_timeout_is_refused(tmp_path: Path) -> None:
    """Every bid would be stale when the round allocates: validate says so, at the line."""
    from btmission.diagnostics import SpecError

    body = ROBOTS.replace(
        "coordination: {auction_rate_hz: 10, agent_timeout_s: 1.0}",
        "coordination: {auction_rate_hz: 10, agent_timeout_s: 1.0, bid_window_s: 1.0}",
    )
    assert body != ROBOTS
    with pytest.raises(SpecError) as err:
        mission_text(body, tmp_path)
    (diag,) = err.value.diagnostics
    assert diag.item == "coordination.bid_window_s" and diag.where.line == 13
    assert "must be shorter than agent_timeout_s (1 s)" in diag.message
