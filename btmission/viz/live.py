"""A live run's viewer: the feed behind a queue, and the server once the run is built.

What ``btmission run --view`` does, as a class the tests and the benchmark use too::

    viewer = LiveViewer(port=0)                  # takes the port now: in use → ViewerError
    with RunSession(mission, observers=[viewer.observer]) as session:
        run = session.start()
        url = viewer.attach(session, run)        # serves the page from here on
                                                 # (console=True: commands too, with the
                                                 # token in viewer.server.console_url)
        session.run()
    viewer.close()

The run only appends the events the page draws to a :class:`~btmission.runtime.observers.
QueuedObserver` (it never waits for the viewer), delivered in batches to keep thread switches
few; the :class:`~btmission.viz.feed.LiveFeed` behind it keeps the records
and samples the run's snapshots for poses on a thread of its own; the server reads the feed.
"""

from __future__ import annotations

from typing import Any

from btmission.console.api import READ_ONLY, is_loopback, new_token
from btmission.console.service import Console
from btmission.runtime.eventkinds import PoseEvent
from btmission.runtime.events import (
    Event,
    Observer,
)
from btmission.runtime.observers import QueuedObserver
from btmission.viz.feed import LiveFeed, draws
from btmission.viz.server import DEFAULT_PORT, ViewerServer, ViewerSource, mission_info

BATCH_S = 0.05
"""The viewer's queue is delivered in batches, at most every this many seconds."""


class ViewerKinds:
    """Passes on, on the run's thread, only the events the feed keeps: the run does not queue
    the ``pose`` events (the feed takes poses from the snapshots) nor the auction rounds that
    changed nothing (ten a second) for a thread that would only drop them."""

    def __init__(self, inner: Observer) -> None:
        self.inner = inner

    def on_event(self, event: Event) -> None:
        if event.kind != PoseEvent.KIND and draws(event):  # (poses: not typed for nothing)
            self.inner.on_event(event)


class LiveViewer:
    """A running mission's viewer (module docstring)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        *,
        port_tries: int = 1,
        pose_hz: float = 10.0,
        queue_size: int = 10_000,
        console: bool = False,
        token: str | None = None,
        tls: tuple[str, str] | None = None,
    ) -> None:
        self.run: Any = None
        self.feed = LiveFeed(
            lambda: self.run.snapshot if self.run is not None else None, pose_hz=pose_hz
        )
        self.queue = QueuedObserver(self.feed, maxsize=queue_size, name="viewer", batch_s=BATCH_S)
        self.observer = ViewerKinds(self.queue)
        """Give this to the run (``RunSession(observers=[...])``)."""
        self.console = console
        """Serve the operator console too (commands need ``token``; a new one if None)."""
        self.server = ViewerServer(
            None,
            host,
            port,
            port_tries=port_tries,
            # the console's commands need a token, and so does every view off loopback
            token=(token or new_token()) if console or not is_loopback(host) else None,
            tls=tls,
        )
        self.server.bind()
        self.serving = False

    def attach(self, session: Any, run: Any) -> str:
        """Serve ``run`` (built by ``session``); the page's URL."""
        from btmission.planning.risk import RiskParams

        mission = session.mission
        rt = mission.spec.runtime
        header = {
            "mission": mission.name,
            "description": mission.spec.description,
            "agents": [
                {"id": a.id, "library": a.library, "start": list(a.start)} for a in mission.agents
            ],
            "step_s": run.dt,
        }
        self.server.source = ViewerSource(
            mission_info(header, mode="live", source=str(session.log_path or "")),
            self.feed,
            run.map,
            scene_options={"risk": RiskParams(rt.risk_radius_m, rt.unknown_cost)},
        )
        # the status answers on every live run; commands only with the console (--console)
        self.server.console = Console(session, run, read_only=None if self.console else READ_ONLY)
        self.run = run
        url = self.server.start()
        self.serving = True
        self.feed.start()
        return url

    def finish(self) -> None:
        """The run has ended: deliver every queued event and the last poses (the page keeps
        being served until :meth:`close`)."""
        self.queue.close(timeout=10.0)
        self.feed.close()

    def close(self) -> None:
        self.finish()
        self.server.close()
