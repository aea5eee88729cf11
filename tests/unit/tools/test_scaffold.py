"""``btmission library new``: the scaffolded plugin loads, checks clean, passes its own test, and
is found through its entry point once pip has installed it."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from btmission import Severity, check_library, dry_run, load_library, synthesize
from btmission.scaffold import EXAMPLE_GOAL, ScaffoldError, render_plugin, scaffold_plugin

NAME = "scaffold_probe"
"""A library name no real installation uses, so its entry point can only come from the test."""

EXPECTED_FILES = [
    "pyproject.toml",
    "README.md",
    f"btmission_{NAME}/__init__.py",
    f"btmission_{NAME}/{NAME}.yaml",
    f"tests/test_{NAME}.py",
]


@pytest.fixture()
def pkg(tmp_path: Path) -> Path:
    """A freshly scaffolded plugin package."""
    target = tmp_path / f"btmission-{NAME.replace('_', '-')}"
    scaffold_plugin(NAME, target)
    return target


@pytest.fixture()
def importable(pkg: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """``pkg`` on sys.path (as if installed), its module forgotten again afterwards."""
    monkeypatch.syspath_prepend(str(pkg))
    yield pkg
    sys.modules.pop(f"btmission_{NAME}", None)


@pytest.fixture()
def cli() -> click.Group:
    """The ``btmission`` click group (imported here, so the API tests don't depend on the CLI)."""
    from btmission.cli.main import cli as group

    command: click.Group = group
    return command


def _run(
    args: list[str], *, cwd: Path, pythonpath: Path | None = None
) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(pythonpath)} if pythonpath else dict(os.environ)
    return subprocess.run(
        args,
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def _output(proc: subprocess.CompletedProcess[str]) -> str:
    return f"exit {proc.returncode}\n--- stdout\n{proc.stdout}\n--- stderr\n{proc.stderr}"


# --------------------------------------------------------------------------------------------
# The generated package
# --------------------------------------------------------------------------------------------
def test_writes_the_package_files(tmp_path: Path) -> None:
    target = tmp_path / "plugin"
    written = scaffold_plugin(NAME, target)
    assert written == [target / rel for rel in EXPECTED_FILES]
    assert all(p.is_file() for p in written)
    assert sorted(str(p.relative_to(target)) for p in target.rglob("*") if p.is_file()) == sorted(
        EXPECTED_FILES
    )
    pyproject = (target / "pyproject.toml").read_text(encoding="utf-8")
    assert 'name = "btmission-scaffold-probe"' in pyproject
    assert 'version = "0.1.0"' in pyproject
    assert 'dependencies = ["btmission"]' in pyproject
    assert '[project.entry-points."btmission.libraries"]' in pyproject
    assert f'{NAME} = "btmission_{NAME}:SPEC"' in pyproject
    assert 'requires = ["setuptools>=77"]' in pyproject


def test_output_is_deterministic(tmp_path: Path) -> None:
    a = scaffold_plugin(NAME, tmp_path / "a")
    b = scaffold_plugin(NAME, tmp_path / "b")
    assert [p.read_bytes() for p in a] == [p.read_bytes() for p in b]
    assert render_plugin(NAME) == render_plugin(NAME)
    assert all("$" not in text for text in render_plugin(NAME).values())  # every field filled


def test_generated_library_loads_and_checks_clean(importable: Path) -> None:
    loaded = load_library(str(importable / f"btmission_{NAME}" / f"{NAME}.yaml"))
    assert loaded.library.name == NAME
    assert loaded.library.module == f"btmission_{NAME}"
    assert loaded.import_error is None
    assert loaded.implementations is not None and "is_ready" in loaded.implementations.conditions
    report = check_library(loaded.library, loaded.diagnostics)
    assert [d.format() for d in report.diagnostics] == []  # not even a note
    assert [str(g) for g in loaded.library.goals] == [EXAMPLE_GOAL]
    assert len(loaded.library.conditions) == 4 and len(loaded.library.actions) == 4
    assert any(c.params for c in loaded.library.conditions.values())  # at(place)
    synthesis = synthesize(loaded.library, [EXAMPLE_GOAL])
    assert synthesis.ok and not synthesis.assumed
    result = dry_run(synthesis.tree, loaded.library)
    assert result.success and result.violations == []


def test_generated_library_needs_no_module_to_check(pkg: Path) -> None:
    """Without its package importable, the YAML still loads; only the import is reported."""
    loaded = load_library(str(pkg / f"btmission_{NAME}" / f"{NAME}.yaml"), import_module=False)
    report = check_library(loaded.library, loaded.diagnostics)
    assert not [d for d in report.diagnostics if d.severity is not Severity.INFO]


def test_generated_test_passes(pkg: Path) -> None:
    proc = _run([sys.executable, "-m", "pytest", "-q", str(pkg / "tests")], cwd=pkg, pythonpath=pkg)
    assert proc.returncode == 0, _output(proc)
    assert "3 passed, 3 skipped" in proc.stdout, _output(proc)  # entry point: not installed


REPLACEMENT_LIBRARY = f"""\
library: {NAME}
version: 1
description: Rail-mounted inspection cart
module: btmission_{NAME}
variables:
  home: {{doc: Parking position at the end of the rail}}
goals:
  - photo_taken(spot)
  - at_goal(home)
conditions:
  powered: Drive and camera powered
  at_goal: {{doc: At the position on the rail, params: [goal]}}
  photo_taken: {{doc: A photo of the spot is stored, params: [spot]}}
actions:
  power_on: {{doc: Power the drive and camera, post: [powered]}}
  move_to: {{doc: Move along the rail, params: [goal], pre: [powered], post: [at_goal(goal)]}}
  photograph: {{doc: Take a photo, params: [spot], pre: [at_goal(spot)], post: [photo_taken(spot)]}}
"""
"""A library with none of the example's names, as a user writes after replacing the example."""


def _replace_example(pkg: Path, library: str) -> subprocess.CompletedProcess[str]:
    """Do what docs/plugins.md says (replace the example library and the example
    implementation's name), then run the scaffolded tests."""
    (pkg / f"btmission_{NAME}" / f"{NAME}.yaml").write_text(library, encoding="utf-8")
    init = pkg / f"btmission_{NAME}" / "__init__.py"
    text = init.read_text(encoding="utf-8")
    assert '@IMPLEMENTATIONS.condition("is_ready")' in text
    init.write_text(text.replace('condition("is_ready")', 'condition("powered")'), encoding="utf-8")
    return _run([sys.executable, "-m", "pytest", "-q", str(pkg / "tests")], cwd=pkg, pythonpath=pkg)


def test_generated_test_passes_after_the_example_is_replaced(pkg: Path) -> None:
    """The scaffolded tests read the names from the library, so they test the user's library
    instead of failing on the example's names."""
    proc = _replace_example(pkg, REPLACEMENT_LIBRARY)
    assert proc.returncode == 0, _output(proc)
    # the check once, and a tree and a dry run for each of the two goals; by path only
    assert "5 passed, 5 skipped" in proc.stdout, _output(proc)
    assert "is_ready" not in (pkg / "tests" / f"test_{NAME}.py").read_text(encoding="utf-8")


@pytest.mark.slow
def test_generated_test_fails_on_a_broken_replacement(pkg: Path) -> None:
    """The scaffolded tests can fail: an action whose precondition nothing achieves."""
    broken = REPLACEMENT_LIBRARY.replace("pre: [powered]", "pre: [powered, docked]").replace(
        "  powered: Drive and camera powered\n",
        "  powered: Drive and camera powered\n  docked: At the charger\n",
    )
    proc = _replace_example(pkg, broken)
    assert proc.returncode == 1, _output(proc)
    assert "'docked' is assumed" in proc.stdout, _output(proc)


def test_plugin_is_found_once_installed(pkg: Path, tmp_path: Path) -> None:
    site = tmp_path / "site"
    proc = _run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(site),
            str(pkg),
        ],
        cwd=tmp_path,
    )
    assert proc.returncode == 0, (
        "pip could not build the plugin; --no-build-isolation needs setuptools>=77 in the test "
        "environment\n" + _output(proc)
    )
    listed = _run(
        [sys.executable, "-m", "btmission.cli.main", "library", "list"],
        cwd=tmp_path,
        pythonpath=site,
    )
    assert listed.returncode == 0, _output(listed)
    row = next((line for line in listed.stdout.splitlines() if line.split()[:1] == [NAME]), None)
    assert row is not None, _output(listed)
    assert "4 actions" in row and "4 conditions" in row and "ERROR" not in row, row
    checked = _run(
        [sys.executable, "-m", "btmission.cli.main", "library", "check", NAME],
        cwd=tmp_path,
        pythonpath=site,
    )
    assert checked.returncode == 0, _output(checked)
    assert "0 error(s), 0 warning(s)" in checked.stdout, _output(checked)
    # the generated test's entry-point cases now run instead of skipping
    tested = _run(
        [sys.executable, "-m", "pytest", "-q", str(pkg / "tests")], cwd=pkg, pythonpath=site
    )
    assert tested.returncode == 0, _output(tested)
    assert "6 passed" in tested.stdout, _output(tested)


# --------------------------------------------------------------------------------------------
# Refusals
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "bad",
    ["Bad-Name", "1abc", "bad name", "", "CamelCase", "_private", "trailing_", "a__b", "class"],
)
def test_bad_names_are_refused(bad: str, tmp_path: Path) -> None:
    with pytest.raises(ScaffoldError, match="invalid library name") as info:
        scaffold_plugin(bad, tmp_path / "x")
    assert "\n" not in str(info.value)
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("good", ["a", "robot2", "my_robot", "x1_y2_z3"])
def test_good_names_are_accepted(good: str) -> None:
    assert f"btmission_{good}/{good}.yaml" in render_plugin(good)


def test_non_empty_target_needs_force(tmp_path: Path) -> None:
    target = tmp_path / "plugin"
    target.mkdir()
    (target / "notes.txt").write_text("mine\n", encoding="utf-8")
    with pytest.raises(ScaffoldError, match="not empty"):
        scaffold_plugin(NAME, target)
    assert sorted(p.name for p in target.iterdir()) == ["notes.txt"]  # nothing written

    (target / "pyproject.toml").write_text("old\n", encoding="utf-8")
    written = scaffold_plugin(NAME, target, force=True)
    assert len(written) == len(EXPECTED_FILES)
    assert (target / "notes.txt").read_text(encoding="utf-8") == "mine\n"  # left alone
    assert "btmission-scaffold-probe" in (target / "pyproject.toml").read_text(encoding="utf-8")


def test_empty_existing_target_is_fine(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    assert len(scaffold_plugin(NAME, tmp_path / "empty")) == len(EXPECTED_FILES)


def test_target_that_is_a_file_is_refused(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("", encoding="utf-8")
    with pytest.raises(ScaffoldError, match="not a directory"):
        scaffold_plugin(NAME, tmp_path / "f", force=True)


# --------------------------------------------------------------------------------------------
# Through the CLI
# --------------------------------------------------------------------------------------------
def test_cli_library_new(cli: click.Group, tmp_path: Path) -> None:
    out = tmp_path / "x"
    result = CliRunner().invoke(cli, ["library", "new", "demo_lib", "-o", str(out)])
    assert result.exit_code == 0, result.output
    for rel in [
        "pyproject.toml",
        "README.md",
        "btmission_demo_lib/__init__.py",
        "btmission_demo_lib/demo_lib.yaml",
        "tests/test_demo_lib.py",
    ]:
        assert (out / rel).is_file(), rel
        assert f"created {out / rel}" in result.output
    assert f"pip install -e {out}" in result.output


def test_cli_library_new_refuses_non_empty_target(cli: click.Group, tmp_path: Path) -> None:
    (tmp_path / "keep.txt").write_text("", encoding="utf-8")
    result = CliRunner().invoke(cli, ["library", "new", "demo_lib", "-o", str(tmp_path)])
    assert result.exit_code == 2
    assert "--force" in result.stderr
    result = CliRunner().invoke(cli, ["library", "new", "demo_lib", "-o", str(tmp_path), "--force"])
    assert result.exit_code == 0, result.output


def test_cli_library_new_bad_name(
    cli: click.Group, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # the default target is ./btmission-NAME
    result = CliRunner().invoke(cli, ["library", "new", "bad name"])
    assert list(tmp_path.iterdir()) == []  # nothing created
    assert result.exit_code == 2
    assert isinstance(result.exception, SystemExit)
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("Error: invalid library name 'bad name'")
