"""How a run ends: when it should, and what it returns and logs then.

:func:`why_finished` is asked by the loop before every step: a run ends when every task is done
(or failed, or unreachable by any agent), nothing is left to arrive and every agent has finished
its default behaviour (or waits, if it has none); a distributed run's agent process ends when its
coordinator says so (:func:`heard_end`). :func:`result_of` is the :class:`RunResult` the loop
returns; :func:`end_before_build` the ``end`` event of a run stopped while it was being built.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from btmission.allocation.tasks import TaskState
from btmission.links.bus import MissionEnd
from btmission.runtime.command_port import settle
from btmission.runtime.eventkinds import EndEvent
from btmission.runtime.events import Event

if TYPE_CHECKING:
    from btmission.runtime.distribution import Part
    from btmission.runtime.runner import MissionRun
    from btmission.spec.mission import Mission


@dataclass
class RunResult:
    """How a run ended."""

    reason: str
    """completed, finished with open tasks, time limit, until, interrupted, no agents left."""
    time_s: float
    wall_s: float
    steps: int
    done: list[str] = field(default_factory=list)
    open: dict[str, str] = field(default_factory=dict)
    """Tasks not done → state and reason (tasks that have arrived)."""
    collisions: int = 0
    pending: list[str] = field(default_factory=list)
    """Tasks still to arrive (``at:`` after the end: the run was cut short)."""
    cancelled: list[str] = field(default_factory=list)
    """Tasks the operator cancelled (not counted as open)."""

    @property
    def speedup(self) -> float:
        return self.time_s / self.wall_s if self.wall_s > 0 else math.inf


def why_finished(run: MissionRun) -> str | None:
    """Why the run should end now (None: go on)."""
    if run.part is not None:
        return _part_finished(run)
    agents = run.agents.values()
    pool = run.coordinator.state.pool
    if not _settled(run, run.now()):
        if any(a.alive and not a.recalled and a.stood_down is None for a in agents):
            return None  # someone can still take the open tasks
        live = [a for a in agents if a.alive]  # killed or recalled: nobody can any more
        if any(not t.state.terminal for t in pool) and all(a.at_rest for a in live):
            return "no agents left"  # (the recalled ones are home)
        return None
    live = [a for a in agents if a.alive]
    if not all(a.at_rest for a in live):
        return None
    if all(t.state in (TaskState.DONE, TaskState.CANCELLED) for t in pool):
        return "completed"  # (what the operator cancelled is not left open)
    return "finished with open tasks"


def _part_finished(run: MissionRun) -> str | None:
    """An agent process ends when its coordinator says the mission is over; the
    coordinator's when every task is settled and every agent it hears from is at rest
    (its last status, within the agent timeout) — or when none is left to do them."""
    if not run.runs_coordinator:
        ended = heard_end(run.part)
        return ended.reason if ended is not None else None
    now = run.now()
    timeout = run.coordinator.state.config.agent_timeout_s
    heard = {a: st for a, st in run.coordinator.statuses.items() if now - st.time_s <= timeout}
    pool = run.coordinator.state.pool
    if not _settled(run, now):
        return None
    if not heard and any(not t.state.terminal for t in pool):
        return None  # nobody to do them yet (agents may come back)
    if not all(st.at_rest for st in heard.values()):
        return None
    if all(t.state in (TaskState.DONE, TaskState.CANCELLED) for t in pool):
        return "completed"
    return "finished with open tasks"


def _settled(run: MissionRun, now: float) -> bool:
    """Nothing left to allocate: the coordinator's pool is settled and no task added is still
    queued to enter it."""
    return run.coordinator.settled(now) and not run.port.tasks.waiting


def heard_end(part: Part | None) -> MissionEnd | None:
    """The coordinator's end of the mission, once an agent process has heard it."""
    if part is None:
        return None
    for link in part.agent_links.values():
        ended = getattr(link, "ended", None)
        if ended is not None:
            return ended  # type: ignore[no-any-return]
    return None


def result_of(run: MissionRun, reason: str) -> RunResult:
    """How the run stands now, ended for ``reason`` (what :meth:`run` returns)."""
    now = run.now()
    ended = heard_end(run.part) if not run.runs_coordinator else None
    if ended is not None:  # an agent process: the mission as its coordinator ended it
        return RunResult(
            reason, now, run.wall_used, run.steps, list(ended.done), dict(ended.open),
            run.collisions,
        )  # fmt: skip
    everything = run.coordinator.state.pool
    pool = [t for t in everything if t.info.arrival_s <= now + 1e-9]
    return RunResult(  # tasks still to arrive (``at:`` later) are neither done nor open
        reason,
        now,
        run.wall_used,
        run.steps,
        [t.id for t in pool if t.state is TaskState.DONE],
        {
            t.id: f"{t.state.value}: {t.note}"
            for t in pool
            if t.state not in (TaskState.DONE, TaskState.CANCELLED)
        },
        run.collisions,
        [
            t.id
            for t in everything
            if t.info.arrival_s > now + 1e-9 and t.state is not TaskState.CANCELLED
        ],
        [t.id for t in everything if t.state is TaskState.CANCELLED],
    )


def end_before_build(mission: Mission, reason: str, wall_s: float) -> Event:
    """The ``end`` event of a run stopped while it was being built (after its header):
    nothing ran, every task is still to arrive."""
    return EndEvent(
        t=0.0,
        reason=reason,
        wall_s=wall_s,
        steps=0,
        done=[],
        open={},
        pending=[t.id for t in mission.tasks],
    ).to_event()


def publish_end(run: MissionRun, result: RunResult) -> None:
    """What ending does, once: every command still queued is answered (not applied), the last
    snapshot is published, the agents' pending tree events go out, then the ``end`` event; a
    distributed run's coordinator tells its agent processes."""
    settled = run.port.settle_unapplied()
    run.publish(result.reason)
    settle(settled)
    for a in run.agents.values():
        a.flush_tree_events()
    run.emit_event(
        EndEvent(
            reason=result.reason,
            wall_s=result.wall_s,
            steps=result.steps,
            done=result.done,
            open=result.open,
            pending=result.pending,
            cancelled=result.cancelled or None,  # only when there are any
        )
    )
    send_end = getattr(run.coordinator.link, "end", None)
    if run.part is not None and run.runs_coordinator and send_end is not None:
        send_end(MissionEnd(run.now(), result.reason, tuple(result.done), result.open))
