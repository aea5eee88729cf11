"""The abstract behaviour tree: plain, immutable data produced by synthesis (DESIGN.md §4.2).

Synthesis never builds py_trees objects directly; it returns a :class:`Node` tree that the py_trees
builder, the symbolic dry run and every exporter (ascii, dot, svg/png, BehaviorTree.CPP XML, JSON)
read. Nodes are frozen, so identical subtrees may be *shared* (synthesis memoises the expansion of
each ground condition): treat the structure as a tree whose repeated subtrees happen to be the same
object. Walk it with :func:`walk` (iterative, so 10,000-deep chains are fine).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import Enum


class Kind(str, Enum):
    """Node types. Composites are memory-less (reactive), as back-chained PPA trees require."""

    FALLBACK = "fallback"  # py_trees Selector(memory=False); BT.CPP ReactiveFallback
    SEQUENCE = "sequence"  # py_trees Sequence(memory=False); BT.CPP ReactiveSequence
    CONDITION = "condition"
    ACTION = "action"

    @property
    def is_composite(self) -> bool:
        return self in (Kind.FALLBACK, Kind.SEQUENCE)


class Role(str, Enum):
    """Why a node is in the tree; exporters may style by role, the runtime binds by it."""

    PLAIN = "plain"  # a library condition/action chosen by back-chaining
    ASSUMED = "assumed"  # a condition no action achieves: checked, never achieved
    CYCLE = "cycle"  # a condition whose expansion would loop; left unexpanded (an error)
    BUILTIN = (
        "builtin"  # runtime-provided leaf of the mission tree (task_assigned, idle_timeout, wait)
    )
    GOAL = "goal"  # composite that ensures a goal condition (PPA fallback)
    ACHIEVE = "achieve"  # composite sequence: preconditions then the action
    TASK = "task"  # mission tree branch that runs one task type's subtree
    DEFAULT = "default"  # mission tree branch that runs the default behaviour
    MISSION = "mission"  # the root of a mission tree (seed 000 Fig. 7)


@dataclass(frozen=True, slots=True)
class Arg:
    """A parameter binding of a leaf: ``param`` gets ``value``.

    ``value`` is a *symbol* (a blackboard key / task field such as ``location``) unless
    ``literal`` is true, in which case it is a constant (e.g. ``type="inspect"``).
    """

    param: str
    value: str
    literal: bool = False

    def render(self) -> str:
        return f'"{self.value}"' if self.literal else self.value


@dataclass(frozen=True, slots=True)
class Node:
    """One node of the abstract tree.

    Attributes:
        kind: fallback / sequence / condition / action.
        name: leaf: the library condition or action name (``at_goal``); composite: a label.
        args: leaf parameter bindings, in the declared parameter order.
        children: composite children, in tick order.
        role: why the node is there (see :class:`Role`).
        doc: the library's description of the leaf (empty for composites).
        meta: extra key/value pairs (e.g. ``commit_after`` on a task branch); sorted by key.
    """

    kind: Kind
    name: str
    args: tuple[Arg, ...] = ()
    children: tuple[Node, ...] = ()
    role: Role = Role.PLAIN
    doc: str = ""
    meta: tuple[tuple[str, str], ...] = field(default=())

    def __repr__(self) -> str:  # shallow: dataclass repr would recurse through deep trees
        kids = f", {len(self.children)} children" if self.children else ""
        return f"Node({self.kind.value} {self.label!r}{kids})"

    @property
    def label(self) -> str:
        """``name`` for composites and argument-less leaves, ``name(a, b)`` otherwise."""
        if not self.args:
            return self.name
        return f"{self.name}({', '.join(a.render() for a in self.args)})"

    @property
    def is_leaf(self) -> bool:
        return not self.kind.is_composite

    def get_meta(self, key: str, default: str | None = None) -> str | None:
        for k, v in self.meta:
            if k == key:
                return v
        return default


def walk(root: Node) -> Iterator[tuple[int, Node]]:
    """Pre-order traversal yielding ``(depth, node)``; iterative (no recursion limit)."""
    stack: list[tuple[int, Node]] = [(0, root)]
    while stack:
        depth, node = stack.pop()
        yield depth, node
        for child in reversed(node.children):
            stack.append((depth + 1, child))


def walk_distinct(root: Node) -> Iterator[tuple[int, Node]]:
    """Like :func:`walk`, but each shared subtree object is visited once (at its first occurrence)."""
    seen: set[int] = set()
    stack: list[tuple[int, Node]] = [(0, root)]
    while stack:
        d, node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        yield d, node
        for child in reversed(node.children):
            stack.append((d + 1, child))


def distinct_postorder(root: Node) -> list[Node]:
    """Each distinct node object once, every child before any of its parents; iterative.

    The order to fold a shared tree bottom-up (sizes, conversions) without recursion.
    """
    done: set[int] = set()
    out: list[Node] = []
    stack: list[tuple[Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        if id(node) in done:
            continue
        if children_done:
            done.add(id(node))
            out.append(node)
            continue
        stack.append((node, True))
        stack.extend((c, False) for c in reversed(node.children) if id(c) not in done)
    return out


def count_nodes(root: Node) -> int:
    """Number of nodes of the expanded tree (shared subtrees counted once per occurrence)."""
    sizes: dict[int, int] = {}
    for node in distinct_postorder(root):
        sizes[id(node)] = 1 + sum(sizes[id(c)] for c in node.children)
    return sizes[id(root)]


def depth(root: Node) -> int:
    """Depth of the tree (a single leaf has depth 1); linear in the *distinct* nodes."""
    depths: dict[int, int] = {}
    for node in distinct_postorder(root):
        depths[id(node)] = 1 + max((depths[id(c)] for c in node.children), default=0)
    return depths[id(root)]


def leaf_signatures(root: Node) -> dict[tuple[Kind, str], tuple[str, ...]]:
    """Every distinct leaf type with its parameter names (what a node model / manifest needs)."""
    out: dict[tuple[Kind, str], tuple[str, ...]] = {}
    for _, node in walk(root):
        if node.is_leaf:
            out.setdefault((node.kind, node.name), tuple(a.param for a in node.args))
    return out


# Small constructors keep synthesis and tests readable.
def condition(name: str, *args: Arg, role: Role = Role.PLAIN, doc: str = "") -> Node:
    return Node(Kind.CONDITION, name, tuple(args), (), role, doc)


def action(name: str, *args: Arg, role: Role = Role.PLAIN, doc: str = "") -> Node:
    return Node(Kind.ACTION, name, tuple(args), (), role, doc)


def fallback(
    name: str, *children: Node, role: Role = Role.GOAL, meta: dict[str, str] | None = None
) -> Node:
    return Node(
        Kind.FALLBACK, name, (), tuple(children), role, "", tuple(sorted((meta or {}).items()))
    )


def sequence(
    name: str, *children: Node, role: Role = Role.ACHIEVE, meta: dict[str, str] | None = None
) -> Node:
    return Node(
        Kind.SEQUENCE, name, (), tuple(children), role, "", tuple(sorted((meta or {}).items()))
    )
