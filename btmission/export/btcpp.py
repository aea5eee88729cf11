"""BehaviorTree.CPP v4 XML (loadable by BT.CPP 4.x and Groot2) from an abstract tree, and back.

Format, as read by BT.CPP's ``src/xml_parsing.cpp`` (4.x)::

    <?xml version="1.0" encoding="UTF-8"?>
    <root BTCPP_format="4" main_tree_to_execute="MainTree">
      <BehaviorTree ID="MainTree">
        <ReactiveFallback name="at_goal(goal)">
          <Condition ID="at_goal" name="at_goal(goal)" goal="{goal}"/>
          <ReactiveSequence name="follow_path(goal)">
            <Condition ID="has_path" name="has_path(goal)" goal="{goal}"/>
            <Action ID="follow_path" name="follow_path(goal)" goal="{goal}"/>
          </ReactiveSequence>
        </ReactiveFallback>
      </BehaviorTree>
      <TreeNodesModel>
        <Condition ID="at_goal">
          <input_port name="goal"/>
          <description>The robot is at the goal.</description>
        </Condition>
        ...
      </TreeNodesModel>
    </root>

* Our composites are memory-less, so fallback/sequence become ``ReactiveFallback`` /
  ``ReactiveSequence`` (as in BT.CPP's reactive back-chaining example), named by ``name``.
* Leaves use the explicit form ``<Action ID=...>`` / ``<Condition ID=...>`` with the instance
  ``name`` set to :attr:`Node.label`; each argument is an input port attribute: a symbol ``goal``
  becomes the blackboard reference ``{goal}``, a literal its plain value.
* ``<TreeNodesModel>`` lists every leaf type once, sorted by kind then ID, with one
  ``<input_port>`` per parameter (the union over all occurrences, in first-seen order) and the
  library's description as a ``<description>`` child (BT.CPP's XSD places it after the ports).

Names BT.CPP would reject (model IDs or port names with forbidden characters, reserved port names,
a literal that looks like a blackboard reference) raise :class:`ValueError` instead of producing a
file that fails to load. Roles and ``meta`` have no place in BT.CPP's format and are not written, so
:func:`parse_btcpp_xml` returns every node with role PLAIN and no meta.

Serialisation and parsing are iterative (ElementTree's own writer and ``ET.indent`` recurse once
per level), and indentation stops growing after :data:`MAX_INDENT_LEVELS` levels, so a
10,000-deep tree gives a file linear in its size. Note that BT.CPP 4.x itself refuses XML nested
deeper than 256 elements.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

from btmission.synthesis.tree import Arg, Kind, Node, Role, walk

__all__ = ["MAX_INDENT_LEVELS", "parse_btcpp_xml", "render_btcpp_xml"]

MAX_INDENT_LEVELS = 64
"""Elements deeper than this are indented as if at this depth (the whitespace is insignificant)."""

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
def _check_model_name(name: str, what: str) -> None:
    if not name:
        raise ValueError(f"BehaviorTree.CPP {what} cannot be empty")
    if name == "Root":
        raise ValueError(f"BehaviorTree.CPP {what} cannot be 'Root' (reserved)")
    bad = _FORBIDDEN_NAME_CHARS.search(name)
    if bad:
        raise ValueError(
            f"BehaviorTree.CPP {what} {name!r} contains the forbidden character {bad.group()!r}"
        )


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


def render_btcpp_xml(root: Node, tree_id: str = "MainTree") -> str:
    """BehaviorTree.CPP v4 XML for ``root`` as the tree ``tree_id`` (see the module docstring).

    Raises:
        ValueError: a name, port or value BehaviorTree.CPP would reject.
    """
    _check_model_name(tree_id, "tree ID")
    models = _node_models(root)
    for kind, name, params, _ in models:
        _check_model_name(name, f"{kind.value} ID")
        if name == tree_id:
            raise ValueError(f"tree ID {tree_id!r} clashes with the {kind.value} of that name")
        for param in params:
            _check_port_name(param, name)

    document = ET.Element("root", {"BTCPP_format": "4", "main_tree_to_execute": tree_id})
    tree = ET.SubElement(document, "BehaviorTree", {"ID": tree_id})
    stack: list[tuple[ET.Element, Node]] = [(tree, root)]
    while stack:  # pre-order; children pushed reversed so SubElement appends them in tick order
        parent, node = stack.pop()
        if node.kind.is_composite:
            element = ET.SubElement(parent, _COMPOSITE_TAG[node.kind], {"name": node.name})
            stack.extend((element, child) for child in reversed(node.children))
        else:
            attributes = {"ID": node.name, "name": node.label}
            for arg in node.args:
                attributes[arg.param] = _port_value(arg, node.name)
            ET.SubElement(parent, _LEAF_TAG[node.kind], attributes)

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


def _select_tree(document: ET.Element) -> ET.Element:
    trees = document.findall("BehaviorTree")
    if not trees:
        raise ValueError("no <BehaviorTree> in the document")
    main = document.get("main_tree_to_execute")
    if main is not None:
        for tree in trees:
            if tree.get("ID") == main:
                return tree
        raise ValueError(f"main_tree_to_execute={main!r} names no <BehaviorTree>")
    if len(trees) > 1:
        raise ValueError("several <BehaviorTree> elements and no main_tree_to_execute")
    return trees[0]


def parse_btcpp_xml(text: str) -> Node:
    """Read BehaviorTree.CPP v4 XML (as written by :func:`render_btcpp_xml`) back into a tree.

    Supports (Reactive)Fallback / (Reactive)Sequence composites and Action / Condition leaves in
    the explicit (``<Action ID="x">``) or compact (``<x>``, typed by ``<TreeNodesModel>``) form.
    A ``{key}`` attribute becomes a symbol argument, anything else a literal one; a leaf's doc is
    its model's description; a composite's name is its ``name`` attribute (else its tag). Every
    node gets role PLAIN and no meta. Iterative, so deep trees are fine.

    Raises:
        ValueError: not BT.CPP v4 XML, or a node type this project does not produce.
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
    tree = _select_tree(document)
    top = list(tree)
    if len(top) != 1:
        raise ValueError(f"<BehaviorTree ID={tree.get('ID')!r}> must have exactly one child")

    order: list[ET.Element] = []
    pending = [top[0]]
    while pending:
        element = pending.pop()
        order.append(element)
        pending.extend(reversed(list(element)))

    built: dict[int, Node] = {}
    for element in reversed(order):  # children before parents
        kind = _TAG_KIND.get(element.tag)
        if kind is None and element.tag in models:
            kind = models[element.tag][0]
            node_id: str | None = element.tag
        else:
            node_id = element.get("ID")
        if kind is None:
            raise ValueError(f"unsupported node <{element.tag}> (no model in <TreeNodesModel>)")
        if kind.is_composite:
            children = tuple(built.pop(id(child)) for child in element)
            name = element.get("name", element.tag)
            built[id(element)] = Node(kind, name, children=children)
            continue
        if not node_id:
            raise ValueError(f"<{element.tag}> without an ID attribute")
        if len(element):
            raise ValueError(f"leaf <{element.tag} ID={node_id!r}> has child elements")
        args = []
        for key, value in element.attrib.items():
            if key in ("ID", "name") or key.startswith("_"):
                continue
            stripped = value.strip()
            if len(stripped) >= 2 and stripped[0] == "{" and stripped[-1] == "}":
                args.append(Arg(key, stripped[1:-1]))
            else:
                args.append(Arg(key, value, literal=True))
        doc = models.get(node_id, (kind, ""))[1]
        built[id(element)] = Node(kind, node_id, tuple(args), (), Role.PLAIN, doc)
    return built[id(order[0])]
