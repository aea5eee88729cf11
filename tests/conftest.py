"""Shared fixtures: the built-in libraries, a CLI runner, small library builders, a browser."""

from __future__ import annotations

import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from click.testing import CliRunner

from btmission.plugins import load_library
from btmission.spec.library import Library, load_library_text
from tests.wallclock import WallClock

if TYPE_CHECKING:
    from playwright.sync_api import Browser, Page

    from tests.browser import BrowserSession


@pytest.fixture(scope="session")
def aerial() -> Library:
    return load_library("aerial").library


@pytest.fixture(scope="session")
def ground() -> Library:
    return load_library("ground").library


@pytest.fixture()
def runner() -> CliRunner:
    return CliRunner()


def lib_from(body: str, file: str = "lib.yaml"):  # type: ignore[no-untyped-def]
    """Load a library from an indented YAML snippet; returns (library, diagnostics)."""
    return load_library_text(textwrap.dedent(body).lstrip("\n"), file)


# -- the browser (tests/browser.py: flags, skip-or-fail under CI, why `browser` is per test) -----
# Imported inside the fixtures: tests that use no browser never load Playwright, Pillow or numpy.


@pytest.fixture(scope="session")
def browser_session() -> Iterator[BrowserSession]:
    """One headless chromium for the session; skips (fails when CI is set) if it cannot start."""
    from tests.browser import BrowserSession

    session = BrowserSession.launch()
    yield session
    session.close()


@pytest.fixture()
def browser(browser_session: BrowserSession) -> Iterator[Browser]:
    """The session's chromium, usable for the length of one test."""
    with browser_session.active() as active:
        yield active


@pytest.fixture()
def page(browser: Browser) -> Iterator[Page]:
    """A new page with the fixed viewport tests.browser.VIEWPORT (1280x800), closed after the test."""
    from tests.browser import VIEWPORT

    page = browser.new_page(viewport=VIEWPORT)
    yield page
    page.close()


@pytest.fixture(scope="session")
def mine_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The event log of the seed 000 mission's first 120 s (track controller): tasks assigned
    and done, routes, tree events with blackboards, poses (the viewer's tests replay it)."""
    from btmission.runtime.session import RunSession

    path = tmp_path_factory.mktemp("mine-log") / "mine.jsonl"
    mission = Path(__file__).resolve().parents[1] / "missions" / "mine_inspection.yaml"
    with RunSession(mission, controller="track", log_path=path) as s:
        s.run(until=120.0)
    return path


# -- a failure on a busy machine says so (tests/load.py) -----------------------------------------
@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    from tests.load import load_per_cpu, note

    if call.when == "setup":
        item.stash[_LOAD_AT_START] = load_per_cpu()
    outcome = yield
    report = outcome.get_result()  # type: ignore[attr-defined]
    if report.failed:
        text = note(item.stash.get(_LOAD_AT_START, None))
        if text is not None:
            report.sections.append(("machine load", text))


_LOAD_AT_START = pytest.StashKey[float]()


@pytest.fixture()
def wall(monkeypatch: pytest.MonkeyPatch) -> WallClock:
    """A wall clock the test moves by hand: ``time.monotonic`` reads ``wall.t``."""
    clock = WallClock()
    monkeypatch.setattr("time.monotonic", clock)
    return clock
