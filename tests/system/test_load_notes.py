"""A test that fails on a busy machine says the machine was busy (tests/load.py, conftest.py);
wall-clock bounds stretch with the load."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests import load

ROOT = Path(__file__).resolve().parents[2]

pytest_plugins = ["pytester"]


def test_the_margin_follows_the_load_per_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(load.os, "cpu_count", lambda: 2)
    for load1, want in ((0.5, 1.0), (2.0, 1.0), (6.0, 3.0), (40.0, load.MAX_MARGIN)):
        monkeypatch.setattr(load.os, "getloadavg", lambda v=load1: (v, v, v))
        assert load.margin() == want
    monkeypatch.setattr(load.os, "getloadavg", lambda v=10.0: (v, v, v))
    text = load.note(at_start=1.0)
    assert text is not None and "load average 10.0 on 2 CPUs (2.0 when it started)" in text
    monkeypatch.setattr(load.os, "getloadavg", lambda v=1.0: (v, v, v))
    assert load.note(at_start=0.5) is None  # a quiet machine: nothing to say


@pytest.mark.parametrize(("load1", "said"), [(30.0, True), (0.2, False)])
def test_a_failure_on_a_busy_machine_says_so(
    pytester: pytest.Pytester, load1: float, said: bool
) -> None:
    pytester.makeconftest(
        f"import os, sys\nsys.path.insert(0, {str(ROOT)!r})\n"
        f"os.getloadavg = lambda: ({load1}, {load1}, {load1})\n"
        "os.cpu_count = lambda: 2\n"
        "from tests.conftest import pytest_runtest_makereport, _LOAD_AT_START  # noqa: F401\n"
    )
    pytester.makepyfile("def test_late():\n    assert False, 'no heartbeat within 5 s'\n")
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider", "-p", "no:xdist")
    result.assert_outcomes(failed=1)
    text = result.stdout.str()
    assert ("machine load" in text and "load average 30.0 on 2 CPUs" in text) is said
