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
``ProgressAck``      coordinator → agent    the progress reports it has taken
===================  =====================  =============================================

plus, between agents, the predicted trajectories the seed 003 distributed NMPC shares
(:class:`Prediction`). :mod:`btmission.links.wire` turns each into versioned JSON.

The coordinator sees the transport only through :class:`CoordinatorLink`, an agent only through
its :class:`AgentLink` (one per agent), so a network transport can replace this bus without
touching either. :class:`InMemoryBus` implements both (:meth:`InMemoryBus.agent_link` gives an
agent's end).

Delivery is synchronous and lossless while an agent's link is up: an announcement reaches every
connected agent at once and their bids are back in the coordinator's inbox before the round
allocates (a bid window of 0). :meth:`InMemoryBus.set_link` cuts an agent off (messages both
ways are dropped), which is how tests and the operator simulate a lost link: the agent keeps
executing its current task (seed 000 §I, §V-C) while the coordinator, hearing nothing, drops it
from the auction after ``coordination.agent_timeout_s`` and re-offers its task when its lease
(``coordination.lease_s`` after its last bid) ends; the agent stops the task before that. The agent keeps its progress reports until the
coordinator acknowledges them (:class:`ProgressAck`), so a completion made while it was cut off
is delivered when the link returns.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Inbox, Progress
from btmission.types import FloatArray, recorder

SMALL_FLEET = 8
"""Up to this many sharing agents a neighbour query tests each one (the vectorised test over
every agent's start costs more)."""


@dataclass(frozen=True)
class Assignment:
    """The result of an auction round: every live agent → its task (None: no task)."""

    time_s: float
    round: int
    tasks: Mapping[str, str | None]
    announcement: Announcement
    sent_s: float | None = None
    """The coordinator's clock when it sent the assignment (``time_s`` is the round's
    announcement's): what an agent process sets its mission clock from."""


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
    vehicle_link: bool = True
    """The agent hears its vehicle (its autopilot's heartbeats); False while that link is lost."""
    at_rest: bool = False
    """No task, and its default behaviour is over (e.g. landed at home): what a coordinator in
    another process needs to tell that the mission is over."""


@dataclass(frozen=True)
class MissionEnd:
    """The coordinator ended the mission (coordinator → agents): agent processes stop."""

    time_s: float
    reason: str
    done: tuple[str, ...] = ()
    open: Mapping[str, str] = field(default_factory=dict)


ProgressKey = tuple[str, str, float]
"""What identifies one progress report of an agent: (task, event, time_s)."""


def progress_key(p: Progress) -> ProgressKey:
    return (p.task, p.event, p.time_s)


@dataclass(frozen=True)
class ProgressAck:
    """The coordinator has taken these progress reports of ``agent``: it stops resending them."""

    agent: str
    keys: tuple[ProgressKey, ...]


@dataclass(frozen=True, eq=False)
class Prediction:
    """An agent's predicted positions, (N+1, 2) or (N+1, 3), made at ``time_s`` (seed 003 §VI)."""

    agent: str
    time_s: float
    positions: FloatArray
    velocity: FloatArray | None = None
    """The agent's velocity (3,) when it shared, if it says (a drone sharing where it is): what
    the separation rule credits a neighbour moving away with
    (:func:`~btmission.control.apf.separation_bound`). None: unknown."""


@dataclass
class CoordinatorInbox(Inbox):
    statuses: list[AgentStatus] = field(default_factory=list)


OnAnnouncement = Callable[[Announcement], None]
OnAssignment = Callable[[Assignment], None]
OnAck = Callable[[ProgressAck], None]


class CoordinatorLink(Protocol):
    """The coordinator's side of the transport."""

    def announce(self, announcement: Announcement) -> None:
        """To every reachable agent."""

    def assign(self, assignment: Assignment) -> None:
        """To every reachable agent."""

    def acknowledge(self, ack: ProgressAck) -> None:
        """To ``ack.agent``."""

    def drain(self) -> CoordinatorInbox:
        """Bids, progress and statuses that arrived since the last call."""
        ...


class AgentLink(Protocol):
    """One agent's side of the transport."""

    @property
    def agent(self) -> str: ...

    @property
    def up(self) -> bool:
        """Whether the coordinator can be reached now (as far as this end can tell)."""
        ...

    def connect(
        self, on_announcement: OnAnnouncement, on_assignment: OnAssignment, on_ack: OnAck
    ) -> None:
        """Receive the coordinator's messages through these callbacks."""

    def disconnect(self) -> None: ...

    def send_bid(self, bid: Bid) -> None: ...

    def send_progress(self, progress: Progress) -> None: ...

    def send_status(self, status: AgentStatus) -> None: ...

    def share_prediction(
        self, time_s: float, positions: FloatArray, velocity: FloatArray | None = None
    ) -> None:
        """Publish this agent's predicted positions to the other agents (and its velocity,
        when it knows it; a transport that cannot carry it drops it: the others then take the
        agent's velocity as unknown)."""

    def predictions(
        self,
        time_s: float,
        step_s: float,
        near: FloatArray | None = None,
        within_m: float = math.inf,
    ) -> list[FloatArray]:
        """The other agents' predictions (:func:`advance_predictions`)."""
        ...


@dataclass
class _Endpoint:
    on_announcement: OnAnnouncement
    on_assignment: OnAssignment
    on_ack: OnAck | None = None
    up: bool = True


class InMemoryBus:
    """Synchronous in-process transport (module docstring): a :class:`CoordinatorLink`, and
    through :meth:`agent_link` every agent's :class:`AgentLink`."""

    def __init__(self) -> None:
        self._agents: dict[str, _Endpoint] = {}
        self._inbox = CoordinatorInbox()
        self._predictions: dict[str, Prediction] = {}
        # where each agent's prediction starts, one row per agent in the order of the dict
        # above (a row is appended when an agent first shares; NaN once it has gone): the
        # neighbours of a position are found for all agents at once (:meth:`predictions`)
        self._rows: dict[str, int] = {}
        self._row_names: list[str] = []
        self._starts = np.full((8, 3), np.nan)
        """Each row's first predicted position (z NaN for a 2D prediction)."""
        self._vel = np.full((8, 3), np.nan)
        """Each row's shared velocity (NaN: not shared)."""
        self._multi = np.zeros(8, dtype=bool)
        """Each row's prediction has more than one point (its first moves with time)."""
        self._trajectories = 0
        """Rows whose :attr:`_multi` is set (none: a neighbour's point is its row's start)."""
        self.dropped = 0
        """Messages lost on cut links."""

    # ---------------------------------------------------------------- connections
    def agent_link(self, agent: str) -> InMemoryAgentLink:
        """``agent``'s end of the bus."""
        return InMemoryAgentLink(self, agent)

    def connect(
        self,
        agent: str,
        on_announcement: OnAnnouncement,
        on_assignment: OnAssignment,
        on_ack: OnAck | None = None,
    ) -> None:
        self._agents[agent] = _Endpoint(on_announcement, on_assignment, on_ack)

    def disconnect(self, agent: str) -> None:
        self._agents.pop(agent, None)
        self._predictions.pop(agent, None)
        row = self._rows.pop(agent, None)
        if row is not None:
            self._starts[row] = np.nan
            self._vel[row] = np.nan
            self._set_multi(row, False)

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

    def acknowledge(self, ack: ProgressAck) -> None:
        ep = self._agents.get(ack.agent)
        if ep is None or not ep.up:
            self.dropped += 1
        elif ep.on_ack is not None:
            ep.on_ack(ack)

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
    def share_prediction(
        self, agent: str, time_s: float, positions: FloatArray, velocity: FloatArray | None = None
    ) -> None:
        """Publish an agent's predicted (N+1, 2) positions (seed 003 §VI), with its velocity
        when it gives it."""
        vel = None if velocity is None else np.asarray(velocity, dtype=float).reshape(3)
        pred = Prediction(agent, time_s, np.asarray(positions, dtype=float), vel)
        self._predictions[agent] = pred
        row = self._rows.get(agent)
        if row is None:
            row = self._rows[agent] = len(self._row_names)
            self._row_names.append(agent)
            if row >= len(self._starts):
                grown = np.full((2 * len(self._starts), 3), np.nan)
                grown[:row] = self._starts
                self._starts = grown
                vels = np.full((2 * len(self._vel), 3), np.nan)
                vels[:row] = self._vel
                self._vel = vels
                multi = np.zeros(2 * len(self._multi), dtype=bool)
                multi[:row] = self._multi
                self._multi = multi
        pts = pred.positions
        self._vel[row] = np.nan if vel is None else vel
        if pts.shape == (1, 3):  # where it is now (every drone, every control step)
            self._starts[row] = pts[0]
            if self._trajectories:
                self._set_multi(row, False)
            return
        self._starts[row] = np.nan
        self._starts[row, : min(3, pts.shape[1])] = pts[0, :3]
        self._set_multi(row, len(pts) > 1)

    def share_positions(
        self,
        time_s: float,
        shares: Sequence[tuple[str, FloatArray]],
        at: tuple[NDArray[np.int64], FloatArray] | None = None,
        velocities: FloatArray | None = None,
    ) -> None:
        """:meth:`share_prediction` of each ``(agent, positions)``, every ``positions`` (1, 3) —
        where the agent is — at once (a fleet's drones, every control step): the same state as
        sharing them one by one, in order. ``at``: the agents' rows of the bus and their
        positions stacked ((n,), (n, 3)), when the caller has them (the fleet step);
        ``velocities``: the agents' velocities stacked (n, 3), None when they do not give them."""
        rows = self._rows
        if self._trajectories or (at is None and any(a not in rows for a, _ in shares)):
            for i, (agent, pts) in enumerate(shares):
                self.share_prediction(
                    agent, time_s, pts, None if velocities is None else velocities[i]
                )
            return
        preds = self._predictions
        new = recorder(Prediction)
        for i, (agent, pts) in enumerate(shares):
            v = None if velocities is None else velocities[i]
            preds[agent] = new(agent=agent, time_s=time_s, positions=pts, velocity=v)
        where = at[0] if at is not None else [rows[a] for a, _ in shares]
        if at is not None:
            self._starts[where] = at[1]
        else:
            self._starts[where] = np.concatenate([p for _, p in shares])
        self._vel[where] = np.nan if velocities is None else velocities

    def _set_multi(self, row: int, multi: bool) -> None:
        """Mark ``row``'s prediction as a trajectory (or not), keeping :attr:`_trajectories`."""
        self._trajectories += int(multi) - int(self._multi[row])
        self._multi[row] = multi

    def predictions(
        self,
        agent: str,
        time_s: float,
        step_s: float,
        near: FloatArray | None = None,
        within_m: float = math.inf,
    ) -> list[FloatArray]:
        """The other agents' predictions (:func:`advance_predictions`); with a finite
        ``within_m`` the candidates come from one vectorised distance test over every agent's
        start (a fleet's agents each ask every control step)."""
        rows = self._near_rows(agent, near, within_m)
        if rows is None:
            return advance_predictions(self._predictions, agent, time_s, step_s, near, within_m)
        names = self._row_names
        return [_advanced(self._predictions[names[r]], time_s, step_s) for r in rows]

    def neighbour_positions(
        self, agent: str, time_s: float, step_s: float, near: FloatArray, within_m: float
    ) -> FloatArray:
        """The first point of each of :meth:`predictions` (same order), stacked (k, 3), z NaN
        for a 2D prediction: where the neighbours are now, without a list of arrays (every
        agent asks every control step)."""
        n = len(self._row_names)
        if not math.isfinite(within_m) or n <= SMALL_FLEET:
            return first_points(
                advance_predictions(self._predictions, agent, time_s, step_s, near, within_m)
            )
        if self._trajectories:  # some agent shares a trajectory: its point at time_s
            rows = self._near_rows(agent, near, within_m)
            assert rows is not None
            out = self._starts[rows]
            names = self._row_names
            for i, r in enumerate(rows):
                if self._multi[r]:
                    pred = _advanced(self._predictions[names[r]], time_s, step_s)
                    out[i] = first_points([pred])[0]
            return out
        from btmission.links._neighbour_kernels import near_points

        points: FloatArray = near_points(
            self._starts, n, float(near[0]), float(near[1]), float(within_m),
            self._rows.get(agent, -1),
        )  # fmt: skip
        return points

    def neighbour_states(
        self, agent: str, time_s: float, step_s: float, near: FloatArray, within_m: float
    ) -> FloatArray:
        """:meth:`neighbour_positions` (columns 0:3) beside each neighbour's shared velocity
        (3:6, NaN where it gave none), (k, 6): what the separation rule reads."""
        n = len(self._row_names)
        if not math.isfinite(within_m) or n <= SMALL_FLEET:
            near_ones = _near_predictions(self._predictions, agent, near, within_m)
            out = np.full((len(near_ones), 6), np.nan)
            out[:, :3] = first_points([_advanced(p, time_s, step_s) for p in near_ones])
            for i, p in enumerate(near_ones):
                if p.velocity is not None:
                    out[i, 3:] = p.velocity
            return out
        if self._trajectories:
            rows = self._near_rows(agent, near, within_m)
            assert rows is not None
            out = np.empty((len(rows), 6))
            out[:, :3] = self.neighbour_positions(agent, time_s, step_s, near, within_m)
            out[:, 3:] = self._vel[rows]
            return out
        from btmission.links._neighbour_kernels import near_states

        states: FloatArray = near_states(
            self._starts, self._vel, n, float(near[0]), float(near[1]), float(within_m),
            self._rows.get(agent, -1),
        )  # fmt: skip
        return states

    def _near_rows(self, agent: str, near: FloatArray | None, within_m: float) -> list[int] | None:
        """The rows of the agents other than ``agent`` whose prediction starts within
        ``within_m`` of ``near``, nearest first (equal distances in row order): one vectorised
        test over every agent's start. None for a small fleet or no bound (the caller asks
        :func:`advance_predictions`, which gives the same answer)."""
        n = len(self._row_names)
        if near is None or not math.isfinite(within_m) or n <= SMALL_FLEET:
            return None
        from btmission.links._neighbour_kernels import near_rows

        rows: list[int] = near_rows(
            self._starts, n, float(near[0]), float(near[1]), float(within_m),
            self._rows.get(agent, -1),
        ).tolist()  # fmt: skip
        return rows


def first_points(predictions: Sequence[FloatArray]) -> FloatArray:
    """The first point of each prediction, stacked (k, 3); z is NaN for a 2D prediction."""
    out = np.full((len(predictions), 3), np.nan)
    for i, pts in enumerate(predictions):
        out[i, : min(3, pts.shape[1])] = pts[0, :3]
    return out


def advance_predictions(
    shared: Mapping[str, Prediction],
    agent: str,
    time_s: float,
    step_s: float,
    near: FloatArray | None = None,
    within_m: float = math.inf,
) -> list[FloatArray]:
    """The predictions of the agents other than ``agent`` in ``shared`` (each agent's latest) —
    (N+1, 2) or (N+1, 3) positions, a vehicle that only shares where it is gives one row —
    advanced to ``time_s`` (shifted by the steps of ``step_s`` since they were published, the
    last point repeated), nearest to ``near`` first, those farther than ``within_m`` left out.
    Pure: every transport's :meth:`AgentLink.predictions` gives the same answer (the distance is
    √(dx² + dy²) from ``near`` to each prediction's first point; equal ones keep ``shared``'s
    order)."""
    return [_advanced(p, time_s, step_s) for p in _near_predictions(shared, agent, near, within_m)]


def _near_predictions(
    shared: Mapping[str, Prediction], agent: str, near: FloatArray | None, within_m: float
) -> list[Prediction]:
    """The predictions of :func:`advance_predictions`, in its order, not yet advanced."""
    out: list[tuple[float, Prediction]] = []
    for other, pred in shared.items():
        if other == agent:
            continue
        d = 0.0
        if near is not None:
            dx = float(pred.positions[0, 0] - near[0])
            dy = float(pred.positions[0, 1] - near[1])
            d = math.sqrt(dx * dx + dy * dy)
            if d > within_m:
                continue
        out.append((d, pred))
    out.sort(key=lambda x: x[0])
    return [p for _, p in out]


def _advanced(pred: Prediction, time_s: float, step_s: float) -> FloatArray:
    """``pred``'s positions shifted by the steps of ``step_s`` since it was made (the last point
    repeated)."""
    pts = pred.positions
    k = max(0, round((time_s - pred.time_s) / step_s))
    if k and len(pts) > 1:
        k = min(k, len(pts) - 1)
        pts = np.vstack([pts[k:], np.repeat(pts[-1:], k, axis=0)])
    return pts


class InMemoryAgentLink:
    """One agent's end of an :class:`InMemoryBus` (an :class:`AgentLink`)."""

    def __init__(self, bus: InMemoryBus, agent: str) -> None:
        self._bus = bus
        self._agent = agent

    @property
    def bus(self) -> InMemoryBus:
        return self._bus

    @property
    def agent(self) -> str:
        return self._agent

    @property
    def up(self) -> bool:
        return self._bus.link_up(self._agent)

    def connect(
        self, on_announcement: OnAnnouncement, on_assignment: OnAssignment, on_ack: OnAck
    ) -> None:
        self._bus.connect(self._agent, on_announcement, on_assignment, on_ack)

    def disconnect(self) -> None:
        self._bus.disconnect(self._agent)

    def send_bid(self, bid: Bid) -> None:
        self._bus.send_bid(bid)

    def send_progress(self, progress: Progress) -> None:
        self._bus.send_progress(progress)

    def send_status(self, status: AgentStatus) -> None:
        self._bus.send_status(status)

    def share_prediction(
        self, time_s: float, positions: FloatArray, velocity: FloatArray | None = None
    ) -> None:
        self._bus.share_prediction(self._agent, time_s, positions, velocity)

    def predictions(
        self,
        time_s: float,
        step_s: float,
        near: FloatArray | None = None,
        within_m: float = math.inf,
    ) -> list[FloatArray]:
        return self._bus.predictions(self._agent, time_s, step_s, near, within_m)

    def neighbour_positions(
        self, time_s: float, step_s: float, near: FloatArray, within_m: float
    ) -> FloatArray:
        """:meth:`InMemoryBus.neighbour_positions` (:func:`neighbour_positions`)."""
        return self._bus.neighbour_positions(self._agent, time_s, step_s, near, within_m)

    def neighbour_states(
        self, time_s: float, step_s: float, near: FloatArray, within_m: float
    ) -> FloatArray:
        """:meth:`InMemoryBus.neighbour_states` (:func:`neighbour_states`)."""
        return self._bus.neighbour_states(self._agent, time_s, step_s, near, within_m)


class ForwardingAgentLink:
    """An :class:`AgentLink` around another (``inner``) that forwards everything to it; a
    subclass changes what it needs (a test transport's faults, an agent process's clock)."""

    def __init__(self, inner: AgentLink) -> None:
        self.inner = inner

    @property
    def agent(self) -> str:
        return self.inner.agent

    @property
    def up(self) -> bool:
        return self.inner.up

    def connect(
        self, on_announcement: OnAnnouncement, on_assignment: OnAssignment, on_ack: OnAck
    ) -> None:
        self.inner.connect(on_announcement, on_assignment, on_ack)

    def disconnect(self) -> None:
        self.inner.disconnect()

    def send_bid(self, bid: Bid) -> None:
        self.inner.send_bid(bid)

    def send_progress(self, progress: Progress) -> None:
        self.inner.send_progress(progress)

    def send_status(self, status: AgentStatus) -> None:
        self.inner.send_status(status)

    def share_prediction(
        self, time_s: float, positions: FloatArray, velocity: FloatArray | None = None
    ) -> None:
        self.inner.share_prediction(time_s, positions, velocity)

    def predictions(
        self,
        time_s: float,
        step_s: float,
        near: FloatArray | None = None,
        within_m: float = math.inf,
    ) -> list[FloatArray]:
        return self.inner.predictions(time_s, step_s, near, within_m)


def neighbour_positions(
    link: AgentLink, time_s: float, step_s: float, near: FloatArray, within_m: float
) -> FloatArray:
    """Where the other agents within ``within_m`` of ``near`` are at ``time_s``: the first
    point of each of ``link.predictions(...)``, stacked (k, 3), nearest first, z NaN for a 2D
    prediction — from the link's own ``neighbour_positions`` when it has one (the in-memory
    bus, vectorised over the fleet), else from its predictions."""
    fast = getattr(link, "neighbour_positions", None)
    if fast is not None:
        out: FloatArray = fast(time_s, step_s, near, within_m)
        return out
    return first_points(link.predictions(time_s, step_s, near, within_m))


def neighbour_states(
    link: AgentLink, time_s: float, step_s: float, near: FloatArray, within_m: float
) -> FloatArray:
    """:func:`neighbour_positions` (columns 0:3) with each neighbour's shared velocity (3:6),
    (k, 6) — from the link's own ``neighbour_states`` when it has one (the in-memory bus); a
    link without it gives the positions with the velocities unknown (NaN)."""
    fast = getattr(link, "neighbour_states", None)
    if fast is not None:
        out: FloatArray = fast(time_s, step_s, near, within_m)
        return out
    pos = neighbour_positions(link, time_s, step_s, near, within_m)
    states = np.full((len(pos), 6), np.nan)
    states[:, :3] = pos
    return states
