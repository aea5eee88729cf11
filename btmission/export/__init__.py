"""Exporters of the abstract behaviour tree (ascii, dot, svg, png, BehaviorTree.CPP XML, JSON).

Every exporter reads only the abstract :class:`~btmission.synthesis.tree.Node` tree, is a pure
function returning text or bytes (the CLI writes the files), and is iterative, so trees thousands of
levels deep are fine. Only svg/png run a program (Graphviz ``dot``, see :mod:`.graphviz`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from btmission.lazy import lazy_attributes

if TYPE_CHECKING:
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

# The exporters are imported on first use (PEP 562): `btmission validate` and `mission tree`'s
# option parsing need FORMATS, not the XML name patterns, ElementTree or subprocess behind them.
_LAZY: dict[str, str] = {
    "render_ascii": "btmission.export.ascii",
    "parse_btcpp_xml": "btmission.export.btcpp",
    "render_btcpp_xml": "btmission.export.btcpp",
    "render_dot": "btmission.export.dot",
    "GraphvizFailed": "btmission.export.graphviz",
    "GraphvizMissing": "btmission.export.graphviz",
    "graphviz_available": "btmission.export.graphviz",
    "render_graphviz": "btmission.export.graphviz",
    "parse_json": "btmission.export.jsonfmt",
    "render_json": "btmission.export.jsonfmt",
    "tree_from_dict": "btmission.export.jsonfmt",
    "tree_to_dict": "btmission.export.jsonfmt",
}
__getattr__, __dir__ = lazy_attributes(__name__, globals(), _LAZY)

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
        from btmission.export.ascii import render_ascii

        return render_ascii(root, unicode=unicode)
    if fmt in ("dot", "svg", "png"):
        from btmission.export.dot import render_dot

        dot = render_dot(root, name=name)
        if fmt == "dot":
            return dot
        from btmission.export.graphviz import render_graphviz

        return render_graphviz(dot, "svg" if fmt == "svg" else "png")
    if fmt == "xml":
        from btmission.export.btcpp import render_btcpp_xml

        return render_btcpp_xml(root, tree_id=name)
    if fmt == "json":
        from btmission.export.jsonfmt import render_json

        return render_json(root, name=name, **dict(extra or {}))
    raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
