"""One root exception (issue #35): every exception class btmission defines is a BtmissionError.

* every module of btmission (the CLI and the built-in libraries included) is imported and each
  exception class defined in it must derive from :class:`~btmission.errors.BtmissionError`, so a
  new class without the root fails here;
* each keeps the standard base its callers catch (``except ValueError`` still works);
* the exceptions round-trip through pickle;
* the CLI's last-resort handler reports them as before (exit codes unchanged);
* the example in docs/api.md prints what the page shows.
"""

from __future__ import annotations

import ast
import contextlib
import importlib
import inspect
import io
import os
import pickle
import pkgutil
import re
from functools import cache
from pathlib import Path
from types import ModuleType

import click
import pytest
from click.testing import CliRunner, Result

from btmission.errors import BtmissionError

ROOT = Path(__file__).resolve().parents[3]
OURS = ("btmission", "btmission_library")
"""Top-level packages whose modules are btmission's (``btmission.cli`` is under ``btmission``)."""

OUTSIDE_THE_ROOT: dict[str, str] = {
    "btmission.runtime.session.RunStopped": "a BaseException like KeyboardInterrupt, so that "
    "`except Exception` in library code does not swallow a stop signal; BtmissionError is an "
    "Exception",
}
"""Exception classes that deliberately do not derive from BtmissionError, and why."""

NEEDS_MORE: dict[str, str] = {
    "btmission.diagnostics.SpecError": "a list of Diagnostic",
    "btmission.console.service.ConsoleError": "an HTTP status, then the message",
    "btmission.console.api._TooLarge": "the limit in bytes (an int)",
    "btmission.spec.source.FileRefused": "the message and a code",
}
"""Exception classes that cannot be built from one message string (left out of the pickle
round-trip), and what their constructor takes instead."""

SAMPLE_MESSAGE: dict[str, str] = {"btmission.runtime.session.RunStopped": "interrupted"}
"""The single string argument for classes that take a particular one (default: a message)."""


def _walk(package: ModuleType) -> list[str]:
    """Names of ``package`` and of every module under it (packages that fail are listed too:
    importing them again reports why)."""
    names = [package.__name__]
    for info in pkgutil.walk_packages(package.__path__, package.__name__ + ".", lambda n: None):
        names.append(info.name)
    return names


@cache
def _modules() -> tuple[tuple[ModuleType, ...], tuple[str, ...]]:
    """Every module of btmission, and the ones skipped because a third-party package they need
    is not installed (``name: missing package``)."""
    import btmission.cli
    import btmission_library

    names: list[str] = []
    for package in (btmission, btmission.cli, btmission_library):
        # an editable install maps btmission.cli from cli/, outside btmission's __path__
        names += [n for n in _walk(package) if n not in names]
    modules: list[ModuleType] = []
    skipped: list[str] = []
    for name in names:
        try:
            modules.append(importlib.import_module(name))
        except ImportError as exc:
            if exc.name is None or exc.name.partition(".")[0] in OURS:
                raise  # a broken import of our own, not an optional dependency
            skipped.append(f"{name}: {exc.name}")
    return tuple(modules), tuple(skipped)


@cache
def exception_classes() -> dict[str, type[BaseException]]:
    """``module.qualname`` → every exception class defined in a btmission module."""
    found: dict[str, type[BaseException]] = {}
    for module in _modules()[0]:
        for obj in vars(module).values():
            if (
                isinstance(obj, type)
                and issubclass(obj, BaseException)
                and obj.__module__ == module.__name__
            ):
                found[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return found


# ------------------------------------------------------------------------------ the root
def test_every_module_imports() -> None:
    """A module left out for a missing optional dependency is a skip here (shown by -ra), and a
    failure in CI, where every extra is installed."""
    modules, skipped = _modules()
    assert len(modules) > 150  # the walk saw the package (btmission.cli and the libraries too)
    if skipped:
        message = "not imported, a third-party package is missing: " + "; ".join(skipped)
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)


def test_every_exception_class_derives_from_the_root() -> None:
    found = exception_classes()
    assert len(found) >= 40, sorted(found)  # a vacuous walk would pass
    without = sorted(
        name
        for name, cls in found.items()
        if not issubclass(cls, BtmissionError) and name not in OUTSIDE_THE_ROOT
    )
    assert without == [], (
        "derive these from btmission.errors.BtmissionError (keeping their standard base, e.g. "
        "`class XError(BtmissionError, ValueError)`), or list them in OUTSIDE_THE_ROOT with why"
    )
    for name in OUTSIDE_THE_ROOT:  # no stale entry
        assert name in found and not issubclass(found[name], BtmissionError), name


def test_the_root_is_at_the_bottom() -> None:
    """btmission.errors imports nothing of btmission (every layer imports it)."""
    tree = ast.parse((ROOT / "btmission" / "errors.py").read_text(encoding="utf-8"))
    imported = [
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.Import)
        for alias in node.names
    ] + [node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)]
    assert not [m for m in imported if m.partition(".")[0] in OURS]


# ------------------------------------------------------------------ what callers catch
@pytest.mark.parametrize(
    ("name", "standard"),
    [
        ("btmission.spec.costexpr.CostExprError", ValueError),
        ("btmission.world.voxel.MapError", ValueError),
        ("btmission.planning.dstar.PlanningError", ValueError),
        ("btmission.links.wire.UnknownAnnouncement", ValueError),
        ("btmission.spec.source.FileRefused", OSError),
        ("btmission.vehicles.provider.ProviderError", LookupError),
        ("btmission.vehicles.provider.VehicleUnavailable", RuntimeError),
        ("btmission.backends.mavlink_link.MavlinkError", RuntimeError),
        ("btmission.transport.zenoh_session.ZenohMissing", RuntimeError),
        ("btmission.cli.common.BadInput", click.ClickException),
        ("btmission.cli.common.ChecksFailed", click.ClickException),
    ],
)
def test_each_keeps_its_standard_base(name: str, standard: type[Exception]) -> None:
    cls = exception_classes()[name]
    assert issubclass(cls, BtmissionError) and issubclass(cls, standard)


def test_subclasses_of_our_exceptions_keep_them() -> None:
    found = exception_classes()
    pairs = [
        ("btmission.backends.mavlink_link.MavlinkError", "btmission.vehicles.provider.VehicleUnavailable"),
        ("btmission.planning.dstar.PlanningError", "btmission.world.voxel.MapError"),
        ("btmission.links.wire.UnknownAnnouncement", "btmission.links.wire.WireError"),
        ("btmission.transport.zenoh_session.ZenohMissing", "btmission.transport.zenoh_session.TransportError"),
    ]  # fmt: skip
    for sub, base in pairs:
        assert issubclass(found[sub], found[base]), sub


def test_spec_error_is_an_exception_not_a_value_error() -> None:
    """What it always was: callers catch SpecError itself (it carries the diagnostics)."""
    from btmission.diagnostics import Diagnostic, Severity, SpecError

    exc = SpecError([Diagnostic(Severity.ERROR, "bad-thing", "a bad thing")])
    assert isinstance(exc, BtmissionError) and not isinstance(exc, ValueError)
    assert exc.diagnostics[0].message == "a bad thing"


def test_a_raised_error_is_caught_by_its_standard_base_and_by_the_root() -> None:
    from btmission.spec.costexpr import CostExprError, parse_cost

    for catch in (ValueError, BtmissionError, CostExprError):
        with pytest.raises(catch, match="unknown function 'speed'"):
            parse_cost("speed(location)")


def test_file_refused_is_still_an_os_error_without_errno(tmp_path: Path) -> None:
    from btmission import limits
    from btmission.spec.source import FileRefused, read_regular_file

    with pytest.raises(OSError) as info:
        read_regular_file(tmp_path, limits.MAX_FILE_BYTES)
    exc = info.value
    assert isinstance(exc, FileRefused) and isinstance(exc, BtmissionError)
    assert exc.errno is None and exc.code == "unreadable" and "a directory" in str(exc)


def test_run_stopped_stays_outside_exception() -> None:
    from btmission.runtime.session import RunStopped

    assert not issubclass(RunStopped, Exception)
    assert RunStopped("terminated").code == 143


# ------------------------------------------------------------------------------- pickling
def _needs_more(cls: type[BaseException]) -> bool:
    """Whether ``cls`` cannot be built from one message string: its own ``__init__`` (if one of
    btmission's classes defines it) takes something else, or more."""
    owner = next(c for c in cls.__mro__ if "__init__" in vars(c))
    if owner.__module__.partition(".")[0] not in OURS:
        return False  # Exception's, ClickException's: (message)
    params = list(inspect.signature(vars(owner)["__init__"]).parameters.values())[1:]
    required = [
        p
        for p in params
        if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]
    return len(required) != 1 or required[0].annotation not in ("str", str)


def test_the_classes_that_need_more_than_a_message_are_listed() -> None:
    found = exception_classes()
    assert {n for n, cls in found.items() if _needs_more(cls)} == set(NEEDS_MORE)


def test_exceptions_round_trip_through_pickle() -> None:
    """Every exception built from one string comes back equal: type, args, message, attributes
    (those in NEEDS_MORE are left out)."""
    broken = []
    for name, cls in sorted(exception_classes().items()):
        if name in NEEDS_MORE:
            continue
        exc = cls(SAMPLE_MESSAGE.get(name, "a message"))
        back = pickle.loads(pickle.dumps(exc))
        if (type(back), back.args, str(back), vars(back)) != (cls, exc.args, str(exc), vars(exc)):
            broken.append(name)
    assert broken == []


# ------------------------------------------------------------- the CLI's last-resort handler
@pytest.fixture
def state_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    state = tmp_path / "state"
    monkeypatch.setenv("XDG_STATE_HOME", str(state))
    monkeypatch.delenv("BTMISSION_DEBUG", raising=False)
    return state


def _synth_raising(monkeypatch: pytest.MonkeyPatch, exc: BaseException) -> Result:
    """``synth --dry-run`` with the dry run raising ``exc``."""
    import btmission.cli.synth_cmds as synth_cmds
    from btmission.cli.main import cli

    def fail(*args: object, **kwargs: object) -> None:
        raise exc

    monkeypatch.setattr(synth_cmds, "dry_run_fn", fail)
    return CliRunner().invoke(cli, ["synth", "aerial", "--goal", "at_goal(goal)", "--dry-run"])


@pytest.mark.parametrize(
    ("make", "shown"),
    [
        ("costexpr", "CostExprError: unknown function 'speed'"),
        # an OSError without errno: not the environment refusing (exit 2), a bug (70)
        ("refused", "FileRefused: /x is a directory"),
    ],
)
def test_an_escaping_btmission_error_is_still_an_internal_error(
    make: str, shown: str, state_home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A BtmissionError the command did not turn into a message is a bug of the command: one
    line, exit 70 and a traceback file, as for any other exception."""
    from btmission.spec.costexpr import CostExprError
    from btmission.spec.source import FileRefused

    exc = {
        "costexpr": CostExprError("unknown function 'speed'"),
        "refused": FileRefused("/x is a directory", "unreadable"),
    }[make]
    r = _synth_raising(monkeypatch, exc)
    assert r.exit_code == 70, r.output
    (line,) = r.stderr.splitlines()
    assert line.startswith(f"internal error: {shown}; details in ")
    assert "Traceback" not in r.output
    assert len(list((state_home / "btmission").iterdir())) == 1


@pytest.mark.parametrize(("cls", "code"), [("BadInput", 2), ("ChecksFailed", 1)])
def test_the_cli_own_errors_keep_their_exit_codes(
    cls: str, code: int, state_home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import btmission.cli.common as common

    r = _synth_raising(monkeypatch, getattr(common, cls)("the reason"))
    assert r.exit_code == code
    assert r.stderr.strip() == "Error: the reason"
    assert not (state_home / "btmission").exists()


def test_the_error_sink_still_lets_spec_errors_and_click_errors_pass() -> None:
    from btmission.cli.common import BadInput, internal_error_sink
    from btmission.diagnostics import Diagnostic, Severity, SpecError
    from btmission.spec.costexpr import CostExprError

    seen: list[str] = []

    def sink(exc: BaseException, trace: str) -> None:
        seen.append(type(exc).__name__)

    expected = [SpecError([Diagnostic(Severity.ERROR, "x", "x")]), BadInput("x")]
    for exc in [*expected, CostExprError("x")]:
        with contextlib.suppress(type(exc)), internal_error_sink(sink):
            raise exc
    assert seen == ["CostExprError"]


# ------------------------------------------------------------------------------- the docs
def test_the_docs_example_prints_what_the_page_shows(monkeypatch: pytest.MonkeyPatch) -> None:
    page = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    section = page.split("## Errors: `BtmissionError`\n", 1)[1].split("\n## ", 1)[0]
    m = re.search(r"```python\n(.*?)```\s*prints\s*```text\n(.*?)```", section, re.S)
    assert m is not None
    monkeypatch.chdir(ROOT)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(m.group(1), "<docs example>", "exec"), {"__name__": "__docs_example__"})
    assert out.getvalue() == m.group(2)
