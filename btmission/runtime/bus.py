"""The in-memory message bus between the coordinator and the agents (DESIGN.md §3).

The coordinator and the agents exchange only these messages, so that a network transport (Zenoh)
can later carry exactly the same ones:

===================  =====================  =============================================
message              direction              content
===================  =====================  =============================================
``Announcement``     coordinator → agents   the open tasks (:mod:`btmission.allocation`)
``Bid``              agent → coordinator    one cost per announced task (eq. 8-10)
``Assignment``       coordinator → agents   who executes what after the round
``AgentStatus``      agent → coordinator    pose, mode, battery, current task and action
``Progress``         agent → coordinator    commit point passed, task done, task failed
===================  =====================  =============================================

plus, between agents, the predicted trajectories the seed 003 distributed NMPC shares
(:meth:`InMemoryBus.share_prediction`).

Delivery is synchronous and lossless while an agent's link is up: an announcement reaches every
connected agent at once and their bids are back in the coordinator's inbox before the round
allocates. :meth:`InMemoryBus.set_link` cuts an agent off (messages both ways are dropped), which
is how tests and the operator simulate a lost link: the agent keeps executing its current task
(seed 000 §I, §V-C) while the coordinator, hearing nothing, drops it after
``coordination.agent_timeout_s``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Inbox, Progress
from btmission.types import FloatArray


@dataclass(frozen=True)
class Assignment:
    """The result of an auction round: every live agent → its task (None: no task)."""

    time_s: float
    round: int
    tasks: Mapping[str, str | None]
    announcement: Announcement


@dataclass(frozen=True)
class AgentStatus:
    """An agent's periodic report (also what an operator display shows)."""

    agent: str
    time_s: float
    position: tuple[float, float, float]
    mode: str
    armed: bool
    battery: float
    task: str | None
    action: str


@dataclass
class _Endpoint:
    on_announcement: Callable[[Announcement], None]
    on_assignment: Callable[[Assignment], None]
    up: bool = True


@dataclass
class _Prediction:
    time_s: float
    positions: FloatArray


@dataclass
class CoordinatorInbox(Inbox):
    statuses: list[AgentStatus] = field(default_factory=list)


class InMemoryBus:
    """Synchronous in-process transport (module docstring)."""

    def __init__(self) -> None:
        self._agents: dict[str, _Endpoint] = {}
        self._inbox = CoordinatorInbox()
        self._predictions: dict[str, _Prediction] = {}
        self.dropped = 0
        """Messages lost on cut links."""

    # ---------------------------------------------------------------- connections
    def connect(
        self,
        agent: str,
        on_announcement: Callable[[Announcement], None],
        on_assignment: Callable[[Assignment], None],
    ) -> None:
        self._agents[agent] = _Endpoint(on_announcement, on_assignment)

    def disconnect(self, agent: str) -> None:
        self._agents.pop(agent, None)
        self._predictions.pop(agent, None)

    def set_link(self, agent: str, up: bool) -> None:
        """Cut (``up=False``) or restore an agent's link to the coordinator."""
        if agent in self._agents:
            self._agents[agent].up = up

    def link_up(self, agent: str) -> bool:
        ep = self._agents.get(agent)
        return ep is not None and ep.up

    # ---------------------------------------------------------------- coordinator → agents
    def announce(self, announcement: Announcement) -> None:
        for ep in list(self._agents.values()):
            if ep.up:
                ep.on_announcement(announcement)
            else:
                self.dropped += 1

    def assign(self, assignment: Assignment) -> None:
        for ep in list(self._agents.values()):
            if ep.up:
                ep.on_assignment(assignment)
            else:
                self.dropped += 1

    # ---------------------------------------------------------------- agents → coordinator
    def send_bid(self, bid: Bid) -> None:
        if self.link_up(bid.agent):
            self._inbox.bids.append(bid)
        else:
            self.dropped += 1

    def send_progress(self, progress: Progress) -> None:
        if self.link_up(progress.agent):
            self._inbox.progress.append(progress)
        else:
            self.dropped += 1

    def send_status(self, status: AgentStatus) -> None:
        if self.link_up(status.agent):
            self._inbox.statuses.append(status)
        else:
            self.dropped += 1

    def drain(self) -> CoordinatorInbox:
        """Everything that arrived for the coordinator since the last call."""
        inbox, self._inbox = self._inbox, CoordinatorInbox()
        return inbox

    # ---------------------------------------------------------------- agent ↔ agent
    def share_prediction(self, agent: str, time_s: float, positions: FloatArray) -> None:
        """Publish an agent's predicted (N+1, 2) positions (seed 003 §VI)."""
        self._predictions[agent] = _Prediction(time_s, np.asarray(positions, dtype=float))

    def predictions(
        self,
        agent: str,
        time_s: float,
        step_s: float,
        near: FloatArray | None = None,
        within_m: float = math.inf,
    ) -> list[FloatArray]:
        """The other agents' predictions — (N+1, 2) or (N+1, 3) positions, a vehicle that only
        shares where it is gives one row — advanced to ``time_s`` (shifted by the steps of
        ``step_s`` since they were published, the last point repeated), nearest to ``near``
        first, those farther than ``within_m`` left out."""
        out: list[tuple[float, FloatArray]] = []
        for other, pred in self._predictions.items():
            if other == agent:
                continue
            pts = pred.positions
            d = 0.0
            if near is not None:
                d = math.dist(pts[0, :2], near[:2])
                if d > within_m:
                    continue
            k = max(0, round((time_s - pred.time_s) / step_s))
            if k and len(pts) > 1:
                k = min(k, len(pts) - 1)
                pts = np.vstack([pts[k:], np.repeat(pts[-1:], k, axis=0)])
            out.append((d, pts))
        out.sort(key=lambda x: x[0])
        return [p for _, p in out]
