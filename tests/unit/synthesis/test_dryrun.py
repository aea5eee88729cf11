"""Symbolic dry run: the back-chained tree reaches its goal from every initial state, and never
ticks an action whose preconditions are false (the point of seed 000's full expansion)."""

from __future__ import annotations

import itertools

import py_trees
from hypothesis import given, settings
from hypothesis import strategies as st

from btmission.spec.library import Library, LibrarySpec, compile_library
from btmission.synthesis.backchain import synthesize
from btmission.synthesis.dryrun import conditions_in, dry_run
from btmission.synthesis.pytrees import build_behaviour_tree


def test_table1_tree_reaches_goal_from_every_initial_state(aerial: Library) -> None:
    s = synthesize(aerial, ["at_goal(goal)"])
    conds = conditions_in(s.tree)
    assert len(conds) == 6  # has_home, is_armed, in_offboard, is_flying, has_path, at_goal
    for values in itertools.product([False, True], repeat=len(conds)):
        initial = dict(zip(conds, values))
        r = dry_run(s.tree, aerial, initial, action_ticks=3)
        assert r.success, initial
        assert r.violations == [], (initial, r.violations)
        assert r.world.holds("at_goal(goal)")


def test_default_tree_reaches_goal_from_every_initial_state(aerial: Library) -> None:
    s = synthesize(aerial, ["landed_at_home"])
    conds = conditions_in(s.tree)
    for values in itertools.product([False, True], repeat=len(conds)):
        r = dry_run(s.tree, aerial, dict(zip(conds, values)))
        assert r.success and not r.violations


def test_pick_and_deliver_from_every_initial_state(ground: Library) -> None:
    s = synthesize(ground, ["delivered(pickup, dropoff)"])
    conds = conditions_in(s.tree)
    for values in itertools.product([False, True], repeat=len(conds)):
        r = dry_run(s.tree, ground, dict(zip(conds, values)))
        assert r.success and not r.violations


def test_trace_shows_what_ran(aerial: Library) -> None:
    s = synthesize(aerial, ["at_goal(goal)"])
    r = dry_run(
        s.tree,
        aerial,
        {"has_home": True, "is_armed": True, "in_offboard": True, "is_flying": True},
        action_ticks=1,
    )
    text = r.format_trace(unicode=False)
    assert r.ticks == 1  # one-tick actions: update_path then follow_path in the same tick
    assert (
        "tick   1: - at_goal(goal)  + is_flying  - has_path(goal)  * update_path(goal) [1/1]  "
        "* follow_path(goal) [1/1]"
    ) in text
    assert "goal reached after 1 tick(s); 0 precondition violation(s)" in text


def test_goal_already_true_runs_nothing(aerial: Library) -> None:
    s = synthesize(aerial, ["at_goal(goal)"])
    r = dry_run(s.tree, aerial, {"at_goal(goal)": True})
    assert r.ticks == 1 and [lt.label for lt in r.world.trace[0]] == ["at_goal(goal)"]


def test_a_tree_with_an_assumed_false_condition_never_succeeds() -> None:
    lib, _ = compile_library(
        LibrarySpec.model_validate(
            {
                "library": "t",
                "version": 1,
                "conditions": {"done": "", "battery_ok": ""},
                "actions": {"work": {"pre": ["battery_ok"], "post": ["done"]}},
            }
        )
    )
    s = synthesize(lib, ["done"])
    r = dry_run(s.tree, lib, {}, max_ticks=20)
    assert not r.success and r.ticks == 20
    assert "goal NOT reached" in r.format_trace()


def test_py_trees_composites_are_memoryless(aerial: Library) -> None:
    s = synthesize(aerial, ["at_goal(goal)"])
    root = build_behaviour_tree(s.tree, lambda n: py_trees.behaviours.Success(name=n.label))
    composites = [b for b in root.iterate() if isinstance(b, py_trees.composites.Composite)]
    assert len(composites) == 8 and all(c.memory is False for c in composites)
    assert isinstance(root, py_trees.composites.Selector)
    assert sum(1 for _ in root.iterate()) == 20


# ---- property: random acyclic libraries --------------------------------------------------------
@st.composite
def acyclic_library(draw: st.DrawFn) -> tuple[Library, str]:
    """Conditions c0..cn-1; each achieved (or not) by an action whose preconditions are drawn from
    lower-numbered conditions only, so the library is acyclic by construction."""
    n = draw(st.integers(2, 7))
    actions = {}
    for i in range(n):
        if i > 0 and draw(st.booleans()) is False and i != n - 1:
            continue  # c_i is assumed
        pre = draw(st.lists(st.integers(0, i - 1), unique=True, max_size=3)) if i > 0 else []
        actions[f"make_c{i}"] = {"pre": [f"c{j}" for j in pre], "post": [f"c{i}"]}
    spec = LibrarySpec.model_validate(
        {
            "library": "rand",
            "version": 1,
            "conditions": {f"c{i}": "" for i in range(n)},
            "actions": actions,
        }
    )
    lib, diags = compile_library(spec)
    assert not diags
    return lib, f"c{n - 1}"


@settings(max_examples=150, deadline=None)
@given(acyclic_library(), st.data())
def test_random_acyclic_libraries_reach_goal_without_violations(
    case: tuple[Library, str], data: st.DataObject
) -> None:
    lib, goal = case
    s = synthesize(lib, [goal])
    assert s.ok
    conds = conditions_in(s.tree)
    initial = {c: data.draw(st.booleans(), label=c) for c in conds}
    assumed = {str(a) for a in s.assumed}
    r = dry_run(s.tree, lib, initial, action_ticks=data.draw(st.integers(1, 3)), max_ticks=500)
    reachable = all(initial.get(a, False) for a in assumed) or initial.get(goal, False)
    if reachable:
        assert r.success and not r.violations
    else:
        assert not r.violations  # it may be stuck on a false assumption, but never acts wrongly
