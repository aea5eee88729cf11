"""Exporters of the abstract behaviour tree (ascii, dot, svg, png, BehaviorTree.CPP XML, JSON).

Every exporter reads only the abstract :class:`~btmission.synthesis.tree.Node` tree, is a pure
function returning text or bytes (the CLI writes the files), and is iterative, so trees thousands of
levels deep are fine. Only svg/png run a program (Graphviz ``dot``, see :mod:`.graphviz`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from btmission.export.ascii import render_ascii
from btmission.export.btcpp import parse_btcpp_xml, render_btcpp_xml
from btmission.export.dot import render_dot
from btmission.export.graphviz import (
    GraphvizFailed,
    GraphvizMissing,
    graphviz_available,
    render_graphviz,
)
from btmission.export.jsonfmt import parse_json, render_json, tree_from_dict, tree_to_dict
from btmission.synthesis.tree import Node

__all__ = [
    "BINARY_FORMATS",
    "FORMATS",
    "GraphvizFailed",
    "GraphvizMissing",
    "export_tree",
    "graphviz_available",
    "parse_btcpp_xml",
    "parse_json",
    "render_ascii",
    "render_btcpp_xml",
    "render_dot",
    "render_graphviz",
    "render_json",
    "tree_from_dict",
    "tree_to_dict",
]

FORMATS = ("ascii", "dot", "svg", "png", "xml", "json")
"""Every format :func:`export_tree` accepts."""

BINARY_FORMATS = frozenset({"svg", "png"})
"""Formats :func:`export_tree` returns as ``bytes`` (the others are ``str``)."""


def export_tree(
    root: Node,
    fmt: str,
    *,
    name: str = "MainTree",
    unicode: bool = True,
    extra: Mapping[str, Any] | None = None,
) -> bytes | str:
    """``root`` in format ``fmt`` (one of :data:`FORMATS`).

    Args:
        root: the abstract tree.
        fmt: ``ascii``, ``dot``, ``xml`` and ``json`` give ``str``; ``svg`` and ``png`` give
            ``bytes`` rendered by Graphviz ``dot``.
        name: the graph name (dot/svg/png), BehaviorTree ID (xml) or ``name`` key (json).
        unicode: box-drawing characters in the ascii rendering (ignored by other formats).
        extra: additional top-level keys of the json document (e.g. library, goals, inputs).

    Raises:
        ValueError: unknown ``fmt``, or a tree BehaviorTree.CPP cannot represent (xml).
        GraphvizMissing, GraphvizFailed: svg/png without a working Graphviz.
    """
    if fmt == "ascii":
        return render_ascii(root, unicode=unicode)
    if fmt == "dot":
        return render_dot(root, name=name)
    if fmt in ("svg", "png"):
        return render_graphviz(render_dot(root, name=name), "svg" if fmt == "svg" else "png")
    if fmt == "xml":
        return render_btcpp_xml(root, tree_id=name)
    if fmt == "json":
        return render_json(root, name=name, **dict(extra or {}))
    raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
