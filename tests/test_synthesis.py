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

from .conftest import lib_from


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
