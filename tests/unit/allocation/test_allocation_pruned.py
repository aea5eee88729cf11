"""The pruned assignment solver against brute force and against the dense solver.

Small ``k`` (1-3 best bids per agent) makes the duals' proof fail often, so the rescans and the
hand-over to the dense solver are exercised on small instances, ties and partial participation
included.
"""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btmission.allocation import pruned
from btmission.allocation.solvers import (
    AssignmentProblem,
    Matching,
    choose_method,
    evaluate,
    solve,
)
from btmission.bench.auction import instance_costs
from tests.unit.allocation.test_allocation_solvers import brute_force, check_matching, instances


def pruned_or_dense(problem: AssignmentProblem, k: int) -> Matching:
    """The pruned solver, rescanning however many agents fail (so that small k exercises the
    rescans), else the dense one (as ``solve`` does)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pruned, "MAX_FAILED_SHARE", 1.0)
        got = pruned.solve_pruned(problem, k)
    return got if got is not None else solve(problem, "dense")


@pytest.mark.parametrize("k", [1, 2, 24])
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(inst=instances(max_agents=5, max_tasks=6, priorities=True))
def test_pruned_is_optimal_against_brute_force(
    k: int, inst: tuple[np.ndarray, np.ndarray | None]
) -> None:
    costs, bonus = inst
    p = AssignmentProblem.dense(costs, bonus=bonus)
    got = check_matching(p, pruned_or_dense(p, k))
    assert got.same_as(brute_force(costs, bonus)), (costs, bonus, got)


@st.composite
def medium(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Up to 30 × 60 with integer costs (many exact ties), NaN and +inf holes, partial
    participation (each agent's cheapest fraction), priorities and incumbents."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    na, nt = int(rng.integers(1, 31)), int(rng.integers(1, 61))
    costs = rng.integers(0, draw(st.sampled_from([3, 20, 1000])), (na, nt)).astype(float)
    share = draw(st.sampled_from([0.05, 0.3, 0.6, 0.9, 1.0]))
    k = max(1, int(np.ceil(share * nt)))
    if k < nt:
        drop = np.argpartition(costs, k - 1, axis=1)[:, k:]
        np.put_along_axis(costs, drop, np.nan, axis=1)
    costs[rng.random((na, nt)) < 0.05] = np.inf
    bonus = rng.choice([0.0, 0.0, 5.0, 1000.0], nt) if draw(st.booleans()) else None
    inc = None
    if draw(st.booleans()):
        inc = np.full(na, -1)
        held = rng.permutation(nt)[: min(na, nt)]
        who = rng.permutation(na)[: len(held)]
        inc[who] = held
        inc[rng.random(na) < 0.3] = -1
    return costs, bonus, inc


@pytest.mark.parametrize("k", [1, 3])
@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(inst=medium())
def test_pruned_reaches_the_dense_optimum(
    k: int, inst: tuple[np.ndarray, np.ndarray | None, np.ndarray | None]
) -> None:
    """Same count and value as the dense solver; with incumbents, the same tie-break (every
    optimum of the shifted costs ``q``, which carry the incumbents' δ, has the same ``Σ q``)."""
    costs, bonus, inc = inst
    p = AssignmentProblem.dense(costs, bonus=bonus, incumbent=inc)
    want = check_matching(p, solve(p, "dense"))
    m = pruned_or_dense(p, k)
    assert check_matching(p, m).same_as(want)
    if inc is not None:  # ties broken the same way: as many incumbents kept
        kept = lambda mm: sum(int(inc[r] == c) for r, c in zip(mm.rows, mm.cols))  # noqa: E731
        assert kept(m) == kept(solve(p, "dense"))


def test_rescans_and_the_dense_hand_over_are_exact(monkeypatch: pytest.MonkeyPatch) -> None:
    """Everyone wants the same few tasks: k = 1 cannot prove anything, the rescans widen the
    agents that fail; with one round only, ``solve`` hands the problem to the dense solver."""
    rng = np.random.default_rng(4)
    costs = rng.uniform(0, 1, (40, 200))
    costs[:, :5] = rng.uniform(0, 0.01, (40, 5))
    p = AssignmentProblem.dense(costs)
    want = evaluate(p, solve(p, "dense"))
    assert pruned.solve_pruned(p, 1) is None  # most agents fail: straight to dense
    monkeypatch.setattr(pruned, "MAX_FAILED_SHARE", 1.0)
    got = pruned.solve_pruned(p, 1)
    assert got is not None and got.method == "pruned"
    assert evaluate(p, got).same_as(want)
    monkeypatch.setattr(pruned, "MAX_ROUNDS", 1)
    assert pruned.solve_pruned(p, 1) is None
    monkeypatch.setattr(pruned, "DEFAULT_K", 1)
    m = solve(p, "pruned")
    assert m.method == "dense" and evaluate(p, m).same_as(want)


@pytest.mark.parametrize("threads", [1, 2])
def test_benchmark_instance_same_pairs_as_dense(
    threads: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scaled-down benchmark instance (200 × 2,000, 30 % participation): the pairs themselves
    equal the dense solver's (random real costs: the optimum is unique), with the scan on one
    thread or split between two."""
    monkeypatch.setattr(pruned, "PARALLEL_MIN_CELLS", 1 if threads == 2 else 10**12)
    monkeypatch.setattr(pruned, "_threads", lambda: 2)
    costs = instance_costs(200, 2000, 0.3, 0)
    p = AssignmentProblem.dense(costs)
    want = solve(p, "dense")
    got = solve(p, "pruned")
    assert got.method == "pruned"
    assert np.array_equal(got.rows, want.rows) and np.array_equal(got.cols, want.cols)


def test_auto_prunes_large_matrices_only() -> None:
    assert choose_method(AssignmentProblem.dense(np.ones((500, 1000)))) == "pruned"
    assert choose_method(AssignmentProblem.dense(np.ones((50, 400)))) == "dense"
    assert choose_method(AssignmentProblem.dense(np.ones((10_000, 60)))) != "pruned"
    assert choose_method(AssignmentProblem.dense(np.ones((1000, 1999)))) != "pruned"
    edges = AssignmentProblem.sparse(1000, 1000, [0], [0], [1.0])
    assert choose_method(edges) != "pruned"
    assert solve(edges, "pruned").as_dict() == {0: 0}  # edges: handed to dense/sparse


def test_empty_and_holes() -> None:
    for costs in (np.zeros((0, 3)), np.zeros((3, 0)), np.full((2, 2), np.nan)):
        m = solve(AssignmentProblem.dense(costs), "pruned")
        assert len(m) == 0
    costs = np.array([[np.inf, 3.0], [np.inf, np.inf], [np.nan, 1.0]])
    assert solve(AssignmentProblem.dense(costs), "pruned").as_dict() == {2: 1}


@pytest.mark.parametrize("bonus", [None, [5.0, 0.0]])
@pytest.mark.parametrize("bad", [-1.0, -np.inf, 1e13])
def test_out_of_range_costs_are_rejected(bad: float, bonus: list[float] | None) -> None:
    with pytest.raises(ValueError, match="bid costs must be in"):
        solve(AssignmentProblem.dense(np.array([[1.0, bad]]), bonus=bonus), "pruned")


def test_incumbent_kept_on_exact_ties() -> None:
    costs = np.full((3, 50), 7.0)
    for held in ([0, 1, 2], [49, 10, 3], [5, -1, 6]):
        p = AssignmentProblem.dense(costs, incumbent=held)
        got = pruned.solve_pruned(p, 1)
        assert got is not None
        assert all(got.as_dict()[a] == t for a, t in enumerate(held) if t >= 0)


def test_the_scan_does_not_wait_for_a_stalled_helper(monkeypatch: pytest.MonkeyPatch) -> None:
    """The helper thread claims a block and then gets no CPU (as on a busy machine): the caller
    computes that block itself and returns the same result as a scan on one thread, without
    waiting for the helper."""
    kern = pruned._kernels()
    stalled, release, gave_up = threading.Event(), threading.Event(), threading.Event()

    def scan_rows(*args: object) -> None:
        if threading.current_thread() is threading.main_thread():
            stalled.wait(5)  # let the helper claim a block first
        else:
            stalled.set()
            if not release.wait(5):  # a caller that waited for the helper would see this
                gave_up.set()
        kern.scan_rows(*args)

    costs = instance_costs(60, 3000, 0.3, 0)
    bonus, inc, rows = None, np.full(60, -1), np.arange(60)
    alone = pruned._scan(costs, bonus, inc, rows, 5)
    fake = SimpleNamespace(scan_rows=scan_rows)
    monkeypatch.setattr(pruned, "_kernels", lambda: fake)
    monkeypatch.setattr(pruned, "PARALLEL_MIN_CELLS", 1)
    monkeypatch.setattr(pruned, "BLOCK_CELLS", 3000 * 7)
    monkeypatch.setattr(pruned, "_threads", lambda: 2)
    try:
        shared = pruned._scan(costs, bonus, inc, rows, 5)
        assert stalled.is_set() and not gave_up.is_set()  # returned while the helper hung
    finally:
        release.set()
    for a, b in zip((alone.cols, alone.x, alone.next_x, alone.stats),
                    (shared.cols, shared.x, shared.next_x, shared.stats)):  # fmt: skip
        np.testing.assert_array_equal(a, b)


def test_auction_rounds_at_fleet_scale_match_the_dense_solver() -> None:
    """Whole auction rounds (participation 30 %, priorities, then the holders as incumbents in
    the next rounds while the agents move): the mission's default solver prunes and gives every
    round the same assignment as the dense solver."""
    from btmission.allocation.auction import AuctionConfig, AuctionState, Bid, auction_round
    from btmission.allocation.tasks import TaskInfo, TaskPool

    na, nt = 60, 8500  # 510,000 cells, > 2 tasks per agent: auto prunes
    rng = np.random.default_rng(9)
    task_xy = rng.uniform(0, 100, (nt, 2))
    ids = [f"T{j:05d}" for j in range(nt)]
    pool = TaskPool().add_all(
        TaskInfo(tid, "inspect", {}, priority=float(rng.choice([1.0, 1.0, 2.0]))) for tid in ids
    )
    agents = [f"R{i:03d}" for i in range(na)]
    states = {
        solver: AuctionState(AuctionConfig(participation=0.3, solver=solver), pool)
        for solver in ("assignment", "dense")
    }
    pos = rng.uniform(0, 100, (na, 2))
    for rnd in range(3):
        pos = pos + rng.normal(0, 2.0, pos.shape)
        costs = np.linalg.norm(pos[:, None] - task_xy[None], axis=2)
        out = {}
        for solver, st_ in states.items():  # bids by task id (the first round announces)
            bids = [Bid.of(a, float(rnd), dict(zip(ids, costs[i]))) for i, a in enumerate(agents)]
            assignments, states[solver], report = auction_round(st_, bids, float(rnd))
            out[solver] = (assignments, report.method)
        assert out["assignment"][1] == "pruned" and out["dense"][1] == "dense"
        assert out["assignment"][0] == out["dense"][0]
        assert sum(t is not None for t in out["dense"][0].values()) == na
