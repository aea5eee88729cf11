"""The per-agent mission tree (seed 000 Fig. 7) and the checks a mission's trees must pass.

Fig. 7 switches between a task-specific subtree and a default behaviour; the paper notes it extends
"to include more tasks by adding additional condition nodes to check which task is currently
active". For an agent with library L the tree is::

    ? Fallback  mission(R1)
    ├── → Sequence  task(inspect)            {task_type, commit_after}
    │   ├── task_assigned("inspect")         built-in condition: the auction gave me such a task
    │   └── <back-chained subtree for the type's goal>
    ├── → Sequence  …one branch per task type L can do…
    ├── → Sequence  default                  {idle_timeout_s}
    │   ├── idle_timeout("10")               built-in condition: no task for that long
    │   └── <back-chained subtree for the default goal>  (seed 000 Fig. 9)
    └── wait                                 built-in action: hold position, RUNNING

A multi-stage type's ``commit_after`` condition (seed 003) is recorded on its branch; the runtime
sets k_bt = 0 once that condition has held (eq. 8-10). The commit condition must occur in the
type's subtree, otherwise the agent could never commit
(:func:`btmission.spec.agent_trees.check_agent_trees` checks every agent's trees of a mission).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

from btmission.diagnostics import Diagnostic
from btmission.spec.library import Atom, Library
from btmission.synthesis.backchain import Synthesis, Synthesizer
from btmission.synthesis.tree import Arg, Kind, Node, Role, walk


class TaskTypeModel(Protocol):
    """What a mission's task type gives its branch of the tree."""

    @property
    def goals(self) -> tuple[Atom, ...]: ...

    @property
    def commit_after(self) -> Atom | None: ...


class DefaultModel(Protocol):
    """What a mission's default behaviour gives its branch."""

    @property
    def goals(self) -> tuple[Atom, ...]: ...

    @property
    def idle_timeout_s(self) -> float: ...


class LibraryModel(Protocol):
    @property
    def library(self) -> Library: ...


class MissionModel(Protocol):
    """What the tree needs of a mission (:class:`btmission.spec.mission.Mission` is one):
    synthesis sits below the mission's file model and reads it through this."""

    @property
    def task_types(self) -> Mapping[str, TaskTypeModel]: ...

    @property
    def default_behavior(self) -> DefaultModel | None: ...

    def library_of(self, agent_id: str) -> LibraryModel: ...


def task_assigned(task_type: str) -> Node:
    return Node(
        Kind.CONDITION,
        "task_assigned",
        (Arg("type", task_type, literal=True),),
        (),
        Role.BUILTIN,
        "The agent's current task (from the auction) is of this type",
    )


def idle_timeout(seconds: float) -> Node:
    return Node(
        Kind.CONDITION,
        "idle_timeout",
        (Arg("seconds", f"{seconds:g}", literal=True),),
        (),
        Role.BUILTIN,
        "No task has been assigned for this long",
    )


WAIT = Node(
    Kind.ACTION, "wait", (), (), Role.BUILTIN, "Hold position until something changes (RUNNING)"
)


def can_do(library: Library, goals: Sequence[Atom]) -> str | None:
    """None if ``library`` declares every goal condition, else the first missing name."""
    for g in goals:
        if g.name not in library.conditions:
            return g.name
    return None


def contains_condition(tree: Node, atom: Atom) -> bool:
    for _, n in walk(tree):
        if (
            n.kind is Kind.CONDITION
            and n.name == atom.name
            and tuple(a.value for a in n.args) == atom.args
        ):
            return True
    return False


@dataclass
class MissionTree:
    """An agent's mission tree with the synthesis behind each branch."""

    agent: str
    tree: Node
    branches: dict[str, Synthesis]
    """Task type name (or ``"default"``) → its synthesis."""
    skipped: dict[str, str]
    """Task types this agent cannot do → why."""

    @property
    def diagnostics(self) -> list[Diagnostic]:
        return [d for s in self.branches.values() for d in s.diagnostics]


def build_mission_tree(
    mission: MissionModel,
    agent_id: str,
    task_types: Sequence[str] | None = None,
    *,
    strict: bool = False,
) -> MissionTree:
    """Synthesise ``agent_id``'s Fig. 7 tree for all task types it can do (or only ``task_types``)."""
    lib = mission.library_of(agent_id).library
    synth = Synthesizer(lib)
    names = list(mission.task_types) if task_types is None else list(task_types)
    branches: list[Node] = []
    results: dict[str, Synthesis] = {}
    skipped: dict[str, str] = {}
    for name in names:
        tt = mission.task_types[name]
        missing = can_do(lib, tt.goals)
        if missing:
            skipped[name] = f"library '{lib.name}' has no condition '{missing}'"
            continue
        s = synth.synthesize(tt.goals, strict=strict)
        results[name] = s
        meta = {"task_type": name}
        if tt.commit_after is not None:
            meta["commit_after"] = str(tt.commit_after)
        branches.append(
            Node(
                Kind.SEQUENCE,
                f"task({name})",
                (),
                (task_assigned(name), s.tree),
                Role.TASK,
                "",
                tuple(sorted(meta.items())),
            )
        )
    db = mission.default_behavior
    if db is not None and db.goals and can_do(lib, db.goals) is None:
        s = synth.synthesize(db.goals, strict=strict)
        results["default"] = s
        branches.append(
            Node(
                Kind.SEQUENCE,
                "default",
                (),
                (idle_timeout(db.idle_timeout_s), s.tree),
                Role.DEFAULT,
                "",
                (("idle_timeout_s", f"{db.idle_timeout_s:g}"),),
            )
        )
    root = Node(Kind.FALLBACK, f"mission({agent_id})", (), (*branches, WAIT), Role.MISSION)
    return MissionTree(agent_id, root, results, skipped)
