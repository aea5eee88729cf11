"""Load, check and tick an exported tree in real BehaviorTree.CPP, through the PyPI package behaviortreepy.

``tests/btcpp/btcpp_check.cpp`` does this in C++ where a BehaviorTree.CPP build is at hand; this
module does it wherever ``pip install behaviortreepy`` works (a manylinux wheel that bundles
BehaviorTree.CPP itself), so the check runs in CI. It prints the same one-line report.

behaviortreepy 0.1.4 registers Python nodes without ports (``register_simple_action(name, fn)``
has no way to declare them), and BehaviorTree.CPP refuses an attribute that is not a declared
port ("a port with name [goal] is found in the XML ... but not in the providedPorts() of its
registered node type"). So every leaf of the file is handed to BehaviorTree.CPP as a SubTree
call, whose attributes are port remappings that need no declaration:

    <at_goal name="at_goal(goal)" goal="{goal}"/>
        becomes
    <SubTree ID="at_goal" name="at_goal(goal)" goal="{goal}"/>
    <BehaviorTree ID="at_goal"><at_goal__leaf/></BehaviorTree>

where ``at_goal__leaf`` is a Python condition (or stateful action) that reads each port the leaf
was given from its SubTree's blackboard (BehaviorTree.CPP resolves the remapping, through every
``_autoremap`` SubTree between the leaf and the root). What BehaviorTree.CPP's manifest check
would have refused, :func:`check_xml` refuses in Python first: an attribute of a leaf that is not
a port declared for it in ``<TreeNodesModel>``. Everything else (the document, every other
element, SubTrees and their remapping, the composites' rules) is BehaviorTree.CPP's to accept:
the rewritten document is registered with ``register_behavior_tree_from_text`` and the main tree
created with ``create_tree``.

Then, all in BehaviorTree.CPP (:func:`check_xml`):

1. every leaf reads its ports, in a copy of the document whose composites are all ``Sequence``
   and whose leaves all succeed, so that one tick reaches every leaf instance, in its place
   among the SubTrees (btcpp_check reads them after loading; a Python node can only read them
   when it is ticked, and the tree as written does not tick every leaf);
2. the tree as written is ticked with btcpp_check's leaves until it stops RUNNING (at most
   :data:`MAX_TICKS` ticks): a condition fails on its first tick and succeeds afterwards, an
   action returns RUNNING once and then SUCCESS, so the reactive composites halt and restart
   children;
3. and once more with conditions failing and actions succeeding: one tick then walks every
   branch of a back-chained tree.

Not checked, unlike btcpp_check: ``BT::VerifyXML`` and the tree's creation against manifests
registered with the leaves' ports (BehaviorTree.CPP sees SubTree calls, not the leaves; the
port check above stands in for its manifest check, and the rules VerifyXML applies to a
composite's children see ``SubTree`` where the file has a leaf).
"""

from __future__ import annotations

import sys
import xml.etree.ElementTree as ET
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from xml.parsers import expat

import behaviortreepy as btpy

from btmission.export.btcpp import _serialize  # iterative: the files may be 2,000 levels deep
from btmission.spec.library import BTCPP_BUILTIN_NODES

MAX_TICKS = 1000
"""As btcpp_check's default: a tree still RUNNING after this many ticks fails the check."""

BUNDLED_BTCPP = {"0.1.4": "4.8.2"}
"""The BehaviorTree.CPP each behaviortreepy release bundles (its git submodule; the library has
no call that reports it)."""

_KINDS = ("Action", "Condition")
_PORT_TAGS = ("input_port", "description")


class CheckFailed(Exception):
    """The file does not load or tick in BehaviorTree.CPP (or breaks a rule it would enforce)."""


@dataclass(frozen=True)
class Report:
    """What one check saw; :meth:`line` is btcpp_check's one-line report, then what only this
    check counts."""

    path: Path
    version: str
    models: int
    trees: int
    """(Sub)trees instantiated for the file's own <BehaviorTree>s (the leaves' wrappers aside)."""
    nodes: int
    """Nodes of those (sub)trees, as BehaviorTree.CPP creates them from the file."""
    keys: frozenset[str]
    ticks: int
    status: str
    leaf_ticks: int
    ticked_types: frozenset[str]
    halts: int
    """Actions halted while RUNNING (the reactive composites restarting a branch)."""
    leaves: int
    """Leaf instances in the instantiated tree (each has had its ports read)."""
    branch_leaves: int
    """Leaf instances ticked in the run with conditions failing and actions succeeding."""
    branch_status: str
    reads: Counter[tuple[str, str, str]] = field(compare=False)
    """``(leaf ID, port, value read from BehaviorTree.CPP's blackboard) -> leaf instances``."""

    def line(self) -> str:
        return (
            f"OK: {self.path}: BehaviorTree.CPP {self.version}, {self.models} node models, "
            f"{self.trees} (sub)trees, {self.nodes} nodes, {len(self.keys)} blackboard keys; "
            f"{self.ticks} ticks -> {self.status}, {self.leaf_ticks} leaf ticks, "
            f"{len(self.ticked_types)} node types ticked, {self.halts} halted; "
            f"{self.leaves} leaves' ports read; "
            f"conditions failing: {self.branch_leaves} leaves ticked -> {self.branch_status}"
        )


def btcpp_version() -> str:
    version = btpy.__version__
    return f"{BUNDLED_BTCPP.get(version, 'unknown')} (behaviortreepy {version})"


# ------------------------------------------------------------------------------------ reading
def _parse(text: str) -> tuple[ET.Element, dict[ET.Element, int]]:
    """The document and each element's line; expat's callbacks, so any depth is fine."""
    parser = expat.ParserCreate()
    lines: dict[ET.Element, int] = {}
    stack: list[ET.Element] = []
    top: list[ET.Element] = []

    def start(tag: str, attributes: dict[str, str]) -> None:
        if stack:
            element = ET.SubElement(stack[-1], tag, attributes)
        else:
            element = ET.Element(tag, attributes)
            top.append(element)
        lines[element] = parser.CurrentLineNumber
        stack.append(element)

    parser.StartElementHandler = start
    parser.EndElementHandler = lambda _tag: stack.pop()
    try:
        parser.Parse(text, True)
    except expat.ExpatError as exc:
        raise CheckFailed(f"not well-formed XML: {exc}") from exc
    return top[0], lines


def _models(root: ET.Element) -> dict[str, tuple[str, tuple[str, ...]]]:
    """``ID -> (Action|Condition, declared input ports)``, read as btcpp_check reads them."""
    model_root = root.find("TreeNodesModel")
    if model_root is None:
        raise CheckFailed("no <TreeNodesModel>")
    models: dict[str, tuple[str, tuple[str, ...]]] = {}
    for model in model_root:
        if model.tag not in _KINDS:
            raise CheckFailed(f"unexpected <{model.tag}> in <TreeNodesModel>")
        node_id = model.get("ID")
        if node_id is None:
            raise CheckFailed(f"<{model.tag}> without ID in <TreeNodesModel>")
        if node_id in BTCPP_BUILTIN_NODES:
            raise CheckFailed(f"ID [{node_id}] is one of BehaviorTree.CPP's own node types")
        if node_id in models:
            raise CheckFailed(f"ID [{node_id}] is declared twice in <TreeNodesModel>")
        ports = []
        for port in model:
            if port.tag not in _PORT_TAGS or (port.tag == "input_port" and not port.get("name")):
                raise CheckFailed(f"unexpected <{port.tag}> in the model of {node_id}")
            if port.tag == "input_port":
                ports.append(port.get("name", ""))
        models[node_id] = (model.tag, tuple(ports))
    return models


def _is_port(attribute: str) -> bool:
    """BehaviorTree.CPP's IsAllowedPortName: a letter first, and not reserved (its other
    reserved attributes, ``_autoremap`` and the pre/post conditions, start with ``_``)."""
    return attribute[:1].isascii() and attribute[:1].isalpha() and attribute not in ("name", "ID")


def blackboard_key(attribute: str, value: str) -> str | None:
    """The key a port value refers to (BehaviorTree.CPP's isBlackboardPointer), else None."""
    stripped = value.strip(" ")
    if stripped == "{=}":
        return attribute
    if len(stripped) >= 3 and stripped[0] == "{" and stripped[-1] == "}":
        return stripped[1:-1]
    return None


# ----------------------------------------------------------------------------------- rewriting
@dataclass
class _Plan:
    """The rewritten document and what the leaves registered for it must read."""

    document: ET.Element
    wrappers: dict[str, tuple[str, str, tuple[str, ...]]]
    """SubTree ID of a leaf wrapper -> (its Python node's ID, leaf ID, ports it reads)."""
    keys: set[str]
    trees: int
    nodes: int
    leaves: int
    main: str


def _plan(root: ET.Element, lines: dict[ET.Element, int]) -> tuple[_Plan, dict[str, str]]:
    """Check the leaves as BehaviorTree.CPP's manifest check would, and rewrite them into SubTree
    calls; count what BehaviorTree.CPP will instantiate. Returns the plan and each model's kind."""
    models = _models(root)
    tree_ids = [tree.get("ID", "") for tree in root.findall("BehaviorTree")]
    wrapper_of: dict[tuple[str, tuple[str, ...]], str] = {}
    wrappers: dict[str, tuple[str, str, tuple[str, ...]]] = {}
    keys: set[str] = set()
    per_tree: dict[str, tuple[int, int, list[str]]] = {}  # ID -> (elements, leaves, SubTree IDs)
    if len(set(tree_ids)) < len(tree_ids):
        raise CheckFailed(f"two <BehaviorTree> elements with the same ID: {sorted(tree_ids)}")
    for tree in root.findall("BehaviorTree"):
        elements = leaves = 0
        calls: list[str] = []
        stack = list(tree)
        while stack:
            element = stack.pop()
            elements += 1
            stack.extend(element)
            for attribute, value in element.attrib.items():
                key = blackboard_key(attribute, value)
                if key is not None and _is_port(attribute):
                    keys.add(key)
            if element.tag == "SubTree":
                calls.append(element.get("ID", ""))
            if element.tag not in models:
                continue  # BehaviorTree.CPP's to accept or refuse
            leaves += 1
            where = f"<{element.tag}>, line {lines[element]}"
            if len(element):
                raise CheckFailed(f"{where}: the leaf '{element.tag}' must not have any child")
            declared = models[element.tag][1]
            ports = []
            for attribute in element.attrib:
                if attribute == "name":
                    continue
                if attribute == "ID":
                    raise CheckFailed(f"{where}: Attribute [ID] is not allowed in <{element.tag}>")
                if not _is_port(attribute):
                    raise CheckFailed(
                        f"{where}: attribute [{attribute}] is not a port; this check passes "
                        "only ports and name on a leaf (btmission writes nothing else)"
                    )
                if attribute not in declared:
                    raise CheckFailed(
                        f"a port with name [{attribute}] is found in the XML ({where}) but "
                        f"not in the <TreeNodesModel> of {element.tag} (declared: "
                        f"{', '.join(declared) or 'none'})"
                    )
                ports.append(attribute)
            signature = (element.tag, tuple(sorted(ports)))
            wrapper = wrapper_of.get(signature)
            if wrapper is None:
                n = sum(1 for leaf, _ in wrapper_of if leaf == element.tag)
                wrapper = element.tag if n == 0 else f"{element.tag}__ports{n}"
                wrapper_of[signature] = wrapper
                wrappers[wrapper] = (f"{wrapper}__leaf", element.tag, signature[1])
            attributes = dict(element.attrib)
            element.clear()
            element.tag = "SubTree"
            element.attrib.update({"ID": wrapper, **attributes})
        tree_id = tree.get("ID", "")
        per_tree[tree_id] = (elements, leaves, calls)
    # the wrapper of X is the tree X (a model's ID is not a registered node, a tree's may be it);
    # every other name made up here must be new
    made_up = {w for w, (_, leaf, _) in wrappers.items() if w != leaf}
    nodes_made = {node for node, _, _ in wrappers.values()}
    clashes = ({*wrappers} & {*tree_ids}) | ((made_up | nodes_made) & ({*models} | {*tree_ids}))
    if clashes:
        raise CheckFailed(
            f"cannot hand the leaves to BehaviorTree.CPP as SubTrees: {sorted(clashes)} are "
            "already IDs of the file"
        )
    main = root.get("main_tree_to_execute") or (tree_ids[0] if len(tree_ids) == 1 else "")
    trees, nodes, leaves = _instances(per_tree, main)
    return _Plan(root, wrappers, keys, trees, nodes, leaves, main), {
        n: kind for n, (kind, _) in models.items()
    }


def _instances(per_tree: dict[str, tuple[int, int, list[str]]], main: str) -> tuple[int, int, int]:
    """(sub)trees, nodes and leaves BehaviorTree.CPP instantiates from ``main``, by counting (a
    SubTree referenced twice is instantiated twice) rather than expanding."""
    if main not in per_tree:
        raise CheckFailed(f"main_tree_to_execute={main!r} names no <BehaviorTree>")
    order: list[str] = []  # post-order: callees before their callers
    state: dict[str, int] = {}  # 1: open, 2: done
    stack: list[tuple[str, int]] = [(main, 0)]
    while stack:
        tree_id, next_call = stack.pop()
        calls = per_tree[tree_id][2]
        state[tree_id] = 1
        if next_call < len(calls):
            stack.append((tree_id, next_call + 1))
            callee = calls[next_call]
            if callee not in per_tree:
                raise CheckFailed(f"<SubTree ID={callee!r}> names no <BehaviorTree>")
            if state.get(callee) == 1:
                raise CheckFailed(f"<SubTree ID={callee!r}> contains itself")
            if callee not in state:
                stack.append((callee, 0))
            continue
        state[tree_id] = 2
        order.append(tree_id)
    count = dict.fromkeys(order, 0)
    count[main] = 1
    for tree_id in reversed(order):
        for callee in per_tree[tree_id][2]:
            count[callee] += count[tree_id]
    return (
        sum(count.values()),
        sum(n * per_tree[t][0] for t, n in count.items()),
        sum(n * per_tree[t][1] for t, n in count.items()),
    )


# ------------------------------------------------------------------------------------- ticking
@dataclass
class _Round:
    """What the leaves did while the tree was ticked one way."""

    leaf_ticks: int = 0
    ticked_types: set[str] = field(default_factory=set)
    instances: set[int] = field(default_factory=set)  # UIDs of the leaf nodes ticked
    condition_ticks: Counter[int] = field(default_factory=Counter)
    halts: int = 0  # RUNNING actions halted by their parents


class _Leaves:
    """The Python nodes behind the leaves of one tree: how they answer (``mode``), what they
    count, and the first error (behaviortreepy prints a Python exception and returns FAILURE,
    so none may escape a callback).

    Modes: ``"ports"``: everything succeeds; ``"btcpp_check"``: a condition fails on its first
    tick and succeeds afterwards, an action returns RUNNING once, then SUCCESS; ``"branches"``:
    conditions fail, actions succeed (a back-chained tree then ticks every branch in one tick).
    """

    def __init__(self) -> None:
        self.mode = "ports"
        self.round = _Round()
        self.read: set[int] = set()
        self.reads: Counter[tuple[str, str, str]] = Counter()
        self.errors: list[str] = []

    def start(self, mode: str) -> _Round:
        self.mode, self.round = mode, _Round()
        return self.round

    def _tick(self, node: btpy.TreeNode, leaf: str, ports: tuple[str, ...]) -> bool:
        """Count the tick; the first time this node ticks, read its ports. False on an error."""
        self.round.leaf_ticks += 1
        self.round.ticked_types.add(leaf)
        uid = node.uid()
        self.round.instances.add(uid)
        if uid in self.read:
            return True
        self.read.add(uid)
        blackboard = node.config().blackboard
        for port in ports:
            try:
                value = blackboard.get_string(port)
            except Exception as exc:  # BehaviorTree.CPP's error, e.g. a key no one set
                path = node.full_path().rpartition("/")[0]  # the SubTree's: the leaf's own name
                self.errors.append(f"node '{path}' ({leaf}): input port '{port}': {exc}")
                return False
            self.reads[(leaf, port, value)] += 1
        return True

    def condition(self, leaf: str, ports: tuple[str, ...]) -> Callable[[btpy.TreeNode], object]:
        def tick(node: btpy.TreeNode) -> btpy.NodeStatus:
            if not self._tick(node, leaf, ports):
                return btpy.NodeStatus.FAILURE
            if self.mode == "ports":
                return btpy.NodeStatus.SUCCESS
            if self.mode == "btcpp_check":
                self.round.condition_ticks[node.uid()] += 1
                if self.round.condition_ticks[node.uid()] > 1:
                    return btpy.NodeStatus.SUCCESS
            return btpy.NodeStatus.FAILURE

        return tick

    def action(
        self, leaf: str, ports: tuple[str, ...]
    ) -> tuple[Callable[[btpy.TreeNode], object], ...]:
        def on_start(node: btpy.TreeNode) -> btpy.NodeStatus:
            if not self._tick(node, leaf, ports):
                return btpy.NodeStatus.FAILURE
            if self.mode == "btcpp_check":
                return btpy.NodeStatus.RUNNING
            return btpy.NodeStatus.SUCCESS

        def on_running(node: btpy.TreeNode) -> btpy.NodeStatus:
            self.round.leaf_ticks += 1
            return btpy.NodeStatus.SUCCESS

        def on_halted(node: btpy.TreeNode) -> None:
            self.round.halts += 1

        return on_start, on_running, on_halted


def _load(plan: _Plan, kinds: dict[str, str], document: ET.Element) -> tuple[btpy.Tree, _Leaves]:
    """``document`` (the plan's or its port-reading copy) loaded in a new factory, its main
    tree created on a blackboard holding every key the file references; and its leaves."""
    factory = btpy.BehaviorTreeFactory()
    leaves = _Leaves()
    for wrapper, (node_id, leaf, ports) in plan.wrappers.items():
        if kinds[leaf] == "Condition":
            factory.register_simple_condition(node_id, leaves.condition(leaf, ports))
        else:
            factory.register_simple_stateful_action(node_id, *leaves.action(leaf, ports))
        factory.register_behavior_tree_from_text(
            f'<root BTCPP_format="4"><BehaviorTree ID="{wrapper}"><{node_id}/></BehaviorTree></root>'
        )
    blackboard = btpy.Blackboard.create()
    for key in plan.keys:
        blackboard.set_string(key, f"value of {key}")
    factory.register_behavior_tree_from_text(_serialize(document))
    return factory.create_tree(plan.main, blackboard), leaves


def _run(tree: btpy.Tree, leaves: _Leaves, mode: str, max_ticks: int) -> tuple[_Round, int, str]:
    """Tick ``tree`` with the leaves in ``mode`` until it stops RUNNING (or an error); halt it."""
    done = leaves.start(mode)
    status = btpy.NodeStatus.RUNNING
    ticks = 0
    while status == btpy.NodeStatus.RUNNING and ticks < max_ticks and not leaves.errors:
        status = tree.tick_once()
        ticks += 1
    tree.halt_tree()
    if leaves.errors:
        raise CheckFailed(leaves.errors[0])
    if status == btpy.NodeStatus.RUNNING:
        raise CheckFailed(f"still RUNNING after {ticks} ticks ({mode})")
    return done, ticks, status.name


def _port_copy(document: ET.Element) -> ET.Element:
    """The rewritten document with every composite a plain ``Sequence``: with every leaf
    succeeding, one tick reaches each leaf once, in its place among the SubTrees."""
    copy = _parse(_serialize(document))[0]
    for tree in copy.findall("BehaviorTree"):
        stack = list(tree)
        while stack:
            element = stack.pop()
            if len(element) and element.tag != "SubTree":
                name = element.get("name")
                element.attrib.clear()
                element.tag = "Sequence"
                if name is not None:
                    element.set("name", name)
            stack.extend(element)
    return copy


def check_xml(path: Path, *, max_ticks: int = MAX_TICKS) -> Report:
    """Load ``path`` in BehaviorTree.CPP (behaviortreepy), read every leaf's ports, tick it to
    completion (the module docstring says how); :class:`CheckFailed` with BehaviorTree.CPP's
    message, or the Python checks'. The file as written is loaded first, so that its errors are
    the ones reported."""
    root, lines = _parse(path.read_text(encoding="utf-8"))
    if root.tag != "root":
        raise CheckFailed("The XML must have a root node called <root>")
    plan, kinds = _plan(root, lines)
    try:
        tree, leaves = _load(plan, kinds, plan.document)
        port_tree, port_leaves = _load(plan, kinds, _port_copy(plan.document))
        ports, _, _ = _run(port_tree, port_leaves, "ports", 1)
        if len(ports.instances) != plan.leaves:
            raise CheckFailed(
                f"the file has {plan.leaves} leaf instances, but BehaviorTree.CPP ticked "
                f"{len(ports.instances)} in a tree of Sequences"
            )
        btcpp_check, ticks, status = _run(tree, leaves, "btcpp_check", max_ticks)
        branches, _, branches_status = _run(tree, leaves, "branches", max_ticks)
    except RuntimeError as exc:  # BehaviorTree.CPP's exceptions, as behaviortreepy raises them
        raise CheckFailed(" ".join(str(exc).split())) from exc
    return Report(
        path=path,
        version=btcpp_version(),
        models=len(kinds),
        trees=plan.trees,
        nodes=plan.nodes,
        keys=frozenset(plan.keys),
        ticks=ticks,
        status=status,
        leaf_ticks=btcpp_check.leaf_ticks,
        ticked_types=frozenset(btcpp_check.ticked_types),
        halts=btcpp_check.halts,
        leaves=plan.leaves,
        branch_leaves=len(branches.instances),
        branch_status=branches_status,
        reads=port_leaves.reads,
    )


def main(argv: list[str]) -> int:
    """``python -m tests.btcpp_py FILE.xml``: btcpp_check's report line and exit status."""
    if len(argv) != 1:
        print("usage: python -m tests.btcpp_py FILE.xml", file=sys.stderr)
        return 2
    try:
        print(check_xml(Path(argv[0])).line())
    except CheckFailed as exc:
        print(f"FAIL: {argv[0]}: {exc}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
