"""The layering the project keeps (issue #35, CONTRIBUTING.md).

``make lint`` checks the layers of ``btmission/`` with import-linter (the contract is in
pyproject.toml). The command-line front end lives outside that tree (``cli/``, installed as
``btmission.cli``), where import-linter does not see it; this test checks the one rule about it:
nothing in ``btmission/`` imports the CLI, at module level or inside a function.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

ALLOWED: dict[str, str] = {
    "btmission/__main__.py": "`python -m btmission` is the CLI's entry point",
    "btmission/warmup.py": "the install's warm-up runs CLI commands; it moves under cli/",
}
"""Modules of btmission/ that may import the CLI, and why."""


def cli_imports(path: Path) -> list[int]:
    """Lines of ``path`` that import ``btmission.cli`` (or anything under it)."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        if any(n == "btmission.cli" or n.startswith("btmission.cli.") for n in names):
            lines.append(node.lineno)
    return lines


def test_nothing_below_the_cli_imports_it() -> None:
    found = {
        p.relative_to(ROOT).as_posix(): cli_imports(p)
        for p in sorted((ROOT / "btmission").rglob("*.py"))
    }
    offenders = {f: lines for f, lines in found.items() if lines and f not in ALLOWED}
    assert offenders == {}, "btmission/ must not import btmission.cli (the top layer)"
    assert {f for f, lines in found.items() if lines} == set(ALLOWED)  # no stale exception


def test_the_check_sees_every_form_of_import(tmp_path: Path) -> None:
    p = tmp_path / "m.py"
    p.write_text(
        "import os\nimport btmission.cli.main\n"
        "def f():\n    from btmission.cli import common\n    from btmission import cli\n"
        "from btmission.clinic import x\n"
    )
    assert cli_imports(p) == [2, 4, 5]


def test_every_module_is_in_a_layer_of_the_contract() -> None:
    """import-linter checks only the modules its layers name: a new module of btmission/ that
    no layer covers would escape the contract (pyproject.toml, [tool.importlinter])."""
    import tomllib

    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    layers = next(c for c in contracts["contracts"] if c["id"] == "layers")["layers"]
    named = [n.strip() for layer in layers for n in layer.replace(":", "|").split("|")]
    outside = []
    for path in sorted((ROOT / "btmission").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        if module in ("btmission", "btmission.__main__", "btmission.spec"):
            continue  # the package roots and the entry point (spec's __init__ is empty)
        if not any(module == n or module.startswith(n + ".") for n in named):
            outside.append(module)
    assert outside == []


# --------------------------------------------------------------------- the tests mirror the code
TEST_GROUPS: dict[str, str] = {
    "base": "the base layer's own modules (errors, diagnostics, kernel cache)",
    "tools": "the tools layer: benchmarks, warm-up, scaffold, mavsim",
}
"""Directories of tests/unit/ that are not named after a package of btmission/, and what they
hold."""


def test_unit_tests_sit_under_their_package_and_system_tests_apart() -> None:
    """tests/unit/<package>/ holds the tests of one package or module of btmission/ (or of a group in
    TEST_GROUPS), tests/system/ the end-to-end ones (the CLI, whole runs, the browser, the
    golden runs, the docs); no test file is left at the top of tests/ (CONTRIBUTING.md)."""
    tests = ROOT / "tests"
    assert sorted(p.name for p in tests.glob("test_*.py")) == []
    packages = {  # btmission's packages and top-level modules (btmission.plugins)
        p.stem
        for p in (ROOT / "btmission").iterdir()
        if (p / "__init__.py").is_file() or p.suffix == ".py"
    }
    groups = {p.name for p in (tests / "unit").iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert groups - packages - set(TEST_GROUPS) == set()
    for group in groups:
        assert (tests / "unit" / group / "__init__.py").is_file(), group
        assert list((tests / "unit" / group).glob("test_*.py")), f"tests/unit/{group} is empty"
    assert len(list((tests / "system").glob("test_*.py"))) > 0


# --------------------------------------------------------------------------- module sizes
MAX_MODULE_LINES = 800
"""A module of btmission/ outside the tools layer stays under this many lines (issue #35): past
it, split it where its parts separate (navigation → navconfig, mavlink_connect → mavlink_requests)."""
MAX_LOOP_LINES = 500
"""The run loop's module (runtime/runner.py) stays under this: building a run, commands, pacing,
snapshots and the end live beside it."""
TOOLS = ("btmission/bench/", "btmission/warmup.py", "btmission/scaffold", "btmission/mavsim.py")


def module_sizes() -> dict[str, int]:
    return {
        p.relative_to(ROOT).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
        for p in sorted((ROOT / "btmission").rglob("*.py"))
    }


def test_no_module_below_the_tools_outgrows_its_budget() -> None:
    sizes = module_sizes()
    too_long = {f: n for f, n in sizes.items() if n > MAX_MODULE_LINES and not f.startswith(TOOLS)}
    assert too_long == {}
    assert sizes["btmission/runtime/runner.py"] < MAX_LOOP_LINES
    assert any(f.startswith(TOOLS) and n > MAX_MODULE_LINES for f, n in sizes.items())  # sees them
