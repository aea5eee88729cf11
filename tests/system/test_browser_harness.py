"""The browser harness (tests/browser.py) works here: chromium gets WebGL, and meshcat renders.

The meshcat test takes the route the live viewer page will take: commands encoded by meshcat's
Python package (``SetObject(...).lower()``, packed with umsgpack), shipped as base64 and fed to
the three.js viewer's ``handle_command_bytearray``; the bundle is served from loopback.
"""

from __future__ import annotations

import asyncio
import base64
import io
import urllib.error
import urllib.request
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import umsgpack
from PIL import Image
from playwright.sync_api import Page

from tests.browser import (
    VIEWPORT,
    BrowserSession,
    colour_at,
    colour_centroid,
    colour_fraction,
    image_stats,
    meshcat_dist,
    next_frames,
    pixels,
    region_diff,
    serve_static,
    unavailable,
    webgl_renderer,
)

with warnings.catch_warnings():
    # meshcat imports its ZeroMQ server, which imports zmq.eventloop.ioloop: pyzmq warns that
    # module is deprecated. Nothing here uses that server; only this one warning is silenced.
    warnings.filterwarnings("ignore", "zmq.eventloop.ioloop is deprecated", DeprecationWarning)
    from meshcat import commands, geometry, transformations
    from meshcat.path import Path as ScenePath

RED_LOW, RED_HIGH = (100, 0, 0), (255, 60, 60)
"""The lit faces of a 0xff0000 Lambert box (~(180, 0, 0) to (240, 0, 0)); no background pixel is red."""

PAGE = b"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><link rel="icon" href="data:,">
<style>body { margin: 0 } #pane { width: 100vw; height: 100vh; overflow: hidden }</style></head>
<body><div id="pane"></div>
<script src="main.min.js"></script>
<script>
window.viewer = new MeshCat.Viewer(document.getElementById("pane"));
window.feed = b64 => viewer.handle_command_bytearray(Uint8Array.from(atob(b64), c => c.charCodeAt(0)));
</script></body></html>
"""

PROJECT = """path => {
    const mesh = viewer.scene_tree.find(path).object;
    const world = new MeshCat.THREE.Vector3();
    mesh.getWorldPosition(world);
    const ndc = world.clone().project(viewer.camera);
    const rect = viewer.renderer.domElement.getBoundingClientRect();
    return {type: mesh.type,
            x: rect.left + (ndc.x + 1) / 2 * rect.width,
            y: rect.top + (1 - ndc.y) / 2 * rect.height};
}"""
"""Where the centre of the mesh at a scene path lands on the screen, in CSS pixels."""

BOX = ScenePath(("meshcat", "box"))


def png(
    size: tuple[int, int],
    colour: tuple[int, int, int],
    rect: tuple[int, int, int, int] | None = None,
    fill: tuple[int, int, int] = (255, 0, 0),
) -> bytes:
    """A PNG of `size` in `colour`, with `rect` (left, top, right, bottom; exclusive) in `fill`."""
    image = Image.new("RGB", size, colour)
    if rect is not None:
        image.paste(fill, rect)
    out = io.BytesIO()
    image.save(out, format="PNG")
    return out.getvalue()


def around(x: float, y: float, half: int = 30) -> tuple[int, int, int, int]:
    """The box of 2*half pixels a side centred on (x, y)."""
    return round(x) - half, round(y) - half, round(x) + half, round(y) + half


# -- helpers without a browser ------------------------------------------------------------------


def test_pixel_helpers_measure_a_known_image() -> None:
    blank = png((200, 100), (10, 20, 30))
    square = png((200, 100), (10, 20, 30), rect=(50, 20, 90, 60))

    assert image_stats(blank) == (20.0, pytest.approx(8.165, abs=1e-3), 1)
    mean, std, colours = image_stats(square)
    assert colours == 2 and std > 30 and mean > 20
    assert colour_at(square, 60, 30) == (255, 0, 0) and colour_at(square, 10, 10) == (10, 20, 30)
    assert colour_fraction(square, RED_LOW, RED_HIGH) == pytest.approx(40 * 40 / (200 * 100))
    assert colour_fraction(square, RED_LOW, RED_HIGH, box=(50, 20, 90, 60)) == 1.0
    assert colour_centroid(square, RED_LOW, RED_HIGH) == (69.5, 39.5)
    assert colour_centroid(blank, RED_LOW, RED_HIGH) is None
    assert region_diff(blank, square, (0, 0, 200, 100)) == pytest.approx(0.08)
    assert region_diff(blank, square, (50, 20, 70, 40)) == 1.0
    assert region_diff(blank, square, (100, 0, 200, 100)) == 0.0
    decoded = pixels(square)  # helpers take the decoded array as well as the PNG
    assert decoded.shape == (100, 200, 3) and image_stats(decoded) == (mean, std, colours)
    assert region_diff(blank, decoded, (50, 20, 70, 40)) == 1.0
    with pytest.raises(ValueError, match="no pixels"):
        region_diff(blank, square, (300, 0, 400, 10))
    with pytest.raises(ValueError, match="differ in size"):
        region_diff(blank, png((100, 100), (0, 0, 0)), (0, 0, 10, 10))
    with pytest.raises(ValueError, match="outside"):
        colour_at(blank, 200, 0)


def test_static_server_serves_a_mapping_and_a_directory_on_loopback(tmp_path: Path) -> None:
    with serve_static({"index.html": b"<p>hi</p>", "/js/app.js": b"let a = 1;"}) as url:
        assert url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url + "/") as answer:
            assert answer.read() == b"<p>hi</p>" and answer.headers["Content-Type"] == "text/html"
        with urllib.request.urlopen(url + "/js/app.js?v=2") as answer:
            assert answer.read() == b"let a = 1;" and "javascript" in answer.headers["Content-Type"]
        with pytest.raises(urllib.error.HTTPError) as missing:
            urllib.request.urlopen(url + "/nope.js")
        assert missing.value.code == 404
        missing.value.close()
    with pytest.raises(urllib.error.URLError):  # stopped: the port no longer answers
        urllib.request.urlopen(url + "/", timeout=2)

    (tmp_path / "data.json").write_text('{"a": 1}')
    with serve_static(tmp_path) as url, urllib.request.urlopen(url + "/data.json") as answer:
        assert answer.read() == b'{"a": 1}'


def test_unavailable_browser_skips_locally_and_fails_under_ci(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="no chromium"):
        unavailable("no chromium")
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match=r"no chromium \(CI is set"):
        unavailable("no chromium")


# -- the browser --------------------------------------------------------------------------------


def test_chromium_has_software_webgl_and_the_fixed_viewport(page: Page) -> None:
    renderer = webgl_renderer(page)
    assert renderer is not None and "SwiftShader" in renderer
    assert page.evaluate("[innerWidth, innerHeight]") == [VIEWPORT["width"], VIEWPORT["height"]]


def test_asyncio_runs_while_the_browser_session_is_open(browser_session: BrowserSession) -> None:
    """The session's chromium stays open between tests; other tests' asyncio.run must still work."""

    async def answer() -> int:
        await asyncio.sleep(0)
        return 42

    assert asyncio.run(answer()) == 42
    with browser_session.active() as browser:  # and the browser still works afterwards
        assert browser.is_connected()


@pytest.fixture()
def meshcat_page(page: Page) -> Iterator[Page]:
    """`page` showing meshcat's viewer (its bundle served from loopback); no page errors allowed."""
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    files = {"index.html": PAGE, "main.min.js": (meshcat_dist() / "main.min.js").read_bytes()}
    with serve_static(files) as url:
        page.goto(url + "/")
        page.wait_for_function("() => window.viewer !== undefined")
        yield page
    assert errors == []


def send(page: Page, command: Any) -> None:
    """Feed a meshcat command (commands.SetObject(...) etc.) as msgpack bytes; wait until drawn."""
    page.evaluate("feed", base64.b64encode(umsgpack.packb(command.lower())).decode("ascii"))
    page.wait_for_function("() => !viewer.needs_render")
    next_frames(page)


def test_meshcat_renders_a_red_box_and_moves_it(meshcat_page: Page, tmp_path: Path) -> None:
    page = meshcat_page
    context = page.evaluate(
        """() => { const gl = viewer.renderer.getContext(), canvas = viewer.renderer.domElement;
                   return [gl.constructor.name, gl.isContextLost(), canvas.width, canvas.height]; }"""
    )
    assert context[0] in ("WebGLRenderingContext", "WebGL2RenderingContext")
    assert context[1:] == [False, VIEWPORT["width"], VIEWPORT["height"]]

    # The axes helper draws a red line at the origin: hidden, so red means the box.
    send(page, commands.SetProperty("visible", False, ScenePath(("Axes",))))
    empty = pixels(page.screenshot(path=tmp_path / "empty.png"))
    assert colour_fraction(empty, RED_LOW, RED_HIGH) == 0.0

    send(
        page,
        commands.SetObject(
            geometry.Box([1, 1, 1]), geometry.MeshLambertMaterial(color=0xFF0000), BOX
        ),
    )
    shot = pixels(page.screenshot(path=tmp_path / "box.png"))
    _, std, colours = image_stats(shot)
    assert std > 30 and colours > 100  # the sky gradient, the grid and the box: not a blank canvas
    centre = page.evaluate(PROJECT, ["meshcat", "box", "<object>"])
    assert centre["type"] == "Mesh"
    near = around(centre["x"], centre["y"])
    assert colour_fraction(shot, RED_LOW, RED_HIGH, near) > 0.9
    assert region_diff(empty, shot, near) > 0.9
    red = colour_centroid(shot, RED_LOW, RED_HIGH)
    assert red is not None and abs(red[0] - centre["x"]) < 30 and abs(red[1] - centre["y"]) < 30

    send(page, commands.SetTransform(transformations.translation_matrix([0, 1.5, 0]), BOX))
    moved = pixels(page.screenshot(path=tmp_path / "moved.png"))
    after = page.evaluate(PROJECT, ["meshcat", "box", "<object>"])
    assert after["x"] - centre["x"] > 150  # +y is to the right of the default camera
    assert colour_fraction(moved, RED_LOW, RED_HIGH, near) < 0.05
    assert colour_fraction(moved, RED_LOW, RED_HIGH, around(after["x"], after["y"])) > 0.9
    assert region_diff(shot, moved, near) > 0.9
    assert region_diff(shot, moved, (0, 40, 400, 250)) == 0.0  # the sky is untouched
    red_after = colour_centroid(moved, RED_LOW, RED_HIGH)
    assert red_after is not None and abs((red_after[0] - red[0]) - (after["x"] - centre["x"])) < 40


def test_launch_without_chromium_skips_with_one_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setattr("tests.browser.chromium_executable", lambda: None)
    with pytest.raises(pytest.skip.Exception, match="no chromium: install Debian's chromium"):
        BrowserSession.launch()


def test_chromium_that_does_not_start_fails_under_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    """Playwright starts, the browser does not: one reason, Playwright stopped, no loop left running."""
    monkeypatch.setenv("CI", "1")
    monkeypatch.setattr("tests.browser.chromium_executable", lambda: "/bin/false")
    with pytest.raises(pytest.fail.Exception, match=r"chromium at /bin/false did not start: "):
        BrowserSession.launch()
    assert asyncio.run(asyncio.sleep(0, result="free")) == "free"
