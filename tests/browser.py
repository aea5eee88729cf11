"""The browser test harness: Debian's chromium driven by Playwright, pixel checks, a loopback server.

Pages (the live 3D viewer, meshcat's three.js bundle) are tested in a real browser: the system's
``chromium`` (Debian's package; ``make install`` installs it when run as root) driven through
Playwright's sync API with ``executable_path``. Playwright's own browser download
(``playwright install``) is never used.

Fixtures (in ``tests/conftest.py``, built on this module):

- ``browser_session`` (session): one chromium for the whole test session (:class:`BrowserSession`).
- ``browser`` (function): that session's :class:`playwright.sync_api.Browser`, active for one test.
- ``page`` (function): a new page with a fixed :data:`VIEWPORT`, closed after the test.

Skip or fail: when chromium is missing, or Playwright is, or the browser does not start, every test
using these fixtures is skipped with one reason (e.g. "no chromium: install Debian's chromium
package ..."). When the environment variable ``CI`` is set (CI runs as root, where ``make``
installs chromium) the same condition fails them instead (an error at fixture setup, with the
same reason), so CI can never silently skip the browser tests.

Why ``browser`` is function-scoped over a session-scoped launch: Playwright's sync API runs its
asyncio loop in a greenlet, and between two sync calls it leaves that loop marked as the thread's
running loop. A browser kept open for the session would then make every later test that calls
``asyncio.run()`` (or anything built on it) fail with "cannot be called from a running event
loop". :meth:`BrowserSession.active` marks the loop running only while a browser test runs.

Chromium flags (:data:`CHROMIUM_ARGS`), as found on this machine (chromium 156, headless, root,
no network, no GPU):

- ``--no-sandbox``: needed as root ("Running as root without --no-sandbox is not supported");
  Playwright also adds it by default (``chromium_sandbox=False``), it is spelled out here.
- ``--enable-unsafe-swiftshader``: WebGL in software (SwiftShader). Without it WebGL still works
  today through an "automatic fallback to software WebGL" that chromium logs as deprecated; the
  flag makes the software path explicit before that fallback goes away.
- ``--use-gl=angle --use-angle=swiftshader``: pin the GL backend to ANGLE on SwiftShader, so a
  machine with a GPU renders the same pixels as CI. (``--use-gl=swiftshader``, the old spelling,
  leaves chromium without WebGL.)
- ``--disable-background-networking --disable-component-update --disable-sync --no-first-run
  --disable-quic``: no traffic beyond loopback (machines without network, and CI, must not see
  chromium's background requests; Playwright's defaults already include the first two).

The pixel helpers take a PNG screenshot as bytes (``page.screenshot()``), or that screenshot decoded
once by :func:`pixels` (decoding a 1280x800 PNG takes ~30 ms: decode once when checking a shot
several times); a box is ``(left, top, right, bottom)`` in pixels, right and bottom exclusive
(Pillow's convention).

Debian's ``/usr/bin/chromium`` is a shell wrapper (it adds the flags in /etc/chromium.d, then runs
/usr/lib/chromium/chromium); its /dev/shm size check prints "[: ...: unexpected operator" to the
browser's stderr on some machines, which is harmless and only shows in Playwright's launch log.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import importlib.util
import io
import mimetypes
import os
import re
import shutil
import threading
import time
import urllib.parse
from collections.abc import Iterator, Mapping
from http.server import BaseHTTPRequestHandler, SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import numpy as np
import pytest
from PIL import Image

if TYPE_CHECKING:
    from playwright.sync_api import Browser, Page, Playwright, ViewportSize

VIEWPORT: ViewportSize = {"width": 1280, "height": 800}
"""The ``page`` fixture's viewport, in CSS pixels (device scale factor 1)."""

CHROMIUM_ARGS = (
    "--no-sandbox",
    "--enable-unsafe-swiftshader",
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
)
"""Chromium's command-line flags for the tests (see the module docstring for why each)."""

Box = tuple[int, int, int, int]
RGB = tuple[int, int, int]
Shot = bytes | np.ndarray
"""A screenshot: PNG bytes, or its (height, width, 3) uint8 RGB array from :func:`pixels`."""


def chromium_executable() -> str | None:
    """The system chromium: ``chromium`` on PATH, else /usr/bin/chromium; None when neither exists."""
    found = shutil.which("chromium")
    if found:
        return found
    return "/usr/bin/chromium" if os.access("/usr/bin/chromium", os.X_OK) else None


def unavailable(reason: str) -> NoReturn:
    """Skip the requesting test for `reason`, or fail it when ``CI`` is set (CI must not skip)."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason} (CI is set: the browser tests must run, not skip)", pytrace=False)
    pytest.skip(reason)


class BrowserSession:
    """One chromium launched through Playwright's sync API, shared by a test session.

    Use :meth:`launch` to start it, :meth:`active` around every use of :attr:`browser` (the
    ``browser`` fixture does), and :meth:`close` once at the end.
    """

    def __init__(
        self, playwright: Playwright, browser: Browser, loop: asyncio.AbstractEventLoop | None
    ):
        self.playwright = playwright
        self.browser = browser
        self._loop = loop

    @classmethod
    def launch(cls) -> BrowserSession:
        """Start Playwright and chromium; skip (or fail under ``CI``) when that is impossible."""
        executable = chromium_executable()
        if executable is None:
            unavailable(
                "no chromium: install Debian's chromium package (`make install` does it as root)"
            )
        try:
            from playwright.sync_api import Error, sync_playwright
        except ImportError:
            unavailable("no playwright: install the test extra (pip install -e '.[test]')")
        try:
            playwright = sync_playwright().start()
        except Exception as error:  # its driver (node) missing or broken, or a loop running here
            unavailable(f"playwright did not start: {_launch_failure(str(error))}")
        # Playwright leaves its loop marked running in this thread between sync calls (see the
        # module docstring); keep a handle to mark it again in active().
        loop = asyncio._get_running_loop()
        try:
            browser = playwright.chromium.launch(
                executable_path=executable, headless=True, args=list(CHROMIUM_ARGS)
            )
        except Error as error:
            playwright.stop()
            asyncio._set_running_loop(None)
            unavailable(f"chromium at {executable} did not start: {_launch_failure(str(error))}")
        asyncio._set_running_loop(None)
        return cls(playwright, browser, loop)

    @contextlib.contextmanager
    def active(self) -> Iterator[Browser]:
        """Make the browser usable in this block; outside it asyncio sees no running loop."""
        asyncio._set_running_loop(self._loop)
        try:
            yield self.browser
        finally:
            asyncio._set_running_loop(None)

    def close(self) -> None:
        """Close chromium and stop Playwright (its driver process and event loop)."""
        asyncio._set_running_loop(self._loop)
        try:
            self.browser.close()
        finally:
            self.playwright.stop()
            asyncio._set_running_loop(None)


_CHROMIUM_ERROR = re.compile(r":(?:ERROR|FATAL):[^\]]*\] (.+)")
"""A line chromium logged at ERROR or FATAL level: ``[pid:tid:time:ERROR:file.cc:103] message``."""


def _launch_failure(message: str) -> str:
    """One line from Playwright's launch error: its summary, chromium's own error, the exit code."""
    lines = [line.strip(" -") for line in message.splitlines() if line.strip()]
    if not lines:
        return "no error message"
    parts = [lines[0].removeprefix("BrowserType.launch: ")]
    logged = [
        found.group(1)
        for line in lines
        if (found := _CHROMIUM_ERROR.search(line)) and ":ERROR:dbus/" not in line  # benign, common
    ]
    parts += logged[:1]
    parts += [code.group() for line in lines if (code := re.search(r"exitCode=\d+", line))][:1]
    return "; ".join(parts)


def next_frames(page: Page, frames: int = 2) -> None:
    """Wait until the page has run `frames` more animation frames (a render has reached the screen)."""
    page.evaluate(
        """n => new Promise(done => {
            const step = k => k === 0 ? done() : requestAnimationFrame(() => step(k - 1));
            step(n);
        })""",
        frames,
    )


def webgl_renderer(page: Page) -> str | None:
    """The WebGL renderer a fresh canvas in `page` gets (e.g. "ANGLE (... SwiftShader ...)"), or None."""
    result: str | None = page.evaluate(
        """() => {
            const gl = document.createElement('canvas').getContext('webgl');
            if (!gl) return null;
            const info = gl.getExtension('WEBGL_debug_renderer_info');
            return gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER);
        }"""
    )
    return result


def meshcat_dist() -> Path:
    """The installed meshcat package's three.js viewer bundle directory (``main.min.js``, ...).

    Located without importing meshcat (its import warns about pyzmq deprecations).
    """
    spec = importlib.util.find_spec("meshcat")
    if spec is None or spec.origin is None:
        raise FileNotFoundError("meshcat is not installed (pip install -e '.[viz]')")
    return Path(spec.origin).parent / "viewer" / "dist"


# -- pixels -------------------------------------------------------------------------------------


def docs_shot(page: Page, name: str) -> None:
    """With ``BTMISSION_DOCS_SCREENSHOTS`` set, save the page as ``docs/img/<name>``."""
    if os.environ.get("BTMISSION_DOCS_SCREENSHOTS"):
        page.screenshot(path=str(Path(__file__).resolve().parents[1] / "docs" / "img" / name))


def wait_js(page: Page, script: str, timeout_s: float = 30.0) -> Any:
    """The first truthy value of ``script`` in the page, polled every 0.1 s (an
    AssertionError after ``timeout_s``)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = page.evaluate(script)
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {script}")


def open_page(page: Page, url: str) -> list[str]:
    """Open the viewer at ``url`` and wait until it is ready; the list its script errors go to."""
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_selector("body[data-ready='1']", timeout=30_000)
    return errors


def pixels(png: Shot) -> np.ndarray:
    """The PNG's pixels as an (height, width, 3) uint8 RGB array (alpha dropped); arrays pass through."""
    if isinstance(png, np.ndarray):
        return png
    with Image.open(io.BytesIO(png)) as image:
        return np.asarray(image.convert("RGB"), dtype=np.uint8)


def _crop(rgb: np.ndarray, box: Box | None) -> np.ndarray:
    """`rgb` cut to `box` (clipped to the image); ValueError when nothing of it is left."""
    if box is None:
        return rgb
    height, width = rgb.shape[:2]
    left, top, right, bottom = box
    left, right = max(0, left), min(width, right)
    top, bottom = max(0, top), min(height, bottom)
    if left >= right or top >= bottom:
        raise ValueError(f"box {box} has no pixels inside the {width}x{height} image")
    return rgb[top:bottom, left:right]


def image_stats(png: Shot, box: Box | None = None) -> tuple[float, float, int]:
    """(mean, standard deviation, number of distinct colours) of the pixel values in `box`.

    Mean and deviation are over all RGB channel values (0-255); a blank canvas has a deviation
    near 0 and a handful of colours.
    """
    rgb = _crop(pixels(png), box)
    packed = (
        (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8) | rgb[..., 2]
    )
    return float(rgb.mean()), float(rgb.std()), int(np.unique(packed).size)


def colour_at(png: Shot, x: int, y: int) -> RGB:
    """The (r, g, b) colour of the pixel at column `x`, row `y`."""
    rgb = pixels(png)
    height, width = rgb.shape[:2]
    if not (0 <= x < width and 0 <= y < height):
        raise ValueError(f"pixel ({x}, {y}) is outside the {width}x{height} image")
    r, g, b = (int(v) for v in rgb[y, x])
    return r, g, b


def _matching(rgb: np.ndarray, low: RGB, high: RGB) -> np.ndarray:
    """Mask of the pixels whose every channel lies in [low, high]."""
    inside: np.ndarray = np.all((rgb >= np.array(low)) & (rgb <= np.array(high)), axis=-1)
    return inside


def colour_fraction(png: Shot, low: RGB, high: RGB, box: Box | None = None) -> float:
    """The fraction of the pixels in `box` whose r, g and b each lie within [low, high]."""
    return float(_matching(_crop(pixels(png), box), low, high).mean())


def colour_centroid(png: Shot, low: RGB, high: RGB) -> tuple[float, float] | None:
    """The mean (x, y) of the pixels within [low, high] per channel; None when there are none."""
    rows, cols = np.nonzero(_matching(pixels(png), low, high))
    if rows.size == 0:
        return None
    return float(cols.mean()), float(rows.mean())


def region_diff(png_a: Shot, png_b: Shot, box: Box, tolerance: int = 24) -> float:
    """The fraction of the pixels in `box` that changed between two screenshots of equal size.

    A pixel changed when any channel differs by more than `tolerance` (which absorbs
    antialiasing and dithering noise).
    """
    a, b = pixels(png_a), pixels(png_b)
    if a.shape != b.shape:
        raise ValueError(f"screenshots differ in size: {a.shape[:2]} and {b.shape[:2]}")
    delta = np.abs(_crop(a, box).astype(np.int16) - _crop(b, box).astype(np.int16))
    return float((delta.max(axis=-1) > tolerance).mean())


# -- a loopback static server -------------------------------------------------------------------


class _QuietFiles(SimpleHTTPRequestHandler):
    """Serve a directory; no request log on stderr."""

    def log_message(self, format: str, *args: Any) -> None:
        """Drop the per-request log line."""


class _MappingHandler(BaseHTTPRequestHandler):
    """Serve an in-memory {path: bytes} mapping (``/`` is ``index.html``); 404 for anything else."""

    files: Mapping[str, bytes] = {}

    def do_GET(self) -> None:
        """Answer with the file's bytes, its guessed content type and no caching."""
        path = (
            urllib.parse.unquote(urllib.parse.urlsplit(self.path).path).lstrip("/") or "index.html"
        )
        body = self.files.get(path)
        if body is None:
            self.send_error(404, f"{path} is not served")
            return
        self.send_response(200)
        self.send_header(
            "Content-Type", mimetypes.guess_type(path)[0] or "application/octet-stream"
        )
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        """Drop the per-request log line."""


@contextlib.contextmanager
def serve_static(content: Path | Mapping[str, bytes]) -> Iterator[str]:
    """Serve a directory, or a {path: bytes} mapping, on 127.0.0.1 at a free port, in a thread.

    Yields the base URL (``http://127.0.0.1:<port>``, no trailing slash); the server stops and
    its socket closes when the block ends. Mapping keys are paths relative to the root
    (``"index.html"``, ``"js/main.min.js"``; a leading ``/`` is ignored).
    """
    handler: Any
    if isinstance(content, Mapping):
        files = {str(path).lstrip("/"): bytes(body) for path, body in content.items()}
        handler = type("_Files", (_MappingHandler,), {"files": files})
    else:
        root = Path(content)
        if not root.is_dir():
            raise NotADirectoryError(f"{root} is not a directory")
        handler = functools.partial(_QuietFiles, directory=str(root))
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(
        target=server.serve_forever, args=(0.05,), name="serve_static", daemon=True
    )
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
