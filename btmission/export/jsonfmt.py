"""Lossless JSON form of an abstract tree (for tools, diffs and re-loading).

Document layout::

    {"format": "btmission-tree", "version": 1, <extra keys>..., "tree": <node>}

    <node> = {"type": "fallback" | "sequence" | "condition" | "action",
              "name": str,
              "args": [{"param": str, "value": str, "literal": bool}, ...],
              "role": "plain" | "assumed" | ...,
              "doc": str,
              "meta": {key: value, ...},
              "children": [<node>, ...]}

``type``, ``name`` and ``role`` are always present; ``args``, ``doc``, ``meta`` and ``children`` are
omitted when empty (a missing ``role`` reads as ``plain``). Every field of :class:`Node` is kept, so
``tree_from_dict(tree_to_dict(t)) == t`` exactly.

Trees may be 10,000 levels deep. All conversions here are iterative, and :func:`render_json`
uses its own iterative encoder rather than :func:`json.dumps`: the C encoder recurses once per
nesting level and crashes the interpreter (no ``RecursionError``) a few tens of thousands of levels
down, and indentation growing with depth would make deep documents quadratic in size. The encoder
writes the same text as ``json.dumps(doc, indent=2, ensure_ascii=False)`` except that indentation
stops growing after :data:`MAX_INDENT_LEVELS` nesting levels (JSON whitespace is insignificant).
"""

from __future__ import annotations

import json
import json.scanner
import sys
from collections.abc import Mapping
from typing import Any

from btmission.recursion import recursion_limit
from btmission.synthesis.tree import Arg, Kind, Node, Role, distinct_postorder

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MAX_INDENT_LEVELS",
    "parse_json",
    "render_json",
    "tree_from_dict",
    "tree_to_dict",
]

FORMAT_NAME = "btmission-tree"
FORMAT_VERSION = 1
MAX_INDENT_LEVELS = 64
"""JSON nesting levels after which indentation stops growing (two levels per tree level)."""

_INDENT = "  "
_RESERVED_KEYS = frozenset({"format", "version", "tree"})
# json.loads recurses in C once per nesting level; beyond roughly this many levels the C stack
# (8 MiB main thread) could overflow, so the recursion limit is never raised past it.
_MAX_PARSE_NESTING = 30_000


# ------------------------------------------------------------------------- tree <-> dict
def _node_fields(node: Node) -> dict[str, Any]:
    """The dict of ``node`` without ``children``."""
    out: dict[str, Any] = {"type": node.kind.value, "name": node.name}
    if node.args:
        out["args"] = [
            {"param": a.param, "value": a.value, "literal": a.literal} for a in node.args
        ]
    out["role"] = node.role.value
    if node.doc:
        out["doc"] = node.doc
    if node.meta:
        meta = dict(node.meta)
        if len(meta) != len(node.meta):
            raise ValueError(f"node {node.label!r} has duplicate meta keys: {node.meta!r}")
        out["meta"] = meta
    return out


def tree_to_dict(root: Node) -> dict[str, Any]:
    """The JSON-ready dict of ``root`` (see the module docstring); iterative.

    A subtree shared by several parents is converted once and its dict shared likewise, so the
    work is linear in the number of *distinct* nodes; treat the result as read-only.
    """
    done: dict[int, dict[str, Any]] = {}
    for node in distinct_postorder(root):
        fields = _node_fields(node)
        if node.children:
            fields["children"] = [done[id(child)] for child in node.children]
        done[id(node)] = fields
    return done[id(root)]


def _expect(condition: bool, where: str, message: str) -> None:
    if not condition:
        raise ValueError(f"invalid tree JSON at {where}: {message}")


def _parse_fields(d: object, where: str) -> Node:
    """A childless :class:`Node` from the fields of one node dict (``children`` not read)."""
    _expect(isinstance(d, Mapping), where, f"expected an object, got {type(d).__name__}")
    assert isinstance(d, Mapping)
    unknown = set(d) - {"type", "name", "args", "role", "doc", "meta", "children"}
    _expect(not unknown, where, f"unknown keys {sorted(unknown)}")
    try:
        kind = Kind(d.get("type"))
    except ValueError:
        raise ValueError(f"invalid tree JSON at {where}: bad type {d.get('type')!r}") from None
    name = d.get("name")
    _expect(isinstance(name, str), where, "'name' must be a string")
    try:
        role = Role(d.get("role", Role.PLAIN.value))
    except ValueError:
        raise ValueError(f"invalid tree JSON at {where}: bad role {d.get('role')!r}") from None
    doc = d.get("doc", "")
    _expect(isinstance(doc, str), where, "'doc' must be a string")
    raw_args = d.get("args", [])
    _expect(isinstance(raw_args, list), where, "'args' must be a list")
    args: list[Arg] = []
    for i, raw in enumerate(raw_args):
        _expect(
            isinstance(raw, Mapping)
            and isinstance(raw.get("param"), str)
            and isinstance(raw.get("value"), str)
            and isinstance(raw.get("literal", False), bool)
            and set(raw) <= {"param", "value", "literal"},
            f"{where}.args[{i}]",
            'expected {"param": str, "value": str, "literal": bool}',
        )
        args.append(Arg(raw["param"], raw["value"], raw.get("literal", False)))
    raw_meta = d.get("meta", {})
    _expect(
        isinstance(raw_meta, Mapping)
        and all(isinstance(k, str) and isinstance(v, str) for k, v in raw_meta.items()),
        where,
        "'meta' must map strings to strings",
    )
    assert isinstance(name, str) and isinstance(doc, str)
    return Node(kind, name, tuple(args), (), role, doc, tuple(raw_meta.items()))


def tree_from_dict(d: Mapping[str, Any]) -> Node:
    """The :class:`Node` tree described by ``d`` (a node dict, see the module docstring).

    Iterative; a sub-dict appearing several times (as :func:`tree_to_dict` produces for shared
    subtrees) becomes one shared :class:`Node`.

    Raises:
        ValueError: ``d`` is not a valid node dict (the message gives the path of the culprit).
    """
    built: dict[int, Node] = {}
    # iterative post-order over distinct dicts: validated on the way down, built on the way up
    stack: list[tuple[object, str, bool]] = [(d, "tree", False)]
    while stack:
        item, where, children_done = stack.pop()
        if id(item) in built:
            continue
        _expect(isinstance(item, Mapping), where, f"expected an object, got {type(item).__name__}")
        assert isinstance(item, Mapping)
        children = item.get("children", [])
        _expect(isinstance(children, list), where, "'children' must be a list")
        if not children_done:
            stack.append((item, where, True))
            stack.extend(
                (child, f"{where}.children[{i}]", False)
                for i, child in reversed(list(enumerate(children)))
                if id(child) not in built
            )
            continue
        node = _parse_fields(item, where)
        if children:
            _expect(node.kind.is_composite, where, f"a {node.kind.value} cannot have children")
            node = Node(
                node.kind,
                node.name,
                node.args,
                tuple(built[id(child)] for child in children),
                node.role,
                node.doc,
                node.meta,
            )
        built[id(item)] = node
    return built[id(d)]


# ----------------------------------------------------------------------------- encoding
def _newline(level: int) -> str:
    return "\n" + _INDENT * min(level, MAX_INDENT_LEVELS)


def _encode(value: object) -> str:
    """``json.dumps(value, indent=2, ensure_ascii=False)`` with capped indentation; iterative."""
    out: list[str] = []
    # Items are either text to emit as is, or (value, nesting level) to encode.
    stack: list[str | tuple[object, int]] = [(value, 0)]
    while stack:
        item = stack.pop()
        if isinstance(item, str):
            out.append(item)
            continue
        current, level = item
        if isinstance(current, Mapping):
            if not current:
                out.append("{}")
                continue
            out.append("{")
            stack.append(_newline(level) + "}")
            entries = list(current.items())
            inner = _newline(level + 1)
            for index in range(len(entries) - 1, -1, -1):
                key, child = entries[index]
                if not isinstance(key, str):
                    raise TypeError(f"JSON object keys must be strings, got {key!r}")
                stack.append((child, level + 1))
                stack.append(inner + json.dumps(key, ensure_ascii=False) + ": ")
                if index:
                    stack.append(",")
        elif isinstance(current, (list, tuple)):
            if not current:
                out.append("[]")
                continue
            out.append("[")
            stack.append(_newline(level) + "]")
            inner = _newline(level + 1)
            for index in range(len(current) - 1, -1, -1):
                stack.append((current[index], level + 1))
                stack.append(inner)
                if index:
                    stack.append(",")
        else:  # scalars: str, int, float, bool, None (json.dumps raises TypeError for others)
            out.append(json.dumps(current, ensure_ascii=False))
    return "".join(out)


def render_json(root: Node, **extra: Any) -> str:
    """The JSON document of ``root``, with ``extra`` top-level keys (e.g. ``name``, ``library``).

    Keys are ``format``, ``version``, then ``extra`` in the given order, then ``tree``; the text is
    indented by two spaces and ends with a newline.

    Raises:
        ValueError: an ``extra`` key collides with ``format``, ``version`` or ``tree``.
    """
    clash = _RESERVED_KEYS.intersection(extra)
    if clash:
        raise ValueError(f"extra keys {sorted(clash)} are reserved by the tree JSON format")
    document: dict[str, Any] = {"format": FORMAT_NAME, "version": FORMAT_VERSION}
    document.update(extra)
    document["tree"] = tree_to_dict(root)
    return _encode(document) + "\n"


# ------------------------------------------------------------------------------ parsing
def _loads_deep(text: str) -> Any:
    """:func:`json.loads` for documents nested thousands of levels deep.

    The C decoder recurses once per nesting level. On Python 3.10/3.11 it obeys the recursion
    limit, which is raised for the call (never past :data:`_MAX_PARSE_NESTING`, to keep the C
    stack safe). From 3.12 it has a fixed C-level limit instead; there, a document it refuses is
    decoded again with the pure-Python scanner, whose Python-to-Python calls use no C stack.
    """
    nesting_bound = text.count("{") + text.count("[")  # an upper bound on the nesting depth
    try:
        with recursion_limit(min(nesting_bound, _MAX_PARSE_NESTING) + 1000, cap=None):
            return json.loads(text)
    except RecursionError:
        if sys.version_info < (3, 12):
            raise
    decoder = json.JSONDecoder()
    decoder.scan_once = json.scanner.py_make_scanner(decoder)
    with recursion_limit(3 * nesting_bound + 1000, cap=None):
        return decoder.decode(text)


def parse_json(text: str) -> Node:
    """The tree of a document written by :func:`render_json` (extra keys are ignored).

    Works for trees thousands of levels deep (see :func:`_loads_deep`).

    Raises:
        ValueError: not JSON, not a btmission tree document, an unsupported version, a malformed
            tree, or (Python 3.10/3.11 only) nested more than about 15,000 tree levels.
    """
    try:
        document = _loads_deep(text)
    except RecursionError:
        raise ValueError(
            f"tree JSON is nested more than {_MAX_PARSE_NESTING} levels; too deep to load"
        ) from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"not valid JSON: {exc}") from exc
    if not isinstance(document, dict) or document.get("format") != FORMAT_NAME:
        raise ValueError(f"not a {FORMAT_NAME!r} document")
    if document.get("version") != FORMAT_VERSION:
        raise ValueError(
            f"unsupported {FORMAT_NAME} version {document.get('version')!r} "
            f"(this btmission reads version {FORMAT_VERSION})"
        )
    tree = document.get("tree")
    if not isinstance(tree, dict):
        raise ValueError("the document has no 'tree' object")
    return tree_from_dict(tree)
