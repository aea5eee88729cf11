"""btmission: multi-robot missions from declarative capability libraries.

The public API, one import away::

    from btmission import load_library, synthesize, export_tree
    lib = load_library("aerial").library
    tree = synthesize(lib, ["at_goal(goal)"]).tree
    print(export_tree(tree, "ascii"))
"""

from btmission._version import __version__
from btmission.diagnostics import Diagnostic, Severity, SpecError
from btmission.plugins import Implementations, LoadedLibrary, installed_libraries, load_library
from btmission.spec.library import Atom, Library, load_library_file, load_library_text
from btmission.spec.mission import Mission, load_mission, load_mission_text
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
