"""Assignment solvers against brute force and against each other (seed 003 eq. 4-7)."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_bipartite_matching

from btmission.allocation.solvers import (
    MAX_COST,
    AssignmentProblem,
    Matching,
    Objective,
    build_ilp,
    choose_method,
    evaluate,
    solve,
    solve_ilp,
)

EXACT = ("dense", "sparse", "ilp-scip")


def matchings(costs: np.ndarray) -> Iterator[list[tuple[int, int]]]:
    """Every matching of bid pairs (NaN = no bid), by brute force."""
    na, nt = costs.shape

    def rec(k: int, used: frozenset[int]) -> Iterator[list[tuple[int, int]]]:
        if k == na:
            yield []
            return
        yield from rec(k + 1, used)  # agent k gets nothing
        for j in range(nt):
            if j not in used and math.isfinite(costs[k, j]):
                for rest in rec(k + 1, used | {j}):
                    yield [(k, j), *rest]

    yield from rec(0, frozenset())


def brute_force(costs: np.ndarray, bonus: np.ndarray | None = None) -> Objective:
    """The lexicographic optimum: most pairs, then the largest Σ(bonus − cost)."""
    b = np.zeros(costs.shape[1]) if bonus is None else bonus
    best = Objective(0, 0.0, 0.0)
    for m in matchings(costs):
        value = sum(b[j] - costs[k, j] for k, j in m)
        cand = Objective(len(m), value, sum(costs[k, j] for k, j in m))
        if cand.better_than(best, rel=0.0):
            best = cand
    return best


@st.composite
def instances(
    draw: st.DrawFn, max_agents: int = 5, max_tasks: int = 5, priorities: bool = False
) -> tuple[np.ndarray, np.ndarray | None]:
    na = draw(st.integers(1, max_agents))
    nt = draw(st.integers(1, max_tasks))
    # integer-valued costs make exact ties common (the hard case for tie handling)
    cost = st.one_of(
        st.integers(0, 20).map(float),
        st.floats(0, 1000, allow_nan=False, allow_infinity=False),
    )
    c = np.array([[draw(cost) for _ in range(nt)] for _ in range(na)])
    density = draw(st.sampled_from([0.2, 0.5, 1.0]))
    keep = np.array([[draw(st.booleans()) or density == 1.0 for _ in range(nt)] for _ in range(na)])
    if density == 0.2:
        keep &= np.array([[draw(st.integers(0, 4)) == 0 for _ in range(nt)] for _ in range(na)])
    c[~keep] = np.nan
    bonus = None
    if priorities:
        bonus = np.array([draw(st.sampled_from([0.0, 0.0, 50.0, 2000.0])) for _ in range(nt)])
    return c, bonus


def check_matching(problem: AssignmentProblem, m: Matching) -> Objective:
    """A valid matching: each agent and task at most once, only bid pairs (evaluate raises)."""
    assert len(set(m.rows.tolist())) == len(m.rows)
    assert len(set(m.cols.tolist())) == len(m.cols)
    assert list(m.rows) == sorted(m.rows)
    return evaluate(problem, m)


@pytest.mark.parametrize("method", ["dense", "sparse"])
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(inst=instances())
def test_assignment_solvers_are_optimal(method: str, inst: tuple[np.ndarray, None]) -> None:
    costs, _ = inst
    p = AssignmentProblem.dense(costs)
    got = check_matching(p, solve(p, method))
    want = brute_force(costs)
    assert got.same_as(want), (costs, got, want)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(inst=instances(max_agents=4, max_tasks=4))
def test_paper_ilp_on_scip_is_optimal(inst: tuple[np.ndarray, None]) -> None:
    costs, _ = inst
    p = AssignmentProblem.dense(costs)
    got = check_matching(p, solve(p, "ilp-scip"))
    assert got.same_as(brute_force(costs))


@pytest.mark.parametrize("method", EXACT)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(inst=instances(max_agents=4, max_tasks=4, priorities=True))
def test_priorities_are_part_of_the_optimum(
    method: str, inst: tuple[np.ndarray, np.ndarray]
) -> None:
    costs, bonus = inst
    p = AssignmentProblem.dense(costs, bonus=bonus)
    assert check_matching(p, solve(p, method)).same_as(brute_force(costs, bonus))


@pytest.mark.parametrize(("na", "nt"), [(3, 6), (6, 3), (4, 4), (1, 5), (5, 1)])
def test_more_tasks_than_agents_and_vice_versa(na: int, nt: int) -> None:
    rng = np.random.default_rng(na * 10 + nt)
    for _ in range(20):
        costs = rng.uniform(0, 100, (na, nt))
        costs[rng.random((na, nt)) < 0.3] = np.nan
        want = brute_force(costs)
        p = AssignmentProblem.dense(costs)
        for method in EXACT:
            got = check_matching(p, solve(p, method))
            assert got.same_as(want), (method, costs)
            assert got.assigned <= min(na, nt)


def test_sparse_edge_input_matches_dense() -> None:
    rng = np.random.default_rng(3)
    costs = rng.uniform(0, 50, (6, 9))
    costs[rng.random(costs.shape) < 0.6] = np.nan
    r, c = np.nonzero(np.isfinite(costs))
    edges = AssignmentProblem.sparse(6, 9, r, c, costs[r, c])
    dense = AssignmentProblem.dense(costs)
    want = brute_force(costs)
    for method in EXACT:
        assert check_matching(edges, solve(edges, method)).same_as(want)
        assert check_matching(dense, solve(dense, method)).same_as(want)


def test_maximum_cardinality_against_hopcroft_karp() -> None:
    """The number of assigned tasks equals the maximum matching size of the bid graph, even when
    that means giving an agent an expensive task (scipy's Hopcroft-Karp as the reference)."""
    rng = np.random.default_rng(11)
    for trial in range(30):
        na, nt = rng.integers(5, 40), rng.integers(5, 40)
        costs = rng.uniform(0, 1000, (na, nt))
        costs[rng.random((na, nt)) < rng.uniform(0.5, 0.95)] = np.nan
        graph = csr_matrix(np.isfinite(costs).astype(np.int8))
        size = int(np.count_nonzero(maximum_bipartite_matching(graph, perm_type="column") >= 0))
        p = AssignmentProblem.dense(costs)
        for method in EXACT if trial < 5 else ("dense", "sparse"):
            assert len(solve(p, method)) == size


def test_cardinality_beats_cost() -> None:
    """A2 can only do T1: taking T1 from the cheap A1 assigns both, so the optimum does it."""
    costs = np.array([[1.0, 900.0], [5.0, np.nan]])
    for method in EXACT:
        m = solve(AssignmentProblem.dense(costs), method)
        assert m.as_dict() == {0: 1, 1: 0}


def test_priority_bonus_wins_over_cost() -> None:
    """One agent, a cheap normal task and an expensive high-priority one (seed 003 scenario 3)."""
    costs = np.array([[10.0, 300.0]])
    for method in EXACT:
        assert solve(AssignmentProblem.dense(costs), method).as_dict() == {0: 0}
        boosted = AssignmentProblem.dense(costs, bonus=[1000.0, 2000.0])
        assert solve(boosted, method).as_dict() == {0: 1}


@pytest.mark.parametrize("method", ["dense", "sparse"])
def test_exact_ties_keep_the_incumbent(method: str) -> None:
    """Two agents at the same cost from two tasks: whoever holds a task keeps it. (The ILP's
    tie-break δ is below SCIP's tolerances, so SCIP returns one of the tied optima.)"""
    costs = np.full((2, 2), 7.0)
    for held in ([0, 1], [1, 0]):
        p = AssignmentProblem.dense(costs, incumbent=held)
        assert solve(p, method).as_dict() == {0: held[0], 1: held[1]}
    # an incumbent does not override a real cost difference
    costs = np.array([[5.0, 7.0], [7.0, 5.0]])
    p = AssignmentProblem.dense(costs, incumbent=[1, 0])
    assert solve(p, method).as_dict() == {0: 0, 1: 1}


@pytest.mark.parametrize("method", ["dense", "sparse"])
def test_solvers_are_deterministic(method: str) -> None:
    costs = np.ones((5, 5))
    first = solve(AssignmentProblem.dense(costs), method).as_dict()
    for _ in range(3):
        assert solve(AssignmentProblem.dense(costs), method).as_dict() == first


def test_all_solvers_agree_on_medium_instances() -> None:
    rng = np.random.default_rng(5)
    for p_keep in (0.3, 0.6, 0.9):
        pos_a = rng.uniform(0, 100, (15, 2))
        pos_t = rng.uniform(0, 100, (40, 2))
        costs = np.linalg.norm(pos_a[:, None] - pos_t[None], axis=2)
        costs[rng.random(costs.shape) > p_keep] = np.nan
        p = AssignmentProblem.dense(costs, bonus=rng.choice([1000.0, 2000.0], 40))
        objs = {m: check_matching(p, solve(p, m)) for m in EXACT}
        assert objs["dense"].same_as(objs["sparse"]) and objs["dense"].same_as(objs["ilp-scip"])
        assert objs["dense"].assigned == 15
        # random real costs: the optimum is unique, so the pairs agree too
        pairs = {m: solve(p, m).as_dict() for m in EXACT}
        assert pairs["dense"] == pairs["sparse"] == pairs["ilp-scip"]


def test_empty_problems() -> None:
    for p in (
        AssignmentProblem.dense(np.zeros((0, 3))),
        AssignmentProblem.dense(np.zeros((3, 0))),
        AssignmentProblem.dense(np.full((2, 2), np.nan)),
        AssignmentProblem.sparse(2, 2, [], [], []),
    ):
        for method in ("auto", *EXACT):
            assert len(solve(p, method)) == 0


def test_unreachable_inf_is_no_bid() -> None:
    costs = np.array([[np.inf, 3.0], [np.inf, np.inf]])
    for method in EXACT:
        assert solve(AssignmentProblem.dense(costs), method).as_dict() == {0: 1}


def test_ilp_model_has_one_variable_per_bid() -> None:
    costs = np.array([[1.0, np.nan, 2.0], [np.nan, 4.0, 5.0]])
    model = build_ilp(AssignmentProblem.dense(costs))
    assert len(model.rows) == 4 and len(model.profit) == 4
    assert np.all(model.profit > 0)  # every bid is worth more than leaving it out (eq. 4)
    assert solve_ilp(model).as_dict() == {0: 0, 1: 1}


def test_auto_chooses_sparse_for_sparse_large_problems() -> None:
    na, nt = 1000, 10000
    rows = np.repeat(np.arange(na), 5)
    cols = np.arange(na * 5) % nt
    sparse = AssignmentProblem.sparse(na, nt, rows, cols, np.ones(na * 5))
    assert choose_method(sparse) == "sparse"
    assert choose_method(AssignmentProblem.dense(np.ones((50, 400)))) == "dense"


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: AssignmentProblem.dense(np.ones(3)), "2-D"),
        (lambda: AssignmentProblem.dense(np.ones((2, 2)), bonus=[1.0]), "bonus"),
        (lambda: AssignmentProblem.dense(np.ones((2, 2)), incumbent=[0]), "incumbent"),
        (lambda: AssignmentProblem.sparse(2, 2, [0], [0, 1], [1.0]), "same length"),
        (lambda: AssignmentProblem.sparse(2, 2, [2], [0], [1.0]), "out of range"),
        (lambda: AssignmentProblem.sparse(2, 2, [0], [0], [np.nan]), "finite"),
        (lambda: AssignmentProblem(-1, 2, np.ones((0, 2))), "negative"),
        (lambda: AssignmentProblem(2, 2, np.ones((2, 3))), r"expected \(2, 2\)"),
    ],
)
def test_bad_problems_are_rejected(make: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        make()  # type: ignore[operator]


@pytest.mark.parametrize("bad", [-1.0, -np.inf, MAX_COST * 10])
@pytest.mark.parametrize("method", EXACT)
def test_out_of_range_costs_are_rejected(bad: float, method: str) -> None:
    costs = np.array([[1.0, bad]])
    with pytest.raises(ValueError, match="bid costs must be in"):
        solve(AssignmentProblem.dense(costs), method)


def test_unknown_method() -> None:
    with pytest.raises(ValueError, match="unknown solver method 'hungarian'"):
        solve(AssignmentProblem.dense(np.ones((1, 1))), "hungarian")


def test_evaluate_rejects_invalid_matchings() -> None:
    p = AssignmentProblem.dense(np.array([[1.0, np.nan], [2.0, 3.0]]))
    with pytest.raises(ValueError, match="used twice"):
        evaluate(p, Matching(np.array([0, 1]), np.array([0, 0]), "x"))
    with pytest.raises(ValueError, match="without a bid"):
        evaluate(p, Matching(np.array([0]), np.array([1]), "x"))
    assert evaluate(p, Matching(np.array([0, 1]), np.array([0, 1]), "x")) == Objective(2, -4.0, 4.0)
    assert p.cost(0, 1) != p.cost(0, 1)  # NaN: no bid
    sp = AssignmentProblem.sparse(2, 2, [1], [1], [3.0])
    assert sp.cost(1, 1) == 3.0 and math.isnan(sp.cost(0, 0))


def test_denormal_cost_span_still_assigns_with_every_solver() -> None:
    """Regression (found by hypothesis): costs 0 and 5e-324 made all ILP profits underflow, and
    SCIP assigned nothing."""
    costs = np.array([[0.0, 0.0, 0.0, 5e-324]])
    for method in ("dense", "sparse", "ilp-scip"):
        m = solve(AssignmentProblem.dense(costs), method)
        assert len(m.rows) == 1, method
