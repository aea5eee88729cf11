"""Back-chaining synthesis (seed 000 Alg. 1, 2): exact trees for Table I, and every check."""

from __future__ import annotations

import pytest

from btmission.diagnostics import Severity
from btmission.spec.library import Library
from btmission.synthesis.backchain import Synthesizer, synthesize
from btmission.synthesis.checks import check_library
from btmission.synthesis.tree import (
    Arg,
    Kind,
    Node,
    Role,
    action,
    condition,
    count_nodes,
    depth,
    fallback,
    sequence,
    walk,
)
from tests.conftest import lib_from


def g(sym: str) -> Arg:
    return Arg("goal", sym)


def takeoff_subtree() -> Node:
    """Fallback(is_flying, Sequence(ensure has_home, ensure is_armed, ensure in_offboard, takeoff))."""
    return fallback(
        "is_flying",
        condition("is_flying"),
        sequence(
            "takeoff",
            fallback("has_home", condition("has_home"), action("set_home")),
            fallback("is_armed", condition("is_armed"), action("arm")),
            fallback("in_offboard", condition("in_offboard"), action("set_offboard")),
            action("takeoff"),
        ),
    )


def fig8(sym: str = "goal") -> Node:
    """Seed 000 Fig. 8: the inspection tree back-chained from 'At goal point' over Table I."""
    return fallback(
        f"at_goal({sym})",
        condition("at_goal", g(sym)),
        sequence(
            f"follow_path({sym})",
            takeoff_subtree(),
            fallback(
                f"has_path({sym})", condition("has_path", g(sym)), action("update_path", g(sym))
            ),
            action("follow_path", g(sym)),
        ),
    )


def shape(n: Node) -> tuple[object, ...]:
    """Kinds, names, args and order of the whole tree (docs and roles ignored)."""
    return (
        n.kind,
        n.name,
        tuple((a.param, a.value, a.literal) for a in n.args),
        tuple(shape(c) for c in n.children),
    )


def test_table1_gives_fig8_exactly(aerial: Library) -> None:
    s = synthesize(aerial, ["at_goal(goal)"])
    assert s.ok and not s.diagnostics
    assert shape(s.tree) == shape(fig8())
    assert s.size == 20 and depth(s.tree) == 6
    assert s.inputs == ("goal",)
    assert s.used_actions == {
        "set_home",
        "arm",
        "set_offboard",
        "takeoff",
        "update_path",
        "follow_path",
    }


def test_parameters_bind_through_the_chain(aerial: Library) -> None:
    s = synthesize(aerial, ["at_goal(location)"])
    assert shape(s.tree) == shape(fig8("location"))
    assert s.inputs == ("location",)


def test_default_behaviour_fig9(aerial: Library) -> None:
    """Fig. 9: return home (follow_path bound to the library variable home) and land."""
    s = synthesize(aerial, ["landed_at_home"])
    expected = fallback(
        "landed_at_home",
        condition("landed_at_home"),
        sequence("land", fig8("home"), action("land")),
    )
    assert shape(s.tree) == shape(expected)
    assert s.inputs == ()  # home is a library variable, not a task input


def test_leaf_docs_and_roles(aerial: Library) -> None:
    s = synthesize(aerial, ["at_goal(goal)"])
    leaves = [n for _, n in walk(s.tree) if n.is_leaf]
    assert all(n.role is Role.PLAIN for n in leaves)
    assert next(n for n in leaves if n.name == "arm").doc == "Arm the motors"


def test_multi_goal_is_a_sequence_in_order(aerial: Library) -> None:
    s = synthesize(aerial, ["is_armed", "has_home"])
    assert s.tree.kind is Kind.SEQUENCE
    assert [c.name for c in s.tree.children] == ["is_armed", "has_home"]


def test_output_is_deterministic(aerial: Library) -> None:
    a = synthesize(aerial, ["landed_at_home"]).tree
    b = synthesize(aerial, ["landed_at_home"]).tree
    assert a == b


def test_lowest_cost_achiever_wins_and_choice_is_reported() -> None:
    lib, diags = lib_from("""
        library: t
        version: 1
        conditions: {there: "", walking: ""}
        actions:
          walk: {post: [there], cost: 5}
          fly:  {post: [there], cost: 2}
    """)
    assert not diags
    s = synthesize(lib, ["there"])
    assert s.tree.children[1].name == "fly"
    info = [d for d in s.diagnostics if d.code == "choice"]
    assert len(info) == 1 and info[0].severity is Severity.INFO and "chose fly" in info[0].message


def test_ambiguous_achievers_warn_and_declaration_order_decides() -> None:
    lib, _ = lib_from("""
        library: t
        version: 1
        conditions: {there: ""}
        actions:
          walk: {post: [there]}
          fly:  {post: [there]}
    """)
    s = synthesize(lib, ["there"])
    assert s.tree.children[1].name == "walk"
    amb = [d for d in s.diagnostics if d.code == "ambiguous-achiever"]
    assert len(amb) == 1 and amb[0].severity is Severity.WARNING
    assert "walk" in amb[0].message and "fly" in amb[0].message
    strict = Synthesizer(lib).synthesize(s.goals, strict=True)
    assert not strict.ok


def test_specific_postcondition_only_matches_its_variable() -> None:
    lib, diags = lib_from("""
        library: t
        version: 1
        variables: {home: ""}
        conditions: {at: {params: [p]}}
        actions:
          go_home: {post: [at(home)], cost: 0.5}
          go:      {params: [p], post: [at(p)]}
    """)
    assert not diags
    assert synthesize(lib, ["at(home)"]).tree.children[1].name == "go_home"
    assert synthesize(lib, ["at(dock)"]).tree.children[1].name == "go"


def test_assumed_condition_stays_a_leaf_and_strict_rejects_it() -> None:
    lib, _ = lib_from("""
        library: t
        version: 1
        conditions: {done: "", battery_ok: ""}
        actions:
          work: {pre: [battery_ok], post: [done]}
    """)
    s = synthesize(lib, ["done"])
    leaf = s.tree.children[1].children[0]
    assert (leaf.kind, leaf.name, leaf.role) == (Kind.CONDITION, "battery_ok", Role.ASSUMED)
    assert s.ok and [d.code for d in s.diagnostics] == ["assumed-condition"]
    assert s.diagnostics[0].where.line == 5  # the reference in work.pre
    assert not Synthesizer(lib).synthesize(s.goals, strict=True).ok


def test_cycle_reported_with_chain() -> None:
    lib, _ = lib_from(
        """
        library: t
        version: 1
        conditions: {a: "", b: "", c: ""}
        actions:
          make_a: {pre: [b], post: [a]}
          make_b: {pre: [c], post: [b]}
          make_c: {pre: [a], post: [c]}
    """,
        "cyc.yaml",
    )
    s = synthesize(lib, ["a"])
    assert not s.ok
    (d,) = [d for d in s.diagnostics if d.code == "cycle"]
    assert "a (by make_a) needs b (by make_b) needs c (by make_c) needs a" in d.message
    assert (d.where.file, d.where.line) == ("cyc.yaml", 7)  # make_c's pre, which closes the loop
    roles = [n.role for _, n in walk(s.tree) if n.name == "a" and n.kind is Kind.CONDITION]
    assert Role.CYCLE in roles


def test_self_cycle() -> None:
    lib, _ = lib_from("""
        library: t
        version: 1
        conditions: {a: ""}
        actions:
          make_a: {pre: [a], post: [a]}
    """)
    s = synthesize(lib, ["a"])
    assert [d.code for d in s.diagnostics] == ["cycle"]


def test_shared_preconditions_expand_once_but_count_every_occurrence() -> None:
    lib, _ = lib_from("""
        library: t
        version: 1
        conditions: {top: "", l: "", r: "", base: ""}
        actions:
          make_base: {post: [base]}
          make_l: {pre: [base], post: [l]}
          make_r: {pre: [base], post: [r]}
          make_top: {pre: [l, r], post: [top]}
    """)
    s = synthesize(lib, ["top"])
    left_base = s.tree.children[1].children[0].children[1].children[0]
    right_base = s.tree.children[1].children[1].children[1].children[0]
    assert left_base is right_base  # memoised
    assert s.size == count_nodes(s.tree) == sum(1 for _ in walk(s.tree)) == 18


def test_deep_chain_needs_no_recursion() -> None:
    n = 3000
    conds = "\n".join(f"  c{i}: ''" for i in range(n + 1))
    acts = "\n".join(
        f"  a{i}: {{pre: [c{i}], post: [c{i + 1}]}}" if i else f"  a{i}: {{post: [c{i + 1}]}}"
        for i in range(n)
    )
    lib, diags = lib_from(f"library: t\nversion: 1\nconditions:\n{conds}\nactions:\n{acts}\n")
    assert not diags
    s = synthesize(lib, [f"c{n}"])
    assert s.ok and depth(s.tree) == 2 * n and s.size == 4 * n - 1


# ---- library checks on minimal bad libraries ----------------------------------------------------
@pytest.mark.parametrize(
    ("body", "code", "line", "needle"),
    [
        (
            "conditions: {a: ''}\nactions:\n  x: {post: [b]}\n",
            "undefined-condition",
            5,
            "undefined condition 'b'",
        ),
        (
            "conditions: {a: {params: [p]}}\nactions:\n  x: {params: [p], post: [a(q)]}\n",
            "undefined-parameter",
            5,
            "undefined parameter 'q'",
        ),
        (
            "conditions: {a: {params: [p]}}\nactions:\n  x: {params: [p], post: ['a(p, p)']}\n",
            "bad-arguments",
            5,
            "takes 1",
        ),
        (
            "conditions: {a: {params: [p]}}\nactions:\n  x: {post: [a]}\n",
            "bad-arguments",
            5,
            "unbound",
        ),
        (
            "conditions: {a: {params: [p]}}\nactions:\n  x: {params: [p], post: ['a(z=p)']}\n",
            "bad-arguments",
            5,
            "no parameter 'z'",
        ),
        (
            "conditions: {a: '', b: {params: [p]}}\nactions:\n  x: {params: [p], post: [a]}\n",
            "unbound-parameter",
            5,
            "does not bind parameter(s) p",
        ),
        (
            "conditions: {a: ''}\nactions:\n  x: {post: ['a(']}\n",
            "ref-syntax",
            5,
            "unbalanced parentheses",
        ),
        (
            "conditions: {a: ''}\nactions:\n  a: {post: [a]}\n",
            "name-clash",
            5,
            "same name as a condition",
        ),
        ("conditions: {wait: ''}\nactions:\n  x: {post: [wait]}\n", "reserved-name", 3, "reserved"),
        (
            "conditions: {a: {params: [p, p]}}\nactions:\n  x: {post: [a]}\n",
            "duplicate-param",
            3,
            "unique",
        ),
    ],
)
def test_reference_checks_name_the_item_and_line(
    body: str, code: str, line: int, needle: str
) -> None:
    _lib, diags = lib_from("library: t\nversion: 1\n" + body, "bad.yaml")
    hits = [d for d in diags if d.code == code]
    assert hits, [d.format() for d in diags]
    assert hits[0].severity is Severity.ERROR
    assert hits[0].where.file == "bad.yaml" and hits[0].where.line == line
    assert needle in hits[0].message


def test_check_reports_unreachable_and_unused() -> None:
    lib, diags = lib_from("""
        library: t
        version: 1
        goals: [a]
        conditions: {a: "", e: "", u: ""}
        actions:
          A: {post: [a]}
          A2: {post: [a], cost: 5}
          E: {post: [e]}
          N: {}
    """)
    report = check_library(lib, diags)
    by_item = {(d.code, d.item) for d in report.diagnostics}
    assert ("unreachable-action", "actions.A2") in by_item  # always beaten by A
    assert ("unreachable-action", "actions.E") in by_item  # not used by the declared goal
    assert ("unreachable-action", "actions.N") in by_item  # no postconditions
    assert ("unused-condition", "conditions.u") in by_item
    assert report.ok
    assert not check_library(lib, diags, strict=True).ok


def test_check_finds_cycles_not_reachable_from_goals() -> None:
    lib, diags = lib_from("""
        library: t
        version: 1
        conditions: {a: "", b: "", c: ""}
        actions:
          A: {post: [a]}
          B: {pre: [c], post: [b]}
          C: {pre: [b], post: [c]}
    """)
    report = check_library(lib, diags)
    assert not report.ok
    assert [d.code for d in report.diagnostics if d.severity is Severity.ERROR] == ["cycle"]


@pytest.mark.parametrize("name", ["aerial", "ground", "compra"])
def test_builtin_libraries_check_clean_in_strict_mode(name: str) -> None:
    from btmission.plugins import load_library

    loaded = load_library(name)
    report = check_library(loaded.library, loaded.diagnostics, strict=True)
    assert report.ok and not [d for d in report.diagnostics if d.severity is not Severity.INFO]


def test_check_does_not_call_variable_specific_conditions_assumed() -> None:
    """An achiever whose postcondition names a library variable (at_goal(home)) must not make the
    checker report the generic at_goal(goal) as assumed."""
    lib, diags = lib_from("""
        library: t
        version: 1
        variables: {home: ""}
        conditions: {at_goal: {params: [goal]}, landed: ""}
        actions:
          go_home: {post: [at_goal(home)]}
          land: {pre: [at_goal(home)], post: [landed]}
    """)
    report = check_library(lib, diags, strict=True)
    assert report.ok, [d.format() for d in report.diagnostics]


def test_check_skips_reachability_noise_when_loading_failed() -> None:
    lib, diags = lib_from("""
        library: t
        version: 1
        conditions: {a: "", b: ""}
        actions:
          A: {pre: [nope], post: [a]}
          B: {post: [b]}
    """)
    report = check_library(lib, diags)
    codes = {d.code for d in report.diagnostics}
    assert "undefined-condition" in codes and not codes & {"unused-condition", "unreachable-action"}


# ---- the quiet composites' lean tick is py_trees' own, step for step (issue 19)
_STATUSES = ("SUCCESS", "FAILURE", "RUNNING")


def _scripted_leaf(
    guarded: bool, name: str, script: list[str], log: list[tuple[str, ...]]
) -> object:
    """A leaf whose update returns ``script[tick]`` (cycling) and that logs every initialise,
    update and terminate: a py_trees ``Behaviour`` or the runtime's ``GuardedLeaf``."""
    import py_trees

    from btmission.runtime.leaves import GuardedLeaf

    base = GuardedLeaf if guarded else py_trees.behaviour.Behaviour

    class Leaf(base):  # type: ignore[misc, valid-type]
        def initialise(self) -> None:
            log.append(("initialise", name))

        def update(self) -> py_trees.common.Status:
            status = py_trees.common.Status[script[self.calls % len(script)]]
            self.calls += 1
            log.append(("update", name, status.value))
            return status

        def terminate(self, new_status: py_trees.common.Status) -> None:
            log.append(("terminate", name, new_status.value))

    leaf = Leaf(name=name)
    leaf.calls = 0
    return leaf


def _tree_pair(data: object) -> tuple[object, object, list[tuple[str, ...]], list[tuple[str, ...]]]:
    """The same random tree twice: py_trees' composites with py_trees leaves, and the quiet
    composites with (mostly) guarded leaves; each with its own call log."""
    import py_trees
    from hypothesis import strategies as st

    from btmission.synthesis.pytrees import QuietSelector, QuietSequence

    ref_log: list[tuple[str, ...]] = []
    new_log: list[tuple[str, ...]] = []
    counter = [0]

    def build(depth: int) -> tuple[object, object]:
        if depth == 0 or data.draw(st.booleans()):  # type: ignore[attr-defined]
            counter[0] += 1
            name = f"L{counter[0]}"
            script = data.draw(st.lists(st.sampled_from(_STATUSES), min_size=1, max_size=4))  # type: ignore[attr-defined]
            guarded = data.draw(st.integers(0, 4)) > 0  # type: ignore[attr-defined]
            return (
                _scripted_leaf(False, name, script, ref_log),
                _scripted_leaf(guarded, name, script, new_log),
            )
        n = data.draw(st.integers(0, 3))  # type: ignore[attr-defined]
        kids = [build(depth - 1) for _ in range(n)]
        counter[0] += 1
        name = f"C{counter[0]}"
        if data.draw(st.booleans()):  # type: ignore[attr-defined]
            ref = py_trees.composites.Selector(name, memory=False, children=[k[0] for k in kids])
            new = QuietSelector(name, memory=False, children=[k[1] for k in kids])
        else:
            ref = py_trees.composites.Sequence(name, memory=False, children=[k[0] for k in kids])
            new = QuietSequence(name, memory=False, children=[k[1] for k in kids])
        return ref, new

    ref, new = build(4)
    return ref, new, ref_log, new_log


def _state(root: object) -> list[tuple[str, str, str | None]]:
    return [
        (b.name, b.status.value, getattr(getattr(b, "current_child", None), "name", None))
        for b in root.iterate()  # type: ignore[attr-defined]
    ]


@pytest.mark.filterwarnings("ignore")
def test_the_quiet_composites_tick_as_py_trees_does() -> None:
    """Random trees of selectors, sequences and scripted leaves ticked many times (with a stop
    between some ticks): every call to a leaf, every status and every current child is the
    same under py_trees' composites and under the quiet ones' lean tick."""
    import py_trees
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=300, deadline=None)
    @given(st.data())
    def check(data: st.DataObject) -> None:
        ref, new, ref_log, new_log = _tree_pair(data)
        for _ in range(data.draw(st.integers(1, 8))):
            ref.tick_once()  # type: ignore[attr-defined]
            for _node in new.tick():  # type: ignore[attr-defined]
                pass
            assert new_log == ref_log
            assert _state(new) == _state(ref)
            if data.draw(st.integers(0, 5)) == 0:
                ref.stop(py_trees.common.Status.INVALID)  # type: ignore[attr-defined]
                new.stop(py_trees.common.Status.INVALID)  # type: ignore[attr-defined]
                assert new_log == ref_log and _state(new) == _state(ref)

    check()


def test_a_leaf_with_its_own_tick_keeps_it() -> None:
    """A ``GuardedLeaf`` subclass that defines ``tick`` has no lean ``tick_now``: the quiet
    composites run its generator, so its own tick is what happens."""
    import py_trees

    from btmission.runtime.leaves import GuardedLeaf
    from btmission.synthesis.pytrees import QuietSequence, tick_behaviour

    calls: list[str] = []

    class Own(GuardedLeaf):
        def tick(self):  # type: ignore[no-untyped-def]
            calls.append("own tick")
            self.status = py_trees.common.Status.SUCCESS
            yield self

        def update(self) -> py_trees.common.Status:
            raise AssertionError("not called: its own tick does not update")

    leaf = Own(name="own")
    assert leaf.tick_now is None  # type: ignore[comparison-overlap]
    root = QuietSequence("root", memory=False, children=[leaf])
    tick_behaviour(root)
    assert calls == ["own tick"] and root.status is py_trees.common.Status.SUCCESS


def test_a_stopped_behaviour_still_hands_out_a_fresh_tick_generator() -> None:
    """py_trees keeps a fresh tick generator in ``iterator``; the quiet composites and the
    runtime's leaves make it when it is read (not at every stop): running it out ticks."""
    import py_trees

    from btmission.synthesis.pytrees import QuietSequence

    log: list[tuple[str, ...]] = []
    leaf = _scripted_leaf(True, "L", ["SUCCESS"], log)
    root = QuietSequence("root", memory=False, children=[leaf])  # type: ignore[list-item]
    root.stop(py_trees.common.Status.INVALID)
    assert [b.name for b in root.iterator] == ["root"]
    assert root.status is py_trees.common.Status.SUCCESS and log[-1] == (
        "terminate",
        "L",
        "SUCCESS",
    )
    assert [b.name for b in leaf.iterator] == ["L"]  # type: ignore[attr-defined]


def test_a_condition_ticks_as_a_guarded_leaf_without_its_no_op_hooks() -> None:
    """ConditionLeaf's own tick_now gives GuardedLeaf.tick_now's statuses (a failing condition
    included); a subclass that overrides a hook ticks through GuardedLeaf.tick_now, hooks run."""
    from typing import Any

    from btmission.runtime.leaves import AgentContext, Blackboard, ConditionLeaf, GuardedLeaf
    from btmission.synthesis.tree import Kind, Node

    none: Any = None
    ctx = AgentContext("A", Blackboard("/a"), none, none, none, none, lambda: 0.0, {},
                       (0.0, 0.0, 0.0), events=lambda ev: None)  # fmt: skip
    answers = [True, False, True, True]

    def fn(ctx: Any) -> bool:
        if not answers:
            raise RuntimeError("no more answers")
        return answers.pop(0)

    lean, full = ConditionLeaf(Node(Kind.CONDITION, "c"), fn, ctx), None
    assert type(lean).tick_now is ConditionLeaf.tick_now
    seen = []
    for _ in range(5):
        lean.tick_now()
        seen.append(lean.status.value)
    answers[:] = [True, False, True, True]
    full = ConditionLeaf(Node(Kind.CONDITION, "c"), fn, ctx)
    ref = []
    for _ in range(5):
        GuardedLeaf.tick_now(full)
        ref.append(full.status.value)
    assert seen == ref == ["SUCCESS", "FAILURE", "SUCCESS", "SUCCESS", "FAILURE"]

    calls: list[str] = []

    class Hooked(ConditionLeaf):
        def initialise(self) -> None:
            calls.append("initialise")

        def terminate(self, new_status: Any) -> None:
            calls.append(f"terminate {new_status.value}")

    assert Hooked.tick_now is GuardedLeaf.tick_now
    answers[:] = [False]
    hooked = Hooked(Node(Kind.CONDITION, "h"), fn, ctx)
    hooked.tick_now()
    assert calls == ["initialise", "terminate FAILURE"] and hooked.status.value == "FAILURE"


def test_a_conditions_arguments_and_errors_tick_as_through_its_guarded_update() -> None:
    """The inlined update of ConditionLeaf.tick_now: literal arguments, blackboard symbols (an
    unset one fails), an exception (FAILURE and one leaf_error, as the update guard) — the
    statuses and events of GuardedLeaf.tick_now; a subclass's own update is what ticks."""
    from typing import Any

    from btmission.runtime.leaves import AgentContext, Blackboard, ConditionLeaf, GuardedLeaf
    from btmission.synthesis.tree import Arg, Kind, Node

    none: Any = None

    def run(tick: Any) -> tuple[list[str], list[tuple[str, Any, Any]]]:
        events: list[tuple[str, Any, Any]] = []
        ctx = AgentContext("A", Blackboard("/a"), none, none, none, none, lambda: 0.0, {},
                           (0.0, 0.0, 0.0),
                           events=lambda ev: events.append((ev.kind, getattr(ev, "leaf", None),
                                                            getattr(ev, "phase", None))))  # fmt: skip

        def near(ctx: Any, kind: str, goal: Any) -> bool:
            if goal == "boom":
                raise ValueError("bad goal")
            return bool(kind == "inspect" and goal[0] > 1.0)

        node = Node(Kind.CONDITION, "near", (Arg("kind", "inspect", True), Arg("goal", "location")))
        leaf = ConditionLeaf(node, near, ctx)
        const = ConditionLeaf(Node(Kind.CONDITION, "k", (Arg("kind", "x", True),)),
                              lambda ctx, kind: kind == "x", ctx)  # fmt: skip
        statuses = []
        for value in (None, (2.0, 0.0), (0.5, 0.0), "boom", (3.0, 1.0)):
            if value is not None:
                ctx.blackboard.set("location", value)
            tick(leaf)
            tick(const)
            statuses += [leaf.status.value, const.status.value]
        return statuses, events

    lean, lean_events = run(lambda leaf: leaf.tick_now())
    full, full_events = run(lambda leaf: GuardedLeaf.tick_now(leaf))
    assert lean == full == ["FAILURE", "SUCCESS", "SUCCESS", "SUCCESS", "FAILURE", "SUCCESS",
                            "FAILURE", "SUCCESS", "SUCCESS", "SUCCESS"]  # fmt: skip
    assert lean_events == full_events == [("leaf_error", 'near("inspect", location)', "update")]

    class Own(ConditionLeaf):
        def update(self) -> Any:
            return "not a status"  # (the guard makes it FAILURE)

    assert Own.tick_now is not ConditionLeaf.tick_now
    own = Own(Node(Kind.CONDITION, "o"), lambda ctx: True, AgentContext(
        "A", Blackboard("/a"), none, none, none, none, lambda: 0.0, {}, (0.0, 0.0, 0.0),
        events=lambda ev: None))  # fmt: skip
    own.tick_now()
    assert own.status.value == "FAILURE"
