"""Loading a mission: its file, checked by the file model (:mod:`btmission.spec.mission`), with
each agent's library found and its implementations bound by :mod:`btmission.plugins`.

The file model is a leaf (issue #35): it never imports library code itself. Loading is the one
place that joins the two, so checking a mission (``btmission validate``) and building a run
load libraries the same way, under :func:`btmission.plugins.implementation_imports`.
"""

from __future__ import annotations

from pathlib import Path

from btmission.diagnostics import Location
from btmission.plugins import LoadedLibrary, load_library
from btmission.spec.mission import Mission, compile_mission, mission_spec
from btmission.spec.source import Source, parse_yaml, read_yaml

LoadedMission = Mission[LoadedLibrary]
"""A mission loaded to run: each agent's library with its implementations."""


def _resolve(ref: str, base: Path, where: Location) -> LoadedLibrary:
    return load_library(ref, base, where=where)


def load_mission_source(src: Source) -> LoadedMission:
    """A parsed mission file, checked, with its libraries. Raises :class:`SpecError`."""
    return compile_mission(mission_spec(src), src, _resolve)


def load_mission(path: str | Path) -> LoadedMission:
    """Read and validate a mission file. Raises :class:`SpecError` listing every problem."""
    return load_mission_source(read_yaml(path))


def load_mission_text(text: str, file: str = "<input>") -> LoadedMission:
    """Validate a mission given as YAML text (``file`` names it in messages)."""
    return load_mission_source(parse_yaml(text, file))
