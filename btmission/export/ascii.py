"""Plain-text rendering of an abstract tree, one line per node (for terminals, logs and docs).

Convention (``unicode=True``; the ASCII fallback is in brackets)::

    ? Fallback: at_goal(goal)
    ├── (at_goal(goal))
    └── → Sequence: follow_path(goal)
        ├── (has_path(goal)) [assumed]
        └── [follow_path(goal)]

* fallback: ``? Fallback: <name>``; sequence: ``→ Sequence: <name>`` (``-> Sequence: <name>``);
* condition: ``(<label>)``, action: ``[<label>]``, where the label is :attr:`Node.label`
  (``name(arg, ...)``, literal arguments quoted);
* role markers after the node: `` [assumed]``, `` [cycle!]``, `` [builtin]`` (other roles are
  implied by the structure and not shown);
* ``meta`` (e.g. a task branch's ``commit_after``) as `` {key=value, key=value}``;
* guides: "├── ", "└── ", "│   " ("|-- ", "`-- ", "|   "), four columns per level.

Control characters in labels are escaped (a newline becomes backslash-n), so the output always has
exactly one line per node occurrence (shared subtrees are printed wherever they occur).

Back-chained trees can be thousands of levels deep, and full guides would make the text grow with
the *square* of the depth (a 10,000-deep chain would be half a gigabyte). Nodes deeper than
``max_indent`` therefore print only their innermost ``max_indent`` guide columns, preceded by
``… (+N) `` (``... (+N) ``) where N is the number of columns left out. Pass ``max_indent=None``
for full guides at any depth.
"""

from __future__ import annotations

from btmission.synthesis.tree import Kind, Node, Role

__all__ = ["DEFAULT_MAX_INDENT", "render_ascii"]

DEFAULT_MAX_INDENT = 80
"""Guide columns printed before deep lines are elided (see the module docstring)."""

_ROLE_MARKERS: dict[Role, str] = {
    Role.ASSUMED: " [assumed]",
    Role.CYCLE: " [cycle!]",
    Role.BUILTIN: " [builtin]",
}

# (tee, elbow, pipe, blank, sequence arrow, elision mark) per character set.
_UNICODE = ("├── ", "└── ", "│   ", "    ", "→", "…")
_ASCII = ("|-- ", "`-- ", "|   ", "    ", "->", "...")

_CONTROL_ESCAPES = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}


def _one_line(text: str) -> str:
    """Escape control characters so that a label can never break the one-line-per-node rule."""
    if text.isprintable():
        return text
    return "".join(
        _CONTROL_ESCAPES.get(ch, f"\\x{ord(ch):02x}") if ord(ch) < 32 or ord(ch) == 127 else ch
        for ch in text
    )


def _describe(node: Node, arrow: str) -> str:
    """The text of one node (without guides)."""
    if node.kind is Kind.FALLBACK:
        text = f"? Fallback: {node.name}"
    elif node.kind is Kind.SEQUENCE:
        text = f"{arrow} Sequence: {node.name}"
    elif node.kind is Kind.CONDITION:
        text = f"({node.label})"
    else:
        text = f"[{node.label}]"
    text += _ROLE_MARKERS.get(node.role, "")
    if node.meta:
        text += " {" + ", ".join(f"{k}={v}" for k, v in node.meta) + "}"
    return _one_line(text)


def render_ascii(
    root: Node, unicode: bool = True, max_indent: int | None = DEFAULT_MAX_INDENT
) -> str:
    """Render ``root`` as indented text, one line per node occurrence, ending with a newline.

    Args:
        root: the abstract tree.
        unicode: box-drawing guides and ``→`` (default) or pure ASCII.
        max_indent: guide columns shown at most per line (``None``: unlimited); deeper lines are
            prefixed with an elision mark instead, keeping the output linear in the tree size.

    The traversal is iterative, so arbitrarily deep trees are fine.
    """
    if max_indent is not None and max_indent < 1:
        raise ValueError(f"max_indent must be at least 1 or None, got {max_indent}")
    tee, elbow, pipe, blank, arrow, ellipsis = _UNICODE if unicode else _ASCII
    lines: list[str] = []
    # Column ``i`` of the current path: the guide drawn below the ancestor at depth ``i + 1``
    # (a pipe while that ancestor still has siblings to come, blank otherwise).
    columns: list[str] = []
    stack: list[tuple[int, Node, bool]] = [(0, root, True)]
    while stack:
        depth, node, is_last = stack.pop()
        text = _describe(node, arrow)
        if depth == 0:
            lines.append(text)
        else:
            del columns[depth - 1 :]
            connector = elbow if is_last else tee
            hidden = 0 if max_indent is None else max(0, depth - 1 - max_indent)
            if hidden == 0:
                lines.append("".join(columns) + connector + text)
            else:
                shown = "".join(columns[hidden:])
                lines.append(f"{ellipsis} (+{hidden}) {shown}{connector}{text}")
            columns.append(blank if is_last else pipe)
        children = node.children
        for index in range(len(children) - 1, -1, -1):
            stack.append((depth + 1, children[index], index == len(children) - 1))
    return "\n".join(lines) + "\n"
