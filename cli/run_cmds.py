"""``btmission run`` (a mission, in the embedded simulator by default) and ``btmission report``
(from its log)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from btmission.cli.common import (
    POSITIVE,
    SEED,
    BadInput,
    ChecksFailed,
    FiniteFloat,
    echo_diagnostics,
    handle_spec_errors,
    internal_error_sink,
    output_target,
)
from btmission.cli.console_cmds import token_for_run
from btmission.cli.view_cmds import (
    announce_server,
    require_viz,
    serve_until_stopped,
    tls_files,
    viewer_options,
    viewer_port,
)
from btmission.vehicles.provider import VehicleUnavailable

if TYPE_CHECKING:
    from btmission.runtime.events import Event


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
@click.option(
    "--realtime", is_flag=True, help="Pace the run to the wall clock (one step per step_s)."
)
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
@click.option(
    "--yes",
    "-y",
    is_flag=True,
    help="Fly MAVLink vehicles that are not on this machine (a serial port, another host) "
    "without asking first.",
)
@click.option(
    "--mavlink-key-file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="MAVLink 2 signing key of the vehicles (64 hex digits or a passphrase); also "
    "BTMISSION_MAVLINK_KEY_FILE or BTMISSION_MAVLINK_KEY. Never put it in the mission.",
)
@click.option(
    "--view",
    is_flag=True,
    help="Watch the run live in the browser: serves the viewer (3D mine, agents, trees, tasks) "
    "on --host (127.0.0.1) and prints its URL; paces the run to real time unless --speed says "
    "otherwise.",
)
@click.option(
    "--console",
    is_flag=True,
    help="As --view, and the page becomes the operator console: add tasks by clicking the map, "
    "cancel or reprioritise them, recall or exclude agents, pause allocation (docs/operator.md). "
    "Commands need the run's token, printed with the URL; btmission task / status / fleet use "
    "the same console from scripts.",
)
@click.option(
    "--token-file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="The console's token: the first line of this file (default: BTMISSION_TOKEN, else a "
    "new one for each run).",
)
@viewer_options
@click.option(
    "--speed",
    type=FiniteFloat(min=0, max=1e6),
    default=None,
    help="Pace the simulator this many times faster than real time (implies --realtime; 0: as "
    "fast as the machine allows, also with --view).",
)
@click.option(
    "--processes",
    is_flag=True,
    help="Run the coordinator and each agent in its own process on this machine, linked by "
    "Zenoh on 127.0.0.1, their vehicles served by one btmission mavsim (docs/distributed.md); "
    "their logs are merged into one in --log.",
)
@click.option(
    "--listen",
    help="With --processes: the coordinator's Zenoh endpoint [default: a free port, "
    "tcp/127.0.0.1:PORT].",
)
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
    yes: bool,
    mavlink_key_file: Path | None,
    view: bool,
    console: bool,
    token_file: Path | None,
    host: str,
    port: int | None,
    tls_cert: Path | None,
    tls_key: Path | None,
    speed: float | None,
    processes: bool,
    listen: str | None,
) -> None:
    """Run a mission and print its report.

    Each agent's vehicle comes from the provider its backend: URL names (sim: the embedded
    simulator; fake: kinematic test vehicles; mavlink+udp:// ...: PX4 or ArduPilot vehicles,
    asked for confirmation unless they are on this machine or --yes is given; when the run
    stops, a vehicle still flying is told to HOLD, then LAND). Every agent ticks its mission tree (seed 000
    Fig. 7), bids in the auction with D*+ path costs and flies (or drives) with NMPC + APF; the
    coordinator allocates tasks as they arrive. Ctrl-C or SIGTERM stops after the current step
    (again: at once), and the log still ends properly.
    Every event goes to an append-only JSON Lines log in --log; at the end the report (seed 000
    Tables II and III) is computed from that log and a timeline and a top view are drawn.

    \b
    Example:
      btmission run missions/mine_inspection.yaml --controller track --log runs
      btmission report --latest runs

    --view serves the live viewer (docs/viewer.md) while the run goes: closing the browser never
    touches the run; when the run has ended the page stays up, on a terminal, until Ctrl-C
    (btmission view LOG replays it later).

    \b
    Watch it live, 5 times faster than real time:
      btmission run missions/mine_inspection.yaml --controller track --view --speed 5

    --processes spreads it over processes (the coordinator, one per agent, mavsim for the
    vehicles) as on a real fleet; --speed then sets the vehicles' speed-up:

    
      btmission run docs/examples/processes_small.yaml --processes --speed 10

    Exit status: 0 every task done, 1 tasks left open, failed or still to arrive, 2 bad
    mission file, 130 interrupted (Ctrl-C), 143 terminated (SIGTERM): the log and the report
    cover what happened so far.
    """
    from btmission.runtime.session import EXIT_CODES, RunSession, RunStopped

    if listen is not None and not processes:
        raise click.UsageError("--listen is the coordinator's: add --processes")
    if processes:
        if view or console or until is not None or realtime or mavlink_key_file is not None:
            raise click.UsageError(
                "--processes runs on the wall clock, without --view, --console, --until, "
                "--realtime or --mavlink-key-file"
            )
        from btmission.cli.process_cmds import run_processes

        code = run_processes(
            mission_file, log_dir=log_dir, seed=seed, controller=controller, speed=speed,
            quiet=quiet, no_png=no_png, listen=listen,
        )  # fmt: skip
        if code:
            sys.exit(code)
        return
    view = view or console
    tls = tls_files(tls_cert, tls_key)
    if not view and (port is not None or host != "127.0.0.1" or tls is not None):
        raise click.UsageError("--host, --port and --tls-* are the viewer's: add --view")
    if token_file is not None and not console:
        raise click.UsageError("--token-file is the console's: add --console")
    live: LiveView | None = None
    if view:
        require_viz()
        token = token_for_run(token_file) if console else None
        live = LiveView(host, port, console=console, token=token, tls=tls)
    paced = realtime or bool(speed) or (view and speed is None)

    def note(text: str) -> None:
        click.echo(f"\n{text}", err=True)

    session = RunSession(
        mission_file,
        seed=seed,
        controller=controller,
        realtime=paced,
        speed=speed or 1.0,
        log_dir=log_dir,
        observers=[_StderrNotes(), *([live.observer] if live is not None else [])],
        handle_signals=True,
        notify=note,
    )
    if mavlink_key_file is not None:
        from btmission.backends.mavlink_signing import KEY_FILE_ENV, SigningKeyError, load_key

        try:
            load_key(mavlink_key_file)
        except SigningKeyError as exc:
            raise BadInput(str(exc)) from None
        os.environ[KEY_FILE_ENV] = str(mavlink_key_file)  # read by the MAVLink provider
    try:
        with session:
            code = _run(session, until, quiet, no_png, yes, live)
    except RunStopped as stop:  # before the log existed, or after the run had ended
        if session.ended and session.log_path is not None:
            click.echo(f"{stop.reason}; the log is complete: {session.log_path}", err=True)
        else:
            click.echo(f"{stop.reason} before the run started: nothing was run", err=True)
        code = stop.code
    finally:
        if live is not None:  # the page stays up after a run that ended by itself, on a
            signalled = session.exit_code in EXIT_CODES.values()  # terminal; not after Ctrl-C
            live.finish(linger=sys.stdin.isatty() and sys.stderr.isatty() and not signalled)
    if code:
        sys.exit(code)


class LiveView:
    """``run --view``: a :class:`~btmission.viz.live.LiveViewer` (its port taken before anything
    runs), what it prints, and the page kept up after the run on a terminal."""

    def __init__(
        self,
        host: str,
        port: int | None,
        *,
        console: bool = False,
        token: str | None = None,
        tls: tuple[str, str] | None = None,
    ) -> None:
        from btmission.viz.live import LiveViewer
        from btmission.viz.server import ViewerError

        self.host = host
        self.console = console
        self.tls = tls
        first, tries = viewer_port(port)
        try:
            self.viewer = LiveViewer(
                host,
                first,
                port_tries=tries,
                console=console,
                token=token,
                tls=tls,
            )
        except ViewerError as exc:
            raise BadInput(str(exc)) from None
        self.observer = self.viewer.observer

    def serve(self, session: Any, run: Any) -> None:
        """Start serving the run (its map is built)."""
        self.viewer.attach(session, run)
        announce_server(
            self.viewer.server.console_url, self.host, console=self.console, tls=bool(self.tls)
        )

    def finish(self, *, linger: bool) -> None:
        """The run has ended: every event to the page; on a terminal, keep the page up until
        Ctrl-C; then close the server."""
        self.viewer.finish()
        if linger and self.viewer.serving:
            serve_until_stopped(self.viewer.server, "the run has ended; the viewer still shows it")
        else:
            self.viewer.close()


class _StderrNotes:
    """An observer printing a run's warnings and leaf errors on stderr, each once (the log
    has every occurrence's details, the traceback of a leaf error too); and what happens to a
    vehicle that the operator must see at once: its link lost and back, its autopilot taking it
    over (up to :data:`LINK_NOTES` link changes per agent, then only in the log)."""

    LINK_NOTES = 10

    def __init__(self) -> None:
        from btmission.runtime.eventkinds import (
            CoordinatorLinkEvent,
            LeafErrorEvent,
            TakenOverEvent,
            VehicleLinkEvent,
            WarningEvent,
        )

        self._seen: set[str] = set()
        self._kinds = (
            LeafErrorEvent.KIND,
            WarningEvent.KIND,
            VehicleLinkEvent.KIND,
            TakenOverEvent.KIND,
            CoordinatorLinkEvent.KIND,
        )
        self._lost_at: dict[str, float] = {}
        self._link_notes: dict[str, int] = {}

    def on_event(self, ev: Event) -> None:
        if ev.kind not in self._kinds:
            return  # (first: this observer sees every event of the run, poses too)
        from btmission.runtime.eventkinds import (
            CoordinatorLinkEvent,
            LeafErrorEvent,
            TakenOverEvent,
            VehicleLinkEvent,
            WarningEvent,
        )

        typed = ev.typed_or_none()
        if isinstance(typed, LeafErrorEvent):
            line = (
                f"warning: agent {typed.agent}: {typed.leaf} raised {typed.error}: "
                f"{typed.message} (it failed; traceback in the log)"
            )
            key = f"{typed.leaf}|{typed.error}|{typed.message}"
        elif isinstance(typed, WarningEvent):
            line = f"warning: {typed.message}"
            key = line
        elif isinstance(typed, VehicleLinkEvent):
            self._link(typed, ev.t)
            return
        elif isinstance(typed, CoordinatorLinkEvent):
            self._coordinator(typed, ev.t)
            return
        elif isinstance(typed, TakenOverEvent):
            who = "its autopilot's failsafe" if typed.failsafe else "its autopilot or pilot"
            then = (
                "it stands down"
                + (f" and {typed.task} goes back to the pool" if typed.task else "")
                + " (the console's include brings it back)"
                if typed.final
                else "its tree flies on (takeover_is_final: false)"
            )
            click.echo(
                f"warning: {typed.agent}: {who} switched the vehicle to {typed.mode} at "
                f"t={ev.t:.1f} s: {then}",
                err=True,
            )
            return
        else:
            return
        if key not in self._seen:
            self._seen.add(key)
            click.echo(line, err=True)

    def _coordinator(self, ev: Any, t: float) -> None:
        """``coordinator lost`` / ``regained``, counted with the vehicle link's notes."""
        agent = ev.agent
        key = f"coordinator:{agent}"
        n = self._link_notes[key] = self._link_notes.get(key, 0) + 1
        if n > self.LINK_NOTES:
            return
        if ev.up:
            line = f"{agent}: coordinator regained at t={t:.1f} s after {ev.silent_s:.1f} s"
        else:
            line = (
                f"warning: {agent}: coordinator lost at t={t:.1f} s (not heard for "
                f"{ev.silent_s:.1f} s): it keeps its task within its lease"
            )
        if n == self.LINK_NOTES:
            line += f" (further coordinator link changes of {agent} only in the log)"
        click.echo(line, err=True)

    def _link(self, ev: Any, t: float) -> None:
        agent = ev.agent
        n = self._link_notes[agent] = self._link_notes.get(agent, 0) + 1
        if not ev.up:
            self._lost_at[agent] = t
        if n > self.LINK_NOTES:
            return
        if ev.up:
            lost = self._lost_at.pop(agent, None)
            after = f" after {t - lost:.1f} s" if lost is not None else ""
            mode = f" in {ev.mode}" if ev.mode else ""
            line = f"{agent}: vehicle link back at t={t:.1f} s{after}{mode}"
        else:
            line = (
                f"warning: {agent}: vehicle link lost at t={t:.1f} s (its autopilot is not "
                "heard): its tree waits for it"
            )
        if n == self.LINK_NOTES:
            line += f" (further link changes of {agent} only in the log)"
        click.echo(line, err=True)


def _confirm_real_vehicles(mission: Any, yes: bool) -> None:
    """Ask before flying MAVLink vehicles that may be real: on a serial port or another host
    (loopback is SITL or mavsim). Without a terminal to ask, --yes is required."""
    from btmission.backends.mavlink_url import parse_mavlink_url

    remote = []
    for agent in mission.agents:
        if agent.vehicle.scheme != "mavlink":
            continue
        address = parse_mavlink_url(agent.backend)
        if address.transport == "serial" or not address.host.startswith("127."):
            remote.append(f"{agent.id} ({agent.backend})")
    if not remote or yes:
        return
    what = f"{len(remote)} MAVLink vehicle(s) that may be real: " + ", ".join(remote)
    if not sys.stdin.isatty():
        raise BadInput(f"this mission flies {what}; add --yes to fly them without asking")
    if not click.confirm(f"Fly {what}?", default=False, err=True):
        raise click.Abort()


def _run(
    session: Any, until: float | None, quiet: bool, no_png: bool, yes: bool, live: LiveView | None
) -> int:
    """The run command's body (a :class:`~btmission.runtime.session.RunSession` does the
    work; this prints); returns the exit status."""
    from btmission.runtime.report import format_report, format_warnings

    with internal_error_sink(session.record_internal_error):
        mission = session.load()
        echo_diagnostics(session.warnings)
        _confirm_real_vehicles(mission, yes)
        try:
            run = session.start()
        except VehicleUnavailable as exc:  # nothing answers at an agent's backend URL
            raise ChecksFailed(f"{exc}; nothing was run") from None
        if run is not None and live is not None:
            live.serve(session, run)
        if run is not None:
            if not quiet:
                click.echo(
                    f"running {mission.name}: {len(mission.agents)} agent(s), "
                    f"{len(mission.tasks)} task(s), controller {run.controller}, seed "
                    f"{session.seed}; log {session.log_path}",
                    err=True,
                )
            if quiet:
                session.run(until)
            else:
                with _ProgressDisplay(run, until) as display:
                    session.run(until, progress=display)
        else:
            click.echo(
                f"{session.stopped_while_building} while building the run "
                f"({session.build_s:.1f} s)",
                err=True,
            )
    result = session.result
    log_path = session.log_path
    rep = session.report()  # the report comes from the log alone
    if not quiet and result is not None:
        click.echo(
            f"{result.reason}: {result.time_s:.1f} s simulated in {result.wall_s:.1f} s "
            f"({result.speedup:.0f}× real time)",
            err=True,
        )
    click.echo(f"log: {log_path}", err=True)
    if not no_png and result is not None and result.reason != "terminated":  # SIGTERM: be quick
        try:
            pngs = _write_pngs(rep, log_path.parent, log_path.stem)
        except Exception as exc:  # a figure must never hide the report
            click.echo(f"note: could not draw the PNGs ({exc})", err=True)
        else:
            for p in pngs:
                click.echo(f"wrote {p}", err=True)
    for w in format_warnings(rep, incidents=False):  # the incidents were shown as they came
        click.echo(w, err=True)
    click.echo(format_report(rep))
    return int(session.exit_code)


class _ProgressDisplay:
    """The live line while the run goes: mission time, task counts, D*+ searches (rich); the
    run calls it every second of mission time and it reads the run's snapshot."""

    def __init__(self, run: Any, until: float | None) -> None:
        self.run = run
        self.limit = until if until is not None else run.mission.spec.runtime.max_duration_s

    def __call__(self, run: Any) -> None:
        snap = run.snapshot
        counts = "  ".join(f"{k} {v}" for k, v in sorted(snap.counts().items()))
        self._progress.update(self._bar, completed=snap.time_s, counts=counts)

    def __enter__(self) -> _ProgressDisplay:
        from rich.console import Console
        from rich.progress import BarColumn, Progress, ProgressColumn, TextColumn, TimeElapsedColumn
        from rich.text import Text

        run = self.run

        class Searches(ProgressColumn):
            """D*+ searches so far, read live by the display's own refresh: it moves even while
            one long step (the first auction of a large mission) holds the loop."""

            def render(self, task: Any) -> Text:
                return Text(f"D*+ {getattr(run.paths, 'searches', 0):,}", style="dim")

        self._progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            TextColumn("t = {task.completed:>6.1f} s"),
            TextColumn("{task.fields[counts]}"),
            Searches(),
            TimeElapsedColumn(),
            console=Console(stderr=True),
            transient=True,
        )
        self._progress.__enter__()
        self._bar = self._progress.add_task(run.mission.name, total=self.limit, counts="")
        return self

    def __exit__(self, *exc: object) -> None:
        self._progress.__exit__(None, None, None)


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
@click.option(
    "--merge",
    is_flag=True,
    help="The logs are one run spread over processes: the coordinator's first, then its agent "
    "processes' (btmission coordinator / agent); one report of them merged.",
)
def report_cmd(
    log_files: tuple[Path, ...],
    latest_dir: Path | None,
    png_dir: Path | None,
    as_json: bool,
    merge: bool,
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
    if merge:
        from btmission.runtime.report import merge_log_files

        try:
            reports.append((paths[0], merge_log_files(paths[0], paths[1:])))
        except LogError as exc:
            raise BadInput(str(exc)) from None
    for path in [] if merge else paths:  # read them all first: a bad one is reported first
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
