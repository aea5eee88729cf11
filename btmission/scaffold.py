"""Scaffold a pip-installable capability-library plugin (``btmission library new NAME``).

A plugin is an ordinary Python distribution that registers its library YAML in the
``btmission.libraries`` entry-point group, exactly as btmission registers its built-in libraries.
:func:`scaffold_plugin` writes one with a small but working example library, so the result
installs, shows up in ``btmission library list``, checks clean and passes its own test before the
user has changed anything::

    btmission-my-robot/
        pyproject.toml                  entry point my_robot = "btmission_my_robot:SPEC"
        README.md
        btmission_my_robot/__init__.py  SPEC, IMPLEMENTATIONS and one example implementation
        btmission_my_robot/my_robot.yaml
        tests/test_my_robot.py

The files come from plain :class:`string.Template` templates below; the output depends only on
``name`` (no dates, versions or paths are written), so scaffolding twice gives identical files.
"""

from __future__ import annotations

import keyword
import re
from pathlib import Path
from string import Template

from btmission.errors import BtmissionError

__all__ = [
    "EXAMPLE_GOAL",
    "ScaffoldError",
    "package_name",
    "project_name",
    "render_plugin",
    "scaffold_plugin",
    "validate_name",
]

_NAME = re.compile(r"[a-z][a-z0-9]*(?:_[a-z0-9]+)*")
"""Lower snake case: a lowercase letter, then lowercase letters and digits in ``_``-joined words."""


class ScaffoldError(BtmissionError, ValueError):
    """The plugin cannot be scaffolded: bad name or unusable target directory (one-line message)."""


def package_name(name: str) -> str:
    """The import package of library ``name``'s plugin: ``btmission_<name>``."""
    return f"btmission_{name}"


def project_name(name: str) -> str:
    """The distribution (pip) name of ``name``'s plugin: ``btmission-<name-with-dashes>``."""
    return f"btmission-{name.replace('_', '-')}"


def validate_name(name: str) -> None:
    """Raise :class:`ScaffoldError` unless ``name`` is a lower-snake-case Python identifier."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ScaffoldError(
            f"invalid library name {name!r}: use lower snake case, i.e. a lowercase letter "
            "followed by lowercase letters, digits and single underscores (e.g. 'my_robot')"
        )
    if keyword.iskeyword(name):
        raise ScaffoldError(f"invalid library name {name!r}: it is a Python keyword")


def scaffold_plugin(name: str, target: Path, *, force: bool = False) -> list[Path]:
    """Write a plugin package for a new library ``name`` into the directory ``target``.

    ``target`` is created if needed. An existing non-empty ``target`` is refused unless ``force``,
    in which case the scaffold's files are overwritten and any other file is left alone.

    Returns the files written, in a fixed order, each as ``target / <path inside the package>``
    (so they are absolute exactly when ``target`` is).

    Raises:
        ScaffoldError: ``name`` is not lower snake case, or ``target`` is a file, is a non-empty
            directory (without ``force``), or has a directory where a file must go.
    """
    validate_name(name)
    target = Path(target)
    files = render_plugin(name)
    if target.exists() and not target.is_dir():
        raise ScaffoldError(f"cannot scaffold into {target}: it exists and is not a directory")
    if target.is_dir() and any(target.iterdir()) and not force:
        raise ScaffoldError(
            f"cannot scaffold into {target}: the directory is not empty "
            "(use --force to write the plugin's files into it anyway)"
        )
    for rel in files:  # find every conflict before writing anything
        path = target / rel
        if path.is_dir():
            raise ScaffoldError(f"cannot scaffold into {target}: {path} is a directory")
        if path.parent.exists() and not path.parent.is_dir():
            raise ScaffoldError(f"cannot scaffold into {target}: {path.parent} is not a directory")
    written: list[Path] = []
    for rel, text in files.items():
        path = target / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8", newline="\n")
        written.append(path)
    return written


def render_plugin(name: str) -> dict[str, str]:
    """The plugin's files for library ``name``: relative path → text, in writing order."""
    validate_name(name)
    values = {
        "name": name,
        "package": package_name(name),
        "project": project_name(name),
        "goal": EXAMPLE_GOAL,
    }
    pkg = package_name(name)
    templates = {
        "pyproject.toml": _PYPROJECT,
        "README.md": _README,
        f"{pkg}/__init__.py": _INIT,
        f"{pkg}/{name}.yaml": _LIBRARY,
        f"tests/test_{name}.py": _TEST,
    }
    return {rel: Template(text).substitute(values) for rel, text in templates.items()}


EXAMPLE_GOAL = "sample_taken"
"""The goal the example library declares (and its test synthesises)."""

# --------------------------------------------------------------------------------------------
# Templates. ``$name`` is the library name, ``$package`` the import package, ``$project`` the
# distribution name, ``$goal`` the example goal. A literal dollar sign would be written ``$$``.
# --------------------------------------------------------------------------------------------
_PYPROJECT = """\
[build-system]
requires = ["setuptools>=77"]
build-backend = "setuptools.build_meta"

[project]
name = "$project"
version = "0.1.0"
description = "Capability library '$name' for btmission"
readme = "README.md"
requires-python = ">=3.10"
dependencies = ["btmission"]

[project.optional-dependencies]
test = ["pytest>=8"]

# This is what makes btmission find the library: the entry point's name is the library's name
# (`btmission library list`, `library: $name` in missions), its object the library YAML.
[project.entry-points."btmission.libraries"]
$name = "$package:SPEC"

[tool.setuptools]
packages = ["$package"]

# Ship the library YAML inside the package, next to the module that implements it.
[tool.setuptools.package-data]
$package = ["*.yaml"]

[tool.pytest.ini_options]
testpaths = ["tests"]
# Lets the tests import $package before the package is installed.
pythonpath = ["."]
"""

_README = """\
# $project

The `$name` capability library for btmission, as a plugin package. Generated by
`btmission library new $name`.

- `$package/$name.yaml`: the library, i.e. what the platform can check (conditions) and do
  (actions, with pre- and postconditions). btmission synthesises behaviour trees from it by
  back-chaining. It starts as a small working example; replace it with your platform's
  capabilities.
- `$package/__init__.py`: `SPEC` (the YAML, which the entry point points to) and
  `IMPLEMENTATIONS`, the Python code behind the conditions and actions, registered by name.
- `tests/test_$name.py`: checks the library, synthesises each goal it declares and dry-runs the
  trees; it reads the names from the YAML, so it keeps working when you replace the example.

## Install

```sh
pip install -e .
```

## See it

```sh
btmission library list            # $name appears next to the built-in libraries
btmission library show $name
```

## Check it and synthesise a tree

```sh
btmission library check $name     # references, cycles, assumed conditions, unused actions
btmission synth $name --goal '$goal' --dry-run
```

Before installing, give the path instead of the name:
`btmission library check $package/$name.yaml`.

## Test it

```sh
pip install -e '.[test]'
pytest
```

The tests load the library by path, so they also pass before the package is installed; the
entry-point cases are skipped until it is.
"""

_INIT = '''\
"""The ``$name`` capability library for btmission (spec: ``$name.yaml``).

``SPEC`` is the library file: ``pyproject.toml`` registers it in the ``btmission.libraries``
entry-point group under the name ``$name``, which is how ``btmission library list`` and missions
find it. ``IMPLEMENTATIONS`` holds the Python code behind the library's conditions and actions.
"""

from __future__ import annotations

from importlib.resources import files
from typing import Any

from btmission.plugins import Implementations

SPEC = files(__package__).joinpath("$name.yaml")
"""The library file; the ``btmission.libraries`` entry point ``$name`` points here."""

IMPLEMENTATIONS = Implementations("$name")
"""Implementations of the library's conditions and actions, registered by name.

The runtime binds implementations by name: a leaf called ``is_ready`` in a synthesised tree is
bound to whatever is registered here as condition ``is_ready``. Synthesis, checks and export read
only the YAML and never call this code. Registering a name the YAML does not declare is an error
(``btmission library check`` reports it); ``btmission library list`` shows how many declared
names are implemented, and the library is runnable once all of them are.
"""


# An example implementation, in the form btmission.plugins documents: a condition is a function
# of a context and the condition's parameters as keyword arguments, returning whether it holds.
# Actions are registered the same way with @IMPLEMENTATIONS.action("name") on a subclass of
# btmission.runtime.leaves.StatefulAction (on_start sends a request, on_running polls it).
# When you replace the example library, rename or remove this one too: registering a name the
# YAML does not declare is an error (`btmission library check` reports it).
@IMPLEMENTATIONS.condition("is_ready")
def is_ready(ctx: Any, **args: Any) -> bool:
    """Drivers are up and the self-test passed. Replace with a real check of your platform."""
    return False
'''

_LIBRARY = """\
# Capability library '$name' (btmission library format, version 1).
#
# A small working example written by `btmission library new`: replace the conditions and
# actions with your platform's, and keep `btmission library check $name` clean.
# tests/test_$name.py checks the library, synthesises each of its goals and dry-runs the trees.

# library: the name users and missions refer to it by. Keep it equal to the entry point's name
# in pyproject.toml ([project.entry-points."btmission.libraries"]).
library: $name

# version: the version of the library *file format* (not of your package); must be 1.
version: 1

# description: one line, shown by `btmission library list`.
description: Example $name capabilities (generated; replace with your platform's)

# module: the Python module whose IMPLEMENTATIONS registry implements the conditions and actions.
# Optional: without it the library still synthesises, checks and exports, but cannot run.
module: $package

# variables: values the implementations keep on the blackboard, which conditions in `pre`/`post`
# may name as arguments. Here `site`, where the sample is taken, is set by the mission.
variables:
  site: {doc: Where the sample is taken (set by the mission)}

# goals: what the library is built for. `library check` synthesises each goal and warns about any
# action that none of them uses. A goal may name free symbols; they become inputs of the tree.
goals:
  - $goal

# conditions: what the platform can check. `params` names the condition's arguments in order; a
# reference like `at(site)` binds them by position (`at(place=site)` binds by name).
# `doc` is one line, shown by `btmission library show`. A condition that no action
# achieves is only checked, never achieved: the check warns about it ("assumed").
conditions:
  is_ready:     {doc: Drivers are up and the self-test passed}
  is_localized: {doc: A pose estimate is available}
  at:           {doc: Within tolerance of the place, params: [place]}
  $goal: {doc: A sample has been taken at the site}

# actions: what the platform can do.
#   doc:    one line, shown by `btmission library show`.
#   params: the action's parameters in order; each must appear in a postcondition, so that
#           back-chaining knows its value.
#   pre:    conditions that must hold before the action runs, in tick order; back-chaining
#           achieves each of them first. Arguments are the action's params or library variables.
#   post:   conditions the action makes true; back-chaining chooses actions by these.
#   cost:   when several actions achieve the same condition, the lowest cost wins, then the one
#           declared first (default 1).
# Quote references in flow lists: "at(place)".
actions:
  start_up: {doc: Start the drivers and run the self-test, post: [is_ready]}
  localize: {doc: Estimate the pose, pre: [is_ready], post: [is_localized]}
  go_to:
    doc: Drive to the place
    params: [place]
    pre: [is_ready, is_localized]
    post: ["at(place)"]
    cost: 1
  take_sample: {doc: Take a sample at the site, pre: ["at(site)"], post: [$goal]}
"""

_TEST = '''\
"""Tests of the ``$name`` capability library through btmission's public API.

Everything the tests check is read from the library file itself (its goals, conditions and
actions), so they keep passing when you replace the example library with your platform's own:
for every goal the library declares they synthesise the tree, check its shape and dry-run it.
Add tests of your own below for the trees you care about.

The library is loaded by path, so these pass before the package is installed, and by its
entry-point name (as ``btmission`` and missions find it) once it is; that case is skipped until
then.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from btmission import (
    Kind,
    LoadedLibrary,
    Node,
    Severity,
    SpecError,
    check_library,
    dry_run,
    installed_libraries,
    load_library,
    load_library_file,
    synthesize,
)

NAME = "$name"
ENTRY_POINT = "$package:SPEC"
SPEC_PATH = Path(__file__).resolve().parent.parent / "$package" / "$name.yaml"


def declared_goals() -> list[str]:
    """The goals the library file declares (none if it does not load: the check test says why)."""
    try:
        library, _ = load_library_file(SPEC_PATH)
    except (SpecError, OSError):  # a broken file fails test_library_checks_clean with its messages
        return []
    return [str(goal) for goal in library.goals]


GOALS = declared_goals()


@pytest.fixture(params=["path", "entry point"])
def loaded(request: pytest.FixtureRequest) -> LoadedLibrary:
    """The library, loaded by path and by installed name."""
    if request.param == "path":
        return load_library(str(SPEC_PATH))
    ep = installed_libraries().get(NAME)
    if ep is None or ep.value != ENTRY_POINT:
        pytest.skip(f"{NAME} is not installed from this package (pip install -e .)")
    return load_library(NAME)


def nodes(node: Node) -> list[Node]:
    """``node`` and everything below it, in tick order."""
    return [node, *(n for child in node.children for n in nodes(child))]


def test_library_checks_clean(loaded: LoadedLibrary) -> None:
    report = check_library(loaded.library, loaded.diagnostics)
    problems = [d.format() for d in report.diagnostics if d.severity is not Severity.INFO]
    assert problems == []
    assert loaded.library.name == NAME
    assert loaded.implementations is not None, loaded.import_error  # the module imported
    assert GOALS, "declare the library's goals (goals: in the YAML) so they can be tested"


@pytest.mark.parametrize("goal", GOALS)
def test_goal_tree(loaded: LoadedLibrary, goal: str) -> None:
    library = loaded.library
    synthesis = synthesize(library, [goal])
    assert synthesis.ok, [d.format() for d in synthesis.diagnostics]
    tree = synthesis.tree
    # Fallback(goal holds?, Sequence(preconditions of the action achieving it..., action))
    assert (tree.kind, tree.label) == (Kind.FALLBACK, goal)
    check, achieve = tree.children
    assert (check.kind, check.label) == (Kind.CONDITION, goal)
    assert achieve.kind is Kind.SEQUENCE
    action = achieve.children[-1]
    assert action.kind is Kind.ACTION
    assert check.name in {post.name for post in library.actions[action.name].post}
    # every leaf is a declared condition or action
    for node in nodes(tree):
        if node.kind is Kind.ACTION:
            assert node.name in library.actions, node.label
        elif node.kind is Kind.CONDITION:
            assert node.name in library.conditions, node.label


@pytest.mark.parametrize("goal", GOALS)
def test_dry_run_reaches_goal(loaded: LoadedLibrary, goal: str) -> None:
    synthesis = synthesize(loaded.library, [goal])
    result = dry_run(synthesis.tree, loaded.library)
    assert result.success, result.format_trace(unicode=False)
    assert result.violations == []
    assert result.world.holds(synthesis.tree.label)
'''
