"""``btmission view`` (a finished run in the browser, from its log) and what ``run --view`` shares
with it: the viewer options, starting the server, serving until Ctrl-C."""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from btmission.cli.common import BadInput, output_target, write_output

F = TypeVar("F", bound=Callable[..., Any])

NEEDS_VIZ = "the viewer needs the viz extra: pip install 'btmission[viz]' (make installs it)"


def viewer_options(fn: F) -> F:
    """``--host`` and ``--port`` of a command that serves the viewer."""
    fn = click.option(
        "--port",
        type=click.IntRange(0, 65535),
        default=None,
        help="Port of the viewer's web server (default 8470, or the next free one; 0: any "
        "free port).",
    )(fn)
    fn = click.option(
        "--host",
        default="127.0.0.1",
        show_default=True,
        help="Address the viewer listens on. Anything but loopback shows the page (read-only) "
        "to the network.",
    )(fn)
    return fn


def require_viz() -> None:
    """:class:`BadInput` (exit 2) with how to install it, when the viz extra is missing."""
    import importlib.util

    missing = [m for m in ("meshcat", "fastapi", "uvicorn") if importlib.util.find_spec(m) is None]
    if missing:
        raise BadInput(f"{NEEDS_VIZ} (missing: {', '.join(missing)})")


def viewer_port(port: int | None) -> tuple[int, int]:
    """The first port to try and how many: the one the user asked for only, else the default
    and the next free ones up to :data:`~btmission.viz.server.PORT_TRIES`."""
    from btmission.viz.server import DEFAULT_PORT, PORT_TRIES

    return (DEFAULT_PORT, PORT_TRIES) if port is None else (port, 1)


def start_server(source: Any, host: str, port: int | None) -> Any:
    """Serve ``source`` on a :class:`~btmission.viz.server.ViewerServer` and print its URL. A
    port in use is :class:`BadInput`."""
    from btmission.viz.server import ViewerError, ViewerServer

    first, tries = viewer_port(port)
    server = ViewerServer(source, host, first, port_tries=tries)
    try:
        url = server.start()
    except ViewerError as exc:
        raise BadInput(str(exc)) from None
    announce_server(url, host)
    return server


def announce_server(url: str, host: str) -> None:
    """Print the viewer's URL, and a warning when it is not on loopback."""
    if not _loopback(host):
        click.echo(
            f"warning: the viewer listens on {host}: anyone who can reach this machine can "
            "watch the run (the page is read-only)",
            err=True,
        )
    click.echo(f"viewer: {url}", err=True)


def _loopback(host: str) -> bool:
    return host in ("localhost", "::1") or host.startswith("127.")


def serve_until_stopped(server: Any, what: str) -> None:
    """Keep serving until Ctrl-C or SIGTERM, then close the server cleanly."""
    stop = threading.Event()
    previous: dict[signal.Signals, Any] = {}

    def handle(signum: int, frame: Any) -> None:
        stop.set()

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handle)
    click.echo(f"{what} at {server.url}; Ctrl-C to close the viewer", err=True)
    try:
        while not stop.wait(0.25):
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        server.close()
        click.echo("viewer closed", err=True)


@click.command("view")
@click.argument(
    "log_file", metavar="[LOG]", required=False, type=click.Path(dir_okay=False, path_type=Path)
)
@click.option(
    "--latest",
    "latest_dir",
    type=click.Path(file_okay=False, path_type=Path),
    help="Replay the newest log (*.jsonl) in this directory (e.g. runs).",
)
@viewer_options
@click.option(
    "--html",
    "html_out",
    type=click.Path(dir_okay=False, path_type=Path),
    callback=output_target("file"),
    help="Write the viewer as one self-contained HTML file (opens offline; no server) instead "
    "of serving it.",
)
def view_cmd(
    log_file: Path | None,
    latest_dir: Path | None,
    host: str,
    port: int | None,
    html_out: Path | None,
) -> None:
    """Replay a finished run in the browser, from its event log alone.

    Serves the viewer page on 127.0.0.1 (--host, --port) and prints its URL: the mine in 3D
    (meshcat), the agents with their trails and planned routes, the tasks coloured by state,
    each agent's behaviour tree with its node statuses and blackboard, the task table, a
    timeline and the events, with play/pause, speed and a time slider. The map is rebuilt from
    the log's header (a generated map, or the map file it names). Ctrl-C closes it.

    --html FILE writes the same page as one file instead (meshcat's viewer, the scene and the
    records inside: 5.4 MB for the seed 000 mission, at most about 25 MB) that opens offline, for
    reports and sharing. A log cut short (the run was killed) replays up to where it stops,
    with a note.

    \b
    Example:
      btmission run missions/mine_inspection.yaml --controller track --log runs
      btmission view --latest runs
      btmission view --latest runs --html mine_inspection.html

    Exit status: 0 closed (or written), 2 not a log, port in use, or the viz extra missing.
    """
    require_viz()
    from btmission.cli.run_cmds import latest_log
    from btmission.runtime.events import LogError
    from btmission.viz.server import log_source

    if (log_file is None) == (latest_dir is None):
        raise click.UsageError("give a LOG file, or --latest DIR")
    if latest_dir is not None:
        log_file = latest_log(latest_dir)
    assert log_file is not None

    try:
        source, notes = log_source(log_file)
    except LogError as exc:
        raise BadInput(str(exc)) from None
    for note in notes:
        click.echo(f"note: {log_file}: {note}", err=True)
    if html_out is not None:
        from btmission.viz.export import static_html

        write_output(static_html(source), html_out)
        return
    server = start_server(source, host, port)
    serve_until_stopped(server, f"replaying {source.info.get('mission')} from {log_file}")
