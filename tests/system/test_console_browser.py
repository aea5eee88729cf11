"""The operator console on the viewer page, in a real browser (Debian's chromium through
Playwright; see tests/browser.py), against a live run served with its console
(``LiveViewer(console=True, token=...)``, what ``btmission run --console`` does).

What an operator does and sees: a click on the map (Top view) adds a task there, the page tells
the result and then what became of the task, which the run's log confirms; a task inside rock is
refused with the reason and the field marked; a task is cancelled from its row; allocation is
paused and resumed, an agent taken out of the auction and back; a page started with ``--view``
shows no controls; the token comes from the URL, or is asked for.

Screenshots go to the test's tmp directory; with ``BTMISSION_DOCS_SCREENSHOTS=1`` the good ones
are also written to docs/img (the pictures docs/operator.md shows)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from btmission.runtime.events import Event, read_events
from btmission.runtime.session import RunSession
from btmission.viz.live import LiveViewer
from btmission.world.voxel import OCCUPIED, VoxelMap
from tests.browser import colour_fraction, docs_shot, next_frames, open_page, wait_js

ROOT = Path(__file__).resolve().parents[2]
MINE = ROOT / "missions" / "mine_inspection.yaml"
PICK_AND_DELIVER = ROOT / "missions" / "pick_and_deliver.yaml"
TOKEN = "t0ken"
SPEED = 8.0
"""The runs go 8 times faster than real time."""
FREE_FLOOR = (8.0, 3.0)
"""(x, y) of the launch area's floor, beside the agents' starts (free above the floor)."""


def _console_log(page: Any) -> list[tuple[str, str]]:
    """The console log's entries, newest first: (data-ok, text)."""
    rows = page.evaluate(
        "[...document.querySelectorAll('#console-log li')].map(l => [l.dataset.ok, l.textContent])"
    )
    return [(ok, text) for ok, text in rows]


def _last_result(text: str) -> str:
    return f"(document.body.dataset.lastResult || '').includes({text!r})"


def _task_rows(page: Any) -> dict[str, str]:
    """The task table's rows: id → state."""
    rows = page.evaluate(
        "[...document.querySelectorAll('#tasks tbody tr')].map(r => [r.dataset.task, r.dataset.state])"
    )
    return dict(rows)


@dataclass
class Live:
    """A live run served with the viewer (and its console), not yet stepping: :meth:`go`."""

    session: RunSession
    run: Any
    url: str
    log: Path
    until: float
    viewer: LiveViewer
    result: list[Any] = field(default_factory=list)
    worker: threading.Thread | None = None

    def go(self) -> None:
        """The run goes on a thread of its own (paced at SPEED) until ``until`` or :meth:`stop`."""
        self.worker = threading.Thread(
            target=lambda: self.result.append(self.session.run(until=self.until)), daemon=True
        )
        self.worker.start()

    def stop(self) -> None:
        self.run.stop("interrupted")

    def join(self, timeout_s: float = 60.0) -> None:
        if self.worker is not None:
            self.worker.join(timeout_s)
            assert not self.worker.is_alive(), "the run did not end"


@contextlib.contextmanager
def live_run(
    tmp_path: Path, *, console: bool = True, until: float = 240.0, mission: Path = MINE
) -> Iterator[Live]:
    """The seed 000 mission (or ``mission``; track controller) served live, with the console and
    TOKEN unless ``console`` is False. On the way out the run is stopped and its thread joined."""
    viewer = LiveViewer(port=0, console=console, token=TOKEN if console else None)
    log = tmp_path / "console.jsonl"
    try:
        with RunSession(
            mission, controller="track", realtime=True, speed=SPEED, log_path=log,
            observers=[viewer.observer],
        ) as session:  # fmt: skip
            run = session.start()
            live = Live(session, run, viewer.attach(session, run), log, until, viewer)
            try:
                yield live
            finally:
                if live.worker is not None:
                    live.stop()
                    live.join()
    finally:
        viewer.close()


def _events(log: Path) -> list[Event]:
    return read_events(log).events


def _rock_point(vmap: VoxelMap) -> list[float]:
    """The centre of an occupied voxel beside the launch area (east of it, 1 m up)."""
    for x in range(14, 40):
        centre = vmap.index_to_world(vmap.world_to_index([x + 0.1, 5.1, 1.1]))
        p = [round(float(c), 2) for c in centre]
        if vmap.state_at(p) == OCCUPIED:
            return p
    raise AssertionError("no rock east of the launch area")


def _rock_columns(vmap: VoxelMap, margin_m: float = 3.0, step_m: float = 4.0) -> list[list[float]]:
    """(x, y) on a ``step_m`` grid of the columns of solid rock, every voxel occupied from the
    map's bottom to its top within ``margin_m`` around: the rock between tunnels."""
    solid = (vmap.state == OCCUPIED).all(axis=2)
    k = max(1, round(margin_m / vmap.resolution))
    nx, ny = solid.shape
    padded = np.pad(solid, k, constant_values=False)
    inner = solid.copy()
    for dx in range(2 * k + 1):
        for dy in range(2 * k + 1):
            inner &= padded[dx : dx + nx, dy : dy + ny]
    step = max(1, round(step_m / vmap.resolution))
    out = []
    for i, j in zip(*np.nonzero(inner[::step, ::step]), strict=True):
        x, y, _ = vmap.index_to_world([i * step, j * step, 0])
        out.append([round(float(x), 2), round(float(y), 2)])
    return out


_PICK_ROCK = """([cols, z]) => {
  // of the rock columns, the one nearest the pane's middle whose top is seen (the map's canvas
  // under it, no panel) and under which the mine's surface has nothing
  const r = document.getElementById('view3d').getBoundingClientRect();
  const cx = (r.left + r.right) / 2, cy = (r.top + r.bottom) / 2;
  let best = null;
  for (const [wx, wy] of cols) {
    const [x, y] = btm.worldScreen([wx, wy, z]);
    const el = document.elementFromPoint(x, y);
    if (!el || el.tagName !== 'CANVAS' || btm.surfacePick(x, y)) continue;
    const d = Math.hypot(x - cx, y - cy);
    if (!best || d < best[2]) best = [x, y, d, wx, wy];
  }
  return best;
}"""


def _rect(page: Any, selector: str) -> list[float]:
    return page.evaluate(
        f"(() => {{ const r = document.querySelector({selector!r}).getBoundingClientRect();"
        " return [r.left, r.top, r.right, r.bottom]; })()"
    )


def test_click_on_the_map_adds_a_task_that_is_then_done(page: Any, tmp_path: Path) -> None:
    """Top view, + Task, a click on the launch area's floor: the form opens with the point 1 m
    above the floor (a marker there), T8 is added (urgent), and the console log tells the
    answer, then who was assigned T8 and who did it; the log has the same story."""
    with live_run(tmp_path) as live:
        errors = open_page(page, f"{live.url}?token={TOKEN}")
        live.go()
        # the token: kept for this tab, gone from the address bar
        assert page.url == live.url
        assert page.evaluate("sessionStorage.getItem('btm-token')") == TOKEN
        assert page.is_visible("#btn-add-task") and page.is_visible("#btn-pause")
        assert page.is_hidden("#token-form") and page.is_hidden("#console-ro")
        floor = live.run.map.ground_z([*FREE_FLOOR, 0.5])
        page.click("#btn-top")
        next_frames(page)
        page.click("#btn-add-task")
        assert page.evaluate("document.getElementById('view3d').classList.contains('arming')")
        x, y = page.evaluate(f"btm.worldScreen([{FREE_FLOOR[0]}, {FREE_FLOOR[1]}, {floor}])")
        hit = page.evaluate(f"btm.surfacePick({x}, {y})")
        assert hit["p"] == pytest.approx([*FREE_FLOOR, floor], abs=0.3)
        assert hit["normal"] == pytest.approx([0, 0, 1], abs=1e-6)  # the floor, seen from above
        page.mouse.click(x, y)
        location = wait_js(
            page,
            "(() => { const v = ['x', 'y', 'z'].map(c => "
            "document.querySelector(`#task-form [name='location.${c}']`).value);"
            " return v.every(s => s !== '') && v.map(Number); })()",
        )
        assert location == pytest.approx([*FREE_FLOOR, floor + 1.0], abs=0.11)
        assert page.input_value("#task-form [name=id]") == "T8"
        assert page.input_value("#task-form [name=type]") == "inspect"
        assert not page.evaluate("document.getElementById('view3d').classList.contains('arming')")
        next_frames(page, 3)
        shot = page.screenshot()
        box = (round(x) - 14, round(y) - 14, round(x) + 14, round(y) + 14)
        marker = colour_fraction(shot, (200, 90, 215), (255, 160, 255), box)
        page.select_option("#task-form [name=priority]", "urgent")
        docs_shot(page, "console_add.png")
        page.click("#task-form-submit")
        wait_js(page, "document.getElementById('task-form').hidden", 15)
        wait_js(page, _last_result("T8 done by"), 90)
        entries = _console_log(page)
        wait_js(
            page, "document.querySelector('#tasks tr[data-task=\"T8\"]')?.dataset.state === 'done'"
        )
        page.evaluate("btm.scene.onPick('task', 'T8')")  # its row highlighted, for the picture
        next_frames(page, 3)
        time.sleep(0.3)
        docs_shot(page, "console_result.png")
        live.stop()
    assert errors == []
    assert marker > 0.05, "no marker where the task goes"
    events = _events(live.log)
    commands = [e for e in events if e.kind == "command" and e.get("task") == "T8"]
    assert [(c.get("command"), c.get("ok")) for c in commands] == [("add_task", True)]
    assert str(commands[0].get("by")).startswith("page@")
    (added,) = [e for e in events if e.kind == "task_added" and e.get("task") == "T8"]
    assert added.get("fields")["location"] == pytest.approx([*FREE_FLOOR, floor + 1.0], abs=0.11)
    assert added.get("priority") == pytest.approx(4.0)  # urgent: 4 × the type's 1
    states = [(e.t, e.get("state"), e.get("agent")) for e in events if e.kind == "task" and e.get("task") == "T8"]  # fmt: skip
    assigned = [s for s in states if s[1] == "assigned"]
    done = [s for s in states if s[1] == "done"]
    assert assigned and done and assigned[0][0] <= done[0][0]
    texts = [text for _ok, text in entries]
    assert any(t.startswith("T8 added at") for t in texts)
    assert f"T8 assigned to {assigned[0][2]} at {assigned[0][0]:.1f} s" in texts
    assert f"T8 done by {done[0][2]} at {done[0][0]:.1f} s" in texts
    assert all(ok == "1" for ok, _ in entries)


def test_a_click_on_rock_between_tunnels_fills_nothing(page: Any, tmp_path: Path) -> None:
    """Top view, + Task, a click on the rock between two tunnels, where no open space is under
    the cursor (the ray meets no face of the mine): a hint says so, in the form and where the
    click was; no point is filled or marked, the map still waits for a click, and nothing is
    sent. The form is docked at the pane's right edge (the map's middle and left, where clicks
    go, stay in sight) and folds to its title; its hint says Esc stops picking. Add task with
    nothing filled says what is missing, and the click hint goes; closing the form clears it."""
    with live_run(tmp_path) as live:  # (the run need not step)
        errors = open_page(page, f"{live.url}?token={TOKEN}")
        sent: list[str] = []
        page.on("request", lambda r: sent.append(f"{r.method} {r.url}") if r.method != "GET" else None)  # fmt: skip
        page.click("#btn-top")
        next_frames(page)
        page.click("#btn-add-task")
        armed_hint = page.text_content("#pick-hint")
        pane, form = _rect(page, "#view3d"), _rect(page, "#task-form")
        page.click("#task-form-fold")
        folded = _rect(page, "#task-form")
        folded_hint = page.is_visible("#pick-hint") and page.is_hidden("#task-form [name=id]")
        page.click("#task-form-fold")
        lo, hi = live.run.map.bounds
        found = page.evaluate(_PICK_ROCK, [_rock_columns(live.run.map), hi[2]])
        assert found, "no rock column in sight in the Top view"
        x, y, _d, wx, wy = found
        assert lo[0] < wx < hi[0] and lo[1] < wy < hi[1]  # (the map's floor is under it)
        page.mouse.click(x, y)
        wait_js(page, "!document.getElementById('pick-note').hidden", 5)
        next_frames(page, 2)
        page.screenshot(path=str(tmp_path / "rock.png"))
        hint = page.text_content("#pick-hint")
        note = page.text_content("#pick-note")
        filled = page.evaluate(
            "['x', 'y', 'z'].map(c => document.querySelector(`#task-form [name='location.${c}']`).value)"
        )
        points = page.evaluate("btm.ops.points.size")
        marks = page.evaluate("[...btm.scene.marks.values()].filter(o => o.group.visible).length")
        arming = page.evaluate("document.getElementById('view3d').classList.contains('arming')")
        page.click("#task-form-submit")  # nothing filled: said on the form, nothing sent
        missing = page.text_content("#task-form-msg")
        hint_after_submit = page.is_visible("#pick-hint")
        arming_after_submit = page.evaluate(
            "document.getElementById('view3d').classList.contains('arming')"
        )
        page.click("#task-form-close")
        closed = page.is_hidden("#task-form") and page.is_hidden("#pick-note")
        time.sleep(0.5)  # (a request would have gone by now)
    assert errors == []
    assert armed_hint is not None and "Esc stops picking" in armed_hint
    mid = (pane[0] + pane[2]) / 2
    assert mid < form[0] and form[2] <= pane[2]  # docked right, clear of the middle and left
    assert folded[3] - folded[1] < 90 and folded_hint
    miss = "no open space under the cursor: click a tunnel (its floor or a wall)"
    assert hint is not None and miss in hint and "Esc stops picking" in hint
    assert note is not None and miss in note
    assert filled == ["", "", ""] and points == 0 and marks == 0 and arming
    assert missing is not None and "location: give x, y and z" in missing
    assert not hint_after_submit and not arming_after_submit and closed
    assert sent == []


def test_a_task_inside_rock_is_refused_with_the_reason(page: Any, tmp_path: Path) -> None:
    """Coordinates typed into the form that are inside rock: the page shows the server's
    refusal, the form stays open with the location marked; nothing is added."""
    with live_run(tmp_path) as live:
        errors = open_page(page, f"{live.url}?token={TOKEN}")
        live.go()
        rock = _rock_point(live.run.map)
        before = wait_js(page, "document.querySelectorAll('#tasks tbody tr').length >= 6")
        before = _task_rows(page)
        page.click("#btn-add-task")  # the form opens, add mode is armed ...
        page.keyboard.press("Escape")  # ... and Esc disarms it (the form stays)
        assert not page.evaluate("document.getElementById('view3d').classList.contains('arming')")
        assert page.is_visible("#task-form")
        for c, v in zip("xyz", rock, strict=True):
            page.fill(f"#task-form [name='location.{c}']", str(v))
        page.click("#task-form-submit")
        wait_js(page, _last_result("inside rock"), 20)
        page.screenshot(path=str(tmp_path / "refused.png"))
        docs_shot(page, "console_refused.png")
        entries = _console_log(page)
        message = page.text_content("#task-form-msg")
        marked = page.evaluate(
            "[...document.querySelectorAll('#task-form .row.bad')].map(r => r.dataset.field)"
        )
        form_open = page.is_visible("#task-form")
        after = _task_rows(page)
        live.stop()
    assert errors == []
    assert entries[0][0] == "0" and "location" in entries[0][1] and "inside rock" in entries[0][1]
    assert message is not None and "inside rock" in message
    assert marked == ["location"] and form_open
    assert "T8" not in after and set(before) <= set(after)
    events = _events(live.log)
    assert not [e for e in events if e.kind == "task_added" and e.get("task") == "T8"]
    adds = [e for e in events if e.kind == "command" and e.get("command") == "add_task"]
    assert adds and all(e.get("ok") is False and "inside rock" in e.get("error") for e in adds)
    assert adds[0].get("by") == "page@127.0.0.1"  # refused, and logged: who tried what


def test_cancel_pause_exclude_then_the_page_closes(page: Any, tmp_path: Path) -> None:
    """A task an agent holds is cancelled from its row's ✕: the log has it cancelled and that
    agent's next task is not it. Allocation is paused and resumed, the agent taken out of the
    auction and back, then recalled (its tab dashed, Recall disabled, Include offered) and
    included again (it bids again), each reflected by the page from api/status. Then the page
    closes and the run goes on to its end time."""
    until = 200.0
    with live_run(tmp_path, until=until) as live:
        errors = open_page(page, f"{live.url}?token={TOKEN}")
        live.go()
        wait_js(page, "window.btm.state.viewT > 3")  # the agents have taken their tasks
        task, agent = wait_js(
            page,
            "(() => { const r = [...document.querySelectorAll('#tasks tbody tr[data-state=\"assigned\"]')]"
            ".find(r => r.querySelector('button.cancel-task'));"
            " return r && [r.dataset.task, r.children[3].textContent]; })()",
        )
        page.click(f"#tasks tr[data-task='{task}'] button.cancel-task")
        wait_js(page, _last_result(f"{task} cancelled"), 20)
        wait_js(
            page,
            f"document.querySelector('#tasks tr[data-task=\"{task}\"]').dataset.state === 'cancelled'",
        )
        cancel_gone = page.evaluate(
            f"!document.querySelector('#tasks tr[data-task=\"{task}\"] button.cancel-task')"
        )
        page.click("#btn-pause")
        wait_js(
            page, "document.getElementById('btn-pause').textContent === 'Resume allocation'", 15
        )
        paused_said = page.evaluate("document.body.dataset.lastResult")
        page.click("#btn-pause")
        wait_js(page, "document.getElementById('btn-pause').textContent === 'Pause allocation'", 15)
        page.click(f"#agent-tabs button[data-agent='{agent}']")
        page.click("#btn-exclude")
        wait_js(page, "[...document.querySelectorAll('#agent-actions .chip')].some(c => c.textContent === 'excluded')", 15)  # fmt: skip
        page.screenshot(path=str(tmp_path / "excluded.png"))
        assert page.text_content("#btn-exclude") == "Include"
        page.click("#btn-exclude")
        wait_js(page, "document.getElementById('btn-exclude').textContent === 'Exclude'", 15)
        # recalled: out of the auction like an excluded agent, and Include brings it back
        page.click("#btn-recall")
        wait_js(page, "[...document.querySelectorAll('#agent-actions .chip')].some(c => c.textContent === 'recalled')", 15)  # fmt: skip
        page.screenshot(path=str(tmp_path / "recalled.png"))
        recalled_buttons = page.evaluate(
            "[...document.querySelectorAll('#agent-actions button')].map(b => [b.id, b.textContent, b.disabled])"
        )
        tab = f"document.querySelector('#agent-tabs button[data-agent=\"{agent}\"]')"
        recalled_tab = page.evaluate(f"[{tab}.classList.contains('out'), getComputedStyle({tab}).borderTopStyle]")  # fmt: skip
        page.click("#btn-exclude")
        wait_js(
            page,
            "document.getElementById('btn-exclude').textContent === 'Exclude'"
            " && !document.getElementById('btn-recall').disabled"
            " && ![...document.querySelectorAll('#agent-actions .chip')].some(c => c.textContent === 'recalled')",
            15,
        )
        status = page.evaluate(f"btm.ops.agentStatus.get({agent!r})")
        included_tab = page.evaluate(f"{tab}.classList.contains('out')")
        entries = _console_log(page)
        t_closed = float(page.evaluate("window.btm.state.viewT"))
        page.close()  # the browser goes away while the run goes on
        live.join(90.0)
    assert errors == []
    assert t_closed < until
    (result,) = live.result
    assert result.reason == "until" and result.time_s == pytest.approx(until)
    assert cancel_gone and "allocation paused" in paused_said
    assert [b[:2] for b in recalled_buttons][:2] == [
        ["btn-recall", "⌂ Recall"],
        ["btn-exclude", "Include"],
    ]
    assert recalled_buttons[0][2] and not recalled_buttons[1][2]  # Recall disabled, Include not
    assert recalled_tab == [True, "dashed"] and not included_tab
    assert status["recalled"] is False and status["excluded"] is False
    assert all(ok == "1" for ok, _ in entries)
    events = _events(live.log)
    (cancelled,) = [e for e in events if e.kind == "task" and e.get("task") == task and e.get("state") == "cancelled"]  # fmt: skip
    later = [e for e in events if e.kind == "task" and e.get("task") == task and e.t > cancelled.t]
    assert later == []  # never taken up again
    held = [e for e in events if e.kind == "agent_task" and e.get("agent") == agent]
    before = [e for e in held if e.t < cancelled.t]
    after = [e for e in held if e.t >= cancelled.t]
    assert before and before[-1].get("task") == task  # it was executing it ...
    assert after and after[0].get("task") != task  # ... and then not (none, or another task)
    assert all(e.get("task") != task for e in after)
    ops = [
        (e.get("command"), e.get("ok"), e.get("paused"), e.get("agent"))
        for e in events
        if e.kind == "command" and str(e.get("by", "")).startswith("page@")
    ]
    assert ops == [
        ("cancel_task", True, None, None),
        ("set_allocation", True, True, None),
        ("set_allocation", True, False, None),
        ("exclude_agent", True, None, agent),
        ("include_agent", True, None, agent),
        ("recall_agent", True, None, agent),
        ("include_agent", True, None, agent),
    ]
    # back in the auction: a task assigned to it after the include, or (none left for it) its
    # status says it is no longer recalled (asserted above)
    included = [e for e in events if e.kind == "command" and e.get("command") == "include_agent"][-1]  # fmt: skip
    won = [e for e in events if e.kind == "task" and e.get("state") == "assigned" and e.get("agent") == agent and e.t >= included.t]  # fmt: skip
    assert won or status["recalled"] is False


def test_a_view_only_page_has_no_console(page: Any, tmp_path: Path) -> None:
    """A live run served without its console (``run --view``): a read-only badge with the
    reason, no console controls, and the server refuses a command sent anyway."""
    with live_run(tmp_path, console=False, until=30.0) as live:
        errors = open_page(page, live.url)
        live.go()
        wait_js(page, "document.querySelectorAll('#tasks tbody tr').length >= 6")
        badge = page.is_visible("#console-ro")
        title = page.get_attribute("#console-ro", "title")
        hidden = page.evaluate(
            "['btn-add-task', 'btn-pause', 'console-panel', 'task-form', 'token-form', 'agent-actions']"
            ".filter(id => document.getElementById(id).offsetParent !== null)"
        )
        controls = page.evaluate(
            "document.querySelectorAll('button.cancel-task, select.task-priority').length"
        )
        refused = page.evaluate(
            """fetch('api/tasks', {method: 'POST', headers: {'Content-Type': 'application/json',
                'X-Btmission-Client': 'page'}, body: JSON.stringify({type: 'inspect', location: [8, 3, 1]})})
              .then(async r => [r.status, (await r.json()).message])"""
        )
        live.stop()
    assert errors == []
    assert badge and title is not None and "read-only" in title and "--console" in title
    assert hidden == [] and controls == 0
    assert refused[0] == 403 and "read-only" in refused[1]


def test_the_token_is_asked_for_when_the_page_has_none(page: Any, tmp_path: Path) -> None:
    """Without a token the console bar asks for it; a command then says it needs one (401), a
    wrong one is refused (403) and the input opens again. The URL's token is kept for the tab
    and taken out of the address bar."""
    with live_run(tmp_path) as live:  # (the run need not step: these are refused up front)
        errors = open_page(page, live.url)
        asked = page.is_visible("#token-input")
        page.click("#btn-pause")
        wait_js(page, _last_result("token"), 10)
        no_token = _console_log(page)[0]
        page.fill("#token-input", "not-the-token")
        page.click("#token-form button[type=submit]")
        closed = page.is_hidden("#token-form")
        page.click("#btn-pause")
        wait_js(page, _last_result("wrong token"), 10)
        asked_again = page.is_visible("#token-input")
        page.goto(f"{live.url}?token={TOKEN}")  # the URL the terminal printed
        page.wait_for_selector("body[data-ready='1']", timeout=30_000)
        url = page.url
        stored = page.evaluate("sessionStorage.getItem('btm-token')")
        asked_with_token = page.is_visible("#token-input")
    assert errors == []
    assert asked and closed and asked_again and not asked_with_token
    assert no_token[0] == "0" and "needs the run's token" in no_token[1]
    assert no_token[1].endswith("— paste it in the token field")
    assert url == live.url and stored == TOKEN


def test_the_form_proposes_the_types_own_next_id(page: Any, tmp_path: Path) -> None:
    """A mission with two task types (pick_and_deliver's P1, inspect's I1, I2): the form's Id
    is the selected type's next id (api/info's next_task_ids: P2, I3) when it opens and when the
    type changes, until the operator writes one; without next_task_ids (a server before it)
    it stays next_task_id. The form's priority menu and the table's say the same. (Its map has
    no rock: a click is picked on the map's floor.)"""
    with live_run(tmp_path, mission=PICK_AND_DELIVER, until=60.0) as live:
        errors = open_page(page, f"{live.url}?token={TOKEN}")
        live.go()
        wait_js(page, "document.querySelector('#tasks tr[data-task=\"P1\"] select.task-priority')")
        table_priority = page.evaluate(
            "document.querySelector('#tasks tr[data-task=\"P1\"] select.task-priority').selectedOptions[0].textContent"
        )
        cfg = page.evaluate("btm.ops.cfg")
        types = sorted(cfg["task_types"])
        server_ids = cfg.get("next_task_ids")
        page.click("#btn-add-task")
        x, y = page.evaluate("btm.worldScreen([6, 4, 0])")
        floor = page.evaluate(f"[btm.scene.hasRock(), btm.surfacePick({x}, {y})]")
        page.keyboard.press("Escape")
        form_priority = page.evaluate(
            "document.querySelector('#task-form [name=priority]').selectedOptions[0].textContent"
        )

        def proposed(kind: str) -> str:
            page.select_option("#task-form [name=type]", kind)
            return str(page.input_value("#task-form [name=id]"))

        fallback = None
        if server_ids is None:  # a server before next_task_ids: the one id for every type ...
            fallback = [proposed(k) for k in types]
            ids = {"inspect": "I9", "pick_and_deliver": "P9"}  # ... and the page's use of them
            page.evaluate(f"btm.ops.cfg.next_task_ids = {ids!r}")
        else:
            ids = server_ids
        by_type = {k: proposed(k) for k in types}
        page.fill("#task-form [name=id]", "X1")  # the operator's own id stays
        kept = [proposed(k) for k in reversed(types)]
        page.click("#task-form-close")
        page.click("#btn-add-task")  # a new form: the type's id again
        reopened = (page.input_value("#task-form [name=type]"), page.input_value("#task-form [name=id]"))  # fmt: skip
        live.stop()
    assert errors == []
    assert types == ["inspect", "pick_and_deliver"]
    assert floor[0] is False and floor[1]["p"] == pytest.approx([6, 4, 0], abs=0.05)
    if fallback is not None:
        assert fallback == [cfg["next_task_id"]] * 2
    else:  # the mission's P1 and I1, I2 (I2 comes at 40 s: I2 or I3)
        assert ids["pick_and_deliver"] == "P2" and ids["inspect"] in ("I2", "I3")
    assert by_type == {k: ids[k] for k in types}
    assert kept == ["X1", "X1"]
    assert reopened == ("inspect", ids["inspect"])
    assert table_priority == form_priority == "normal (×1)"


def test_the_page_says_when_the_runs_server_has_gone(page: Any, tmp_path: Path) -> None:
    """The viewer's server stops while the page watches (the process killed, say: no
    ``complete`` reaches the page): the page says the run's server has gone, in the title bar
    and the console log, and disables the controls, instead of reconnecting for ever."""
    with live_run(tmp_path) as live:
        errors = open_page(page, f"{live.url}?token={TOKEN}")
        live.go()
        wait_js(page, "window.btm.state.viewT > 2")
        live.viewer.server.close()  # the HTTP server only: the run goes on, its feed open
        wait_js(page, "document.body.dataset.gone === '1'", 20)
        conn = page.text_content("#conn")
        first = _console_log(page)[0]
        disabled = page.evaluate(
            "['btn-add-task', 'btn-pause', 'task-form-submit'].map(id => document.getElementById(id).disabled)"
        )
        mode = page.text_content("#mode")
        complete = page.evaluate("document.body.dataset.complete")
        time.sleep(3.0)  # no reconnecting afterwards
        conn_later = page.text_content("#conn")
    assert errors == []
    gone = "the run's server has gone (the run ended or was stopped)"
    assert conn == gone and conn_later == gone and first == ("0", gone)
    assert disabled == [True, True, True] and mode == "ENDED" and complete is None
