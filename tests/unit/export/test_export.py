"""Tests of btmission.export: ascii, dot, svg/png, BehaviorTree.CPP v4 XML and JSON."""

from __future__ import annotations

import inspect
import json
import re
import sys
import xml.etree.ElementTree as ET
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.cli.main import cli
from btmission.export import (
    FORMATS,
    GraphvizFailed,
    GraphvizMissing,
    export_tree,
    graphviz_available,
    parse_btcpp_xml,
    parse_json,
    render_ascii,
    render_btcpp_xml,
    render_dot,
    render_graphviz,
    render_json,
    tree_from_dict,
    tree_to_dict,
)
from btmission.export import btcpp as btcpp_module
from btmission.export.btcpp import SUBTREE_DEPTH
from btmission.export.dot import dot_quote
from btmission.synthesis.tree import (
    Arg,
    Kind,
    Node,
    Role,
    action,
    condition,
    count_nodes,
    depth,
    distinct_postorder,
    fallback,
    leaf_signatures,
    sequence,
    walk,
)

needs_dot = pytest.mark.skipif(not graphviz_available(), reason="graphviz 'dot' not installed")

DEEP = 3000  # depth of the deep chain


# ------------------------------------------------------------------------------- tree builders
def goal() -> Arg:
    return Arg("goal", "goal")


def ppa_tree() -> Node:
    """Fig. 8-like PPA: fly to a goal, planning a path first."""
    return fallback(
        "ensure at_goal(goal)",
        condition("at_goal", goal(), doc="The robot is within tolerance of the goal."),
        sequence(
            "achieve at_goal(goal)",
            fallback(
                "ensure is_flying",
                condition("is_flying", doc="Airborne."),
                action("take_off", doc="Climb to the cruise altitude."),
            ),
            fallback(
                "ensure has_path(goal)",
                condition("has_path", goal()),
                action("update_path", goal(), doc="Plan a path to the goal."),
            ),
            action("follow_path", goal(), doc="Follow the planned path."),
        ),
    )


def mission_tree() -> Node:
    """Literal arguments, builtin/assumed/cycle leaves, meta and non-default composite roles."""
    inspect_branch = sequence(
        "task inspect",
        condition("task_assigned", Arg("type", "inspect", literal=True), role=Role.BUILTIN),
        condition("battery_ok", role=Role.ASSUMED, doc='Battery above "reserve" & safe.'),
        fallback(
            "ensure charged",
            condition("charged", role=Role.CYCLE),
            action("inspect", Arg("target", "location"), Arg("mode", "thermal", literal=True)),
        ),
        role=Role.TASK,
        meta={"commit_after": "holding(pickup)", "priority": "2"},
    )
    default_branch = sequence(
        "default",
        condition("idle_timeout", Arg("seconds", "30", literal=True), role=Role.BUILTIN),
        action("wait", role=Role.BUILTIN),
        role=Role.DEFAULT,
    )
    return fallback("mission", inspect_branch, default_branch, role=Role.MISSION)


def shared_tree() -> Node:
    """The same subtree object used by two parents (as memoised synthesis produces)."""
    shared = fallback(
        "ensure has_path(goal)", condition("has_path", goal()), action("plan", goal())
    )
    return sequence(
        "twice",
        shared,
        fallback("ensure at_goal(goal)", condition("at_goal", goal()), shared),
        action("follow_path", goal()),
    )


def small_tree() -> Node:
    """Five nodes, for exact expected renderings."""
    return fallback(
        "ensure at_goal(goal)",
        condition("at_goal", goal(), doc="At the goal."),
        sequence(
            "achieve at_goal(goal)",
            condition("has_path", goal(), role=Role.ASSUMED),
            action("follow_path", goal(), Arg("speed", "fast", literal=True)),
        ),
        meta={"commit_after": "holding(pickup)"},
    )


def deep_chain(levels: int = DEEP // 2) -> Node:
    """A back-chained chain: each goal needs the previous one; depth 2 * levels + 1. Iterative."""
    node: Node = action("step", Arg("i", "0", literal=True))
    for i in range(1, levels + 1):
        node = fallback(
            f"ensure g{i}",
            condition("reached", Arg("i", str(i), literal=True)),
            sequence(f"achieve g{i}", node, action("step", Arg("i", str(i), literal=True))),
        )
    return node


ALL_TREES = {
    "ppa": ppa_tree,
    "mission": mission_tree,
    "shared": shared_tree,
    "small": small_tree,
}


def assert_same_tree(
    got: Node, expected: Node, *, roles: bool = True, meta: bool = True, docs: bool = True
) -> None:
    """Iterative structural equality (dataclass ``==`` recurses and fails on deep trees)."""
    stack = [(got, expected, "root")]
    while stack:
        a, b, path = stack.pop()
        assert a.kind == b.kind, path
        assert a.name == b.name, path
        assert a.args == b.args, path
        assert len(a.children) == len(b.children), path
        if roles:
            assert a.role == b.role, path
        if meta:
            assert a.meta == b.meta, path
        if docs:
            assert a.doc == b.doc, path
        stack.extend(
            (x, y, f"{path}/{i}")
            for i, (x, y) in enumerate(zip(a.children, b.children, strict=True))
        )


def test_deep_chain_is_deep() -> None:
    tree = deep_chain()
    assert depth(tree) >= DEEP
    assert count_nodes(tree) == 1 + 4 * (DEEP // 2)


# ------------------------------------------------------------------------------------- ascii
SMALL_UNICODE = """\
? Fallback: ensure at_goal(goal) {commit_after=holding(pickup)}
├── (at_goal(goal))
└── → Sequence: achieve at_goal(goal)
    ├── (has_path(goal)) [assumed]
    └── [follow_path(goal, "fast")]
"""

SMALL_ASCII = """\
? Fallback: ensure at_goal(goal) {commit_after=holding(pickup)}
|-- (at_goal(goal))
`-- -> Sequence: achieve at_goal(goal)
    |-- (has_path(goal)) [assumed]
    `-- [follow_path(goal, "fast")]
"""


def test_ascii_small_tree_exact() -> None:
    assert render_ascii(small_tree()) == SMALL_UNICODE
    assert render_ascii(small_tree(), unicode=False) == SMALL_ASCII


def test_ascii_guides_continue_past_siblings() -> None:
    expected = """\
? Fallback: ensure at_goal(goal)
├── (at_goal(goal))
└── → Sequence: achieve at_goal(goal)
    ├── ? Fallback: ensure is_flying
    │   ├── (is_flying)
    │   └── [take_off]
    ├── ? Fallback: ensure has_path(goal)
    │   ├── (has_path(goal))
    │   └── [update_path(goal)]
    └── [follow_path(goal)]
"""
    assert render_ascii(ppa_tree()) == expected


@pytest.mark.parametrize("name", sorted(ALL_TREES))
@pytest.mark.parametrize("unicode", [True, False])
def test_ascii_one_line_per_node(name: str, unicode: bool) -> None:
    tree = ALL_TREES[name]()
    text = render_ascii(tree, unicode=unicode)
    lines = text.splitlines()
    assert text.endswith("\n")
    assert len(lines) == count_nodes(tree)
    for line, (_, node) in zip(lines, walk(tree), strict=True):
        assert node.label in line
    if not unicode:
        assert text.isascii()


def test_ascii_role_and_meta_markers() -> None:
    text = render_ascii(mission_tree())
    lines = text.splitlines()
    assert lines[0] == "? Fallback: mission"
    assert '(task_assigned("inspect")) [builtin]' in text
    assert "(battery_ok) [assumed]" in text
    assert "(charged) [cycle!]" in text
    assert "[wait] [builtin]" in text
    assert '[inspect(location, "thermal")]' in text
    assert "→ Sequence: task inspect {commit_after=holding(pickup), priority=2}" in text


def test_ascii_escapes_line_breaks() -> None:
    tree = sequence("s", action("say", Arg("text", "two\nlines", literal=True)))
    lines = render_ascii(tree).splitlines()
    assert lines == ["→ Sequence: s", '└── [say("two\\nlines")]']


def test_ascii_deep_chain_is_linear_and_elided() -> None:
    tree = deep_chain()
    lines = render_ascii(tree).splitlines()
    assert len(lines) == count_nodes(tree)
    assert max(len(line) for line in lines) < 500  # guides capped at DEFAULT_MAX_INDENT columns
    (deepest,) = [line for line in lines if line.endswith('[step("0")]')]
    hidden = DEEP - 1 - 80  # step("0") is at depth DEEP, i.e. behind DEEP - 1 guide columns
    assert deepest.startswith(f"… (+{hidden}) │   ")
    assert len(deepest) == len(f"… (+{hidden}) ") + 4 * 80 + 4 + len('[step("0")]')


def test_ascii_max_indent() -> None:
    tree = sequence("a", sequence("b", sequence("c", action("x"), action("y"))), action("z"))
    assert render_ascii(tree, unicode=False, max_indent=1) == (
        "-> Sequence: a\n"
        "|-- -> Sequence: b\n"
        "|   `-- -> Sequence: c\n"
        "... (+1)     |-- [x]\n"
        "... (+1)     `-- [y]\n"
        "`-- [z]\n"
    )
    full = render_ascii(deep_chain(60), max_indent=None).splitlines()
    (deepest,) = [line for line in full if line.endswith('[step("0")]')]
    # depth 120: all 119 guide columns (blank below each last-child sequence, a pipe below
    # each fallback that still has its action sibling to come)
    assert deepest == "    │   " * 59 + '    ├── [step("0")]'
    with pytest.raises(ValueError):
        render_ascii(tree, max_indent=0)


# --------------------------------------------------------------------------------------- dot
NODE_STMT = re.compile(r"^  n(\d+) \[(.*)\];$", re.MULTILINE)
EDGE_STMT = re.compile(r"^  n(\d+) -> n(\d+);$", re.MULTILINE)


def preorder_edges(tree: Node) -> list[tuple[int, int]]:
    """(parent index, child index) pairs of the tree in pre-order numbering."""
    edges: list[tuple[int, int]] = []
    parents: list[int] = []  # index of the ancestor at each depth
    for index, (d, _) in enumerate(walk(tree)):
        del parents[d:]
        if parents:
            edges.append((parents[-1], index))
        parents.append(index)
    return edges


@pytest.mark.parametrize("name", sorted(ALL_TREES))
def test_dot_nodes_edges_and_labels(name: str) -> None:
    tree = ALL_TREES[name]()
    text = render_dot(tree, name=name)
    n = count_nodes(tree)
    nodes = NODE_STMT.findall(text)
    edges = EDGE_STMT.findall(text)
    assert [int(i) for i, _ in nodes] == list(range(n))
    assert len(edges) == n - 1
    assert sorted((int(a), int(b)) for a, b in edges) == sorted(preorder_edges(tree))
    assert text.startswith(f"digraph {dot_quote(name)} {{\n")
    assert "rankdir=TB;" in text
    for (_, attrs), (_, node) in zip(nodes, walk(tree), strict=True):
        escaped = dot_quote(node.label)
        if node.kind.is_composite:  # the composite's name is its tooltip
            assert f'tooltip="{node.kind.value}: {escaped[1:-1]}' in attrs
        else:  # a leaf's label is its dot label
            assert f"label={escaped}" in attrs
        if node.kind is Kind.FALLBACK:
            assert 'label="?"' in attrs and 'shape="box"' in attrs
        elif node.kind is Kind.SEQUENCE:
            assert 'label="→"' in attrs and 'shape="box"' in attrs
        elif node.kind is Kind.CONDITION:
            assert 'shape="ellipse"' in attrs
        else:
            assert 'shape="box"' in attrs and "rounded" in attrs


def node_attrs(dot_text: str) -> dict[str, dict[str, str]]:
    """``label -> {attribute: value}`` of every node statement (labels unique in the tree)."""
    out: dict[str, dict[str, str]] = {}
    for match in NODE_STMT.finditer(dot_text):
        attrs = dict(re.findall(r'(\w+)="((?:[^"\\]|\\.)*)"', match.group(2)))
        out[attrs["label"]] = attrs
    return out


def test_dot_styles_roles_differently() -> None:
    attrs = node_attrs(render_dot(mission_tree()))
    plain_condition = node_attrs(render_dot(condition("c")))["c"]
    styles = [
        (a["fillcolor"], a.get("color"), a["style"])
        for a in (plain_condition, attrs["battery_ok"], attrs["charged"], attrs["wait"])
    ]
    assert len(set(styles)) == 4  # plain, assumed, cycle and builtin all look different
    assert "dashed" in attrs["battery_ok"]["style"]
    assert attrs["charged"]["penwidth"] == "2.5"
    assert (
        attrs["battery_ok"]["tooltip"]
        == 'battery_ok [assumed]\\nBattery above \\"reserve\\" & safe.'
    )


def test_dot_quote_escapes() -> None:
    assert dot_quote('say("a\\b")') == '"say(\\"a\\\\b\\")"'
    assert dot_quote("two\nlines") == '"two\\nlines"'


def test_dot_deep_chain() -> None:
    tree = deep_chain()
    text = render_dot(tree)
    assert len(NODE_STMT.findall(text)) == count_nodes(tree)
    assert len(EDGE_STMT.findall(text)) == count_nodes(tree) - 1


# --------------------------------------------------------------------------------- graphviz
def svg_texts(svg: bytes) -> set[str]:
    return {
        "".join(e.itertext()).strip() for e in ET.fromstring(svg).iter() if e.tag.endswith("text")
    }


@needs_dot
def test_svg_parses_and_shows_labels() -> None:
    tree = mission_tree()
    svg = render_graphviz(render_dot(tree), "svg")
    root = ET.fromstring(svg)
    assert root.tag == "{http://www.w3.org/2000/svg}svg"
    texts = svg_texts(svg)
    for _, node in walk(tree):
        if node.is_leaf:
            assert node.label in texts
    assert {"?", "→"} <= texts


@needs_dot
def test_svg_keeps_awkward_labels() -> None:
    tree = sequence("s", action("say", Arg("text", 'back\\slash "quoted"', literal=True)))
    svg = render_graphviz(render_dot(tree), "svg")
    assert tree.children[0].label in svg_texts(svg)


@needs_dot
def test_png_magic() -> None:
    png = render_graphviz(render_dot(ppa_tree()), "png")
    assert png.startswith(b"\x89PNG\r\n\x1a\n")


@needs_dot
def test_graphviz_failure_carries_stderr() -> None:
    with pytest.raises(GraphvizFailed, match="syntax error"):
        render_graphviz("digraph { n0 -> ; }", "svg")


def test_graphviz_bad_format() -> None:
    with pytest.raises(ValueError, match="unsupported graphviz format"):
        render_graphviz("digraph {}", "pdf")  # type: ignore[arg-type]


def test_graphviz_missing(monkeypatch: pytest.MonkeyPatch, tmp_path: object) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))  # an empty directory: no dot anywhere
    assert not graphviz_available()
    message = (
        "graphviz 'dot' was not found on PATH; install graphviz (e.g. apt-get install graphviz) "
        "or export as dot/xml/json/ascii"
    )
    with pytest.raises(GraphvizMissing) as info:
        render_graphviz("digraph {}", "svg")
    assert str(info.value) == message
    assert isinstance(info.value, RuntimeError)
    for fmt in ("svg", "png"):
        with pytest.raises(GraphvizMissing):
            export_tree(ppa_tree(), fmt)
    assert isinstance(export_tree(ppa_tree(), "dot"), str)  # text formats need no graphviz


# ------------------------------------------------------------------------ BehaviorTree.CPP XML
SMALL_XML = """\
<?xml version="1.0" encoding="UTF-8"?>
<root BTCPP_format="4" main_tree_to_execute="MainTree">
  <BehaviorTree ID="MainTree">
    <ReactiveFallback name="ensure at_goal(goal)">
      <at_goal name="at_goal(goal)" goal="{goal}"/>
      <ReactiveSequence name="achieve at_goal(goal)">
        <has_path name="has_path(goal)" goal="{goal}"/>
        <follow_path name="follow_path(goal, &quot;fast&quot;)" goal="{goal}" speed="fast"/>
      </ReactiveSequence>
    </ReactiveFallback>
  </BehaviorTree>
  <TreeNodesModel>
    <Action ID="follow_path">
      <input_port name="goal"/>
      <input_port name="speed"/>
    </Action>
    <Condition ID="at_goal">
      <input_port name="goal"/>
      <description>At the goal.</description>
    </Condition>
    <Condition ID="has_path">
      <input_port name="goal"/>
    </Condition>
  </TreeNodesModel>
</root>
"""

COMPOSITE_TAGS = {Kind.FALLBACK: "ReactiveFallback", Kind.SEQUENCE: "ReactiveSequence"}
MODEL_TAGS = {Kind.ACTION: "Action", Kind.CONDITION: "Condition"}


def test_xml_small_tree_exact() -> None:
    assert render_btcpp_xml(small_tree()) == SMALL_XML


@pytest.mark.parametrize("name", sorted(ALL_TREES))
def test_xml_structure(name: str) -> None:
    tree = ALL_TREES[name]()
    doc = ET.fromstring(render_btcpp_xml(tree, tree_id="Mission"))
    assert doc.tag == "root"
    assert doc.get("BTCPP_format") == "4"
    assert doc.get("main_tree_to_execute") == "Mission"
    (bt,) = doc.findall("BehaviorTree")
    assert bt.get("ID") == "Mission"
    (top,) = list(bt)

    # every node once per occurrence, in pre-order; leaves in the compact form <ID name=.../>
    elements = list(top.iter())
    assert len(elements) == count_nodes(tree)
    for element, (_, node) in zip(elements, walk(tree), strict=True):
        if node.kind.is_composite:
            assert element.tag == COMPOSITE_TAGS[node.kind]
            assert element.attrib == {"name": node.name}
        else:
            assert element.tag == node.name
            expected = {"name": node.label}
            expected.update(
                {a.param: a.value if a.literal else "{" + a.value + "}" for a in node.args}
            )
            assert element.attrib == expected
    assert not doc.findall(".//Action[@name]") and not doc.findall(".//Condition[@name]")

    # TreeNodesModel: each leaf type once, with one input_port per parameter, and its doc
    (model_root,) = doc.findall("TreeNodesModel")
    models = Counter((m.tag, m.get("ID")) for m in model_root)
    assert all(count == 1 for count in models.values())
    signatures = leaf_signatures(tree)
    assert set(models) == {(MODEL_TAGS[kind], leaf) for kind, leaf in signatures}
    docs = {n.name: n.doc for _, n in walk(tree) if n.is_leaf and n.doc}
    for model in model_root:
        kind = Kind.ACTION if model.tag == "Action" else Kind.CONDITION
        ports = [p.get("name") for p in model.findall("input_port")]
        assert tuple(ports) == signatures[(kind, model.get("ID") or "")]
        assert model.findtext("description") == docs.get(model.get("ID") or "")


def test_xml_symbol_and_literal_args() -> None:
    doc = ET.fromstring(render_btcpp_xml(mission_tree()))
    inspect = next(doc.iter("inspect"))
    assert inspect.get("target") == "{location}"
    assert inspect.get("mode") == "thermal"
    assigned = next(doc.iter("task_assigned"))
    assert assigned.get("type") == "inspect"
    assert assigned.get("name") == 'task_assigned("inspect")'


@pytest.mark.parametrize("name", sorted(ALL_TREES))
def test_xml_round_trip(name: str) -> None:
    tree = ALL_TREES[name]()
    back = parse_btcpp_xml(render_btcpp_xml(tree))
    assert_same_tree(back, tree, roles=False, meta=False)
    assert all(node.role is Role.PLAIN and not node.meta for _, node in walk(back))


def test_xml_round_trip_awkward_values() -> None:
    tree = sequence(
        'odd <name> & "quotes"',
        action("say", Arg("text", 'a "b" <c> & d\n\te', literal=True), doc="Say <it> & more"),
        action("say", Arg("text", "", literal=True), doc="Say <it> & more"),
    )
    assert_same_tree(parse_btcpp_xml(render_btcpp_xml(tree)), tree, roles=False)


def element_depths(tree: ET.Element) -> Iterator[tuple[int, ET.Element]]:
    """``(level, element)`` below a <BehaviorTree> (its child is level 1); iterative."""
    stack = [(1, child) for child in tree]
    while stack:
        level, element = stack.pop()
        yield level, element
        stack.extend((level + 1, child) for child in element)


def test_xml_deep_chain_is_split_into_subtrees_and_round_trips() -> None:
    tree = deep_chain()
    text = render_btcpp_xml(tree)
    assert max(map(len, text.splitlines())) < 300  # indentation capped: linear, not quadratic
    doc = ET.fromstring(text)
    trees = doc.findall("BehaviorTree")
    ids = [t.get("ID") for t in trees]
    assert ids[0] == "MainTree"
    assert ids[1:] == [f"MainTree_sub{i}" for i in range(1, len(trees))]
    assert len(trees) >= DEEP // SUBTREE_DEPTH
    for bt in trees:  # BehaviorTree.CPP refuses anything nested deeper than 256 per tree
        levels = [(level, e) for level, e in element_depths(bt)]
        assert max(level for level, _ in levels) <= SUBTREE_DEPTH + 1
        refs = [e for _, e in levels if e.tag == "SubTree"]
        assert [r.attrib for r in refs] == (
            []
            if bt is trees[-1]
            else [{"ID": ids[ids.index(bt.get("ID")) + 1], "_autoremap": "true"}]
        )
        composite_levels = [lv for lv, e in levels if e.tag in COMPOSITE_TAGS.values()]
        assert max(composite_levels) <= SUBTREE_DEPTH
    assert_same_tree(parse_btcpp_xml(text), tree, roles=False)


@contextmanager
def shallow_stack(frames: int = 80) -> Iterator[None]:
    """Only ``frames`` more Python frames than now: anything recursive per level fails."""
    before = sys.getrecursionlimit()
    sys.setrecursionlimit(len(inspect.stack(0)) + frames)
    try:
        yield
    finally:
        sys.setrecursionlimit(before)


def test_xml_writer_and_reader_are_iterative() -> None:
    tree = deep_chain()
    with shallow_stack():
        text = render_btcpp_xml(tree)
        back = parse_btcpp_xml(text)
    assert_same_tree(back, tree, roles=False)


def test_xml_thousand_action_chain_library(tmp_path: Path) -> None:
    """A library a1 (pre c0, post c1), a2 (pre c1, post c2), ...: synth -f xml, then read back."""
    n = 1000
    body = "\n".join(
        ["library: chain", "version: 1", "conditions:"]
        + [f"  c{i}: step {i}" for i in range(n + 1)]
        + ["actions:"]
        + [f"  a{i}: {{pre: [c{i - 1}], post: [c{i}]}}" for i in range(1, n + 1)]
    )
    lib = tmp_path / "chain.yaml"
    lib.write_text(body + "\n", encoding="utf-8")
    result = CliRunner().invoke(cli, ["synth", str(lib), "--goal", f"c{n}", "-f", "xml"])
    assert result.exit_code == 0, result.output
    text = result.stdout
    doc = ET.fromstring(text)
    assert len(doc.findall("BehaviorTree")) == 16  # 2,001 levels, at most 128 per tree
    back = parse_btcpp_xml(text)
    assert count_nodes(back) == 4 * n + 1 and depth(back) == 2 * n + 1
    leaves = [node.name for _, node in walk(back) if node.is_leaf]
    assert leaves[:3] == [f"c{n}", f"c{n - 1}", f"c{n - 2}"] and leaves[-1] == f"a{n}"


def test_xml_cli_refuses_a_leaf_named_like_a_btcpp_node(tmp_path: Path) -> None:
    lib = tmp_path / "sleepy.yaml"
    lib.write_text(
        "library: sleepy\nversion: 1\nconditions: {rested: Rested}\n"
        "actions:\n  Sleep: {post: [rested]}\n",
        encoding="utf-8",
    )
    out = tmp_path / "t.xml"
    result = CliRunner().invoke(cli, ["synth", str(lib), "--goal", "rested", "-o", str(out)])
    assert result.exit_code == 2
    assert (
        "Error: cannot export as xml: BehaviorTree.CPP action ID 'Sleep' is the name of one of "
        "BehaviorTree.CPP's own node types or XML elements" in result.stderr
    )
    assert not out.exists()


def test_xml_shallow_tree_has_no_subtrees() -> None:
    chain = deep_chain(SUBTREE_DEPTH // 2 - 1)  # depth SUBTREE_DEPTH - 1: fits
    assert "<SubTree" not in render_btcpp_xml(chain)
    assert "<SubTree" in render_btcpp_xml(deep_chain(SUBTREE_DEPTH // 2 + 1))


def test_xml_shared_deep_subtree_written_once_and_read_back_shared() -> None:
    shared = deep_chain(SUBTREE_DEPTH)  # deeper than one <BehaviorTree> may be
    root = sequence("both", fallback("f", condition("c"), shared), fallback("g", shared))
    doc = ET.fromstring(render_btcpp_xml(root))
    refs = [e.get("ID", "") for e in doc.iter("SubTree")]
    # both occurrences are cut at the same node: one <BehaviorTree>, referenced twice
    assert refs[:2] == ["MainTree_sub1", "MainTree_sub1"] and refs.count("MainTree_sub1") == 2
    ids = [t.get("ID") for t in doc.findall("BehaviorTree")]
    assert ids == ["MainTree", *sorted(set(refs), key=lambda r: int(r.rsplit("sub", 1)[1]))]
    back = parse_btcpp_xml(render_btcpp_xml(root))
    assert_same_tree(back, root, roles=False)
    # the subtree below the cut is read back once and shared by both occurrences
    assert len(distinct_postorder(back)) < count_nodes(back) < 2 * len(distinct_postorder(back))


def test_xml_subtree_ids_avoid_leaf_ids() -> None:
    text = render_btcpp_xml(
        sequence("s", deep_chain(SUBTREE_DEPTH), action("MainTree_sub1")), tree_id="MainTree"
    )
    ids = [t.get("ID") for t in ET.fromstring(text).findall("BehaviorTree")]
    assert ids[1] == "MainTree_sub_1" and "MainTree_sub1" not in ids


def test_xml_rejects_what_btcpp_rejects() -> None:
    with pytest.raises(ValueError, match="reserved"):
        render_btcpp_xml(action("greet", Arg("name", "who")))
    with pytest.raises(ValueError, match="both as a condition and as a action"):
        render_btcpp_xml(sequence("s", condition("x"), action("x")))
    with pytest.raises(ValueError, match="blackboard reference"):
        render_btcpp_xml(action("say", Arg("text", "{x}", literal=True)))
    with pytest.raises(ValueError, match="forbidden character"):
        render_btcpp_xml(action("go.now"))
    with pytest.raises(ValueError, match="clashes"):
        render_btcpp_xml(action("MainTree"))
    # the compact form makes the ID an element name, so BT.CPP's own types and XML tags are out
    for taken in ("Sleep", "Action", "Condition", "SubTree", "TreeNodesModel", "Sequence"):
        with pytest.raises(ValueError, match=f"'{taken}' is the name of one of BehaviorTree"):
            render_btcpp_xml(sequence("s", condition(taken)))
    with pytest.raises(ValueError, match="'Sequence' is the name of one of BehaviorTree"):
        render_btcpp_xml(action("go"), tree_id="Sequence")
    with pytest.raises(ValueError, match="'2go' is not a valid XML element name"):
        render_btcpp_xml(action("2go"))
    with pytest.raises(ValueError, match="not a valid XML attribute name"):
        render_btcpp_xml(action("go", Arg("a(b", "x")))
    assert "<étape " in render_btcpp_xml(action("étape"))  # non-ASCII letters are fine
    # a tree ID is only an attribute value: <mission>_<agent> may start with a digit
    assert 'main_tree_to_execute="2024_demo_G1"' in render_btcpp_xml(action("go"), "2024_demo_G1")


def test_xml_reads_the_explicit_form() -> None:
    """Files written before the compact form (and by other tools) still load."""
    explicit = SMALL_XML.replace(
        '<at_goal name="at_goal(goal)"', '<Condition ID="at_goal" name="at_goal(goal)"'
    ).replace("<follow_path name=", '<Action ID="follow_path" name=')
    assert explicit.count(' ID="') == SMALL_XML.count(' ID="') + 2
    assert_same_tree(parse_btcpp_xml(explicit), small_tree(), roles=False, meta=False)


def test_xml_parse_errors_and_compact_form() -> None:
    with pytest.raises(ValueError, match="BTCPP_format"):
        parse_btcpp_xml('<root BTCPP_format="3"><BehaviorTree ID="T"><A/></BehaviorTree></root>')
    with pytest.raises(ValueError, match="unsupported node"):
        parse_btcpp_xml(
            '<root BTCPP_format="4"><BehaviorTree ID="T"><Inverter/></BehaviorTree></root>'
        )
    compact = """
    <root BTCPP_format="4">
      <BehaviorTree ID="T">
        <Fallback>
          <IsWarm/>
          <WearJacket size="{s}" colour="red"/>
        </Fallback>
      </BehaviorTree>
      <TreeNodesModel>
        <Condition ID="IsWarm"/>
        <Action ID="WearJacket" description="Put it on."/>
      </TreeNodesModel>
    </root>"""
    expected = Node(
        Kind.FALLBACK,
        "Fallback",
        children=(
            Node(Kind.CONDITION, "IsWarm"),
            Node(
                Kind.ACTION,
                "WearJacket",
                (Arg("size", "s"), Arg("colour", "red", literal=True)),
                doc="Put it on.",
            ),
        ),
    )
    assert parse_btcpp_xml(compact) == expected


SUBTREES_XML = """
<root BTCPP_format="4" main_tree_to_execute="Main">
  <BehaviorTree ID="Main">
    <Sequence>
      <SubTree ID="Go" _autoremap="true"/>
      <SubTree ID="Go" target="{home}" speed="slow"/>
      <SubTree ID="Go" target="{=}"/>
      <SubTree ID="Go" _autoremap="true"/>
    </Sequence>
  </BehaviorTree>
  <BehaviorTree ID="Go">
    <move goal="{target}" speed="{speed}" mode="fly"/>
  </BehaviorTree>
  <TreeNodesModel><Action ID="move"/></TreeNodesModel>
</root>"""


def test_xml_reads_subtrees_with_remapping() -> None:
    root = parse_btcpp_xml(SUBTREES_XML)
    assert root.kind is Kind.SEQUENCE
    got = [tuple((a.param, a.value, a.literal) for a in c.args) for c in root.children]
    fly = ("mode", "fly", True)
    assert got == [
        (("goal", "target", False), ("speed", "speed", False), fly),  # autoremap: same keys
        (("goal", "home", False), ("speed", "slow", True), fly),  # remapped key and literal
        (("goal", "target", False), ("speed", "speed", False), fly),  # {=}; speed stays private
        (("goal", "target", False), ("speed", "speed", False), fly),
    ]
    assert root.children[0] is root.children[3]  # same subtree, same mapping: shared


@pytest.mark.parametrize(
    ("xml", "message"),
    [
        (SUBTREES_XML.replace('ID="Go" target="{=}"', 'ID="Gone"'), "<SubTree ID='Gone'> names no"),
        (
            SUBTREES_XML.replace("<move goal", '<SubTree ID="Main"/><move goal'),
            "exactly one child",
        ),
        (
            SUBTREES_XML.replace(
                '<move goal="{target}" speed="{speed}" mode="fly"/>',
                '<Sequence><SubTree ID="Main"/></Sequence>',
            ),
            "<SubTree ID='Main'> contains itself",
        ),
        (
            SUBTREES_XML.replace('main_tree_to_execute="Main"', ""),
            "several <BehaviorTree> elements and no main_tree_to_execute",
        ),
        (
            SUBTREES_XML.replace('<BehaviorTree ID="Go">', '<BehaviorTree ID="Main">'),
            "two <BehaviorTree> elements with ID='Main'",
        ),
    ],
)
def test_xml_subtree_errors(xml: str, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        parse_btcpp_xml(xml)


def test_xml_subtree_bomb_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """40 levels of two differently remapped references: 2**40 leaves if expanded."""
    trees = [
        f'<BehaviorTree ID="T{i}"><Sequence><SubTree ID="T{i + 1}" k="{{a}}"/>'
        f'<SubTree ID="T{i + 1}" k="{{b}}"/></Sequence></BehaviorTree>'
        for i in range(40)
    ]
    text = (
        '<root BTCPP_format="4" main_tree_to_execute="T0">'
        + "".join(trees)
        + '<BehaviorTree ID="T40"><leaf x="{k}"/></BehaviorTree>'
        + '<TreeNodesModel><Action ID="leaf"/></TreeNodesModel></root>'
    )
    monkeypatch.setattr(btcpp_module, "MAX_PARSED_NODES", 10_000)
    with pytest.raises(ValueError, match="more than 10,000 nodes once its <SubTree>s are expanded"):
        parse_btcpp_xml(text)
    # the same shape with autoremapping only is shared, not expanded: 40 + 1 distinct nodes
    shared = re.sub(r' k="\{[ab]\}"', ' _autoremap="true"', text)
    back = parse_btcpp_xml(shared)
    assert count_nodes(back) == 2**41 - 1  # 2**40 - 1 sequences and 2**40 leaves, built shared


# -------------------------------------------------------------------------------------- JSON
@pytest.mark.parametrize("name", sorted(ALL_TREES))
def test_json_round_trip_exact(name: str) -> None:
    tree = ALL_TREES[name]()
    assert tree_from_dict(tree_to_dict(tree)) == tree
    assert tree_from_dict(json.loads(json.dumps(tree_to_dict(tree)))) == tree
    assert parse_json(render_json(tree)) == tree


def test_json_layout() -> None:
    tree = small_tree()
    text = render_json(tree, name="MainTree", library="aerial")
    doc = json.loads(text)
    assert list(doc) == ["format", "version", "name", "library", "tree"]
    assert doc["format"] == "btmission-tree" and doc["version"] == 1
    assert text == json.dumps(doc, indent=2, ensure_ascii=False) + "\n"
    assert doc["tree"] == {
        "type": "fallback",
        "name": "ensure at_goal(goal)",
        "role": "goal",
        "meta": {"commit_after": "holding(pickup)"},
        "children": [
            {
                "type": "condition",
                "name": "at_goal",
                "args": [{"param": "goal", "value": "goal", "literal": False}],
                "role": "plain",
                "doc": "At the goal.",
            },
            {
                "type": "sequence",
                "name": "achieve at_goal(goal)",
                "role": "achieve",
                "children": [
                    {
                        "type": "condition",
                        "name": "has_path",
                        "args": [{"param": "goal", "value": "goal", "literal": False}],
                        "role": "assumed",
                    },
                    {
                        "type": "action",
                        "name": "follow_path",
                        "args": [
                            {"param": "goal", "value": "goal", "literal": False},
                            {"param": "speed", "value": "fast", "literal": True},
                        ],
                        "role": "plain",
                    },
                ],
            },
        ],
    }


def test_json_minimal_node_and_shared_subtrees() -> None:
    assert tree_from_dict({"type": "action", "name": "wait"}) == action("wait")
    tree = shared_tree()
    back = tree_from_dict(tree_to_dict(tree))
    assert back == tree
    assert back.children[0] is back.children[1].children[1]  # sharing preserved


def test_json_deep_chain_round_trip() -> None:
    tree = deep_chain()
    assert_same_tree(tree_from_dict(tree_to_dict(tree)), tree)
    text = render_json(tree)
    assert max(map(len, text.splitlines())) < 300  # indentation capped: linear, not quadratic
    assert_same_tree(parse_json(text), tree)


def test_json_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match=r"tree\.children\[0\]"):
        tree_from_dict({"type": "sequence", "name": "s", "children": [{"type": "x", "name": "y"}]})
    with pytest.raises(ValueError, match="cannot have children"):
        tree_from_dict(
            {"type": "action", "name": "a", "children": [{"type": "action", "name": "b"}]}
        )
    with pytest.raises(ValueError, match="reserved"):
        render_json(small_tree(), tree="nope")
    with pytest.raises(ValueError, match="version"):
        parse_json('{"format": "btmission-tree", "version": 2, "tree": {}}')
    with pytest.raises(ValueError, match="not a 'btmission-tree' document"):
        parse_json("[]")


def test_json_parse_leaves_recursion_limit_alone() -> None:
    before = sys.getrecursionlimit()
    parse_json(render_json(deep_chain(200)))
    assert sys.getrecursionlimit() == before


# ------------------------------------------------------------------------------- export_tree
def test_formats() -> None:
    assert FORMATS == ("ascii", "dot", "svg", "png", "xml", "json")


@pytest.mark.parametrize("fmt", [f for f in FORMATS if f not in ("svg", "png")])
def test_export_tree_text_formats(fmt: str) -> None:
    tree = mission_tree()
    out = export_tree(tree, fmt, name="Mission", unicode=False)
    assert isinstance(out, str)
    expected = {
        "ascii": render_ascii(tree, unicode=False),
        "dot": render_dot(tree, name="Mission"),
        "xml": render_btcpp_xml(tree, tree_id="Mission"),
        "json": render_json(tree, name="Mission"),
    }[fmt]
    assert out == expected


@needs_dot
def test_export_tree_image_formats() -> None:
    svg = export_tree(ppa_tree(), "svg")
    png = export_tree(ppa_tree(), "png")
    assert isinstance(svg, bytes) and ET.fromstring(svg).tag.endswith("svg")
    assert isinstance(png, bytes) and png.startswith(b"\x89PNG\r\n\x1a\n")


def test_export_tree_unknown_format() -> None:
    with pytest.raises(ValueError, match="unknown export format 'pdf'"):
        export_tree(ppa_tree(), "pdf")


def test_shared_subtree_reached_first_through_a_later_parent() -> None:
    """A subtree shared by an earlier and a later sibling: bottom-up folds must still see every
    child before its parents (regression: a pop-order walk got this wrong)."""
    shared = sequence("b", condition("x"))
    root = sequence("root", sequence("a", shared), shared)
    assert tree_from_dict(tree_to_dict(root)) == root
    assert count_nodes(root) == 6
