"""BehaviorTree.CPP v4 XML (loadable by BT.CPP 4.x and Groot2) from an abstract tree, and back.

Format, as read by BT.CPP's ``src/xml_parsing.cpp`` (4.x)::

    <?xml version="1.0" encoding="UTF-8"?>
    <root BTCPP_format="4" main_tree_to_execute="MainTree">
      <BehaviorTree ID="MainTree">
        <ReactiveFallback name="at_goal(goal)">
          <at_goal name="at_goal(goal)" goal="{goal}"/>
          <ReactiveSequence name="follow_path(goal)">
            <has_path name="has_path(goal)" goal="{goal}"/>
            <follow_path name="follow_path(goal)" goal="{goal}"/>
          </ReactiveSequence>
        </ReactiveFallback>
      </BehaviorTree>
      <TreeNodesModel>
        <Action ID="follow_path">
          <input_port name="goal"/>
        </Action>
        <Condition ID="at_goal">
          <input_port name="goal"/>
          <description>The robot is at the goal.</description>
        </Condition>
        ...
      </TreeNodesModel>
    </root>

* Our composites are memory-less, so fallback/sequence become ``ReactiveFallback`` /
  ``ReactiveSequence`` (as in BT.CPP's reactive back-chaining example), named by ``name``.
* Leaves use the *compact* form: the element is named after the leaf's ID (``<follow_path .../>``)
  and its instance ``name`` is :attr:`Node.label`. The explicit form ``<Action ID="follow_path">``
  is not written, because BT.CPP 4.7 to 4.10 reject it under a ``ReactiveSequence`` ("Unknown node
  type: Action", from the async-children check of ``VerifyXML``). Each argument is an input port
  attribute: a symbol ``goal`` becomes the blackboard reference ``{goal}``, a literal its plain
  value.
* ``<TreeNodesModel>`` lists every leaf type once, sorted by kind then ID, with one
  ``<input_port>`` per parameter (the union over all occurrences, in first-seen order) and the
  library's description as a ``<description>`` child (BT.CPP's XSD places it after the ports).
  It tells Groot2, BT.CPP programs and :func:`parse_btcpp_xml` which IDs are actions and which
  are conditions.
* BT.CPP refuses XML nested deeper than 256 elements below a ``<BehaviorTree>``. A composite that
  would sit :data:`SUBTREE_DEPTH` levels down is therefore written as its own
  ``<BehaviorTree ID="<tree>_sub<k>">`` and referenced with ``<SubTree ID=... _autoremap="true"/>``
  (auto-remapping lets the subtree read the main tree's blackboard keys unchanged). A shared
  subtree object split this way is written once and referenced wherever it occurs.

Names BT.CPP would reject (model IDs that are not XML names, contain forbidden characters or are
BT.CPP's own node types, reserved port names, a literal that looks like a blackboard reference)
raise :class:`ValueError` instead of producing a file that fails to load. Roles and ``meta`` have
no place in BT.CPP's format and are not written, so :func:`parse_btcpp_xml` returns every node
with role PLAIN and no meta.

Serialisation and parsing are iterative (ElementTree's own writer and ``ET.indent`` recurse once
per level), and indentation stops growing after :data:`MAX_INDENT_LEVELS` levels, so a
10,000-deep tree gives a file linear in its size.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass

from btmission.spec.library import BTCPP_BUILTIN_NODES
from btmission.synthesis.tree import Arg, Kind, Node, Role, walk

__all__ = [
    "BTCPP_BUILTIN_NODES",
    "MAX_INDENT_LEVELS",
    "MAX_PARSED_NODES",
    "SUBTREE_DEPTH",
    "parse_btcpp_xml",
    "render_btcpp_xml",
]

MAX_INDENT_LEVELS = 64
"""Elements deeper than this are indented as if at this depth (the whitespace is insignificant)."""

SUBTREE_DEPTH = 128
"""A composite more than this many levels below its ``<BehaviorTree>`` element (whose child is at
level 1) is moved to a ``<BehaviorTree>`` of its own and referenced by a ``<SubTree>``. Half of
BT.CPP 4.x's ``kMaxNestingDepth`` (256)."""

MAX_PARSED_NODES = 2_000_000
""":func:`parse_btcpp_xml` refuses documents whose ``<SubTree>`` references would expand into
more distinct nodes than this (a few kilobytes of XML can reference a subtree 2**40 times with
different port remappings)."""


_INDENT = "  "
_COMPOSITE_TAG = {Kind.FALLBACK: "ReactiveFallback", Kind.SEQUENCE: "ReactiveSequence"}
_LEAF_TAG = {Kind.ACTION: "Action", Kind.CONDITION: "Condition"}
_TAG_KIND = {
    "ReactiveFallback": Kind.FALLBACK,
    "Fallback": Kind.FALLBACK,
    "ReactiveSequence": Kind.SEQUENCE,
    "Sequence": Kind.SEQUENCE,
    "Action": Kind.ACTION,
    "Condition": Kind.CONDITION,
}
_PORT_TAGS = ("input_port", "output_port", "inout_port")

# BT.CPP 4.x name rules (basic_types.cpp: findForbiddenChar, IsAllowedPortName).
_FORBIDDEN_NAME_CHARS = re.compile(r"[\x00-\x20\x7f<>&\"'/\\:*?|.]")
# An XML 1.0 (5th edition) Name without ':' (the compact form makes the ID an element name).
_XML_NAME_START = (
    "A-Z_a-z\xc0-\xd6\xd8-\xf6\xf8-\u02ff\u0370-\u037d\u037f-\u1fff\u200c-\u200d"
    "\u2070-\u218f\u2c00-\u2fef\u3001-\ud7ff\uf900-\ufdcf\ufdf0-\ufffd\U00010000-\U000effff"
)
_XML_NAME = re.compile(
    f"[{_XML_NAME_START}][{_XML_NAME_START}\\-.0-9\xb7\u0300-\u036f\u203f-\u2040]*"
)
_RESERVED_PORT_NAMES = frozenset(
    {
        "ID",
        "name",
        "_description",
        "_autoremap",
        "__shared_blackboard",
        "_failureIf",
        "_successIf",
        "_skipIf",
        "_while",
        "_onHalted",
        "_onFailure",
        "_onSuccess",
        "_post",
    }
)
# Characters XML 1.0 cannot carry at all.
_INVALID_XML_CHARS = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ufffe\uffff\ud800-\udfff]")


# --------------------------------------------------------------------------- validation helpers
def _check_model_name(name: str, what: str, *, element: bool = False) -> None:
    """BT.CPP's rules for a model (node type or tree) ID; ``element``: also an XML element name."""
    if not name:
        raise ValueError(f"BehaviorTree.CPP {what} cannot be empty")
    if name == "Root":
        raise ValueError(f"BehaviorTree.CPP {what} cannot be 'Root' (reserved)")
    bad = _FORBIDDEN_NAME_CHARS.search(name)
    if bad:
        raise ValueError(
            f"BehaviorTree.CPP {what} {name!r} contains the forbidden character {bad.group()!r}"
        )
    if name in BTCPP_BUILTIN_NODES:
        raise ValueError(
            f"BehaviorTree.CPP {what} {name!r} is the name of one of BehaviorTree.CPP's own "
            "node types or XML elements"
        )
    if element and not _XML_NAME.fullmatch(name):
        raise ValueError(f"BehaviorTree.CPP {what} {name!r} is not a valid XML element name")


def _check_port_name(param: str, leaf: str) -> None:
    if not param or not ("a" <= param[0].lower() <= "z"):
        raise ValueError(
            f"parameter {param!r} of {leaf!r} is not a valid BehaviorTree.CPP port name "
            "(it must start with an ASCII letter)"
        )
    if param in _RESERVED_PORT_NAMES:
        raise ValueError(
            f"parameter {param!r} of {leaf!r} is a reserved BehaviorTree.CPP attribute name"
        )
    bad = _FORBIDDEN_NAME_CHARS.search(param)
    if bad:
        raise ValueError(
            f"parameter {param!r} of {leaf!r} contains the character {bad.group()!r}, "
            "forbidden in BehaviorTree.CPP port names"
        )
    if not _XML_NAME.fullmatch(param):
        raise ValueError(
            f"parameter {param!r} of {leaf!r} is not a valid XML attribute name, "
            "as BehaviorTree.CPP port names must be"
        )


def _port_value(arg: Arg, leaf: str) -> str:
    """The attribute value of one argument: ``{symbol}`` or the literal itself."""
    if arg.literal:
        stripped = arg.value.strip()
        if stripped.startswith("{") and stripped.endswith("}"):
            raise ValueError(
                f"literal {arg.value!r} of {leaf!r} would be read by BehaviorTree.CPP as a "
                "blackboard reference"
            )
        return arg.value
    if not arg.value or "{" in arg.value or "}" in arg.value:
        raise ValueError(f"symbol {arg.value!r} of {leaf!r} is not a valid blackboard key")
    return "{" + arg.value + "}"


# ------------------------------------------------------------------------------ serialisation
def _check_xml_chars(text: str) -> str:
    bad = _INVALID_XML_CHARS.search(text)
    if bad:
        raise ValueError(f"{text!r} contains {bad.group()!r}, which XML 1.0 cannot represent")
    return text


def _escape_text(text: str) -> str:
    return _check_xml_chars(text).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _escape_attribute(text: str) -> str:
    # Line breaks and tabs as character references: attribute-value normalisation would turn
    # literal ones into spaces when the file is read back.
    return (
        _escape_text(text)
        .replace('"', "&quot;")
        .replace("\n", "&#10;")
        .replace("\r", "&#13;")
        .replace("\t", "&#9;")
    )


def _serialize(root: ET.Element) -> str:
    """Pretty-printed XML text of ``root`` (elements, attributes and leaf text only); iterative."""
    out: list[str] = ['<?xml version="1.0" encoding="UTF-8"?>\n']
    stack: list[tuple[ET.Element, int] | str] = [(root, 0)]
    while stack:
        item = stack.pop()
        if isinstance(item, str):
            out.append(item)
            continue
        element, level = item
        pad = _INDENT * min(level, MAX_INDENT_LEVELS)
        attributes = "".join(
            f' {key}="{_escape_attribute(value)}"' for key, value in element.attrib.items()
        )
        children = list(element)
        if children:
            out.append(f"{pad}<{element.tag}{attributes}>\n")
            stack.append(f"{pad}</{element.tag}>\n")
            stack.extend((child, level + 1) for child in reversed(children))
        elif element.text:
            out.append(
                f"{pad}<{element.tag}{attributes}>{_escape_text(element.text)}</{element.tag}>\n"
            )
        else:
            out.append(f"{pad}<{element.tag}{attributes}/>\n")
    return "".join(out)


def _node_models(root: Node) -> list[tuple[Kind, str, list[str], str]]:
    """Every leaf type once: ``(kind, name, parameters, doc)``, sorted by kind tag then name."""
    kinds: dict[str, Kind] = {}
    params: dict[str, list[str]] = {}
    docs: dict[str, str] = {}
    for _, node in walk(root):
        if not node.is_leaf:
            continue
        known = kinds.setdefault(node.name, node.kind)
        if known is not node.kind:
            raise ValueError(
                f"{node.name!r} is used both as a {known.value} and as a {node.kind.value}; "
                "BehaviorTree.CPP needs one node type per ID"
            )
        names = params.setdefault(node.name, [])
        for arg in node.args:
            if arg.param not in names:
                names.append(arg.param)
        if node.doc and not docs.get(node.name):
            docs[node.name] = node.doc
    return sorted(
        ((kinds[n], n, params[n], docs.get(n, "")) for n in kinds),
        key=lambda model: (_LEAF_TAG[model[0]], model[1]),
    )


def _subtree_prefix(tree_id: str, leaf_ids: set[str]) -> str:
    """``<tree_id>_sub``, with more underscores until no leaf ID starts with it."""
    prefix = f"{tree_id}_sub"
    while any(leaf.startswith(prefix) for leaf in leaf_ids):
        prefix += "_"
    return prefix


def render_btcpp_xml(root: Node, tree_id: str = "MainTree") -> str:
    """BehaviorTree.CPP v4 XML for ``root`` as the tree ``tree_id`` (see the module docstring).

    Raises:
        ValueError: a name, port or value BehaviorTree.CPP would reject.
    """
    _check_model_name(tree_id, "tree ID")
    models = _node_models(root)
    for kind, name, params, _ in models:
        _check_model_name(name, f"{kind.value} ID", element=True)
        if name == tree_id:
            raise ValueError(f"tree ID {tree_id!r} clashes with the {kind.value} of that name")
        for param in params:
            _check_port_name(param, name)
    prefix = _subtree_prefix(tree_id, {name for _, name, _, _ in models})

    document = ET.Element("root", {"BTCPP_format": "4", "main_tree_to_execute": tree_id})
    subtree_ids: dict[int, str] = {}  # id(node) -> ID of the <BehaviorTree> holding it
    pending: list[tuple[str, Node]] = [(tree_id, root)]  # <BehaviorTree>s still to write
    written = 0
    while written < len(pending):
        this_id, top = pending[written]
        written += 1
        tree = ET.SubElement(document, "BehaviorTree", {"ID": this_id})
        # pre-order; children pushed reversed so SubElement appends them in tick order
        stack: list[tuple[ET.Element, Node, int]] = [(tree, top, 1)]
        while stack:
            parent, node, level = stack.pop()
            if node.kind.is_composite and level > SUBTREE_DEPTH:
                sub_id = subtree_ids.get(id(node))
                if sub_id is None:
                    sub_id = subtree_ids[id(node)] = f"{prefix}{len(pending)}"
                    pending.append((sub_id, node))
                ET.SubElement(parent, "SubTree", {"ID": sub_id, "_autoremap": "true"})
            elif node.kind.is_composite:
                element = ET.SubElement(parent, _COMPOSITE_TAG[node.kind], {"name": node.name})
                stack.extend((element, child, level + 1) for child in reversed(node.children))
            else:
                attributes = {"name": node.label}
                for arg in node.args:
                    attributes[arg.param] = _port_value(arg, node.name)
                ET.SubElement(parent, node.name, attributes)

    model_root = ET.SubElement(document, "TreeNodesModel")
    for kind, name, params, doc in models:
        model = ET.SubElement(model_root, _LEAF_TAG[kind], {"ID": name})
        for param in params:
            ET.SubElement(model, "input_port", {"name": param})
        if doc:
            ET.SubElement(model, "description").text = doc
    return _serialize(document)


# ------------------------------------------------------------------------------------ parsing
def _read_models(document: ET.Element) -> dict[str, tuple[Kind, str]]:
    """``ID -> (kind, description)`` from ``<TreeNodesModel>`` (actions and conditions only)."""
    models: dict[str, tuple[Kind, str]] = {}
    model_root = document.find("TreeNodesModel")
    if model_root is None:
        return models
    for model in model_root:
        kind = _TAG_KIND.get(model.tag)
        node_id = model.get("ID")
        if kind is None or kind.is_composite or not node_id:
            continue
        description = model.findtext("description")
        if description is None:
            description = model.get("description", "")
        models[node_id] = (kind, description)
    return models


def _read_trees(document: ET.Element) -> tuple[dict[str, ET.Element], str]:
    """Every ``<BehaviorTree>``'s single top element by ID, and the main tree's ID."""
    trees = document.findall("BehaviorTree")
    if not trees:
        raise ValueError("no <BehaviorTree> in the document")
    main = document.get("main_tree_to_execute")
    if main is None and len(trees) > 1:
        raise ValueError("several <BehaviorTree> elements and no main_tree_to_execute")
    tops: dict[str, ET.Element] = {}
    main_id: str | None = None
    for tree in trees:
        tree_id = tree.get("ID", "")
        top = list(tree)
        if len(top) != 1:
            raise ValueError(f"<BehaviorTree ID={tree_id!r}> must have exactly one child")
        if tree_id in tops:
            raise ValueError(f"two <BehaviorTree> elements with ID={tree_id!r}")
        tops[tree_id] = top[0]
        if main is None or tree_id == main:
            main_id = tree_id
    if main_id is None:
        raise ValueError(f"main_tree_to_execute={main!r} names no <BehaviorTree>")
    return tops, main_id


@dataclass(frozen=True, slots=True)
class _Scope:
    """How a ``<SubTree>`` maps its blackboard keys onto its parent's.

    ``remap`` pairs a key inside the subtree with the parent's value: ``("k", "{p}")`` reads the
    parent's key ``p``, ``("k", "3")`` the literal ``3``. Keys not remapped are the parent's own
    keys when ``autoremap`` is true, and private to the subtree otherwise.
    """

    remap: tuple[tuple[str, str], ...]
    autoremap: bool


def _blackboard_key(value: str) -> str | None:
    """``k`` for an attribute value ``{k}`` (surrounding blanks allowed), else None."""
    stripped = value.strip()
    if len(stripped) >= 2 and stripped[0] == "{" and stripped[-1] == "}":
        return stripped[1:-1]
    return None


def _resolve(param: str, value: str, scopes: tuple[_Scope, ...]) -> Arg:
    """The argument an attribute ``param=value`` means, seen from the main tree."""
    key = _blackboard_key(value)
    if key is None:
        return Arg(param, value, literal=True)
    for scope in reversed(scopes):
        remapped = dict(scope.remap).get(key)
        if remapped is not None:
            outer = _blackboard_key(remapped)
            if outer is None:
                return Arg(param, remapped, literal=True)
            key = outer
        elif not scope.autoremap:
            break  # a key private to the subtree
    return Arg(param, key)


def _subtree_scope(element: ET.Element) -> _Scope | None:
    """The scope a ``<SubTree>`` opens, or None when it reads its parent's keys unchanged."""
    autoremap = element.get("_autoremap", "false").strip().lower() in ("true", "1")
    remap = []
    for key, value in element.attrib.items():
        if key in ("ID", "name") or key.startswith("_"):
            continue
        if value.strip() == "{=}":
            value = "{" + key + "}"
        if autoremap and _blackboard_key(value) == key:
            continue  # the same as autoremapping it
        remap.append((key, value))
    if autoremap and not remap:
        return None
    return _Scope(tuple(sorted(remap)), autoremap)


def parse_btcpp_xml(text: str) -> Node:
    """Read BehaviorTree.CPP v4 XML (as written by :func:`render_btcpp_xml`) back into a tree.

    Supports (Reactive)Fallback / (Reactive)Sequence composites, Action / Condition leaves in the
    compact (``<x>``, typed by ``<TreeNodesModel>``) or explicit (``<Action ID="x">``) form, and
    ``<SubTree ID=...>`` references, which are expanded in place (port remapping and
    ``_autoremap`` are applied to the leaves' blackboard keys; a subtree referenced twice with
    the same mapping becomes one shared :class:`Node`). A ``{key}`` attribute becomes a symbol
    argument, anything else a literal one; a leaf's doc is its model's description; a
    composite's name is its ``name`` attribute (else its tag). Every node gets role PLAIN and no
    meta. Iterative, so deep trees are fine.

    Raises:
        ValueError: not BT.CPP v4 XML, a node type this project does not produce, a ``<SubTree>``
            that names no tree or contains itself, or more than :data:`MAX_PARSED_NODES` nodes.
    """
    try:
        document = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ValueError(f"not well-formed XML: {exc}") from exc
    if document.tag != "root":
        raise ValueError(f"the document element is <{document.tag}>, expected <root>")
    if document.get("BTCPP_format") != "4":
        raise ValueError(
            f'BTCPP_format is {document.get("BTCPP_format")!r}; only format "4" is supported'
        )
    models = _read_models(document)
    tops, main_id = _read_trees(document)

    # An explicit stack of work items builds children before parents. ("visit", element, scopes)
    # pushes a node's value onto ``values``; ("close", element, n) pops the n children of a
    # composite; ("done", key) remembers a finished subtree and closes it for cycle detection.
    memo: dict[tuple[str, tuple[_Scope, ...]], Node] = {}
    open_trees: list[str] = [main_id]
    values: list[Node] = []
    created = 0
    work: list[tuple[str, ET.Element | None, tuple[_Scope, ...], tuple[str, tuple[_Scope, ...]]]]
    no_key = ("", ())
    work = [("visit", tops[main_id], (), no_key)]
    while work:
        step, element, scopes, key = work.pop()
        if step == "done":
            memo[key] = values[-1]
            open_trees.pop()
            continue
        assert element is not None
        if step == "close":
            count = len(element)
            children = tuple(values[len(values) - count :])
            del values[len(values) - count :]
            values.append(
                Node(_TAG_KIND[element.tag], element.get("name", element.tag), children=children)
            )
            continue
        created += 1
        if created > MAX_PARSED_NODES:
            raise ValueError(
                f"the tree has more than {MAX_PARSED_NODES:,} nodes once its <SubTree>s are "
                "expanded"
            )
        if element.tag == "SubTree":
            sub_id = element.get("ID", "")
            if sub_id not in tops:
                raise ValueError(f"<SubTree ID={sub_id!r}> names no <BehaviorTree>")
            if len(element):
                raise ValueError(f"<SubTree ID={sub_id!r}> has child elements")
            if sub_id in open_trees:
                raise ValueError(f"<SubTree ID={sub_id!r}> contains itself")
            scope = _subtree_scope(element)
            inner = scopes if scope is None else (*scopes, scope)
            sub_key = (sub_id, inner)
            if sub_key in memo:
                values.append(memo[sub_key])
                continue
            open_trees.append(sub_id)
            work.append(("done", None, inner, sub_key))
            work.append(("visit", tops[sub_id], inner, no_key))
            continue
        kind = _TAG_KIND.get(element.tag)
        if kind is None and element.tag in models:
            kind = models[element.tag][0]
            node_id: str | None = element.tag
        else:
            node_id = element.get("ID")
        if kind is None:
            raise ValueError(f"unsupported node <{element.tag}> (no model in <TreeNodesModel>)")
        if kind.is_composite:
            work.append(("close", element, scopes, no_key))
            work.extend(("visit", child, scopes, no_key) for child in reversed(element))
            continue
        if not node_id:
            raise ValueError(f"<{element.tag}> without an ID attribute")
        if len(element):
            raise ValueError(f"leaf <{element.tag} ID={node_id!r}> has child elements")
        args = tuple(
            _resolve(param, value, scopes)
            for param, value in element.attrib.items()
            if param not in ("ID", "name") and not param.startswith("_")
        )
        doc = models.get(node_id, (kind, ""))[1]
        values.append(Node(kind, node_id, args, (), Role.PLAIN, doc))
    (result,) = values
    return result
