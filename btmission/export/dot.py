"""Graphviz ``dot`` text for an abstract tree (rendered to svg/png by :mod:`.graphviz`).

Every node *occurrence* gets its own graph node (``n0``, ``n1``, ... in pre-order), so shared
subtrees are drawn wherever they occur, exactly as the tree ticks. Conventions, following the usual
behaviour-tree figures:

* fallback: a small box labelled ``?``; sequence: a small box labelled ``→``; the composite's name
  (and its ``meta``) is the node's tooltip (shown on hover in svg);
* condition: an ellipse; action: a rounded box; both filled, labelled with :attr:`Node.label`;
* roles: assumed conditions are amber and dashed, cycle leaves red with a thick red outline,
  builtin leaves grey; plain conditions light blue, plain actions light green;
* ``rankdir=TB`` and ``ordering=out`` so children keep their tick order left to right.

Strings are emitted as dot double-quoted strings with backslashes, quotes and line breaks escaped,
so any label round-trips through ``dot`` unchanged.
"""

from __future__ import annotations

from btmission.synthesis.tree import Kind, Node, Role

__all__ = ["dot_quote", "render_dot"]

_COMPOSITE_SYMBOL = {Kind.FALLBACK: "?", Kind.SEQUENCE: "→"}

# Leaf fill colours of plain leaves by kind, and per-role overrides (extra style, attributes).
_PLAIN_FILL = {Kind.CONDITION: "#dbeafe", Kind.ACTION: "#dcfce7"}
_ROLE_STYLE: dict[Role, tuple[str, dict[str, str]]] = {
    Role.ASSUMED: ("dashed", {"fillcolor": "#fef3c7", "color": "#b45309"}),
    Role.CYCLE: ("", {"fillcolor": "#fecaca", "color": "#dc2626", "penwidth": "2.5"}),
    Role.BUILTIN: ("", {"fillcolor": "#e5e7eb", "color": "#4b5563"}),
}


def dot_quote(text: str) -> str:
    """``text`` as a dot double-quoted string (backslash, quote and line breaks escaped).

    Escaping the backslash also disables dot's own escapes (``\\N``, ``\\G``...) inside labels.
    """
    escaped = (
        text.replace("\\", "\\\\")
        .replace('"', '\\"')
        .replace("\r\n", "\\n")
        .replace("\n", "\\n")
        .replace("\r", "\\n")
    )
    return f'"{escaped}"'


def _attributes(node: Node) -> dict[str, str]:
    """Dot attributes (unquoted values) for one node."""
    meta = ", ".join(f"{k}={v}" for k, v in node.meta)
    if node.kind.is_composite:
        tooltip = f"{node.kind.value}: {node.name}" + (f" {{{meta}}}" if meta else "")
        return {
            "label": _COMPOSITE_SYMBOL[node.kind],
            "shape": "box",
            "style": "filled",
            "fillcolor": "#ffffff",
            "fontsize": "18",
            "width": "0.5",
            "height": "0.4",
            "tooltip": tooltip,
        }
    style = ["filled"]
    attrs: dict[str, str] = {"label": node.label}
    if node.kind is Kind.CONDITION:
        attrs["shape"] = "ellipse"
    else:
        attrs["shape"] = "box"
        style.insert(0, "rounded")
    attrs["fillcolor"] = _PLAIN_FILL[node.kind]
    extra_style, overrides = _ROLE_STYLE.get(node.role, ("", {}))
    if extra_style:
        style.append(extra_style)
    attrs["style"] = ",".join(style)
    attrs.update(overrides)
    tooltip = node.label if node.role is Role.PLAIN else f"{node.label} [{node.role.value}]"
    if node.doc:
        tooltip += f"\n{node.doc}"
    if meta:
        tooltip += f"\n{{{meta}}}"
    attrs["tooltip"] = tooltip
    return attrs


def render_dot(root: Node, name: str = "tree") -> str:
    """Graphviz dot text for ``root``: one statement per node occurrence, then one per edge.

    Node ids are ``n<i>`` with ``i`` the pre-order index, so the output is deterministic and the
    ``i``-th node statement describes the ``i``-th node of :func:`~btmission.synthesis.tree.walk`.
    Iterative, so arbitrarily deep trees are fine (laying them out is dot's problem).
    """
    lines = [
        f"digraph {dot_quote(name)} {{",
        "  rankdir=TB;",
        "  ordering=out;",
        '  node [fontname="Helvetica", fontsize=11, margin="0.12,0.04"];',
        '  edge [arrowhead=none, color="#555555"];',
    ]
    edges: list[str] = []
    # (parent id or -1, node); ids are assigned when a node is popped, i.e. in pre-order.
    stack: list[tuple[int, Node]] = [(-1, root)]
    next_id = 0
    while stack:
        parent, node = stack.pop()
        ident = next_id
        next_id += 1
        attrs = ", ".join(f"{key}={dot_quote(value)}" for key, value in _attributes(node).items())
        lines.append(f"  n{ident} [{attrs}];")
        if parent >= 0:
            edges.append(f"  n{parent} -> n{ident};")
        for child in reversed(node.children):
            stack.append((ident, child))
    lines.extend(edges)
    lines.append("}")
    return "\n".join(lines) + "\n"
