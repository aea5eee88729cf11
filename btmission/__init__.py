"""btmission: multi-robot missions from declarative capability libraries.

The public API, one import away::

    from btmission import load_library, synthesize, export_tree
    lib = load_library("aerial").library
    tree = synthesize(lib, ["at_goal(goal)"]).tree
    print(export_tree(tree, "ascii"))
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from btmission._version import __version__
from btmission.lazy import lazy_attributes

# The API is imported on first use (PEP 562), so that `import btmission` (and so the start of the
# `btmission` command, before its Ctrl-C handling exists) costs milliseconds, not half a second.
_LAZY: dict[str, str] = {
    "Diagnostic": "btmission.diagnostics",
    "Severity": "btmission.diagnostics",
    "SpecError": "btmission.diagnostics",
    "Implementations": "btmission.plugins",
    "LoadedLibrary": "btmission.plugins",
    "installed_libraries": "btmission.plugins",
    "load_library": "btmission.plugins",
    "Atom": "btmission.spec.library",
    "Library": "btmission.spec.library",
    "load_library_file": "btmission.spec.library",
    "load_library_text": "btmission.spec.library",
    "Mission": "btmission.spec.mission",
    "load_mission": "btmission.missions",
    "load_mission_text": "btmission.missions",
    "Synthesis": "btmission.synthesis.backchain",
    "Synthesizer": "btmission.synthesis.backchain",
    "synthesize": "btmission.synthesis.backchain",
    "check_library": "btmission.synthesis.checks",
    "dry_run": "btmission.synthesis.dryrun",
    "build_mission_tree": "btmission.synthesis.mission_tree",
    "Kind": "btmission.synthesis.tree",
    "Node": "btmission.synthesis.tree",
    "Role": "btmission.synthesis.tree",
}


__getattr__, __dir__ = lazy_attributes(__name__, globals(), _LAZY)

if TYPE_CHECKING:
    from btmission.diagnostics import Diagnostic, Severity, SpecError
    from btmission.missions import load_mission, load_mission_text
    from btmission.plugins import Implementations, LoadedLibrary, installed_libraries, load_library
    from btmission.spec.library import Atom, Library, load_library_file, load_library_text
    from btmission.spec.mission import Mission
    from btmission.synthesis.backchain import Synthesis, Synthesizer, synthesize
    from btmission.synthesis.checks import check_library
    from btmission.synthesis.dryrun import dry_run
    from btmission.synthesis.mission_tree import build_mission_tree
    from btmission.synthesis.tree import Kind, Node, Role


def export_tree(tree: Node, fmt: str, **kwargs: object) -> str | bytes:
    """Export an abstract tree: ascii, dot, svg, png, xml (BehaviorTree.CPP v4) or json."""
    from btmission.export import export_tree as _export

    return _export(tree, fmt, **kwargs)  # type: ignore[arg-type]


__all__ = [
    "Atom",
    "Diagnostic",
    "Implementations",
    "Kind",
    "Library",
    "LoadedLibrary",
    "Mission",
    "Node",
    "Role",
    "Severity",
    "SpecError",
    "Synthesis",
    "Synthesizer",
    "__version__",
    "build_mission_tree",
    "check_library",
    "dry_run",
    "export_tree",
    "installed_libraries",
    "load_library",
    "load_library_file",
    "load_library_text",
    "load_mission",
    "load_mission_text",
    "synthesize",
]
