"""The viewer's web server: one page, its static files, the scene, the records, LiDAR scans.

A FastAPI app (:func:`create_app`) over a :class:`ViewerSource` — a live run's
:class:`~btmission.viz.feed.LiveFeed` or a finished run's log (:func:`log_source`) — served by
uvicorn on a thread of its own (:class:`ViewerServer`), so the process that runs the mission
keeps its main thread (signals, the run loop).

Routes of the viewer (read-only; the operator console's routes, which can change the run and
need its token, are in :mod:`btmission.console.api`):

==========================  ====================================================================
``GET /``                   the page (``static/index.html``)
``GET /static/…``           ``viewer.js``, ``viewer.css``, and meshcat's ``main.min.js``
``GET /api/info``           mission, mode (live/replay), agents, map bounds (JSON)
``GET /api/scene``          the static scene as packed meshcat commands (:mod:`~btmission.viz.
                            scene`)
``GET /api/stream``         Server-Sent Events: batches of records from ``?cursor=``, the agents'
                            latest poses, then ``{"complete": true}`` once the run has ended and
                            everything was sent
``GET /api/scan``           a simulated LiDAR scan in the map at ``?x=&y=&z=&yaw=`` (world
                            frame points)
==========================  ====================================================================

Every server binds 127.0.0.1 unless told otherwise (``host``); the socket is bound before the
server starts, so a port in use is a clear :class:`ViewerError`, never a traceback from a
thread. A page that goes away, or a slow one, never touches the run: the stream reads the feed
with a cursor and sends whatever is new every :data:`PUSH_S`.
"""

from __future__ import annotations

import asyncio
import errno
import json
import re
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from fastapi import FastAPI, Query, Request
from fastapi.responses import (
    FileResponse,
    HTMLResponse,
    JSONResponse,
    Response,
    StreamingResponse,
)

from btmission.console.api import READ_ONLY, Security
from btmission.console.service import Console
from btmission.errors import BtmissionError
from btmission.viz.feed import LiveFeed
from btmission.viz.scene import Scene, build_scene
from btmission.world.voxel import VoxelMap

DEFAULT_PORT = 8470
"""The viewer's default port (the next free one up to :data:`PORT_TRIES` above it is taken
when it is in use and the user did not ask for it)."""
PORT_TRIES = 20
PUSH_S = 0.1
"""How often a page's stream sends what is new (10 Hz poses)."""
BATCH = 5000
"""Records per stream message (a replay's records arrive in several)."""
DRAIN_S = 2.0
"""How long a closing server waits for its pages to get the last records of the run."""
MAX_CONNECTIONS = 128
"""Connections served at once (pages' streams included); beyond, uvicorn answers 503."""
SEND_BUFFER = 256 * 1024
"""Send buffer (bytes) of the server's connections."""
SCAN_CHANNELS = 16
SCAN_AZIMUTHS = 360
SCAN_RANGE_M = 60.0


class ViewerError(BtmissionError):
    """The viewer cannot start (the port is in use, the address cannot be bound...)."""


def static_dir() -> Path:
    return Path(str(resources.files("btmission.viz") / "static"))


def meshcat_js() -> Path:
    """meshcat's viewer bundle (three.js, its scene tree and controls) from its package."""
    import importlib.util

    spec = importlib.util.find_spec("meshcat")
    if spec is None or spec.origin is None:
        raise ViewerError("meshcat is not installed: pip install 'btmission[viz]'")
    return Path(spec.origin).parent / "viewer" / "dist" / "main.min.js"


@dataclass
class ViewerSource:
    """What a viewer shows: the mission's description (``info``), its map (the scene is built
    from it on first use) and its records (``feed``)."""

    info: dict[str, Any]
    feed: LiveFeed
    vmap: VoxelMap | None
    scene_options: dict[str, Any] = field(default_factory=dict)
    _scene_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @cached_property
    def _scene(self) -> Scene | None:
        if self.vmap is None:
            return None
        return build_scene(self.vmap, **self.scene_options)

    def scene(self) -> Scene | None:
        """The static scene (built once, on first use; None without a map)."""
        with self._scene_lock:
            return self._scene

    def full_info(self) -> dict[str, Any]:
        scene = self.scene()
        return {**self.info, "scene": scene.info if scene is not None else None}

    def scan(self, x: float, y: float, z: float, yaw: float) -> list[float]:
        """World-frame points ``[x0, y0, z0, x1, ...]`` (cm precision) a spinning LiDAR at the
        pose would measure in the map (noise-free; empty outside the map)."""
        from btmission.localization.scan import (
            LidarSensor,
            pose_matrix,
            simulate_scan,
            transform_points,
        )
        from btmission.world.voxel import MapError

        if self.vmap is None:
            return []
        sensor = LidarSensor(
            "viewer", SCAN_CHANNELS, (-30.0, 30.0), SCAN_AZIMUTHS, 0.3, SCAN_RANGE_M, 0.0
        )
        pose = pose_matrix(x, y, z, yaw)
        try:
            local = simulate_scan(self.vmap, pose, sensor, rng=None)
        except MapError:
            return []
        pts = np.round(transform_points(pose, local), 2)
        out: list[float] = pts.ravel().tolist()
        return out


def log_source(path: str | Path) -> tuple[ViewerSource, list[str]]:
    """A finished run's viewer source from its log alone (the map is rebuilt from the header's
    world), and warnings for a person (a log cut short, lines skipped, no map)."""
    from btmission.runtime.events import read_events
    from btmission.runtime.report import world_from_header
    from btmission.viz.feed import replay_records

    contents = read_events(path)
    header = contents.events[0]
    notes = []
    if contents.truncated:
        notes.append("the log's last line is cut off (the run was killed while writing it)")
    if contents.skipped:
        notes.append(f"{len(contents.skipped)} unreadable line(s) skipped")
    vmap = world_from_header(header.data)
    if vmap is None:
        notes.append("the map could not be rebuilt from the log's header: no mine surface")
    records = replay_records(contents.events)
    feed = LiveFeed.of_records(records)
    ended = any(r["ev"] == "end" for r in records)
    if not ended:
        notes.append("the log has no end event (the run is still going, or died)")
    info = mission_info(header.data, mode="replay", source=str(path))
    info["end_t"] = max((r["t"] for r in records), default=0.0)
    return ViewerSource(info, feed, vmap), notes


def mission_info(header: dict[str, Any] | Any, *, mode: str, source: str) -> dict[str, Any]:
    """What the page's title bar and agent list need, from a log header's fields."""
    h = dict(header)
    return {
        "mode": mode,
        "source": source,
        "mission": h.get("mission"),
        "description": h.get("description"),
        "agents": [
            {"id": a.get("id"), "library": a.get("library"), "start": a.get("start")}
            for a in h.get("agents") or []
        ],
        "step_s": h.get("step_s"),
    }


_SLOTS = {
    '<link rel="stylesheet" href="static/viewer.css">': "css",
    '<script src="static/meshcat.js"></script>': "meshcat",
    '<script src="static/viewer.js"></script>': "viewer",
    "/*BTM_CONFIG*/null": "config",
    "<!--BTM_TITLE-->": "title",
}
"""The places in ``static/index.html`` that :func:`page_html` fills, by name."""


def script_safe(text: str) -> str:
    """``text`` safe inside a ``<script>`` element (no ``</script>`` or ``<!--`` in it)."""
    return text.replace("</", "<\\/").replace("<!--", "<\\!--")


def page_html(config_json: str, title: str, inline: Mapping[str, str] | None = None) -> str:
    """The viewer page: ``static/index.html`` with its ``window.BTM_CONFIG`` (``config_json``,
    a JSON object), its title, and the static files named in ``inline`` (``css``, ``meshcat``,
    ``viewer``: their full elements) in place of their links. One pass: inserted text is never
    searched again."""
    parts = {
        "config": script_safe(config_json),
        "title": title.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;"),
        **(inline or {}),
    }
    template = (static_dir() / "index.html").read_text(encoding="utf-8")
    pattern = re.compile("|".join(re.escape(k) for k in _SLOTS))
    return pattern.sub(lambda m: parts.get(_SLOTS[m.group(0)], m.group(0)), template)


REPLAY_READ_ONLY = "a replay of a finished run: there is nothing to command"


def create_app(
    source: ViewerSource,
    closing: threading.Event | None = None,
    *,
    console: Console | None = None,
    security: Security | None = None,
    streams: StreamCount | None = None,
) -> FastAPI:
    """The FastAPI app of ``source`` (module docstring) with the operator console's routes
    (:mod:`btmission.console.api`; commands need ``console``) behind its guard (``security``:
    the bound host and the run's token). ``closing`` set: streams end."""
    from btmission.console.api import Guard, add_console_routes

    stop = closing if closing is not None else threading.Event()
    sec = security if security is not None else Security()
    streams = streams if streams is not None else StreamCount()
    app = FastAPI(
        title="btmission viewer and operator console",
        version=_version(),
        docs_url=None,
        redoc_url=None,
        description="The live viewer's data and the operator console of a running mission "
        "(docs/operator.md). Commands need the run's token: Authorization: Bearer <token>.",
    )
    app.add_middleware(Guard, security=sec)
    read_only = REPLAY_READ_ONLY if source.info.get("mode") == "replay" else READ_ONLY
    add_console_routes(app, console, read_only)
    files = {
        "viewer.js": (static_dir() / "viewer.js", "text/javascript"),
        "viewer.css": (static_dir() / "viewer.css", "text/css"),
        "meshcat.js": (meshcat_js(), "text/javascript"),
    }

    @app.get("/", response_class=HTMLResponse)
    def page() -> str:
        title = str(source.info.get("mission") or "btmission")
        return page_html(json.dumps({"embedded": False, "title": title}), title)

    @app.get("/static/{name}")
    def static(name: str) -> Response:
        if name not in files:
            return JSONResponse({"detail": f"no static file {name!r}"}, status_code=404)
        path, media = files[name]
        return FileResponse(path, media_type=media, headers={"Cache-Control": "no-cache"})

    @app.get("/favicon.ico")
    def favicon() -> Response:
        return Response(status_code=204)

    @app.get("/api/info")
    def info() -> dict[str, Any]:
        out = source.full_info()
        if console is not None:
            out["console"] = {**console.info(), "token_required": not sec.loopback}
        else:
            out["console"] = {"enabled": False, "reason": read_only}
        return out

    @app.get("/api/scene")
    def scene() -> Response:
        s = source.scene()
        return Response(s.packed() if s is not None else b"", media_type="application/octet-stream")

    @app.get("/api/scan")
    def scan(
        x: float = Query(..., allow_inf_nan=False),
        y: float = Query(..., allow_inf_nan=False),
        z: float = Query(..., allow_inf_nan=False),
        yaw: float = Query(0.0, allow_inf_nan=False),
    ) -> dict[str, Any]:
        t0 = time.perf_counter()
        points = source.scan(x, y, z, yaw)
        return {"points": points, "ms": round((time.perf_counter() - t0) * 1000, 1)}

    @app.get("/api/stream")
    async def stream(request: Request, cursor: int = Query(0, ge=0)) -> StreamingResponse:
        return StreamingResponse(
            _counted(_stream(source.feed, cursor, request.is_disconnected, stop), streams),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
        )

    return app


class StreamCount:
    """How many pages are being streamed to (thread-safe): the server waits for them to get
    the run's last records before it closes."""

    def __init__(self) -> None:
        self.n = 0
        self._lock = threading.Lock()

    def add(self, k: int) -> None:
        with self._lock:
            self.n += k


async def _counted(stream: AsyncIterator[str], count: StreamCount) -> AsyncIterator[str]:
    count.add(1)
    try:
        async for part in stream:
            yield part
    finally:
        count.add(-1)


async def _stream(
    feed: LiveFeed, cursor: int, disconnected: Callable[[], Any], stop: threading.Event
) -> AsyncIterator[str]:
    """The records from ``cursor`` on, in batches, every :data:`PUSH_S` (module docstring)."""
    seen = -1
    yield "retry: 1000\n\n"
    while not stop.is_set():
        records, end, latest, seen = feed.read(cursor, seen)
        for i in range(0, max(len(records), 1), BATCH):
            chunk = records[i : i + BATCH]
            last = i + BATCH >= len(records)
            if not chunk and not (last and latest):
                break
            message: dict[str, Any] = {"records": chunk, "cursor": cursor + i + len(chunk)}
            if last and latest:
                message["latest"] = latest
            yield f"id: {message['cursor']}\ndata: {json.dumps(message, separators=(',', ':'))}\n\n"
        cursor = end
        if feed.complete(cursor):
            yield 'event: complete\ndata: {"complete":true}\n\n'
            return
        if await disconnected():
            return
        await asyncio.sleep(PUSH_S)


def _version() -> str:
    from btmission import __version__

    return str(__version__)


def bind_socket(host: str, port: int, *, tries: int = 1) -> socket.socket:
    """A listening TCP socket on ``host``:``port`` (0: any free port), trying the next
    ``tries - 1`` ports when one is in use. :class:`ViewerError` when none can be bound."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    last: OSError | None = None
    for p in range(port, port + max(tries, 1)) if port else [0]:
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            # connections inherit a bounded send buffer: a page that reads slowly holds the
            # stream back (it then gets bigger batches later), instead of the kernel queueing
            # megabytes of records for it
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
            sock.bind((host, p))
            sock.listen(64)
            sock.setblocking(False)
            return sock
        except OSError as exc:
            sock.close()
            last = exc
            if exc.errno != errno.EADDRINUSE:
                break
    if last is not None and last.errno == errno.EADDRINUSE:
        which = f"port {port}" if tries <= 1 else f"ports {port}-{port + tries - 1}"
        raise ViewerError(
            f"{which} on {host} in use: choose another with --port (0 picks any free port)"
        )
    raise ViewerError(f"cannot listen on {host}:{port}: {last.strerror if last else '?'}")


class ViewerServer:
    """Serves a :class:`ViewerSource` on a thread of its own until :meth:`close` (a context
    manager). ``host`` defaults to 127.0.0.1: nothing else on the network sees the page unless
    the user asks (``--host``)."""

    def __init__(
        self,
        source: ViewerSource | None,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        *,
        port_tries: int = 1,
        console: Console | None = None,
        token: str | None = None,
        tls: tuple[str, str] | None = None,
    ) -> None:
        self.source = source
        self.host = host
        self.port = port
        self.port_tries = port_tries
        self.console = console
        """Commands from the page and the API go here (None: read-only)."""
        self.security = Security(host, token)
        self.tls = tls
        """(certificate file, key file): serve HTTPS (uvicorn's ssl_certfile, ssl_keyfile)."""
        self._closing = threading.Event()
        self.streams = StreamCount()
        """Pages being streamed to now."""
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self.address: tuple[str, int] = (host, port)
        """The address the server listens on (set by :meth:`start`)."""

    @property
    def url(self) -> str:
        host, port = self.address[:2]
        shown = f"[{host}]" if ":" in host else host
        return f"{'https' if self.tls else 'http'}://{shown}:{port}/"

    @property
    def console_url(self) -> str:
        """The page's URL with the run's token (what the terminal shows, as Jupyter does)."""
        token = self.security.token
        return f"{self.url}?token={token}" if token else self.url

    def bind(self) -> tuple[str, int]:
        """Take the port now (:class:`ViewerError` if it cannot be had), serve later."""
        if self._sock is None:
            self._sock = bind_socket(self.host, self.port, tries=self.port_tries)
            self.address = self._sock.getsockname()[:2]
        return self.address

    def start(self) -> str:
        """Bind (unless :meth:`bind` did), serve on a daemon thread, wait until it answers;
        the URL."""
        import uvicorn

        self.bind()
        if self.source is None:
            raise ViewerError("nothing to serve yet (no source)")
        app = create_app(
            self.source,
            self._closing,
            console=self.console,
            security=self.security,
            streams=self.streams,
        )
        config = uvicorn.Config(
            app,
            log_level="warning",
            lifespan="off",
            timeout_graceful_shutdown=2,
            limit_concurrency=MAX_CONNECTIONS,
            ssl_certfile=self.tls[0] if self.tls else None,
            ssl_keyfile=self.tls[1] if self.tls else None,
        )
        self._server = uvicorn.Server(config)
        sock = self._sock
        self._thread = threading.Thread(
            target=lambda: asyncio.run(self._server.serve(sockets=[sock])),
            name="viewer-server",
            daemon=True,
        )
        self._thread.start()
        deadline = time.monotonic() + 10.0
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise ViewerError(f"the viewer's server did not start on {self.url}")
            time.sleep(0.01)
        return self.url

    def close(self, timeout: float = 5.0, *, drain_s: float = DRAIN_S) -> None:
        """Let the pages being streamed to get what is left (a finished run's last records
        and its end: at most ``drain_s``), end the streams, stop the server, release the
        port."""
        deadline = time.monotonic() + drain_s
        while self.streams.n > 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        self._closing.set()
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> ViewerServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
