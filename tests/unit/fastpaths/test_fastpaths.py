"""btmission.fastpaths: every performance shortcut keeps the contract it stands in for.

* the quiet composites tick as py_trees' ``Selector``/``Sequence`` (``memory=False``, the only
  memory btmission's trees use) on a table of small trees: every node's status and current
  child, and every call to a leaf's hooks, tick by tick and across stops;
* what reads a tree's nodes (the ``tree`` events' kinds) sees them as it sees py_trees' own;
* ``recorder`` builds records equal to the dataclass's own and hands the class itself back for
  every dataclass whose ``__init__`` does more than store its fields;
* the shortcuts stay in one place.
"""

from __future__ import annotations

import dataclasses
import pickle
import re
from pathlib import Path
from typing import Any, ClassVar

import py_trees
import pytest
from py_trees.common import Status

from btmission.fastpaths.records import record, recorder
from btmission.fastpaths.ticks import QuietSelector, QuietSequence, tick_behaviour
from btmission.runtime.leaves import GuardedLeaf
from btmission.runtime.treestatus import StatusChanges, TreeStatusLogger, node_kind

ROOT = Path(__file__).resolve().parents[3]
_LETTER = {"S": Status.SUCCESS, "F": Status.FAILURE, "R": Status.RUNNING}


# ---------------------------------------------------------------- the composites, tick by tick
def _leaf(
    kind: str, name: str, script: str, log: list[tuple[str, ...]]
) -> py_trees.behaviour.Behaviour:
    """A leaf whose update returns ``script``'s statuses in turn (S, F, R; the last repeats) and
    that logs its hooks: a plain py_trees ``Behaviour`` ("py") or the runtime's ``GuardedLeaf``
    ("guarded", ticked by ``tick_now``)."""
    base: Any = GuardedLeaf if kind == "guarded" else py_trees.behaviour.Behaviour

    class Scripted(base):  # type: ignore[misc]
        calls = 0

        def initialise(self) -> None:
            log.append(("initialise", name))

        def update(self) -> Status:
            status = _LETTER[script[min(self.calls, len(script) - 1)]]
            self.calls += 1
            log.append(("update", name, status.value))
            return status

        def terminate(self, new_status: Status) -> None:
            log.append(("terminate", name, new_status.value))

    return Scripted(name=name)  # type: ignore[no-any-return]


Spec = tuple[str, str, list[Any]] | tuple[str, str]
"""``("sel" | "seq", name, [children])`` or ``(leaf name, script)``."""


def _build(spec: Any, composites: str, leaves: str, log: list[tuple[str, ...]]) -> Any:
    if spec[0] in ("sel", "seq"):
        kind, name, kids = spec
        children = [_build(k, composites, leaves, log) for k in kids]
        if composites == "py_trees":
            cls: Any = (
                py_trees.composites.Selector if kind == "sel" else py_trees.composites.Sequence
            )
        else:
            cls = QuietSelector if kind == "sel" else QuietSequence
        return cls(name, memory=False, children=children)
    name, script = spec
    return _leaf(leaves, name, script, log)


def _state(root: Any) -> list[tuple[str, str, str | None]]:
    return [
        (b.name, b.status.value, getattr(getattr(b, "current_child", None), "name", None))
        for b in root.iterate()
    ]


def _statuses(root: Any) -> dict[str, str]:
    return {b.name: b.status.value[0] for b in root.iterate()}


CASES: dict[str, tuple[Spec, int, set[int]]] = {
    # name: (tree, ticks, ticks after which the root is stopped with INVALID)
    "selector: a higher priority succeeds and interrupts the running one": (
        ("sel", "root", [("A", "FFS"), ("B", "R")]),
        4,
        set(),
    ),
    "selector: running, then success, then the first again": (
        ("sel", "root", [("A", "FFSF"), ("B", "RSRR")]),
        5,
        set(),
    ),
    "selector: all fail": (("sel", "root", [("A", "F"), ("B", "F"), ("C", "F")]), 2, set()),
    "selector: no children": (("sel", "root", []), 2, set()),
    "sequence: a guard fails under a running action": (
        ("seq", "root", [("A", "SSF"), ("B", "R")]),
        4,
        set(),
    ),
    "sequence: runs through, then restarts": (
        ("seq", "root", [("A", "S"), ("B", "RS"), ("C", "SR")]),
        5,
        set(),
    ),
    "sequence: no children": (("seq", "root", []), 2, set()),
    "PPA: fallback(condition, sequence(guard, action)) stopped while running": (
        ("sel", "goal", [("done", "FFFFS"), ("seq", "do", [("pre", "SSFSS"), ("act", "RRRR")])]),
        6,
        {2},
    ),
    "nested: a selector of sequences, interrupts both ways": (
        (
            "sel",
            "root",
            [
                ("seq", "first", [("a1", "FSSF"), ("a2", "RRSR")]),
                ("seq", "second", [("b1", "SSSSS"), ("b2", "RRRS")]),
                ("c", "RF"),
            ],
        ),
        7,
        {4},
    ),
}
"""A table of child status sequences (module docstring)."""


@pytest.mark.parametrize("leaves", ["py", "guarded"])
@pytest.mark.parametrize("case", list(CASES))
def test_the_quiet_composites_tick_as_py_trees_selector_and_sequence(
    case: str, leaves: str
) -> None:
    """Tick by tick (and across a stop), the same statuses, current children and leaf hook
    calls under btmission's composites as under py_trees' ``Selector``/``Sequence``
    (``memory=False``), with py_trees leaves and with the runtime's lean ones."""
    spec, ticks, stops = CASES[case]
    ref_log: list[tuple[str, ...]] = []
    new_log: list[tuple[str, ...]] = []
    ref = _build(spec, "py_trees", "py", ref_log)
    new = _build(spec, "quiet", leaves, new_log)
    for t in range(ticks):
        ref.tick_once()
        tick_behaviour(new)
        assert _state(new) == _state(ref), f"tick {t}"
        assert new_log == ref_log, f"tick {t}"
        assert new.feedback_message == ref.feedback_message == ""
        if t in stops:
            ref.stop(Status.INVALID)
            new.stop(Status.INVALID)
            assert _state(new) == _state(ref) and new_log == ref_log, f"stop after tick {t}"


def test_the_table_pins_py_trees_semantics() -> None:
    """What the table's first cases do, written out (so a change in py_trees shows here too):
    a selector's success stops the lower priority that was running; a sequence's failing guard
    stops the action after it."""
    expected = {
        "selector: a higher priority succeeds and interrupts the running one": [
            {"root": "R", "A": "F", "B": "R"},
            {"root": "R", "A": "F", "B": "R"},
            {"root": "S", "A": "S", "B": "I"},
            {"root": "S", "A": "S", "B": "I"},
        ],
        "sequence: a guard fails under a running action": [
            {"root": "R", "A": "S", "B": "R"},
            {"root": "R", "A": "S", "B": "R"},
            {"root": "F", "A": "F", "B": "I"},
            {"root": "F", "A": "F", "B": "I"},
        ],
    }
    for case, table in expected.items():
        spec, ticks, _ = CASES[case]
        for impl in ("py_trees", "quiet"):
            log: list[tuple[str, ...]] = []
            root = _build(spec, impl, "py", log)
            seen = []
            for _ in range(ticks):
                tick_behaviour(root)
                seen.append(_statuses(root))
            assert seen == table, (case, impl)
            assert ("terminate", "B", "INVALID") in log


def test_the_quiet_composites_are_memoryless_py_trees_composites() -> None:
    """btmission's composites derive from py_trees' public ``Composite`` (not from its
    ``Selector``/``Sequence``), are memoryless — ``memory=True`` is refused, not ignored — and
    their ``tick()`` yields only themselves, once; ``iterator`` is a fresh tick generator."""
    log: list[tuple[str, ...]] = []
    sel = QuietSelector("sel", memory=False, children=[_leaf("py", "A", "R", log)])
    seq = QuietSequence("seq", children=[_leaf("guarded", "B", "S", log)])
    for composite in (sel, seq):
        assert isinstance(composite, py_trees.composites.Composite)
        assert not isinstance(
            composite, (py_trees.composites.Selector, py_trees.composites.Sequence)
        )
        assert composite.memory is False
    assert [b.name for b in sel.tick()] == ["sel"] and sel.status is Status.RUNNING
    assert [b.name for b in seq.iterator] == ["seq"] and seq.status is Status.SUCCESS
    for cls in (QuietSelector, QuietSequence):
        with pytest.raises(ValueError, match="memoryless"):
            cls("m", memory=True)


def _tree_events(spec: Any, impl: str, ticks: int) -> tuple[Any, ...]:
    """The ``tree`` events (changes, nodes) of ``ticks`` ticks of ``spec`` built of ``impl``'s
    composites, the node list and every node's kind."""
    log: list[tuple[str, ...]] = []
    root = _build(spec, impl, "py", log)
    tree = py_trees.trees.BehaviourTree(root)
    events: list[tuple[list[list[Any]], list[list[Any]] | None]] = []

    def publish(changes: list[list[Any]], nodes: list[list[Any]] | None) -> None:
        events.append((changes, nodes))

    logger = TreeStatusLogger(tree, publish, lambda: 0.0, 0.0)
    for _ in range(ticks):
        tree.tick()
    assert isinstance(logger.visitor, StatusChanges)
    return logger.nodes, events, [node_kind(b) for b in root.iterate()]


def test_readers_of_the_tree_see_the_quiet_composites_as_py_trees_ones() -> None:
    """The ``tree`` events' node list (name, parent, kind) and status changes are the same for a
    tree of quiet composites as for the same tree of py_trees' composites."""
    spec = CASES["nested: a selector of sequences, interrupts both ways"][0]
    ref, new = _tree_events(spec, "py_trees", 6), _tree_events(spec, "quiet", 6)
    assert new == ref
    assert [n[2] for n in new[0][:2]] == ["fallback", "sequence"] and len(new[1]) > 1


# ---------------------------------------------------------------- the record builder
@dataclasses.dataclass(frozen=True)
class _Pair:
    a: int
    b: str = "x"


def test_a_record_is_the_dataclass_it_stands_for() -> None:
    new = recorder(_Pair)
    assert recorder(_Pair) is new and new.__qualname__ == "recorder(_Pair)"
    got, ref = new(a=1, b="y"), _Pair(1, "y")
    assert type(got) is _Pair and got == ref and hash(got) == hash(ref) and repr(got) == repr(ref)
    assert vars(got) == vars(ref) and list(vars(got)) == ["a", "b"]
    assert pickle.loads(pickle.dumps(got)) == ref
    assert dataclasses.replace(got, a=2) == _Pair(2, "y") and dataclasses.asdict(got) == {
        "a": 1,
        "b": "y",
    }
    with pytest.raises(dataclasses.FrozenInstanceError):
        got.a = 3  # type: ignore[misc]
    with pytest.raises(TypeError, match="'b'"):
        new(a=1)  # every field by name, its default too
    with pytest.raises(TypeError, match="'c'"):
        new(a=1, b="y", c=2)
    with pytest.raises(TypeError):
        new(1, "y")  # keywords only
    assert record(_Pair, a=5, b="z") == _Pair(5, "z")


def test_a_class_whose_init_does_more_than_store_its_fields_builds_itself() -> None:
    """The fallback: ``recorder(cls) is cls`` for an ``InitVar`` (a parameter that is no field),
    a field out of ``__init__``, a ``__post_init__``, ``slots``, no fields, a class that is no
    dataclass — each found through the public API (``dataclasses.fields``,
    ``inspect.signature``), no private attribute of the dataclasses module."""

    @dataclasses.dataclass(frozen=True)
    class WithInitVar:
        a: int
        scale: dataclasses.InitVar[int] = 1

    @dataclasses.dataclass(frozen=True)
    class OutOfInit:
        a: int
        b: int = dataclasses.field(init=False, default=0)

    @dataclasses.dataclass(frozen=True)
    class Checked:
        a: int

        def __post_init__(self) -> None:
            if self.a < 0:
                raise ValueError("negative")

    @dataclasses.dataclass(frozen=True, slots=True)
    class Slotted:
        a: int

    @dataclasses.dataclass(frozen=True)
    class Empty:
        pass

    class Plain:
        def __init__(self, a: int) -> None:
            self.a = a

    for cls in (WithInitVar, OutOfInit, Checked, Slotted, Empty, Plain):
        assert recorder(cls) is cls, cls.__name__
    with pytest.raises(ValueError, match="negative"):
        recorder(Checked)(a=-1)
    assert recorder(WithInitVar)(a=1, scale=2) == WithInitVar(1)


def test_the_record_builder_of_a_plain_dataclass_and_a_class_var() -> None:
    """A mutable dataclass is built the same way (its ``__init__`` only stores too); a
    ``ClassVar`` is no field, so no argument (``ClassVar`` is imported at the module's top:
    under postponed annotations, that is how dataclasses recognises it)."""

    @dataclasses.dataclass
    class Counter:
        n: int
        limit: ClassVar[int] = 3

    built = recorder(Counter)(n=2)
    assert built == Counter(2) and built is not Counter(2) and vars(built) == {"n": 2}
    built.n = 4
    assert built.n == 4


def test_the_records_of_the_hot_paths_get_the_fast_builder() -> None:
    """The classes the run builds by the thousand are built by the generated builder, not by the
    fallback (a change to one of them that made it fall back would silently make building it
    about four times slower again), and the builder is btmission.types' too."""
    from btmission.allocation.auction import Bid, PoolTask
    from btmission.allocation.bidder import AgentState
    from btmission.links.bus import Prediction
    from btmission.types import recorder as types_recorder
    from btmission.vehicles.base import Telemetry

    assert types_recorder is recorder
    for cls in (Telemetry, Prediction, AgentState, Bid, PoolTask):
        assert recorder(cls) is not cls, cls.__name__


# ---------------------------------------------------------------- one place
def test_the_shortcuts_stay_in_btmission_fastpaths() -> None:
    """Generated code, the dataclasses module's private names and subclasses of py_trees'
    Selector/Sequence appear nowhere in the package outside :mod:`btmission.fastpaths`."""
    patterns = {
        "exec": re.compile(r"\bexec\("),
        "dataclasses' private names": re.compile(r"dataclasses\._"),
        "a subclass of py_trees' Selector/Sequence": re.compile(
            r"^class \w+\([^)]*composites\.(Selector|Sequence)\b", re.M
        ),
    }
    found = []
    for path in sorted((ROOT / "btmission").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith("btmission/fastpaths/"):
            continue
        text = path.read_text(encoding="utf-8")
        found += [f"{rel}: {what}" for what, pattern in patterns.items() if pattern.search(text)]
    assert found == []
    fastpaths = (ROOT / "btmission" / "fastpaths" / "records.py").read_text(encoding="utf-8")
    assert len(re.findall(r"\bexec\(", fastpaths)) == 1
