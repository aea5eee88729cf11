"""The synthesis benchmark's generators and runner (small sizes; no timing assertions)."""

from __future__ import annotations

import csv
from collections.abc import Callable
from pathlib import Path

import pytest

from btmission.bench.synth import (
    CSV_HEADER,
    FANIN_SUB_EVERY,
    Measurement,
    _csv_row,
    _md_cells,
    chain_library,
    describe_load,
    diamond_library,
    environment,
    fanin_library,
    header_lines,
    measure,
    run_synth_benchmark,
)
from btmission.diagnostics import Severity, errors
from btmission.spec.library import Library, LibrarySpec, compile_library
from btmission.synthesis.backchain import Synthesis, Synthesizer, parse_goals
from btmission.synthesis.checks import check_library
from btmission.synthesis.tree import Kind, Node, Role, count_nodes, depth, walk


def build(spec: LibrarySpec) -> tuple[Library, Synthesis]:
    lib, diags = compile_library(spec)
    assert not diags, [d.format() for d in diags]
    return lib, Synthesizer(lib).synthesize(parse_goals(spec.goals, lib))


def chain_nodes(n: int) -> int:
    """c1 expands to Fallback(c1, a0) = 3 nodes; every further c{k} adds
    Fallback + condition + Sequence(<c{k-1} subtree>, action) = 4 nodes."""
    return 3 + 4 * (n - 1)


@pytest.mark.parametrize("n", [1, 2, 3, 10, 50])
def test_chain_tree_has_exact_size_and_linear_depth(n: int) -> None:
    lib, s = build(chain_library(n))
    assert len(lib.actions) == n
    assert s.diagnostics == [] and s.ok
    assert s.size == chain_nodes(n) == 4 * n - 1
    assert count_nodes(s.tree) == s.size
    assert depth(s.tree) == 2 * n
    assert s.used_actions == {f"a{i}" for i in range(n)}
    assert s.inputs == ("x",)


def test_chain_structure_binds_the_parameter_at_every_step() -> None:
    _, s = build(chain_library(3))
    # Fallback(c3(x), Sequence(Fallback(c2(x), Sequence(Fallback(c1(x), a0(x)), a1(x))), a2(x)))
    root = s.tree
    assert (root.kind, root.name, root.role) == (Kind.FALLBACK, "c3(x)", Role.GOAL)
    cond, seq = root.children
    assert (cond.kind, cond.label) == (Kind.CONDITION, "c3(x)")
    assert seq.kind is Kind.SEQUENCE and [c.label for c in seq.children] == ["c2(x)", "a2(x)"]
    inner = seq.children[0].children[1]
    assert [c.label for c in inner.children] == ["c1(x)", "a1(x)"]
    assert [c.label for c in inner.children[0].children] == ["c1(x)", "a0(x)"]
    leaves = [n for _, n in walk(root) if n.is_leaf]
    assert all([(a.param, a.value) for a in leaf.args] == [("x", "x")] for leaf in leaves)


def test_chain_depth_grows_linearly() -> None:
    depths = [build(chain_library(n))[1] for n in (5, 10, 20, 40)]
    assert [depth(s.tree) for s in depths] == [10, 20, 40, 80]


@pytest.mark.parametrize("n", [1, 4, 5, 17, 50])
def test_fanin_root_sequence_has_n_plus_one_children(n: int) -> None:
    lib, s = build(fanin_library(n))
    subs = len(range(1, n + 1, FANIN_SUB_EVERY))
    assert len(lib.actions) == n + subs + 1
    assert s.diagnostics == []
    root = s.tree
    assert root.kind is Kind.FALLBACK and root.name == "top(x)"
    seq = root.children[1]
    assert seq.kind is Kind.SEQUENCE and len(seq.children) == n + 1
    assert [c.name for c in seq.children[:-1]] == [f"p{i}(x)" for i in range(1, n + 1)]
    assert seq.children[-1].label == "finish(x)"
    # Fallback(p_i, a_i) = 3 nodes, or 7 with its own Fallback(q_i, sub_i) in a sequence
    assert s.size == 4 + 3 * n + 4 * subs
    assert depth(s.tree) == 6  # wide and shallow, whatever n


def test_fanin_subprecondition_expansion() -> None:
    _, s = build(fanin_library(2))
    first, second = s.tree.children[1].children[:2]
    assert [c.label for c in second.children] == ["p2(x)", "ach2(x)"]
    seq = first.children[1]
    assert seq.kind is Kind.SEQUENCE
    assert [c.label for c in seq.children] == ["q1", "ach1(x)"]
    assert [c.label for c in seq.children[0].children] == ["q1", "sub1"]


def test_diamond_shares_the_common_precondition() -> None:
    lib, s = build(diamond_library(10))
    assert len(lib.actions) == 10 and s.diagnostics == []
    branches = s.tree.children[1].children[:-1]
    assert len(branches) == 7
    ready = {id(b.children[1].children[0]) for b in branches}
    assert len(ready) == 1  # memoised: one subtree object for every occurrence
    assert s.size == 11 * 7 + 4
    assert depth(s.tree) == 8


@pytest.mark.parametrize("make", [chain_library, fanin_library, diamond_library])
def test_generated_libraries_pass_the_checks(make: Callable[[int], LibrarySpec]) -> None:
    spec = make(20)
    lib, diags = compile_library(spec)
    report = check_library(lib, diags)
    assert report.ok and errors(report.diagnostics) == []
    assert not [d for d in report.diagnostics if d.severity is Severity.WARNING]


def test_generators_reject_empty_sizes() -> None:
    with pytest.raises(ValueError):
        chain_library(0)
    with pytest.raises(ValueError):
        fanin_library(0)


def test_measure_reports_sizes_and_times() -> None:
    m = measure(chain_library(12), "c12(x)", repeat=2, shape="chain", size=12)
    assert (m.shape, m.size, m.actions, m.conditions) == ("chain", 12, 12, 12)
    assert (m.tree_nodes, m.depth, m.errors, m.repeat) == (47, 24, 0, 2)
    assert min(m.compile_ms, m.synth_ms, m.check_ms) > 0
    assert m.total_ms == m.synth_ms + m.check_ms
    assert m.target_met is None  # the target only applies to size 1,000


def test_tree_depth_of_a_leaf() -> None:
    assert depth(Node(Kind.CONDITION, "c")) == 1


def test_run_writes_markdown_and_csv(tmp_path: Path) -> None:
    results = run_synth_benchmark([10], repeat=1, out_dir=tmp_path, echo=lambda *_: None)
    assert [(m.shape, m.size) for m in results] == [("chain", 10), ("fanin", 10)]

    with (tmp_path / "synth.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == CSV_HEADER
    assert rows[0][:6] == ["shape", "size", "actions", "conditions", "tree_nodes", "depth"]
    assert len(rows) == 3
    assert all(len(r) == len(CSV_HEADER) for r in rows)
    chain, fanin = (dict(zip(rows[0], r, strict=True)) for r in rows[1:])
    shown = ("shape", "size", "actions", "tree_nodes", "depth")
    assert tuple(chain[k] for k in shown) == ("chain", "10", "10", "39", "20")
    assert tuple(fanin[k] for k in shown) == ("fanin", "10", "14", "46", "6")
    assert chain["target_met"] == "" and chain["repeat"] == "1"
    assert float(chain["synth_check_ms"]) == pytest.approx(
        float(chain["synth_ms"]) + float(chain["check_ms"]), abs=0.002
    )

    md = (tmp_path / "synth.md").read_text()
    for key in ("date:", "machine:", "CPU(s)", "load: ", "Python:", "btmission:"):
        assert key in md
    assert "noisy" not in md  # no fixed claim: the load line is measured
    assert "| shape | size | actions | tree nodes | depth |" in md
    assert "| chain | 10 | 10 | 39 | 20 |" in md
    assert "| fanin | 10 | 14 | 46 | 6 |" in md


@pytest.mark.parametrize(
    ("start", "end", "own", "other", "quiet"),
    [
        (0.05, 1.02, 1.0, 0.05, True),  # only the benchmark ran
        (0.10, 0.60, 1.0, 0.10, True),  # a short run: the 1-min average had not caught up
        (0.70, 1.10, 1.0, 0.70, False),  # busy when it started
        (0.10, 3.10, 1.0, 2.10, False),  # two other jobs joined during the run
        (0.20, 2.10, 2.0, 0.20, True),  # the benchmark itself used both cores
    ],
)
def test_describe_load_subtracts_the_benchmark_itself(
    start: float, end: float, own: float, other: float, quiet: bool
) -> None:
    note = describe_load(start, end, own)
    assert f"{start:.2f} at start, {end:.2f} at end" in note
    assert f"used {own:.2f} CPU" in note
    assert f"other work ≈ {other:.2f}" in note
    assert ("quiet" in note) is quiet
    assert ("busy" in note) is not quiet


def test_header_lines_measure_the_load_or_say_it_is_unknown() -> None:
    lines = header_lines(environment())
    assert [line.split(":")[0] for line in lines] == [
        "- date",
        "- machine",
        "- load",
        "- Python",
        "- btmission",
    ]
    assert "1-min load average" in lines[2]
    bare = {"date": "d", "machine": "m", "cpus": "2", "python": "p", "btmission": "v"}
    assert "unknown" in header_lines(bare)[2]


def test_run_echoes_the_table_as_it_goes(tmp_path: Path) -> None:
    out: list[str] = []
    run_synth_benchmark(
        [3, 5],
        repeat=1,
        out_dir=tmp_path / "new" / "dir",
        echo=out.append,
        shapes=("chain", "diamond"),
    )
    assert out[2].startswith("| shape | size |") and out[3].startswith("| --- | ---: |")
    rows = [line for line in out if line.startswith(("| chain", "| diamond"))]
    assert [r.split(" | ")[:3] for r in rows] == [
        ["| chain", "3", "3"],
        ["| chain", "5", "5"],
        ["| diamond", "3", "4"],
        ["| diamond", "5", "5"],
    ]
    assert all(r.endswith("| — |") for r in rows)  # the target applies to size 1,000 only
    assert out[-1].startswith("wrote ") and (tmp_path / "new" / "dir" / "synth.md").exists()


def _measurement(size: int, synth_ms: float, check_ms: float) -> Measurement:
    return Measurement(
        "chain", size, size, size, 4 * size - 1, 2 * size, 1.0, synth_ms, check_ms, 1, 0
    )


def test_target_column() -> None:
    assert _measurement(1000, 30.0, 40.0).target_met is True
    assert _measurement(1000, 60.0, 40.0).target_met is False  # 100 ms is not < 100 ms
    assert _measurement(999, 1.0, 1.0).target_met is None
    assert _csv_row(_measurement(1000, 30.0, 40.0))[10] == "true"
    assert _md_cells(_measurement(1000, 60.0, 50.0))[-1] == "**no**"
    assert _md_cells(_measurement(1000, 30.0, 40.0))[-1] == "yes"


def test_run_rejects_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="positive"):
        run_synth_benchmark([0], repeat=1, out_dir=tmp_path, echo=lambda *_: None)
    with pytest.raises(ValueError, match="unknown shape"):
        run_synth_benchmark([5], repeat=1, out_dir=tmp_path, echo=lambda *_: None, shapes=("star",))
    assert not (tmp_path / "synth.csv").exists()


def test_benchmarks_collect_only_their_own_garbage() -> None:
    """Inside a benchmark the caller's objects are frozen (collected once, then left out of the
    collections before each timed call), and released after it."""
    import gc

    from btmission.bench.synth import own_heap

    held = [object() for _ in range(1000)]
    with own_heap():
        assert gc.get_freeze_count() >= len(held)
    assert gc.get_freeze_count() == 0
    gc.freeze()  # a caller that freezes objects itself keeps them frozen
    try:
        frozen = gc.get_freeze_count()
        with own_heap():
            pass
        assert gc.get_freeze_count() == frozen
    finally:
        gc.unfreeze()


def test_a_results_page_keeps_the_runs_before_it(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from btmission.bench.synth import write_page

    page = tmp_path / "x.md"
    write_page(page, "# X benchmark\n\n| a |\n| 1 |\n")
    assert page.read_text() == "# X benchmark\n\n| a |\n| 1 |\n"
    write_page(page, "# X benchmark\n\n| a |\n| 2 |\n")
    write_page(page, "# X benchmark\n\n| a |\n| 3 |\n")
    text = page.read_text()
    assert text.startswith("# X benchmark\n\n| a |\n| 3 |\n")
    new, _, older = text.partition("## Earlier runs")
    assert "| 3 |" in new and "| 2 |" not in new
    assert older.index("| 2 |") < older.index("| 1 |")  # newest first, nothing lost
    assert text.count("## Earlier runs") == 1
