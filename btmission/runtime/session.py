"""A run session: one mission run from its file to its report, as one context manager.

:class:`RunSession` owns every step around the run loop, so that the CLI, the tests and a later
web console run missions the same way::

    from btmission.runtime.session import RunSession

    with RunSession("missions/pick_and_deliver.yaml", controller="track", log_dir="runs") as s:
        s.start()                                 # load, checks, log header, build
        s.submit(CancelTask("I2"))                # any thread, any time: applied between steps
        result = s.run(until=60.0)                # the loop; the log gets its `end` event
        print(s.report().summary.tasks_done)      # computed from the log alone

1. **load and checks** — the mission file (:func:`~btmission.missions.load_mission`) and its
   map (:func:`~btmission.world.checks.check_mission_world`): problems raise
   :class:`~btmission.diagnostics.SpecError` before anything is written;
2. **log** — an append-only JSON Lines event log in ``log_dir`` (or ``log_path``), named after
   the mission, the time and the seed; a run refused while it was being built leaves no log;
3. **the run** — a :class:`~btmission.runtime.runner.MissionRun`; commands
   (:meth:`submit`) go through its queue, and :attr:`snapshot` is the immutable state after
   the last step, for readers on other threads;
4. **signals** (``handle_signals=True``, main thread only) — the first SIGINT or SIGTERM asks
   the loop to stop after the current step; a second one, or one while the run is being built,
   stops at once; either way the log is ended properly and the result says why
   (``interrupted`` / ``terminated``). After the run has ended a signal raises
   :class:`RunStopped` straight away (the log is complete);
5. **end and report** — the ``end`` event is written once, whatever happened;
   :meth:`report` reads the log back (the report always comes from the log alone);
6. **close** — leaving the ``with`` block closes the log, the run's services and its vehicles'
   provider, and restores the signal handlers, even after an exception.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable, Iterable
from datetime import datetime
from pathlib import Path
from types import FrameType, TracebackType
from typing import TYPE_CHECKING, Any

from btmission.diagnostics import Diagnostic, Severity, SpecError, errors
from btmission.runtime.commands import Command
from btmission.runtime.eventkinds import InternalErrorEvent
from btmission.runtime.events import (
    Event,
    JsonlEventLog,
    Observer,
)
from btmission.runtime.substitution import SubstitutionRules, Substitutions
from btmission.vehicles.provider import VehicleUnavailable

if TYPE_CHECKING:
    from btmission.runtime.distribution import Part
    from btmission.runtime.report import MissionReport
    from btmission.runtime.runner import MissionRun, RunResult
    from btmission.runtime.snapshot import RunSnapshot
    from btmission.spec.mission import Mission

EXIT_CODES = {"interrupted": 130, "terminated": 143}
"""Exit status of a run ended by a signal (128 + SIGINT / SIGTERM, as a shell reports it)."""


class RunStopped(BaseException):
    """A signal when there was no run loop to take it: before the log existed (nothing ran) or
    after the run had ended (the log is complete). A BaseException, like KeyboardInterrupt, so
    that ``except Exception`` in library code does not swallow it."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason
        self.code = EXIT_CODES[reason]


def log_path_for(directory: Path, mission: str, seed: int) -> Path:
    """A new log file name in ``directory``: ``<mission>-<YYYYmmdd-HHMMSS>-seed<seed>.jsonl``
    (``-2``, ``-3`` ... appended if that exists already)."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    path = directory / f"{mission}-{stamp}-seed{seed}.jsonl"
    n = 1
    while path.exists():
        n += 1
        path = directory / f"{mission}-{stamp}-seed{seed}-{n}.jsonl"
    return path


class _Signals:
    """SIGINT and SIGTERM while the session is open (module docstring, item 4)."""

    def __init__(self, session: RunSession) -> None:
        self.session = session
        self.asked = False
        """A stop was asked of the run loop (a second signal stops at once)."""
        self.quiet = False
        """While the end event is written: signals are ignored (it must not be cut short)."""
        self._previous: dict[int, Any] = {}

    def install(self) -> None:
        if threading.current_thread() is threading.main_thread():  # (only there can they be set)
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        reason = "terminated" if signum == signal.SIGTERM else "interrupted"
        if self.quiet:
            return
        run = self.session.run_loop
        if run is None or self.asked or self.session.ended:
            raise RunStopped(reason)  # building (or a second one: the step may be a long one)
        self.asked = True
        run.stop(reason, by=signal.Signals(signum).name)  # SIGINT or SIGTERM
        self.session.notify(f"{reason}: stopping after the current step (again to stop at once)")


class RunSession:
    """One mission run, from its file to its report (module docstring)."""

    def __init__(
        self,
        mission: str | Path | Mission,
        *,
        seed: int = 0,
        controller: str | None = None,
        realtime: bool = False,
        speed: float = 1.0,
        log_dir: str | Path | None = "runs",
        log_path: str | Path | None = None,
        observers: Iterable[Observer] = (),
        handle_signals: bool = False,
        notify: Callable[[str], None] | None = None,
        substitutions: Substitutions | SubstitutionRules | None = None,
        part: Part | None = None,
    ) -> None:
        """``part``: what this process runs of a mission spread over processes
        (:mod:`btmission.runtime.distribution`). ``mission``: a mission file or a loaded :class:`~btmission.spec.mission.Mission`.
        The log goes to ``log_path``, else to a new file in ``log_dir``; with neither, no log
        is written (then :meth:`report` is not available). ``notify(text)`` receives the
        session's notes for a person (a signal was taken); default: none. ``substitutions``:
        leaves to replace, for tests (:mod:`btmission.runtime.substitution`). ``realtime`` paces
        the simulator ``speed`` times faster than the wall clock."""
        self._source = mission
        self.seed = seed
        self.controller = controller
        self.realtime = realtime
        self.speed = speed
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.log_path: Path | None = Path(log_path) if log_path is not None else None
        self._observers = list(observers)
        self._notify = notify
        self.substitutions = Substitutions.of(substitutions)
        self.part = part
        self._signals = _Signals(self) if handle_signals else None
        self.mission: Mission | None = None
        self.warnings: list[Diagnostic] = []
        """The mission's and its map's warnings (found by :meth:`load`)."""
        self.run_loop: MissionRun | None = None
        self.log: JsonlEventLog | None = None
        self.result: RunResult | None = None
        """How the run ended (None until it has, or if it was stopped while being built)."""
        self.stopped_while_building: str | None = None
        self.build_s = 0.0
        self.ended = False
        self._wall0 = time.perf_counter()

    # ------------------------------------------------------------------ context manager
    def __enter__(self) -> RunSession:
        if self._signals is not None:
            self._signals.install()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the log, the run's services and provider, and restore the signal handlers."""
        try:
            if self.run_loop is not None:
                self.run_loop.close()
        finally:
            if self.log is not None:
                self.log.close()
            if self._signals is not None:
                self._signals.restore()

    def notify(self, text: str) -> None:
        if self._notify is not None:
            self._notify(text)

    # ------------------------------------------------------------------ the steps
    def load(self) -> Mission:
        """Load the mission and check its map (SpecError on a problem; nothing written)."""
        if self.mission is not None:
            return self.mission
        from btmission.missions import load_mission
        from btmission.spec.mission import Mission
        from btmission.world.checks import check_mission_world

        mission = self._source if isinstance(self._source, Mission) else load_mission(self._source)
        map_diags = check_mission_world(mission)
        if errors(map_diags):
            raise SpecError(
                errors(map_diags) + [d for d in map_diags if d.severity is Severity.WARNING]
            )
        self.warnings = [
            d for d in mission.diagnostics + map_diags if d.severity is Severity.WARNING
        ]
        self.mission = mission
        return mission

    def start(self) -> MissionRun | None:
        """Load (if not yet), open the log and build the run. Returns it — or None when a
        signal stopped the build after the log's header was written (the log then ends with
        an ``end`` event: nothing ran). A signal before the header, or a mission the run
        refuses (SpecError), leaves no log."""
        from btmission.runtime.runner import MissionRun

        if self.run_loop is not None:
            return self.run_loop
        mission = self.load()
        if self.substitutions is not None:  # a rule that replaces nothing: before any log
            self.substitutions.check(mission)
        observers = list(self._observers)
        if self.log_path is None and self.log_dir is not None:
            self.log_path = log_path_for(self.log_dir, mission.name, self.seed)
        if self.log_path is not None:
            self.log = JsonlEventLog(self.log_path)
            observers.insert(0, self.log)
        t0 = time.perf_counter()
        try:
            self.run_loop = MissionRun(
                mission,
                seed=self.seed,
                controller=self.controller,
                observers=observers,
                realtime=self.realtime,
                speed=self.speed,
                substitutions=self.substitutions,
                part=self.part,
            )
        except (SpecError, VehicleUnavailable):  # nothing ran: no log
            self._drop_log()
            raise
        except RunStopped as stop:
            self.build_s = time.perf_counter() - t0
            if self.log is None or self.log.count == 0:  # not even the header: nothing to keep
                self._drop_log()
                raise
            self.stopped_while_building = stop.reason
            self._write(MissionRun.end_before_build(mission, stop.reason, self.build_s))
            self.ended = True
            return None
        self.build_s = time.perf_counter() - t0
        return self.run_loop

    def run(
        self,
        until: float | None = None,
        *,
        progress: Callable[[MissionRun], None] | None = None,
    ) -> RunResult | None:
        """Run until the mission ends (or mission time ``until``, or a signal / :class:`Stop`
        command), then write the ``end`` event. Starts the session first if needed. Returns
        how it ended (None if it was stopped while being built)."""
        run = self.start()
        if run is None:
            return None
        try:
            result = run.run(until, progress=progress)
        except RunStopped as stop:  # a second signal, mid-step
            result = run.result(stop.reason)
        self.end(result)
        return result

    def end(self, result: RunResult) -> None:
        """Write the ``end`` event (once); signals are ignored meanwhile."""
        if self.ended or self.run_loop is None:
            return
        if self._signals is not None:
            self._signals.quiet = True
        try:
            self.run_loop.end(result)
            self.result = result
            self.ended = True
        finally:
            if self._signals is not None:
                self._signals.quiet = False

    def record_internal_error(self, exc: BaseException, trace: str) -> str | None:
        """A bug (ours or a plugin's) ends the run: its traceback and the ``end`` event go into
        the log. Returns the log's path, or None if there is no log to write to."""
        if self.log is None or self.log.count == 0:
            return None
        run = self.run_loop
        self._write(
            InternalErrorEvent(
                t=run.now() if run is not None else 0.0,
                type=type(exc).__name__,
                message=str(exc),
                traceback=trace,
            ).to_event()
        )
        if run is not None:
            self.end(run.result("internal error"))
        elif self.mission is not None and not self.ended:
            from btmission.runtime.runner import MissionRun

            wall_s = time.perf_counter() - self._wall0
            self._write(MissionRun.end_before_build(self.mission, "internal error", wall_s))
            self.ended = True
        return str(self.log_path)

    # ------------------------------------------------------------------ while it runs
    def submit(self, command: Command) -> None:
        """Queue a command for the next step (thread-safe; see btmission.runtime.commands)."""
        if self.run_loop is None:
            raise RuntimeError("the run is not started yet (call start() first)")
        self.run_loop.submit(command)

    @property
    def snapshot(self) -> RunSnapshot | None:
        """The run after its last step (immutable; any thread), None before it is built."""
        return self.run_loop.snapshot if self.run_loop is not None else None

    # ------------------------------------------------------------------ after
    def report(self) -> MissionReport:
        """The report, computed from the log alone (seed 000 Tables II and III)."""
        from btmission.runtime.report import report_from_log

        if self.log_path is None:
            raise RuntimeError("this session writes no log (give log_dir or log_path)")
        if self.log is not None:
            self.log.close()  # everything is flushed; nothing more is written after the end
        return report_from_log(self.log_path)

    @property
    def exit_code(self) -> int:
        """0 every task done; 1 tasks left open, failed or still to arrive; 130 / 143 ended by
        a signal (also when it was stopped while being built)."""
        reason = self.result.reason if self.result is not None else self.stopped_while_building
        if reason in EXIT_CODES:
            return EXIT_CODES[reason]
        if self.result is None:
            return 1
        return 1 if self.result.open or self.result.pending else 0

    # ------------------------------------------------------------------ helpers
    def _write(self, event: Event) -> None:
        if self.log is not None:
            self.log.on_event(event)

    def _drop_log(self) -> None:
        if self.log is not None:
            self.log.close()
            self.log = None
        if self.log_path is not None:
            self.log_path.unlink(missing_ok=True)
            self.log_path = None
