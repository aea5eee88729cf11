"""``btmission run`` (a mission in the embedded simulator) and ``btmission report`` (from its log)."""

from __future__ import annotations

import json
import signal
import sys
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
    output_target,
)
from btmission.diagnostics import Severity, SpecError, errors

EXIT_INTERRUPTED = 130


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
      btmission report runs/mine_inspection-*.jsonl

    Exit status: 0 every task done, 1 tasks left open or failed, 2 bad mission file,
    130 interrupted (Ctrl-C: the log and the report cover what happened so far).
    """
    from btmission.runtime.events import JsonlEventLog
    from btmission.runtime.report import format_report, report_from_log
    from btmission.runtime.runner import MissionRun
    from btmission.spec.mission import load_mission
    from btmission.world.checks import check_mission_world

    mission = load_mission(mission_file)
    map_diags = check_mission_world(mission)
    if errors(map_diags):
        raise SpecError(
            errors(map_diags) + [d for d in map_diags if d.severity is not Severity.ERROR]
        )
    echo_diagnostics([d for d in mission.diagnostics + map_diags if d.severity is Severity.WARNING])
    log_path = _log_path(log_dir, mission.name, seed)
    log = JsonlEventLog(log_path)
    try:
        run = MissionRun(
            mission, seed=seed, controller=controller, observers=[log], realtime=realtime
        )
    except SpecError:
        log.close()
        log_path.unlink(missing_ok=True)
        raise
    if not quiet:
        click.echo(
            f"running {mission.name}: {len(mission.agents)} agent(s), {len(mission.tasks)} task(s), "
            f"controller {run.controller}, seed {seed}; log {log_path}",
            err=True,
        )

    def on_sigint(signum: int, frame: FrameType | None) -> None:
        run.stop("interrupted")

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        result = _run_with_progress(run, until, quiet)
        run.end(result)
    finally:
        signal.signal(signal.SIGINT, previous)
        log.close()
    rep = report_from_log(log_path)  # the report comes from the log alone
    if not quiet:
        click.echo(
            f"{result.reason}: {result.time_s:.1f} s simulated in {result.wall_s:.1f} s "
            f"({result.speedup:.0f}× real time)",
            err=True,
        )
    click.echo(f"log: {log_path}", err=True)
    if not no_png:
        try:
            pngs = _write_pngs(rep, log_dir, log_path.stem)
        except Exception as exc:  # a figure must never hide the report
            click.echo(f"note: could not draw the PNGs ({exc})", err=True)
        else:
            for p in pngs:
                click.echo(f"wrote {p}", err=True)
    click.echo(format_report(rep))
    if result.reason == "interrupted":
        sys.exit(EXIT_INTERRUPTED)
    if result.open:
        sys.exit(1)


def _run_with_progress(run: Any, until: float | None, quiet: bool) -> Any:
    """Run with a live line: mission time, speed, and task counts (rich)."""
    if quiet:
        return run.run(until)
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    limit = until if until is not None else run.mission.spec.runtime.max_duration_s
    console = Console(stderr=True)
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("t = {task.completed:>6.1f} s"),
        TextColumn("{task.fields[counts]}"),
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
@click.argument("log_file", metavar="LOG", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--png",
    "png_dir",
    type=click.Path(file_okay=False, path_type=Path),
    callback=output_target("dir"),
    help="Also draw the timeline and top view as PNG into this directory.",
)
@click.option("--json", "as_json", is_flag=True, help="Print Tables II and III as JSON.")
def report_cmd(log_file: Path, png_dir: Path | None, as_json: bool) -> None:
    """Print the report of a run from its event log (seed 000 Tables III and II).

    The report is computed from the log alone, so a log cut short (the run was killed) still
    gives the report of what happened until then.

    \b
    Example:
      btmission report docs/examples/pick_and_deliver.jsonl --png plots
    """
    from btmission.runtime.events import LogError
    from btmission.runtime.report import format_report, report_from_log, report_json

    try:
        rep = report_from_log(log_file)
    except LogError as exc:
        raise BadInput(str(exc)) from None
    if as_json:
        click.echo(json.dumps(report_json(rep), indent=2, default=str))
    else:
        click.echo(format_report(rep))
    if png_dir is not None:
        for p in _write_pngs(rep, png_dir, log_file.stem):
            click.echo(f"wrote {p}", err=True)
