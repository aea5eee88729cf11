"""The two sides of the run loop: one per agent, one for the coordinator.

A mission's loop is two kinds of periodic work that only talk through messages (the
coordinator ↔ agent link, :mod:`btmission.links.bus`):

* :class:`AgentRuntime` — what runs on a robot's computer: tick its mission tree every
  ``1 / runtime.tick_hz`` s, stream this control period's setpoints, and send its status (also
  pose, mode, battery, task and action: what an operator's display shows) every
  ``1 / runtime.status_hz`` s (its bids, answering the announcements, are its heartbeat);
* :class:`CoordinatorRuntime` — what runs at the base station: the run-wide services of the
  libraries (e.g. the GA fleet dispatcher) and the auction (:class:`~btmission.runtime.
  coordinator.Coordinator`): announcements, bids, allocation, assignments.

:class:`~btmission.runtime.runner.MissionRun` composes them in one process, in lock step with
the vehicles' provider. Each side has a ``step(now)`` that does all of its work due at ``now``,
so a later process per agent (or one for the coordinator) runs exactly this code on its own
clock. In one process the run calls the agent sides phase by phase instead — every agent's
tick, then every agent's control, then every agent's status — which is the order the
simulator's runs have always had (same seed, same run).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from py_trees.common import Status

from btmission.runtime.leaves import ErrorReporter

if TYPE_CHECKING:
    from btmission.runtime.agent import Agent
    from btmission.runtime.coordinator import Coordinator

_EPS = 1e-9


class _Every:
    """A fixed-rate schedule: due at 0, p, 2p, ... (no drift; a late call runs once)."""

    def __init__(self, period_s: float, start_s: float = 0.0) -> None:
        self.period_s = period_s
        self.next_s = start_s

    def due(self, now: float) -> bool:
        if now + _EPS >= self.next_s:
            self.next_s += self.period_s
            return True
        return False


class AgentRuntime:
    """One agent's side of the loop (module docstring)."""

    def __init__(
        self,
        agent: Agent,
        *,
        tick_period_s: float,
        status_period_s: float,
        start_s: float = 0.0,
    ) -> None:
        self.agent = agent
        self.id = agent.id
        self._tick = _Every(tick_period_s, start_s)
        self._status = _Every(status_period_s, start_s)

    def tick(self, now: float) -> Status | None:
        """Tick the mission tree if a tick is due (None: none was)."""
        if self._tick.due(now):
            return self.agent.tick(now)
        return None

    def control(self, now: float) -> None:
        """This control period's setpoints (every step)."""
        self.agent.control_step(now)

    def finish_control(self) -> None:
        """Apply this period's deferred setpoints (an NMPC solve running on the thread pool:
        :attr:`~btmission.runtime.navigation.Navigator.defer_nmpc`); a no-op otherwise."""
        self.agent.navigator.finish_step()

    def report(self, now: float) -> bool:
        """Send the agent's status if one is due; True when it was due."""
        if not self._status.due(now):
            return False
        a = self.agent
        if a.alive:
            a.link.send_status(a.status(now))
        return True

    def step(self, now: float) -> None:
        """Everything due at ``now``: tick, control, status."""
        self.tick(now)
        self.control(now)
        self.finish_control()
        self.report(now)


class CoordinatorRuntime:
    """The coordinator's side of the loop (module docstring)."""

    def __init__(
        self,
        coordinator: Coordinator,
        services: Mapping[str, Mapping[str, Any]],
        errors: ErrorReporter,
    ) -> None:
        self.coordinator = coordinator
        self.services = services
        self.errors = errors
        """Exceptions raised by services' ``step`` → ``leaf_error`` events (once each)."""

    def step(self, now: float) -> None:
        """Step every run-wide service, then the auction (a round when one is due)."""
        for library, services in self.services.items():
            for name, service in services.items():
                step = getattr(service, "step", None)
                if step is not None:
                    try:
                        step(now)
                    except Exception as exc:  # a library's code must not end the run
                        self.errors.report(f"service {library}.{name}", "step", exc)
        self.coordinator.step(now)
