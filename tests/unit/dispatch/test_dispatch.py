"""GA fleet dispatch (seed 004): maps, missions, evaluation, GA, push and swap, dynamic planning."""

from __future__ import annotations

import itertools
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btmission.diagnostics import SpecError
from btmission.dispatch.dynamic import (
    DynamicConfig,
    DynamicPlanner,
    executed_tracks,
    settle_waits,
)
from btmission.dispatch.evaluate import Evaluator, evaluate_reference, timeline
from btmission.dispatch.ga import GAParams, optimize
from btmission.dispatch.maps import BUILTIN_MAPS, TABLE6_SCALE, mine_map, static_map
from btmission.dispatch.missions import (
    FleetMission,
    Mission,
    direct_mission,
    fleet_items,
    initial_fleet,
    insert_pause_visit,
    make_mission,
    remove_pause_visit,
)
from btmission.dispatch.push_and_swap import push_and_swap
from btmission.dispatch.static import plan_static, random_instance
from btmission.dispatch.topomap import Node, NodeKind, Segment, TopoMap, TopoMapError
from btmission.spec.topomap import dump_topomap, load_topomap, load_topomap_text

T, S, Q = NodeKind.TERMINAL, NodeKind.PAUSE, NodeKind.TRANSIT


def corridor() -> TopoMap:
    """A — X — B with a pause node P off X; 10 s per segment (20 s B→X), 3 s to P."""
    return TopoMap.build(
        "corridor",
        [Node("A", T), Node("X", Q), Node("P", S), Node("B", T)],
        [Segment("A", "X", 10, 10), Segment("X", "B", 10, 20), Segment("X", "P", 3, 3)],
    )


def fleet(tmap: TopoMap, *specs: tuple[list[str], list[float]]) -> tuple[Mission, ...]:
    return tuple(make_mission(tmap, [tmap.id(n) for n in names], waits) for names, waits in specs)


def evaluator(tmap: TopoMap, xi_min: int = 1, delta: float = 2.0) -> Evaluator:
    return Evaluator(tmap, xi_min, beta=1e-4, delta=delta)


# ------------------------------------------------------------------------------ maps
def test_loop_is_refused_with_the_loop_named() -> None:
    with pytest.raises(TopoMapError, match=r"segment C-A closes a loop \(A → B → C → A\)"):
        TopoMap.build(
            "loop",
            [Node("A", T), Node("B", Q), Node("C", Q)],
            [Segment("A", "B", 1, 1), Segment("B", "C", 1, 1), Segment("C", "A", 1, 1)],
        )


def test_disconnected_and_bad_segments_are_refused() -> None:
    nodes = [Node("A", T), Node("B", T), Node("C", T)]
    with pytest.raises(TopoMapError, match="not connected: C"):
        TopoMap.build("d", nodes, [Segment("A", "B", 1, 1)])
    with pytest.raises(TopoMapError, match="unknown node 'Z'"):
        TopoMap.build("d", nodes, [Segment("A", "Z", 1, 1)])
    with pytest.raises(TopoMapError, match="must be > 0"):
        TopoMap.build("d", nodes[:2], [Segment("A", "B", 0, 1)])
    with pytest.raises(TopoMapError, match="only terminals can be prioritized"):
        TopoMap.build("d", [Node("A", Q, True), Node("B", T)], [Segment("A", "B", 1, 1)])


def test_map_file_errors_name_file_and_line(tmp_path: Path) -> None:
    text = textwrap.dedent(
        """\
        topomap: bad
        version: 1
        nodes:
          A: {kind: terminal}
          B: {kind: transit}
          C: {kind: terminal}
        segments:
          - {from: A, to: B, time: 5}
          - {from: B, to: C, time: [5, 7]}
          - {from: C, to: A, time: 5}
        """
    )
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(SpecError) as exc:
        load_topomap(f)
    (d,) = exc.value.diagnostics
    assert d.where.file == str(f) and d.where.line == 10 and "closes a loop" in d.message
    with pytest.raises(SpecError) as exc2:
        load_topomap_text(text.replace("kind: transit", "kind: tunnel"), "x.yaml")
    assert "kind" in exc2.value.diagnostics[0].item
    assert exc2.value.diagnostics[0].where.line == 5


@pytest.mark.parametrize("tmap", [static_map("npr"), static_map("spr"), mine_map()])
def test_builtin_maps_roundtrip_through_yaml(tmap: TopoMap) -> None:
    again = load_topomap_text(dump_topomap(tmap))
    assert [n.name for n in again.nodes] == [n.name for n in tmap.nodes]
    np.testing.assert_allclose(again.ttime, tmap.ttime)
    assert (again.prioritized == tmap.prioritized).all()


def _brute_path(tmap: TopoMap, i: int, j: int) -> list[int]:
    """Depth-first search of the unique simple path (reference for Π0)."""
    stack = [(i, [i])]
    while stack:
        x, path = stack.pop()
        if x == j:
            return path
        stack += [(y, [*path, y]) for y in tmap.neighbors[x] if y not in path]
    raise AssertionError("no path")


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, 1_000_000), min_size=1, max_size=25), st.randoms())
def test_path_matrix_matches_brute_force_on_random_trees(parents: list[int], rnd) -> None:  # type: ignore[no-untyped-def]
    n = len(parents) + 1
    nodes = [Node(f"N{i}", T if i % 3 == 0 else Q) for i in range(n)]
    segs = [
        Segment(f"N{p % (i + 1)}", f"N{i + 1}", rnd.uniform(1, 9), rnd.uniform(1, 9))
        for i, p in enumerate(parents)
    ]
    tmap = TopoMap.build("tree", nodes, segs)
    for i in range(n):
        for j in range(n):
            path = _brute_path(tmap, i, j)
            assert tmap.path(i, j) == path
            assert tmap.hops[i, j] == len(path) - 1
            assert tmap.dist[i, j] == pytest.approx(
                sum(tmap.ttime[a, b] for a, b in itertools.pairwise(path))
            )


def test_static_maps_follow_the_paper_description() -> None:
    npr, spr = static_map("npr"), static_map("spr")
    left = [i for i in npr.terminals if npr.nodes[i].group == "left"]
    right = [i for i in npr.terminals if npr.nodes[i].group == "right"]
    assert len(left) == len(right) == 6 and not npr.prioritized.any()
    assert {spr.nodes[i].name for i in np.flatnonzero(spr.prioritized)} == {
        npr.nodes[i].name for i in left
    }
    # right → left takes twice as long as left → right on the same path
    a, b = left[0], right[0]
    assert npr.dist[b, a] == pytest.approx(2 * npr.dist[a, b])
    # every left-right path goes through the central bottleneck, a single lane W0 — M — E0
    # with no pause node inside it (§6.1.2: "the bottleneck in the middle")
    assert all(npr.id("M") in npr.path(x, y) for x in left for y in right)
    assert {npr.nodes[i].name for i in npr.neighbors[npr.id("M")]} == {"W0", "E0"}
    assert npr.pause_neighbors[npr.id("M")] == ()


def test_mine_map_speeds_follow_section_6_2() -> None:
    m = mine_map()
    o = m.id("O")
    assert [m.nodes[i].name for i in np.flatnonzero(m.prioritized)] == ["O"]
    assert len(m.terminals) == 7
    # 100 m from O to J0: 12 s outbound at 30 km/h, 18 s inbound at 20 km/h
    j0 = m.id("J0")
    assert m.ttime[o, j0] == pytest.approx(100 / (30 / 3.6), abs=0.01)
    assert m.ttime[j0, o] == pytest.approx(100 / (20 / 3.6), abs=0.01)
    r0, r1 = m.id("R0"), m.id("R1")  # on the ramp: 10 km/h inbound
    assert m.ttime[r1, r0] == pytest.approx(3 * m.ttime[r0, r1], rel=1e-3)
    pauses_near_o = [p for p in m.pauses if m.dist[p, o] < 60]
    assert len(pauses_near_o) >= 2


def test_mine_table6_is_the_mine_scaled_to_table_6s_round_trip() -> None:
    """Every traversal time is 0.7 × the mine's, and the mean Π0 round trip O → loading site → O
    is the ≈ 874 s that Table 6's two-truck row leaves for driving (maps.py derives it)."""
    m, t6 = mine_map(), BUILTIN_MAPS["mine_table6"]()
    assert t6.name == "mine_table6" and [n.name for n in t6.nodes] == [n.name for n in m.nodes]
    joined = m.edge >= 0
    assert np.allclose(t6.ttime[joined], TABLE6_SCALE * m.ttime[joined], atol=0.01)
    o = t6.id("O")
    loading = [x for x in t6.terminals if x != o]
    trip = float(np.mean([t6.dist[o, x] + t6.dist[x, o] for x in loading]))
    assert trip == pytest.approx(874, abs=2)
    assert float(np.mean([m.dist[o, x] + m.dist[x, o] for x in loading])) == pytest.approx(
        1249, abs=2
    )
    with pytest.raises(ValueError, match="scale"):
        mine_map(0.0)


# ------------------------------------------------------------------------------ missions
def test_stop_times_only_at_start_and_pause_nodes() -> None:
    m = corridor()
    with pytest.raises(ValueError, match="only allowed at the start and at pause nodes"):
        fleet(m, (["A", "X", "B"], [0, 5, 0]))
    ok = fleet(m, (["A", "X", "P", "X", "B"], [4, 0, 9, 0, 0]))[0]
    assert ok.slots.tolist() == [0, 2]
    with pytest.raises(ValueError, match="not joined"):
        fleet(m, (["A", "B"], [0, 0]))


def test_prioritized_missions_follow_pi0_and_stop_only_at_start() -> None:
    m = corridor()
    with pytest.raises(ValueError, match="direct path"):
        make_mission(m, [m.id(x) for x in ["A", "X", "P", "X", "B"]], prioritized=True)
    p = make_mission(m, [m.id("A"), m.id("X"), m.id("B")], [3, 0, 0], prioritized=True)
    assert p.slots.tolist() == [0]


def test_pause_visit_insertion_and_removal_are_inverse() -> None:
    m = corridor()
    base = direct_mission(m, m.id("A"), m.id("B"), wait=2.0)
    ins = insert_pause_visit(m, base, 1, m.id("P"), 7.0)
    assert [m.nodes[i].name for i in ins.nodes] == ["A", "X", "P", "X", "B"]
    assert ins.waits.tolist() == [2.0, 0.0, 7.0, 0.0, 0.0] and ins.pause_visits(m) == [2]
    back = remove_pause_visit(m, ins, 2)
    assert back.nodes.tolist() == base.nodes.tolist() and back.waits.tolist() == [2, 0, 0]


# ------------------------------------------------------------------------------ evaluation
def fork() -> TopoMap:
    """S1, S2 — X — Y — E1, E2: two branches in, one shared segment X-Y, two branches out."""
    return TopoMap.build(
        "fork",
        [Node(n, T) for n in ("S1", "S2", "E1", "E2")] + [Node("X", Q), Node("Y", Q)],
        [
            Segment("S1", "X", 10, 10),
            Segment("S2", "X", 10, 10),
            Segment("X", "Y", 10, 10),
            Segment("Y", "E1", 10, 10),
            Segment("Y", "E2", 10, 10),
        ],
    )


def test_head_on_segment_collision_is_found() -> None:
    m = fork()
    f = fleet(m, (["S1", "X", "Y", "E1"], [0, 0, 0, 0]), (["E2", "Y", "X", "S2"], [0, 0, 0, 0]))
    conflicts, _ = evaluate_reference(m, f, delta=2.0)
    # they meet head-on on X-Y (both on it during 10-20 s), nowhere else
    assert [(c.kind, c.time, sorted(m.nodes[i].name for i in c.where)) for c in conflicts] == [
        ("segment", 20.0, ["X", "Y"])
    ]
    ev = evaluator(m).evaluate(f)
    assert (ev.collisions, ev.t_first, ev.feasible) == (1, 20.0, False) and ev.score < 0
    # one of them waiting 11 s at its start clears the segment: feasible
    ok = fleet(m, (["S1", "X", "Y", "E1"], [0, 0, 0, 0]), (["E2", "Y", "X", "S2"], [23, 0, 0, 0]))
    assert evaluate_reference(m, ok, 2.0)[0] == [] and evaluator(m).evaluate(ok).feasible


@pytest.mark.parametrize(("gap", "grazes"), [(4.0, 0), (2.5, 0), (1.0, 2), (0.0, 2)])
def test_grazing_collision_within_the_window_and_legal_following(gap: float, grazes: int) -> None:
    """Same direction through X and Y, ``gap`` s apart: a graze at X and at Y when gap < δ = 2 s."""
    m = fork()
    f = fleet(m, (["S1", "X", "Y", "E1"], [0, 0, 0, 0]), (["S2", "X", "Y", "E2"], [gap, 0, 0, 0]))
    conflicts, _ = evaluate_reference(m, f, delta=2.0)
    assert [c.kind for c in conflicts] == ["node"] * grazes  # never a segment violation
    assert sorted(m.nodes[c.where[0]].name for c in conflicts) == ["X", "Y"][:grazes]
    assert evaluator(m, delta=2.0).evaluate(f).collisions == grazes


def test_a_parked_vehicle_blocks_its_end_node() -> None:
    m = corridor()
    f = fleet(m, (["A", "X", "P"], [0, 0, 0]), (["B", "X", "P"], [40, 0, 0]))
    conflicts, _ = evaluate_reference(m, f, 2.0)
    assert [(c.kind, m.nodes[c.where[0]].name) for c in conflicts] == [("node", "P")]


def test_vehicles_in_a_convoy_within_the_window_graze() -> None:
    m = static_map("npr")
    a, b = m.id("L1n"), m.id("R1n")
    c = m.id("L2n")
    lead = direct_mission(m, a, b)
    tail = direct_mission(m, c, m.id("R2n"), wait=0.0)
    # same direction through the trunk: the tail follows the lead by 6 s at W1...
    ev = evaluator(m, delta=2.0)
    assert ev.evaluate((lead, tail)).feasible
    assert not evaluator(m, delta=50.0).evaluate((lead, tail)).feasible


def test_score_equations() -> None:
    m = corridor()
    ok = fleet(m, (["A", "X", "P"], [0, 0, 0]), (["B", "X", "A"], [0, 0, 0]))
    ev = Evaluator(m, xi_min=3, beta=1e-4)
    e = ev.evaluate(ok)
    assert e.feasible
    assert e.score == pytest.approx((1 / e.duration) * (3 / 4))  # eq. 2
    bad = fleet(m, (["A", "X", "B"], [0, 0, 0]), (["B", "X", "A"], [0, 0, 0]))
    e2 = ev.evaluate(bad)
    assert e2.score == pytest.approx(-e2.collisions + 1e-4 * e2.t_first)  # eq. 1


def _random_fleet(tmap: TopoMap, rng: np.random.Generator, n: int) -> tuple[Mission, ...]:
    starts = rng.choice(tmap.terminals, n, replace=False)
    out = []
    for s in starts:
        e = int(rng.choice([t for t in tmap.terminals if t != s]))
        m = direct_mission(tmap, int(s), e, wait=float(rng.integers(0, 4)) * 7.5)
        for _ in range(int(rng.integers(0, 3))):
            cands = [
                (i, p)
                for i in range(1, m.items)
                if tmap.is_transit[m.nodes[i]]
                for p in tmap.pause_neighbors[m.nodes[i]]
                if p not in m.nodes
            ]
            if cands:
                i, p = cands[int(rng.integers(len(cands)))]
                m = insert_pause_visit(tmap, m, i, p, float(rng.integers(0, 5)) * 5.0)
        out.append(m)
    return tuple(out)


@pytest.mark.parametrize("seed", range(40))
def test_kernel_matches_event_driven_reference(seed: int) -> None:
    tmap = static_map("npr")
    rng = np.random.default_rng(seed)
    f = _random_fleet(tmap, rng, int(rng.integers(2, 9)))
    delta = float(rng.choice([0.0, 2.0, 5.0]))
    conflicts, t_end = evaluate_reference(tmap, f, delta)
    n_c, t_first, t_end2 = Evaluator(tmap, 1, 1e-4, delta).raw(f)
    assert n_c == len(conflicts)
    assert t_end2 == pytest.approx(t_end)
    if conflicts:
        assert t_first == pytest.approx(min(c.time for c in conflicts))
    else:
        assert math.isinf(t_first)


# ------------------------------------------------------------------------------ GA
def test_ga_solves_a_swap_that_f0_does_not() -> None:
    m = corridor()
    f0 = initial_fleet(m, [(m.id("A"), m.id("B")), (m.id("B"), m.id("A"))])
    ev = Evaluator(m, fleet_items(f0), beta=1e-4, delta=2.0)
    assert not ev.evaluate(f0).feasible
    res = optimize(m, f0, ev, GAParams(max_generations=300, budget_s=30), np.random.default_rng(3))
    assert res.feasible and res.first_feasible_generation is not None
    names = [[m.nodes[i].name for i in mm.nodes] for mm in res.best]
    assert ["X", "P", "X"] in [n[1:4] for n in names]  # one of them stepped aside
    conflicts, _ = evaluate_reference(m, res.best, 2.0)
    assert conflicts == []


def test_ga_is_reproducible_with_a_seed() -> None:
    m = static_map("npr")
    inst = random_instance(m, 4, np.random.default_rng(0))
    p = GAParams(max_generations=40, budget_s=60)
    a = plan_static(m, inst, p, np.random.default_rng(5)).result
    b = plan_static(m, inst, p, np.random.default_rng(5)).result
    assert a.evaluation == b.evaluation and a.generations == b.generations == 40


def test_prioritized_missions_never_get_pause_visits_in_the_spr_map() -> None:
    m = static_map("spr")
    inst = random_instance(m, 6, np.random.default_rng(2))
    run = plan_static(m, inst, GAParams(max_generations=400, budget_s=60), np.random.default_rng(1))
    assert run.result.feasible
    for mission in run.result.best:
        if mission.prioritized:
            assert mission.nodes.tolist() == m.path(mission.start, mission.end)
            assert (mission.waits[1:] == 0).all()
        stops = [i for i in range(mission.items) if mission.waits[i] > 0 and i > 0]
        assert all(m.is_pause[mission.nodes[i]] for i in stops)  # never at transit nodes
    assert evaluate_reference(m, run.result.best)[0] == []


# ------------------------------------------------------------------------------ push and swap
def _replay(tmap: TopoMap, starts: list[int], moves) -> list[int]:  # type: ignore[no-untyped-def]
    pos = list(starts)
    for a, frm, to in moves:
        assert pos[a] == frm and to in tmap.neighbors[frm] and to not in pos
        pos[a] = to
    return pos


@pytest.mark.parametrize("vehicles", [2, 6, 10])
def test_push_and_swap_solves_static_instances(vehicles: int) -> None:
    m = static_map("npr")
    for seed in range(5):
        inst = random_instance(m, vehicles, np.random.default_rng(seed))
        res = push_and_swap(m, inst.starts, inst.ends)
        assert res.success, res.reason
        assert _replay(m, list(inst.starts), res.moves) == list(inst.ends)
        assert (
            res.items
            == len(res.moves)
            >= fleet_items(initial_fleet(m, list(zip(inst.starts, inst.ends))))
        )


def test_push_and_swap_swaps_in_a_corridor_with_a_junction() -> None:
    m = corridor()
    res = push_and_swap(m, [m.id("A"), m.id("B")], [m.id("B"), m.id("A")])
    assert res.success and _replay(m, [m.id("A"), m.id("B")], res.moves) == [m.id("B"), m.id("A")]


@settings(max_examples=12, deadline=None)
@given(st.integers(0, 6))
def test_a_swap_d_hops_back_costs_4d_plus_4_items(d: int) -> None:
    """A — J(+P) — C1 … Cd — B, two agents trading A and B: agent 0 stops next to B (a dead end,
    its partner cannot be pushed out), the pair backs up d hops to J (the only vertex of degree 3),
    swaps there (6 moves) and replays: 2·ℓ + 4d + 4 moves in all, one swap."""
    corr = [f"C{k}" for k in range(1, d + 1)]
    chain = ["J", *corr, "B"]
    m = TopoMap.build(
        "dead_end",
        [Node("A", T), Node("J", Q), Node("P", S), *(Node(c, Q) for c in corr), Node("B", T)],
        [Segment("A", "J", 1, 1), Segment("J", "P", 1, 1)]
        + [Segment(a, b, 1, 1) for a, b in itertools.pairwise(chain)],
    )
    ell = d + 2
    res = push_and_swap(m, [m.id("A"), m.id("B")], [m.id("B"), m.id("A")])
    assert res.success and res.swaps == 1
    assert _replay(m, [m.id("A"), m.id("B")], res.moves) == [m.id("B"), m.id("A")]
    assert res.items == 2 * ell + 4 * d + 4


@pytest.mark.parametrize("vehicles", [2, 4, 10])
def test_push_and_swap_on_the_static_map_swaps_once_per_pair_one_hop_back(vehicles: int) -> None:
    """On the Fig. 6 map a terminal hangs two segments off a trunk junction, so every pair's swap
    is one hop back (d = 1): push and swap needs exactly ξ_min + 8 items per pair, whatever the
    pause nodes (no truck is pushed aside on these instances)."""
    m = static_map("npr")
    rng = np.random.default_rng(vehicles)
    for _ in range(5):
        inst = random_instance(m, vehicles, rng)
        xi_min = fleet_items(initial_fleet(m, list(zip(inst.starts, inst.ends))))
        res = push_and_swap(m, inst.starts, inst.ends)
        assert res.success and res.swaps == vehicles // 2
        assert res.items == xi_min + 8 * (vehicles // 2)


# ------------------------------------------------------------------------------ dynamic
def test_timeline() -> None:
    m = corridor()
    arr, dep = timeline(m, [m.id("A"), m.id("X"), m.id("P")], [5.0, 0.0, 0.0], 1.0)
    assert arr == [1.0, 16.0, 19.0] and dep == [6.0, 16.0, math.inf]


def _small_dynamic(vehicles: int, hours: float = 1.0, seed: int = 4) -> DynamicPlanner:
    cfg = DynamicConfig(
        vehicles,
        duration_s=hours * 3600,
        ga=GAParams(budget_s=60, max_generations=120),
        seed=seed,
    )
    return DynamicPlanner(mine_map(), cfg)


def assert_causal(
    tmap: TopoMap,
    t_done: float,
    before: FleetMission,
    after: FleetMission,
    changed: set[int],
) -> None:
    """No item starting before ``t_done`` changed; changed missions depart after ``t_done``."""
    for k, (old, new) in enumerate(zip(before, after, strict=True)):
        _, dep = timeline(tmap, new.nodes.tolist(), list(new.waits), new.t0)
        if k in changed and new.head == 0:
            assert new.nodes[0] == old.end and dep[0] >= t_done - 1e-9
            continue
        old_arr, _ = timeline(tmap, old.nodes.tolist(), list(old.waits), old.t0)
        started = [i for i in range(old.items) if old_arr[i] < t_done]
        keep = new.head if k in changed else len(started)
        assert new.t0 == old.t0
        assert new.nodes[: keep + 1].tolist() == old.nodes[: keep + 1].tolist()
        assert new.waits[:keep].tolist() == old.waits[:keep].tolist()
        if k in changed:
            assert dep[new.head] >= t_done - 1e-9


def test_dynamic_replanning_is_causal() -> None:
    """No plan changes an item that starts before its optimisation ends; new missions depart after."""
    planner = _small_dynamic(3)
    checks: list[int] = []

    def check(t_done: float, before, after, changed) -> None:  # type: ignore[no-untyped-def]
        assert_causal(planner.tmap, t_done, before, after, changed)
        checks.append(len(changed))

    planner.on_adopt = check
    res = planner.run()
    assert len(checks) >= 6 and res.traversals_per_vehicle > 0
    assert res.optimisations == len(checks) + res.failures


def test_executed_dynamic_plan_is_collision_free() -> None:
    res = _small_dynamic(3, hours=1.0, seed=7).run()
    tracks = executed_tracks(res)
    conflicts, _ = evaluate_reference(mine_map(), tracks)
    assert conflicts == []
    assert 0 <= res.idle_terminal < 1 and 0 <= res.idle_pause < 1


def test_settle_shortens_a_needed_wait_to_the_shortest_feasible_one() -> None:
    """V0 drives B → X → A (at X from 20 s); V1 waits at P for it. Any wait < 6 s collides (V1
    would be on X → B while V0 is on B → X, or at X within δ = 2 s of V0); settling turns V1's
    40 s into 6 s, and the plan stays collision-free and ends earlier."""
    m = corridor()
    f = fleet(m, (["B", "X", "A"], [0, 0, 0]), (["A", "X", "P", "X", "B"], [0, 0, 40.0, 0, 0]))
    ev = evaluator(m, xi_min=4)
    assert evaluate_reference(m, f)[0] == []
    out = settle_waits(f, ev)
    assert 6.0 <= out[1].waits[2] <= 6.05
    assert evaluate_reference(m, out)[0] == []
    assert ev.evaluate(out).duration < ev.evaluate(f).duration
    assert ev(out) >= ev(f)


def test_settle_removes_idle_stops_of_trucks_that_do_not_finish_last() -> None:
    """A truck's stop that does not decide when the last truck arrives costs nothing under eq. 2
    (a plateau of the score); settling takes it to its lower bound (min_wait for the first free
    item) and leaves the score as it was."""
    m = mine_map()
    far = make_mission(m, m.path(m.id("O"), m.id("L3n")), t0=0.0)  # ~440 s, finishes last
    short = make_mission(
        m, m.path(m.id("L1n"), m.id("L1s")), [50.0, 0.0, 0.0], t0=0.0, min_wait=20.0
    )
    ev = Evaluator(m, fleet_items((far, short)), beta=1e-6, t_ref=0.0)
    before = ev.evaluate((far, short))
    assert before.feasible
    out = settle_waits((far, short), ev)
    assert out[1].waits[0] == pytest.approx(20.0)  # its lower bound, not 0
    after = ev.evaluate(out)
    assert after.feasible and after.score == pytest.approx(before.score)
    # an infeasible plan is left alone
    clash = fleet(corridor(), (["A", "X", "B"], [0, 0, 0]), (["B", "X", "A"], [0, 0, 0]))
    assert settle_waits(clash, evaluator(corridor())) == clash


def test_dynamic_needs_one_offloading_site() -> None:
    with pytest.raises(ValueError, match="exactly one prioritized terminal"):
        DynamicPlanner(static_map("npr"), DynamicConfig(2))
    with pytest.raises(ValueError, match="loading sites"):
        DynamicPlanner(mine_map(), DynamicConfig(7))


@pytest.mark.parametrize("variant", ["npr", "spr"])
def test_ga_solves_ten_vehicle_instances(variant: str) -> None:
    """The hardest §6.1 size: every plan the GA returns is feasible under the reference evaluator
    (a generation cap instead of a time budget keeps this reproducible on a busy machine)."""
    tmap = static_map(variant)
    rng = np.random.default_rng(10)
    for k in range(5):
        inst = random_instance(tmap, 10, rng)
        run = plan_static(
            tmap, inst, GAParams(max_generations=1500, budget_s=600), np.random.default_rng(k)
        )
        assert run.result.feasible and run.result.first_feasible_generation is not None
        assert evaluate_reference(tmap, run.result.best)[0] == []
        assert run.xi0 <= run.result.evaluation.items
