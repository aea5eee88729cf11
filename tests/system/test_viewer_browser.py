"""The viewer page in a real browser (Debian's chromium through Playwright, WebGL on SwiftShader;
see tests/browser.py): what a person sees of a live run, of a replay, and of the offline file.

Screenshots go to the test's tmp directory; with ``BTMISSION_DOCS_SCREENSHOTS=1`` the good ones
are also written to docs/img (the pictures docs/viewer.md shows)."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest

from btmission.runtime.session import RunSession
from btmission.viz.export import static_html
from btmission.viz.live import LiveViewer
from btmission.viz.server import ViewerServer, log_source
from tests.browser import docs_shot, image_stats, open_page, pixels, region_diff, wait_js

ROOT = Path(__file__).resolve().parents[2]
MINE = ROOT / "missions" / "mine_inspection.yaml"
PANE = (0, 34, 900, 566)
"""The 3D pane in the 1280x800 viewport (left, top, right, bottom): below the title bar, left
of the tree panel, above the player."""


def _tree_classes(page: Any) -> list[str]:
    return page.evaluate("[...document.querySelectorAll('#tree .bt')].map(e => e.className)")


def _agent_px(page: Any, agent: str) -> tuple[float, float]:
    x, y, _ = page.evaluate(f"window.btm.agentScreen('{agent}')")
    return float(x), float(y)


def test_live_run_moves_markers_and_ticks_trees(page: Any, tmp_path: Path) -> None:
    """A run watched live from its start: the tree panel's node classes change as the trees
    tick (the first seconds, at real time: arm, take off, set off), then, 8× faster than real
    time, the agents' markers move between two screenshots of a canvas that shows the mine;
    closing the page mid-run changes nothing for the run."""
    viewer = LiveViewer(port=0)
    result: list[Any] = []
    with RunSession(
        MINE, controller="track", realtime=True, log_path=tmp_path / "live.jsonl",
        observers=[viewer.observer],
    ) as session:  # fmt: skip
        run = session.start()
        url = viewer.attach(session, run)
        errors = open_page(page, url)
        page.evaluate(TREE_WATCH)

        def go() -> None:
            run.run(until=4.0)  # real time
            run.speed = 8.0
            result.append(session.run(until=30.0))

        worker = threading.Thread(target=go)
        worker.start()
        try:
            assert page.evaluate("window.btm.state.live && window.btm.state.follow")
            wait_js(page, "Number(document.body.dataset.viewT) > 8")
            first = page.screenshot()
            at_first = {a: _agent_px(page, a) for a in ("R1", "R2", "R3")}
            time.sleep(1.5)
            second = page.screenshot()
            at_second = {a: _agent_px(page, a) for a in ("R1", "R2", "R3")}
            tree_states = page.evaluate("window.treeStates.size")
            running = page.evaluate("document.querySelectorAll('#tree .bt.st-RUNNING').length")
            docs_shot(page, "viewer_live.png")
            page.close()  # the browser goes away while the run goes on
        finally:
            worker.join(timeout=120)
        viewer.close()
    assert errors == []
    _mean, std, colours = image_stats(first, PANE)
    assert std > 12 and colours > 200, "the 3D pane is blank"
    moved = [
        a
        for a in at_first
        if abs(at_first[a][0] - at_second[a][0]) + abs(at_first[a][1] - at_second[a][1]) > 4
    ]
    assert moved, f"no marker moved: {at_first} → {at_second}"
    for a in moved:  # the pixels around where the marker was and is did change
        x, y = (round(v) for v in at_second[a])
        box = (max(x - 25, 0), max(y - 25 + PANE[1], 0), x + 25, y + 25 + PANE[1])
        assert region_diff(first, second, box) > 0.01
    assert tree_states >= 3, "the tree panel's statuses did not change as the run went"
    assert running >= 2  # the root and the branch it runs
    assert result and result[0].reason == "until" and result[0].time_s == pytest.approx(30.0)
    assert viewer.queue.dropped.get("task", 0) == 0


TREE_WATCH = """
window.treeStates = new Set();
new MutationObserver(() => window.treeStates.add(
  [...document.querySelectorAll('#tree .bt')].map((e) => e.className).join('|'))
).observe(document.getElementById('tree'), {attributes: true, subtree: true, childList: true});
"""


def test_replay_slider_changes_the_scene(page: Any, mine_log: Path) -> None:
    source, _ = log_source(mine_log)
    with ViewerServer(source, port=0) as server:
        errors = open_page(page, server.url)
        wait_js(page, "document.body.dataset.complete === '1'")
        assert page.evaluate("window.btm.state.live") is False
        page.evaluate("window.btm.seek(5)")
        wait_js(page, "document.body.dataset.viewT === '5.00'")
        time.sleep(0.4)
        early = page.screenshot()
        early_px = _agent_px(page, "R1")
        early_tasks = page.evaluate(
            "[...document.querySelectorAll('#tasks tbody tr')].map(r => r.dataset.state)"
        )
        slider = page.locator("#slider")
        slider.fill("100")  # the slider, as a person drags it
        wait_js(page, "document.body.dataset.viewT === '100.00'")
        time.sleep(0.4)
        late = page.screenshot()
        late_px = _agent_px(page, "R1")
        late_tasks = page.evaluate(
            "[...document.querySelectorAll('#tasks tbody tr')].map(r => r.dataset.state)"
        )
        x, y = _agent_px(page, "R2")  # a click on R2's marker selects it (a 3D pick)
        page.mouse.click(x, y + PANE[1])
        picked = wait_js(page, "document.body.dataset.picked")
        selected = page.evaluate("window.btm.state.selected")
        page.check("#opt-lidar")  # a scan from R2's pose, cast by the server
        lidar = wait_js(page, "Number(document.body.dataset.lidarPoints || 0)")
        before_risk = page.screenshot()
        page.check("#opt-risk")  # the risk layer on demand
        time.sleep(0.4)
        with_risk = page.screenshot()
        page.uncheck("#opt-risk")
        page.uncheck("#opt-lidar")
        page.click("#btn-play")
        time.sleep(1.0)
        played = float(page.evaluate("document.body.dataset.viewT"))
        page.click(".tab[data-tab='timeline']")
        time.sleep(0.3)
        bars = page.evaluate("document.querySelectorAll('#timeline rect').length")
        docs_shot(page, "viewer_replay.png")
    assert errors == []
    assert abs(early_px[0] - late_px[0]) + abs(early_px[1] - late_px[1]) > 20
    assert region_diff(early, late, PANE) > 0.002
    assert early_tasks.count("done") == 0 and late_tasks.count("done") >= 2
    assert played > 100.0  # play moves time on from where the slider was
    assert picked == "agent:R2" and selected == "R2"
    assert lidar > 1000
    assert region_diff(before_risk, with_risk, PANE) > 0.01  # the risk points appeared
    assert bars >= 3  # each agent's task on the timeline


def test_static_html_renders_offline(page: Any, mine_log: Path, tmp_path: Path) -> None:
    source, _ = log_source(mine_log)
    out = tmp_path / "run.html"
    out.write_text(static_html(source), encoding="utf-8")
    fetched: list[str] = []

    def offline(route: Any) -> None:  # nothing but the file itself may load
        if not route.request.url.startswith("file:"):
            fetched.append(route.request.url)
            route.abort()
        else:
            route.continue_()

    page.route("**/*", offline)
    errors = open_page(page, out.as_uri())
    page.evaluate("window.btm.seek(90)")
    wait_js(page, "document.body.dataset.viewT === '90.00'")
    time.sleep(0.4)
    shot = page.screenshot()
    rows = page.evaluate("document.querySelectorAll('#tasks tbody tr').length")
    nodes = page.evaluate("document.querySelectorAll('#tree .bt').length")
    lidar_disabled = page.evaluate("document.getElementById('opt-lidar').disabled")
    assert errors == [] and fetched == []
    _mean, std, colours = image_stats(shot, PANE)
    assert std > 12 and colours > 200
    rgb = pixels(shot)
    assert rgb.shape[:2] == (800, 1280)
    assert rows >= 6 and nodes > 10 and lidar_disabled
