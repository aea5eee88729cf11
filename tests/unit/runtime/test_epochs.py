"""Round epochs: an agent ignores an assignment (or announcement) older than the last one it
acted on, whatever order the transport delivers them in; a restarted coordinator (another
epoch) is followed at once."""

from __future__ import annotations

from pathlib import Path

import pytest

from btmission.allocation.auction import Announcement
from btmission.allocation.tasks import TaskInfo
from btmission.links.bus import Assignment, InMemoryBus
from btmission.runtime.agent import Agent, Freshness
from btmission.runtime.coordinator import Coordinator, new_epoch
from btmission.runtime.events import Recorder
from btmission.runtime.runner import MissionRun
from btmission.transport.faulty import Faults, FaultyAgentLink, fate
from tests.system.test_runtime import ROBOTS, mission_text


def test_freshness_orders_counts_within_an_epoch_and_follows_a_new_one() -> None:
    f = Freshness()
    assert f.accept("assignment", 7, 3, strict=True)
    assert not f.accept("assignment", 7, 3, strict=True)  # the same round again
    assert not f.accept("assignment", 7, 2, strict=True)  # an older one, late
    assert f.accept("assignment", 7, 4, strict=True)
    assert f.accept("announcement", 7, 2, strict=False)  # streams are counted apart
    assert f.accept("announcement", 7, 2, strict=False)  # repeated every round: bid again
    assert not f.accept("announcement", 7, 1, strict=False)
    assert f.accept("assignment", 9, 1, strict=True)  # a restarted coordinator: from 1 again
    assert f.accept("announcement", 9, 1, strict=False)
    assert not f.accept("assignment", 7, 5, strict=True)  # the old one is retired
    assert f.accept("assignment", 0, 1, strict=True)  # epoch 0: unknown, always followed
    assert f.accept("assignment", 0, 1, strict=True)
    assert (f.epoch, f.retired, f.ignored) == (9, [7], 4)


def test_every_coordinator_gets_its_own_epoch(tmp_path: Path) -> None:
    m = mission_text(ROBOTS, tmp_path)
    epochs = {Coordinator(m, InMemoryBus(), lambda: 0.0, lambda *a, **k: None).epoch
              for _ in range(20)}  # fmt: skip
    assert len(epochs) == 20 and all(0 < e < 2**53 for e in epochs)
    assert 0 < new_epoch() < 2**53
    c = Coordinator(m, InMemoryBus(), lambda: 0.0, lambda *a, **k: None, epoch=5)
    c.step(0.0)
    assert c.state.announcement.epoch == 5 and c.state.announcement.serial == 1


def _late_first(stream: str) -> Faults:
    """Faults under which the first message of ``stream`` is held one tick and the second
    goes at once (found from the seed: :func:`fate` is a pure function)."""
    for seed in range(1000):
        f = Faults(delay=0.5, max_delay=1, reorder=True, seed=seed)
        if fate(f, stream, 0).delays == (1,) and fate(f, stream, 1).delays == (0,):
            return f
    raise AssertionError("no such seed")


def _reordered(tmp_path: Path, epoch: int) -> tuple[Agent, Recorder, FaultyAgentLink]:
    """G1 of a run, also connected to a second coordinator's bus through a faulty link that
    delivers round 1's assignment (A) after round 2's (B)."""
    rec = Recorder()
    run = MissionRun(mission_text(ROBOTS, tmp_path), observers=[rec])
    run.run(until=0.0)  # built; the run's own coordinator has assigned A to G1
    agent = run.agents["G1"]
    tasks = (
        TaskInfo("A", "inspect", {"location": [12, 2, 0]}),
        TaskInfo("B", "inspect", {"location": [3, 6, 0]}),
    )
    ann = Announcement(1, 0.0, tasks, epoch)
    bus = InMemoryBus()
    link = FaultyAgentLink(bus.agent_link("G1"), _late_first("to-G1"))
    link.connect(agent.on_announcement, agent.on_assignment, agent.on_ack)
    bus.assign(Assignment(0.1, 1, {"G1": "A", "G2": None}, ann))  # held for a tick
    bus.assign(Assignment(0.2, 2, {"G1": "B", "G2": None}, ann))  # delivered at once
    assert agent.task is not None and agent.task.id == "B"
    link.tick()  # round 1's assignment arrives now, late
    assert link.incoming.stats.delayed == 1 and link.incoming.held == 0
    return agent, rec, link


def test_an_old_assignment_delivered_late_does_not_change_the_task(tmp_path: Path) -> None:
    agent, rec, _ = _reordered(tmp_path, epoch=41)
    assert agent.task is not None and agent.task.id == "B"  # round 2 stands
    assert agent.freshness.ignored == 1
    switches = [e.get("task") for e in rec.of("agent_task") if e.get("agent") == "G1"]
    assert switches[-1] == "B" and "A" not in switches[switches.index("B") :]


def test_without_an_epoch_the_late_assignment_would_undo_the_newer_one(tmp_path: Path) -> None:
    """What the epochs prevent: epoch 0 (unknown, a version 1 sender) orders nothing."""
    agent, _, _ = _reordered(tmp_path, epoch=0)
    assert agent.task is not None and agent.task.id == "A" and agent.freshness.ignored == 0


def test_a_restarted_coordinator_is_followed_and_the_old_one_no_more(tmp_path: Path) -> None:
    agent, _, link = _reordered(tmp_path, epoch=41)
    bus = InMemoryBus()  # the coordinator restarted: another epoch, rounds from 1 again
    link.inner = bus.agent_link("G1")
    link.connect(agent.on_announcement, agent.on_assignment, agent.on_ack)
    c = TaskInfo("C", "inspect", {"location": [6, 4, 0]})
    bus.assign(Assignment(5.0, 1, {"G1": "C"}, Announcement(1, 5.0, (c,), epoch=42)))
    link.tick()  # the faults are seeded per message: let a held one out
    assert agent.task is not None and agent.task.id == "C"
    b = TaskInfo("B", "inspect", {"location": [3, 6, 0]})
    bus.assign(Assignment(5.1, 9, {"G1": "B"}, Announcement(1, 0.0, (b,), epoch=41)))
    link.tick()  # the old coordinator's, delivered late: its epoch is retired
    assert agent.task.id == "C" and agent.freshness.retired == [41]


@pytest.mark.parametrize("late", [True, False])
def test_an_old_announcement_delivered_late_gets_no_bid(tmp_path: Path, late: bool) -> None:
    run = MissionRun(mission_text(ROBOTS, tmp_path))
    run.run(until=0.0)
    agent = run.agents["G1"]
    run.bus.drain()
    task = TaskInfo("A", "inspect", {"location": [12, 2, 0]})
    newer, older = Announcement(3, 1.0, (task,), 7), Announcement(2, 0.5, (task,), 7)
    agent.on_announcement(newer)
    agent.on_announcement(older if late else newer)
    bids = run.bus.drain().bids
    assert [b.serial for b in bids] == ([3] if late else [3, 3])
    assert agent.last_announcement is newer
