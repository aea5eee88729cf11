"""One process's part of a mission spread over several processes (docs/distributed.md).

In one process, :class:`~btmission.runtime.runner.MissionRun` runs the coordinator and every
agent, linked by the in-memory bus. Spread over processes, each runs a :class:`MissionRun`
given a :class:`Part`:

* the **coordinator** process (``btmission coordinator``): the auction and the run-wide
  services over a :class:`~btmission.links.bus.CoordinatorLink` (Zenoh), no vehicle; its
  clock is the wall clock sped up by the mission's ``runtime.mavlink.time_scale`` (the
  vehicles' speed-up), started when the mission starts (or, restarted, continuing from the
  time its log's header recorded); it ends the mission when every task is settled and every
  agent it hears says it is at rest, and tells the agents (:class:`~btmission.links.bus.
  MissionEnd`);
* an **agent** process (``btmission agent --id R1``): its agents' trees, navigators and
  vehicles (MAVLink: one ``mavsim`` serves every process's vehicles in one shared world), each
  over its own :class:`~btmission.links.bus.AgentLink`; its mission clock follows the
  coordinator's (set from the assignments it hears, :class:`ClockFollower`); it ends
  when the coordinator says the mission is over.

Each process writes its own event log; :func:`merge_logs` makes one log of them for the report.
Everything here but :func:`merge_logs` (which takes events already read) is free of I/O.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Protocol

from btmission.errors import BtmissionError
from btmission.links.bus import (
    AgentLink,
    Assignment,
    CoordinatorLink,
    ForwardingAgentLink,
    OnAck,
    OnAnnouncement,
    OnAssignment,
)
from btmission.runtime.events import Event
from btmission.spec.vehicleref import SIM, VehicleRef
from btmission.vehicles.clock import Clock, ScaledWallClock
from btmission.vehicles.provider import AttachOptions, ProviderBase, Vehicle, VehicleEvent

if TYPE_CHECKING:
    from btmission.spec.mission import Mission
    from btmission.types import Vec3
    from btmission.vehicles.base import VehicleKind


@dataclass
class Part:
    """What this process runs of a distributed mission (module docstring)."""

    agents: tuple[str, ...] = ()
    """The mission's agents this process runs (none: the coordinator's process)."""
    coordinator_link: CoordinatorLink | None = None
    """The coordinator runs here, over this link (None: elsewhere)."""
    agent_links: Mapping[str, AgentLink] = field(default_factory=dict)
    """Each of :attr:`agents`' link to the coordinator."""
    started_unix: float | None = None
    """A restarted coordinator: the wall time (Unix s) its mission started, so that its clock
    continues (None: the mission starts now)."""
    resumed_from: str | None = None
    """A restarted coordinator: the log it continues (it writes a ``resumed`` event there instead
    of a new header)."""
    resumed_at_s: float = 0.0
    """The mission time of that log's last event."""
    sync_timeout_s: float = 60.0
    """An agent process waits this long (wall s) for its coordinator's first assignment,
    which sets its clock, before its agents start."""
    live_agents: Callable[[], Iterable[str]] | None = None
    """The agents the coordinator's link can reach now (Zenoh's liveliness), for the early end
    of a round's bid window."""

    @property
    def runs_coordinator(self) -> bool:
        return self.coordinator_link is not None

    def describe(self) -> str:
        return "coordinator" if self.runs_coordinator else "agents " + ", ".join(self.agents)


def with_backends(
    mission: Mission, backends: Mapping[str, str], time_scale: float | None
) -> Mission:
    """``mission`` with these agents' ``backend`` replaced (``btmission agent --backend``: the
    MAVLink vehicle that serves an agent of a simulator mission) and, if given, its
    ``runtime.mavlink.time_scale``. A simulator agent given a MAVLink vehicle keeps its sensors:
    ``runtime.mavlink.map_sensors`` is turned on (LiDAR and camera from the mission map at the
    pose the vehicle reports, as the simulator gave them)."""
    agents = [
        replace(a, vehicle=VehicleRef.parse(backends[a.id])) if a.id in backends else a
        for a in mission.agents
    ]
    spec = mission.spec
    rt = spec.runtime
    update: dict[str, Any] = {}
    if time_scale is not None:
        update["time_scale"] = float(time_scale)
    if any(a.vehicle.scheme == "sim" and a.id in backends for a in mission.agents):
        update["map_sensors"] = True
    if update:
        mav = rt.mavlink.model_copy(update=update)
        spec = spec.model_copy(update={"runtime": rt.model_copy(update={"mavlink": mav})})
    return replace(mission, agents=agents, spec=spec)


class NoVehicles(ProviderBase):
    """The coordinator process's vehicle provider: none (its agents' vehicles are flown by the
    agent processes), and a settable wall clock
    (:class:`~btmission.vehicles.clock.ScaledWallClock`)."""

    realtime = True
    clock: Clock

    def __init__(self, scale: float = 1.0, started_unix: float | None = None) -> None:
        """``started_unix``: when the mission's time was zero (a restarted coordinator's
        clock continues from it); default: now."""
        now = time.time()
        self.started_unix = now if started_unix is None else started_unix
        self.clock = ScaledWallClock(scale, now_s=max(0.0, now - self.started_unix) * scale)

    def attach(
        self,
        agent_id: str,
        kind: VehicleKind,
        start: Vec3,
        ref: VehicleRef = SIM,
        options: AttachOptions = AttachOptions(),
    ) -> Vehicle:
        raise RuntimeError(f"the coordinator's process has no vehicles (asked for {agent_id})")

    def step(self, dt: float) -> Sequence[VehicleEvent]:
        return ()

    def close(self) -> None:
        pass


REMOTE_BID_WINDOW_WALL_S = 0.25
"""How long, in wall time, a coordinator over a network waits at most for a round's bids (it
closes the round as soon as every agent it can reach has bid)."""


def remote_bid_window(period_s: float, time_scale: float) -> float:
    """A round's bid window in mission seconds over a network: :data:`REMOTE_BID_WINDOW_WALL_S`
    of wall time, at most half the auction period."""
    return min(0.5 * period_s, REMOTE_BID_WINDOW_WALL_S * time_scale)


CLOCK_FOLLOW_WALL_S = 0.1
"""An agent's clock is set forward to its coordinator's when it is behind by more than this much
wall time (times the clock's speed-up, in mission seconds)."""


class ClockFollower(ForwardingAgentLink):
    """An agent's link whose coordinator's assignments (their ``sent_s``, the coordinator's
    clock when it sent them: one every round) set the agent process's mission clock
    (``set_now``): an agent process started or restarted at any time runs on its
    coordinator's mission time.

    An assignment arrives after it was sent, so the coordinator's clock is at least its
    ``sent_s`` when it is read: the agent's clock is set forward when it is behind by more than
    :data:`CLOCK_FOLLOW_WALL_S` of wall time, never back for an assignment that merely waited
    (a backlog after a busy step) — except the first one, and the first of a coordinator of
    another epoch (one restarted on another clock). Everything else goes to the wrapped link
    (and what this class does not define, e.g. ``dispatch``, to it as well)."""

    def __init__(
        self, link: AgentLink, clock: SettableClock, on_set: Callable[[float, float], None]
    ) -> None:
        super().__init__(link)
        self._clock = clock
        self._on_set = on_set
        self.synced = False
        self._epoch: int | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def _follow(self, t: float, epoch: int) -> None:
        now = self._clock.now()
        slack = CLOCK_FOLLOW_WALL_S * self._clock.scale
        anew = not self.synced or epoch != self._epoch
        if (anew and abs(now - t) > slack) or t - now > slack or not self.synced:
            self._clock.set_now(t)
            self._on_set(now, t)
        self.synced = True
        self._epoch = epoch

    def connect(
        self, on_announcement: OnAnnouncement, on_assignment: OnAssignment, on_ack: OnAck
    ) -> None:
        def assigned(msg: Assignment) -> None:
            if msg.sent_s is not None:
                self._follow(msg.sent_s, msg.announcement.epoch)
            on_assignment(msg)

        self.inner.connect(on_announcement, assigned, on_ack)


class SettableClock(Protocol):
    def now(self) -> float: ...

    def set_now(self, t: float) -> None: ...

    @property
    def scale(self) -> float: ...


# ---------------------------------------------------------------------------------- the logs
AGENT_SIDE_SKIPPED = frozenset({"header", "built", "end"})
"""Events of an agent process's log that the merged log takes from the coordinator's instead."""


class MergeError(BtmissionError, ValueError):
    """Logs that are not one distributed run's (the text says which and why)."""


def merge_logs(coordinator: Sequence[Event], agents: Sequence[Sequence[Event]]) -> list[Event]:
    """One log of a distributed run: the coordinator's (its header, the auction, the tasks, the
    end) and each agent process's (poses, trees, routes, stages, progress), in time order (a
    stable merge: each log's own order kept). Raises :class:`MergeError` when a log is of
    another mission or not of the part it should be."""
    if not coordinator or coordinator[0].kind != "header":
        raise MergeError("the coordinator's log has no header")
    head = coordinator[0]
    mission = head.get("mission")
    if head.get("part", "coordinator") != "coordinator":
        raise MergeError(
            f"the first log is an agent process's ({head.get('part')}), not the coordinator's"
        )
    streams: list[list[Event]] = [list(coordinator)]
    for i, log in enumerate(agents):
        if not log or log[0].kind != "header":
            raise MergeError(f"agent log {i + 1} has no header")
        if log[0].get("mission") != mission:
            raise MergeError(
                f"agent log {i + 1} is of mission {log[0].get('mission')!r}, not {mission!r}"
            )
        streams.append([e for e in log if e.kind not in AGENT_SIDE_SKIPPED])
    order: list[tuple[float, int, int, Event]] = []
    for s, events in enumerate(streams):
        order.extend((e.t, s, j, e) for j, e in enumerate(events))
    header = streams[0][0]
    rest = sorted((x for x in order if x[3] is not header), key=lambda x: (x[0], x[1], x[2]))
    end = next((x for x in rest if x[1] == 0 and x[3].kind == "end"), None)
    if end is None:  # the coordinator was stopped before its end: everything, in time order
        return [header, *(x[3] for x in rest)]
    # what the agents logged after the mission's end (their last tree events) is left out
    return [header, *(x[3] for x in rest if x[0] <= end[0] and x is not end), end[3]]
