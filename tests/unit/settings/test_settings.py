"""Typed settings (issue #35 item 5): declared once by whoever reads them, checked by
``validate`` against the declared type, built once per run (btmission/settings.py)."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from btmission.cli.main import cli
from btmission.plugins import Implementations
from btmission.runtime.navconfig import SETTINGS_DOC, NavConfig
from btmission.settings import (
    RunSettings,
    Setting,
    SettingError,
    declared_settings,
    settings_from,
    settings_of,
)

ROOT = Path(__file__).resolve().parents[3]


@dataclass(frozen=True)
class Sample:
    """Settings of every type a setting may have."""

    count: int = 3
    """How many."""
    gain: float = 0.5
    """How strong.

    A second paragraph, for readers of the code."""
    enabled: bool = False
    label: str = field(default="", metadata={"doc": "what the metadata says"})
    """The attribute docstring, which the metadata overrides."""


# ------------------------------------------------------------------------------- declaring
def test_a_dataclass_declares_types_defaults_and_docs() -> None:
    declared = declared_settings(Sample)
    assert list(declared) == ["count", "gain", "enabled", "label"]
    assert declared["count"] == Setting("count", int, 3)
    assert declared["count"].doc == "How many."
    assert declared["gain"].kind is float
    assert declared["gain"].doc == "How strong.\n\nA second paragraph, for readers of the code."
    assert declared["enabled"] == Setting("enabled", bool, False)
    assert declared["enabled"].doc == ""
    assert declared["label"].doc == "what the metadata says"


def test_a_mapping_declares_by_its_defaults() -> None:
    declared = declared_settings({"n": 200, "t_s": 2.0, "flag": True, "path": ""})
    assert {name: s.kind for name, s in declared.items()} == {
        "n": int, "t_s": float, "flag": bool, "path": str,
    }  # fmt: skip
    assert Implementations("old", settings={"scan_time_s": 3.0}).settings == {"scan_time_s": 3.0}


@pytest.mark.parametrize(
    "source, message",
    [
        ("@dataclass\nclass S:\n    a: int = 1\n", "S: settings are declared as a frozen dataclass"),
        ("class S:\n    a: int = 1\n", "S: settings are declared as a frozen dataclass"),
        ("@dataclass(frozen=True)\nclass S:\n    a: int\n", "S: setting 'a' has no default"),
        ("@dataclass(frozen=True)\nclass S:\n    a: list[int] = ()\n", "S: setting 'a' is a list[int]"),
        ("@dataclass(frozen=True)\nclass S:\n    a: int = 1.5\n",
         "S: setting 'a': default expected an integer (got 1.5)"),
        ("@dataclass(frozen=True)\nclass S:\n    a: float = True\n",
         "S: setting 'a': default expected a number (got true)"),
    ],
)  # fmt: skip
def test_a_declaration_that_is_not_one_is_refused_when_the_library_loads(
    source: str, message: str
) -> None:
    space: dict[str, Any] = {"dataclass": dataclass}
    exec(source, space)
    with pytest.raises(TypeError, match="^" + re.escape(message)):
        Implementations("lib", settings=space["S"])


def test_a_mapping_default_of_another_type_is_refused() -> None:
    with pytest.raises(TypeError, match="lib: setting 'ids': default \\[1\\] is a list"):
        Implementations("lib", settings={"ids": [1]})  # type: ignore[dict-item]


def test_extend_combines_the_declarations() -> None:
    @dataclass(frozen=True)
    class Base:
        speed_m_s: float = 0.4
        pick_s: float = 2.0

    @dataclass(frozen=True)
    class Variant:
        pick_s: float = 3.0
        extra: str = "x"

    variant = Implementations("base", settings=Base).extend("variant", settings=Variant)
    assert variant.settings == {"speed_m_s": 0.4, "pick_s": 3.0, "extra": "x"}
    assert variant.declared["extra"].kind is str
    with pytest.raises(TypeError, match="v2: setting 'pick_s' is declared int here and float"):
        Implementations("base", settings=Base).extend("v2", settings={"pick_s": 3})
    with pytest.raises(TypeError):  # the defaults are read-only: the declaration says them
        variant.settings["pick_s"] = 1.0  # type: ignore[index]


# ---------------------------------------------------------------------------------- reading
def test_values_are_converted_to_the_declared_types() -> None:
    built = settings_from(Sample, {"count": 7.0, "gain": 2, "enabled": True, "other": "x"})
    assert built == Sample(count=7, gain=2.0, enabled=True)
    assert type(built.count) is int and type(built.gain) is float
    with pytest.raises(
        SettingError, match=re.escape("setting 'count': expected an integer (got 2.5)")
    ):
        settings_from(Sample, {"count": 2.5})


def test_a_run_builds_each_settings_class_once() -> None:
    run = RunSettings({"speed_m_s": 2, "replans": 3.0})
    nav = run.of(NavConfig)
    assert run.of(NavConfig) is nav
    assert nav == NavConfig(speed_m_s=2.0, replans=3)
    assert settings_of(run, NavConfig) is nav  # agents and services share it
    assert settings_of({"tolerance_m": 1}, NavConfig).tolerance_m == 1.0  # a plain mapping
    assert dict(run) == {"speed_m_s": 2, "replans": 3.0}  # the untyped path sees the values


def test_the_navigator_settings_doc_is_read_from_its_fields() -> None:
    assert dict(SETTINGS_DOC) == {  # the text the hand-kept table had
        "speed_m_s": "cruise speed along a route (m/s)",
        "lookahead_m": "carrot distance ahead on the route (m)",
        "tolerance_m": "distance within which a goal counts as reached (m)",
        "altitude_m": "flight height above the ground for take-off and ground-level goals (m)",
        "stuck_s": "a route with no progress for this long is replanned (s)",
        "replans": "replans of a route with no progress before the task fails",
        "apf_gain": "APF gain L per m² of rock surface seen by the LiDAR (seed 002 eq. 3)",
        "clearance_m": "paths keep this far from rock: the map is inflated by it for planning (m)",
    }


def setting_calls(path: Path) -> list[str]:
    """``Class.function`` (or ``function``) around every ``….setting(...)`` call in ``path``."""
    found: list[str] = []

    def visit(node: ast.AST, scope: tuple[str, ...]) -> None:
        for child in ast.iter_child_nodes(node):
            inner = scope
            if isinstance(child, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                inner = (*scope, child.name)
            if (
                isinstance(child, ast.Call)
                and isinstance(child.func, ast.Attribute)
                and child.func.attr == "setting"
            ):
                found.append(".".join(scope))
            visit(child, inner)

    visit(ast.parse(path.read_text(encoding="utf-8")), ())
    return found


def test_built_in_code_reads_no_setting_by_name() -> None:
    """Leaves and services read typed objects: no ``ctx.setting("name", default)`` whose default
    could disagree with the declared one (the untyped path stays for third-party code only)."""
    calls = {
        path.relative_to(ROOT).as_posix(): found
        for path in sorted([*(ROOT / "library").glob("*.py"), *(ROOT / "btmission").rglob("*.py")])
        if (found := setting_calls(path))
    }
    assert calls == {"btmission/runtime/actions.py": ["Timed.duration_s"]}  # its untyped default


# --------------------------------------------------------------------------- validate (CLI)
LIBRARY = """\
library: typedlib
version: 1
module: {module}
conditions:
  done: The job is done
actions:
  work: {{doc: Do the job, post: [done]}}
goals: [done]
"""

MODULE = """\
from dataclasses import dataclass

from py_trees.common import Status

from btmission.plugins import Implementations
from btmission.runtime.leaves import StatefulAction


@dataclass(frozen=True)
class TypedSettings:
    rounds: int = 3
    \"\"\"How many rounds.\"\"\"
    gain: float = 0.5
    verbose: bool = False
    label: str = "job"


IMPLEMENTATIONS = Implementations("typedlib", vehicle="ground", settings=TypedSettings)
IMPLEMENTATIONS.condition("done")(lambda ctx: False)


@IMPLEMENTATIONS.action("work")
class Work(StatefulAction):
    def on_start(self) -> Status:
        return Status.SUCCESS
"""

MISSION = """\
mission: typed
version: 1
world:
  map: {{generate: empty, size: [8, 6, 1]}}
  resolution: 0.25
agents:
  - {{id: G1, library: ./typedlib.yaml, start: [1, 1, 0]}}
tasks: []
task_types:
  job: {{goal: done, cost: "1"}}
runtime:
  settings:
    {setting}
"""

_count = 0


def typed_mission(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, setting: str) -> Path:
    """A library whose settings are a dataclass of all four types, its module (on sys.path and
    PYTHONPATH) and a mission in ``tmp_path`` that sets ``setting`` (line 13)."""
    global _count
    _count += 1
    module = f"typedlib_impl_{os.getpid()}_{_count}"
    (tmp_path / "typedlib.yaml").write_text(LIBRARY.format(module=module))
    (tmp_path / f"{module}.py").write_text(MODULE)
    mission = tmp_path / "typed.yaml"
    mission.write_text(MISSION.format(setting=setting))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), *sys.path]))
    return mission


@pytest.mark.parametrize(
    "setting, column, message",
    [
        ('rounds: "abc"', 13, "runtime.settings.rounds: expected an integer (got 'abc')"),
        ("rounds: 2.5", 13, "runtime.settings.rounds: expected an integer (got 2.5)"),
        ("rounds: true", 13, "runtime.settings.rounds: expected an integer (got true)"),
        ("gain: true", 11, "runtime.settings.gain: expected a number (got true)"),
        ("gain: fast", 11, "runtime.settings.gain: expected a number (got 'fast')"),
        ("verbose: 1", 14, "runtime.settings.verbose: expected true or false (got 1)"),
        ('verbose: "yes"', 14, "runtime.settings.verbose: expected true or false (got 'yes')"),
        ("label: 3", 12, "runtime.settings.label: expected a string (got 3)"),
        ("label: false", 12, "runtime.settings.label: expected a string (got false)"),
    ],
)
def test_validate_refuses_a_value_of_another_type(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, setting: str, column: int, message: str
) -> None:
    mission = typed_mission(tmp_path, monkeypatch, setting)
    result = CliRunner().invoke(cli, ["validate", str(mission), "--with-implementations"])
    assert result.exit_code == 2, result.output
    assert result.output.splitlines()[0] == f"{mission}:13:{column}: {message}"
    assert "Traceback" not in result.output


@pytest.mark.parametrize(
    "setting",
    ["rounds: 4", "rounds: 4.0", "gain: 2", "gain: 0.25", "verbose: true", 'label: "x"',
     "label: text"],
)  # fmt: skip
def test_validate_accepts_values_of_the_declared_type(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, setting: str
) -> None:
    mission = typed_mission(tmp_path, monkeypatch, setting)
    result = CliRunner().invoke(cli, ["validate", str(mission), "--with-implementations"])
    assert result.exit_code == 0, result.output


def test_the_command_line_says_it_in_one_line_with_status_2(tmp_path: Path) -> None:
    """The installed command, in its own process: the message on stderr, no traceback."""
    mission = tmp_path / "haulage.yaml"
    text = (ROOT / "missions" / "mine_haulage.yaml").read_text()
    bad = '  tick_hz: 2\n  settings: {dispatch_generations: "abc"}\n'
    mission.write_text(text.replace("  tick_hz: 2\n", bad))
    done = subprocess.run(
        [sys.executable, "-m", "btmission", "validate", str(mission)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    first = done.stderr.splitlines()[0]
    assert first.startswith(f"{mission}:") and first.endswith(
        ": runtime.settings.dispatch_generations: expected an integer (got 'abc')"
    ), done.stderr
    assert "Traceback" not in done.stderr


def test_every_shipped_mission_validates() -> None:
    for mission in sorted((ROOT / "missions").glob("*.yaml")):
        result = CliRunner().invoke(cli, ["validate", str(mission)])
        assert result.exit_code == 0, (mission.name, result.output)


def test_library_show_lists_the_declared_settings() -> None:
    result = CliRunner().invoke(cli, ["library", "show", "haulage"])
    assert result.exit_code == 0, result.output
    assert (
        "  dispatch_generations int = 200      GA generations per optimisation (a fixed count: "
        "runs are reproducible)." in result.output.splitlines()
    ), result.output


def test_runs_use_the_library_defaults_the_navigator_shares() -> None:
    """A library's default for a navigator setting is the run's (``ground`` drives at 0.4 m/s),
    unless the mission sets it; the library's own object sees the same value."""
    from btmission.missions import load_mission
    from btmission.runtime.assembly import run_settings
    from btmission_library.ground import GroundSettings

    mission = load_mission(ROOT / "missions" / "warehouse.yaml")
    run = run_settings(mission)
    assert run.of(NavConfig).speed_m_s == run.of(GroundSettings).speed_m_s == 0.4
    assert run.of(NavConfig).altitude_m == 2.0  # (no library declares it: the navigator's)
