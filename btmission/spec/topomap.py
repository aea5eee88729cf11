"""Topological map files (seed 004 §3.1; the format is in ``docs/dispatch.md``): the file model,
reading a map file into the dispatcher's :class:`~btmission.dispatch.topomap.TopoMap`, writing one
back, and a mission's ``world.topomap`` reference.

The map itself — nodes, segments, the loop-free check, the path matrix Π0 — is an algorithm's data
and lives with the dispatcher (:mod:`btmission.dispatch.topomap`); this module is the file at its
edge: YAML read with every item's line and column (:mod:`.source`), checked by pydantic
(:class:`TopoMapSpec`), every problem a located :class:`~btmission.diagnostics.SpecError`::

    topomap: tiny
    version: 1
    nodes:
      A: {kind: terminal, prioritized: true, xy: [0, 0]}
      X: {kind: transit, xy: [10, 0]}
      P: {kind: pause, xy: [10, 5]}
      B: {kind: terminal, xy: [20, 0]}
    segments:
      - {from: A, to: X, time: 10}          # the same both ways
      - {from: X, to: B, time: [10, 20]}    # from→to, to→from
      - {from: X, to: P, time: 3}
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from btmission.diagnostics import SpecError
from btmission.dispatch.maps import BUILTIN_MAPS
from btmission.dispatch.topomap import Node, NodeKind, Segment, TopoMap, TopoMapError
from btmission.spec.common import FiniteFloat, Identifier, number_problem, validate_model
from btmission.spec.source import Source, parse_yaml, read_yaml

TOPOMAP_FORMAT_VERSION = 1


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class NodeSpec(_Strict):
    kind: Literal["terminal", "pause", "transit"] = Field(description="Node type (§3.1).")
    prioritized: bool = Field(False, description="Prioritised terminal (T^P), e.g. offloading.")
    xy: tuple[FiniteFloat, FiniteFloat] | None = Field(
        None, description="Position for plots, in metres."
    )
    group: str = Field("", description="Free label, e.g. left/right halves of the static map.")


class SegmentSpec(_Strict):
    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)
    a: Identifier = Field(alias="from", description="Start node.")
    b: Identifier = Field(alias="to", description="End node.")
    time: FiniteFloat | tuple[FiniteFloat, FiniteFloat] = Field(
        description="Traversal time in s: one number for both directions, or [from→to, to→from]."
    )

    @field_validator("time", mode="before")
    @classmethod
    def _number(cls, v: Any) -> Any:
        """One clear message for a bad single number (not one per form of the union)."""
        if isinstance(v, (bool, int, float)):
            problem = number_problem(v)
            if problem:
                raise ValueError(problem)
        return v

    @field_validator("time")
    @classmethod
    def _positive(cls, v: float | tuple[float, float]) -> float | tuple[float, float]:
        vals = (v,) if isinstance(v, (int, float)) else v
        if min(vals) <= 0:
            raise ValueError("traversal times must be > 0 s")
        return v


class TopoMapSpec(_Strict):
    """A topological map file (``version: 1``)."""

    topomap: Identifier
    version: Literal[1]
    description: str = ""
    nodes: dict[Identifier, NodeSpec] = Field(min_length=2)
    segments: list[SegmentSpec] = Field(min_length=1)


def topomap_from_spec(spec: TopoMapSpec, src: Source | None = None) -> TopoMap:
    """Build a :class:`TopoMap` from a validated spec; problems become a located :class:`SpecError`."""
    nodes = [
        Node(name, NodeKind[ns.kind.upper()], ns.prioritized, ns.xy, ns.group)
        for name, ns in spec.nodes.items()
    ]
    segs = []
    for s in spec.segments:
        t_ab, t_ba = (s.time, s.time) if isinstance(s.time, (int, float)) else s.time
        segs.append(Segment(s.a, s.b, float(t_ab), float(t_ba)))
    try:
        return TopoMap.build(spec.topomap, nodes, segs, spec.description)
    except TopoMapError as exc:
        if src is None:
            raise
        raise SpecError([src.diag(exc.path, str(exc), "topomap")]) from None


def load_topomap_source(src: Source) -> TopoMap:
    return topomap_from_spec(validate_model(TopoMapSpec, src, "topological map"), src)


def load_topomap(path: str | Path) -> TopoMap:
    """Read and check a map file. Raises :class:`SpecError` (file:line: item: message)."""
    return load_topomap_source(read_yaml(path))


def load_topomap_text(text: str, file: str = "<input>") -> TopoMap:
    return load_topomap_source(parse_yaml(text, file))


def topomap_data(tmap: TopoMap) -> dict[str, Any]:
    """Plain data in the map file format (:func:`dump_topomap` writes it)."""
    nodes: dict[str, Any] = {}
    for nd in tmap.nodes:
        entry: dict[str, Any] = {"kind": nd.kind.name.lower()}
        if nd.prioritized:
            entry["prioritized"] = True
        if nd.xy is not None:
            entry["xy"] = [round(float(nd.xy[0]), 3), round(float(nd.xy[1]), 3)]
        if nd.group:
            entry["group"] = nd.group
        nodes[nd.name] = entry
    segs: list[dict[str, Any]] = []
    for s in tmap.segments:
        t: Any = s.t_ab if s.t_ab == s.t_ba else [s.t_ab, s.t_ba]
        segs.append({"from": s.a, "to": s.b, "time": t})
    out: dict[str, Any] = {"topomap": tmap.name, "version": TOPOMAP_FORMAT_VERSION}
    if tmap.description:
        out["description"] = tmap.description
    out["nodes"] = nodes
    out["segments"] = segs
    return out


def dump_topomap(tmap: TopoMap) -> str:
    """The map as YAML text in the file format (one node / segment per line)."""
    import yaml

    data = topomap_data(tmap)
    head = {k: v for k, v in data.items() if k not in ("nodes", "segments")}
    lines = [yaml.safe_dump(head, sort_keys=False).rstrip(), "nodes:"]
    for name, entry in data["nodes"].items():
        flow = yaml.safe_dump(entry, default_flow_style=True, sort_keys=False).strip()
        lines.append(f"  {name}: {flow}")
    lines.append("segments:")
    for seg in data["segments"]:
        flow = yaml.safe_dump(seg, default_flow_style=True, sort_keys=False).strip()
        lines.append(f"  - {flow}")
    return "\n".join(lines) + "\n"


def topomap_ref(ref: str, base_dir: Path) -> TopoMap:
    """A mission's ``world.topomap``: a built-in map by name (:data:`~btmission.dispatch.maps
    .BUILTIN_MAPS`), else a map file relative to the mission's directory (the mission loader has
    already checked that it exists and is valid)."""
    if ref in BUILTIN_MAPS:
        return BUILTIN_MAPS[ref]()
    return load_topomap(base_dir / ref)
