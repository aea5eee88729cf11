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
    """``--host``, ``--port`` and the TLS files of a command that serves the viewer."""
    fn = click.option(
        "--tls-key",
        type=click.Path(dir_okay=False, exists=True, path_type=Path),
        help="The TLS certificate's private key (PEM), with --tls-cert.",
    )(fn)
    fn = click.option(
        "--tls-cert",
        type=click.Path(dir_okay=False, exists=True, path_type=Path),
        help="Serve HTTPS with this certificate (PEM; with --tls-key): for --host on a network "
        "you do not trust.",
    )(fn)
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
        help="Address the viewer listens on. Anything but loopback serves the page to the "
        "network (and then every request needs the run's token).",
    )(fn)
    return fn


def tls_files(cert: Path | None, key: Path | None) -> tuple[str, str] | None:
    """(certificate, key) for the server, or None; both or neither (a usage error)."""
    if (cert is None) != (key is None):
        raise click.UsageError("--tls-cert and --tls-key go together")
    return (str(cert), str(key)) if cert is not None and key is not None else None


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


def start_server(
    source: Any, host: str, port: int | None, tls: tuple[str, str] | None = None
) -> Any:
    """Serve ``source`` on a :class:`~btmission.viz.server.ViewerServer` and print its URL. A
    port in use is :class:`BadInput`."""
    from btmission.console.api import is_loopback, new_token
    from btmission.viz.server import ViewerError, ViewerServer

    first, tries = viewer_port(port)
    token = None if is_loopback(host) else new_token()  # off loopback, every view needs it
    server = ViewerServer(source, host, first, port_tries=tries, tls=tls, token=token)
    try:
        server.start()
    except ViewerError as exc:
        raise BadInput(str(exc)) from None
    announce_server(server.console_url, host, tls=tls is not None)
    return server


def announce_server(url: str, host: str, *, console: bool = False, tls: bool = False) -> None:
    """Print the page's URL (with the token when it serves the console), and a warning when it
    is not on loopback."""
    from btmission.console.api import is_loopback

    if not is_loopback(host):
        what = "command the run" if console else "watch the run"
        plain = "" if tls else "; the traffic, token included, is not encrypted: add --tls-cert"
        click.echo(
            f"warning: the {'console' if console else 'viewer'} listens on {host}: anyone who "
            f"can reach this machine and has the token can {what}{plain}",
            err=True,
        )
    click.echo(f"{'console' if console else 'viewer'}: {url}", err=True)


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
    tls_cert: Path | None,
    tls_key: Path | None,
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
    server = start_server(source, host, port, tls_files(tls_cert, tls_key))
    serve_until_stopped(server, f"replaying {source.info.get('mission')} from {log_file}")
