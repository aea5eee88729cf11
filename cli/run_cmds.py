"""``btmission run`` (a mission in the embedded simulator) and ``btmission report`` (from its log)."""

from __future__ import annotations

import json
import signal
import sys
import threading
from datetime import datetime
from pathlib import Path
from types import FrameType
from typing import Any

import click

from btmission.cli.common import (
    POSITIVE,
    SEED,
    BadInput,
    echo_diagnostics,
    handle_spec_errors,
    internal_error_sink,
    output_target,
)
from btmission.diagnostics import Severity, SpecError, errors

EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143
"""Exit status of a run ended by SIGTERM (128 + 15, as a shell reports it)."""


def _log_path(directory: Path, mission: str, seed: int) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    path = directory / f"{mission}-{stamp}-seed{seed}.jsonl"
    n = 1
    while path.exists():
        n += 1
        path = directory / f"{mission}-{stamp}-seed{seed}-{n}.jsonl"
    return path


def _write_pngs(rep: Any, directory: Path, stem: str) -> list[Path]:
    from btmission.runtime.report import dispatch_png, timeline_png, topview_png

    directory.mkdir(parents=True, exist_ok=True)
    out = [
        timeline_png(rep, directory / f"{stem}-timeline.png"),
        topview_png(rep, directory / f"{stem}-topview.png"),
    ]
    if rep.dispatched:  # trucks dispatched by the GA: their schedule (seed 004 Fig. 3)
        out.append(dispatch_png(rep, directory / f"{stem}-dispatch.png"))
    return out


@click.command("run")
@click.argument("mission_file", metavar="MISSION", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--seed",
    default=0,
    show_default=True,
    type=SEED,
    help="Simulator seed (noise, dust, detections).",
)
@click.option("--realtime", is_flag=True, help="Pace the simulation to the wall clock.")
@click.option(
    "--until",
    type=POSITIVE,
    help="Stop at this mission time (s) even if the mission has not ended.",
)
@click.option(
    "--log",
    "log_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("runs"),
    callback=output_target("dir"),
    show_default=True,
    help="Directory for the event log (JSON Lines) and the report's PNGs.",
)
@click.option("--quiet", is_flag=True, help="No progress display; print only the report.")
@click.option(
    "--controller",
    type=click.Choice(["nmpc", "track"]),
    help="Path following: nmpc (the seed 002/003 NMPC) or track (lightweight); default: the "
    "mission's runtime.controller.",
)
@click.option("--no-png", is_flag=True, help="Do not draw the timeline and top-view PNGs.")
@handle_spec_errors
def run_cmd(
    mission_file: Path,
    seed: int,
    realtime: bool,
    until: float | None,
    log_dir: Path,
    quiet: bool,
    controller: str | None,
    no_png: bool,
) -> None:
    """Run a mission in the embedded simulator and print its report.

    Every agent ticks its mission tree (seed 000 Fig. 7), bids in the auction with D*+ path
    costs and flies (or drives) with NMPC + APF; the coordinator allocates tasks as they arrive.
    Every event goes to an append-only JSON Lines log in --log; at the end the report (seed 000
    Tables II and III) is computed from that log and a timeline and a top view are drawn.

    \b
    Example:
      btmission run missions/mine_inspection.yaml --controller track --log runs
      btmission report --latest runs

    Exit status: 0 every task done, 1 tasks left open, failed or still to arrive, 2 bad
    mission file, 130 interrupted (Ctrl-C), 143 terminated (SIGTERM): the log and the report
    cover what happened so far.
    """
    signals = _Signals()
    with signals:
        try:
            code = _run(
                signals, mission_file, seed, realtime, until, log_dir, quiet, controller, no_png
            )
        except _Stopped as stop:  # before the log existed, or after the run had ended
            if signals.log is None:
                click.echo(f"{stop.reason} before the run started: nothing was run", err=True)
            else:
                click.echo(f"{stop.reason}; the log is complete: {signals.log}", err=True)
            code = stop.code
    if code:
        sys.exit(code)


_STOPS = {"interrupted": EXIT_INTERRUPTED, "terminated": EXIT_TERMINATED}


class _Stopped(BaseException):
    """Ctrl-C or SIGTERM while there was no run loop to take it (building, reporting)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason
        self.code = _STOPS[reason]


class _Signals:
    """SIGINT (Ctrl-C) and SIGTERM for the whole command: while the run loop runs, the first asks
    it to stop after the current step (the log gets its ``end`` event, the report is printed) and
    a second stops it at once, mid-step (a first step of a very large mission can take minutes);
    before the loop exists (loading, building) or after it has ended, they raise
    :class:`_Stopped`."""

    def __init__(self) -> None:
        self.run: Any = None
        self.log: Path | None = None
        """The run's log, once it is complete."""
        self.asked = False
        """A stop was asked of the run loop (a second signal stops at once)."""
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> _Signals:
        if threading.current_thread() is threading.main_thread():  # (only there can they be set)
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        reason = "terminated" if signum == signal.SIGTERM else "interrupted"
        if isinstance(self.run, _Ignore):
            return
        if self.run is None or self.asked:  # a second one: the current step may be a long one
            raise _Stopped(reason)
        self.asked = True
        self.run.stop(reason)
        sys.stderr.write(f"\n{reason}: stopping after the current step (again to stop at once)\n")

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


class _Ignore:
    """Takes the place of the run while the end event is written."""

    def stop(self, reason: str) -> None:
        pass


class _StderrNotes:
    """An observer printing a run's warnings and leaf errors on stderr, each once (the log
    has every occurrence's details, the traceback of a leaf error too)."""

    def __init__(self) -> None:
        self._seen: set[str] = set()

    def on_event(self, ev: Any) -> None:
        if ev.kind == "leaf_error":
            line = (
                f"warning: agent {ev.get('agent')}: {ev.get('leaf')} raised {ev.get('error')}: "
                f"{ev.get('message')} (it failed; traceback in the log)"
            )
            key = f"{ev.get('leaf')}|{ev.get('error')}|{ev.get('message')}"
        elif ev.kind == "warning":
            line = f"warning: {ev.get('message')}"
            key = line
        else:
            return
        if key not in self._seen:
            self._seen.add(key)
            click.echo(line, err=True)


def _run(
    signals: _Signals,
    mission_file: Path,
    seed: int,
    realtime: bool,
    until: float | None,
    log_dir: Path,
    quiet: bool,
    controller: str | None,
    no_png: bool,
) -> int:
    """The run command's body; returns the exit status."""
    import time

    from btmission.runtime.events import Event, JsonlEventLog
    from btmission.runtime.report import format_report, format_warnings, report_from_log
    from btmission.runtime.runner import MissionRun
    from btmission.spec.mission import load_mission
    from btmission.world.checks import check_mission_world

    mission = load_mission(mission_file)
    map_diags = check_mission_world(mission)
    if errors(map_diags):
        raise SpecError(
            errors(map_diags) + [d for d in map_diags if d.severity is Severity.WARNING]
        )
    echo_diagnostics([d for d in mission.diagnostics + map_diags if d.severity is Severity.WARNING])
    log_path = _log_path(log_dir, mission.name, seed)
    log = JsonlEventLog(log_path)
    run: Any = None
    wall0 = time.perf_counter()

    def on_internal_error(exc: BaseException, trace: str) -> str | None:
        """A bug (ours or a plugin's) ends the run: its traceback and the end go into the log."""
        if log.count == 0:  # not even the header: the crash file alone tells
            return None
        info = {"type": type(exc).__name__, "message": str(exc), "traceback": trace}
        log.on_event(Event(run.now() if run is not None else 0.0, "internal_error", info))
        if run is not None:
            run.end(run.result("internal error"))
        else:
            wall_s = time.perf_counter() - wall0
            log.on_event(MissionRun.end_before_build(mission, "internal error", wall_s))
        return str(log_path)

    try:
        with internal_error_sink(on_internal_error):
            try:
                run = MissionRun(
                    mission,
                    seed=seed,
                    controller=controller,
                    observers=[log, _StderrNotes()],
                    realtime=realtime,
                )
            except SpecError:
                log.close()
                log_path.unlink(missing_ok=True)
                raise
            signals.run = run
            if not quiet:
                click.echo(
                    f"running {mission.name}: {len(mission.agents)} agent(s), "
                    f"{len(mission.tasks)} task(s), controller {run.controller}, seed {seed}; "
                    f"log {log_path}",
                    err=True,
                )
            result = _run_with_progress(run, until, quiet)
            run.end(result)
    except _Stopped as stop:  # a signal while the run was being built, or a second one mid-step
        signals.run = _Ignore()  # a second one must not cut the end event short
        if run is not None:
            result = run.result(stop.reason)
            run.end(result)
        else:
            result = None
            if log.count == 0:  # not even the header: nothing to report
                log.close()
                log_path.unlink(missing_ok=True)
                raise
            wall_s = time.perf_counter() - wall0
            log.on_event(MissionRun.end_before_build(mission, stop.reason, wall_s))
            click.echo(f"{stop.reason} while building the run ({wall_s:.1f} s)", err=True)
    finally:
        log.close()
        signals.run = None  # from here a signal stops the command at once (the log is whole)
    signals.log = log_path
    rep = report_from_log(log_path)  # the report comes from the log alone
    if not quiet and result is not None:
        click.echo(
            f"{result.reason}: {result.time_s:.1f} s simulated in {result.wall_s:.1f} s "
            f"({result.speedup:.0f}× real time)",
            err=True,
        )
    click.echo(f"log: {log_path}", err=True)
    reason = result.reason if result is not None else rep.summary.end
    if not no_png and result is not None and reason != "terminated":  # SIGTERM: end promptly
        try:
            pngs = _write_pngs(rep, log_dir, log_path.stem)
        except Exception as exc:  # a figure must never hide the report
            click.echo(f"note: could not draw the PNGs ({exc})", err=True)
        else:
            for p in pngs:
                click.echo(f"wrote {p}", err=True)
    for w in format_warnings(rep, incidents=False):  # the incidents were shown as they came
        click.echo(w, err=True)
    click.echo(format_report(rep))
    if reason in _STOPS:
        return _STOPS[reason]
    return 1 if result is not None and (result.open or result.pending) else 0


def _run_with_progress(run: Any, until: float | None, quiet: bool) -> Any:
    """Run with a live line: mission time, speed, and task counts (rich)."""
    if quiet:
        return run.run(until)
    from rich.console import Console
    from rich.progress import BarColumn, Progress, ProgressColumn, TextColumn, TimeElapsedColumn
    from rich.text import Text

    class Searches(ProgressColumn):
        """D*+ searches so far, read live by the display's own refresh: it moves even while one
        long step (the first auction of a large mission) holds the loop."""

        def render(self, task: Any) -> Text:
            return Text(f"D*+ {getattr(run.paths, 'searches', 0):,}", style="dim")

    limit = until if until is not None else run.mission.spec.runtime.max_duration_s
    console = Console(stderr=True)
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("t = {task.completed:>6.1f} s"),
        TextColumn("{task.fields[counts]}"),
        Searches(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as progress:
        bar = progress.add_task(run.mission.name, total=limit, counts="")

        def update(r: Any) -> None:
            states: dict[str, int] = {}
            for t in r.coordinator.state.pool:
                if t.info.arrival_s <= r.now():
                    states[t.state.value] = states.get(t.state.value, 0) + 1
            counts = "  ".join(f"{k} {v}" for k, v in sorted(states.items()))
            progress.update(bar, completed=r.now(), counts=counts)

        return run.run(until, progress=update)


@click.command("report")
@click.argument(
    "log_files", metavar="[LOG]...", nargs=-1, type=click.Path(dir_okay=False, path_type=Path)
)
@click.option(
    "--latest",
    "latest_dir",
    type=click.Path(file_okay=False, path_type=Path),
    help="Report the newest log (*.jsonl) in this directory (e.g. runs).",
)
@click.option(
    "--png",
    "png_dir",
    type=click.Path(file_okay=False, path_type=Path),
    callback=output_target("dir"),
    help="Also draw the timeline and top view as PNG into this directory.",
)
@click.option("--json", "as_json", is_flag=True, help="Print Tables II and III as JSON.")
def report_cmd(
    log_files: tuple[Path, ...], latest_dir: Path | None, png_dir: Path | None, as_json: bool
) -> None:
    """Print the report of a run from its event log (seed 000 Tables III and II).

    The report is computed from the log alone, so a log cut short (the run was killed) still
    gives the report of what happened until then. Several logs give one report each (in the
    order given); --latest DIR picks the newest log in DIR. Warnings (a log cut off, unreadable
    lines) go to stderr.

    \b
    Example:
      btmission report docs/examples/pick_and_deliver.jsonl --png plots
      btmission report --latest runs

    Exit status: 0 reported, 2 not a log (or no log in the --latest directory).
    """
    from btmission.runtime.events import LogError
    from btmission.runtime.report import (
        format_report,
        format_warnings,
        report_from_log,
        report_json,
    )

    paths = list(log_files)
    if latest_dir is not None:
        paths.append(latest_log(latest_dir))
    if not paths:
        raise click.UsageError("give a LOG file (or several), or --latest DIR")
    reports = []
    for path in paths:  # read them all first: a bad one is reported before any output
        try:
            reports.append((path, report_from_log(path)))
        except LogError as exc:
            raise BadInput(str(exc)) from None
    several = len(reports) > 1
    as_list: list[dict[str, Any]] = []
    for i, (path, rep) in enumerate(reports):
        for w in format_warnings(rep):
            click.echo(f"{path}: {w}" if several else w, err=True)
        if as_json:
            as_list.append({"log": str(path), **report_json(rep)} if several else report_json(rep))
        else:
            if several:
                click.echo(("\n" if i else "") + f"==> {path} <==")
            click.echo(format_report(rep))
        if png_dir is not None:
            for p in _write_pngs(rep, png_dir, path.stem):
                click.echo(f"wrote {p}", err=True)
    if as_json:
        click.echo(json.dumps(as_list if several else as_list[0], indent=2, default=str))


def latest_log(directory: Path) -> Path:
    """The newest event log (``*.jsonl``, by modification time, then name) in ``directory``."""
    if not directory.is_dir():
        raise BadInput(f"{directory}: no such directory")
    logs = [p for p in directory.glob("*.jsonl") if p.is_file()]
    if not logs:
        raise BadInput(f"{directory}: no event log (*.jsonl) in this directory")
    return max(logs, key=lambda p: (p.stat().st_mtime_ns, p.name))
