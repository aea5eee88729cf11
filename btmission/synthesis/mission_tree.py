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
type's subtree, otherwise the agent could never commit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from btmission.diagnostics import Diagnostic, Severity
from btmission.spec.library import Atom, Library
from btmission.synthesis.backchain import Synthesis, Synthesizer
from btmission.synthesis.tree import Arg, Kind, Node, Role, walk

if TYPE_CHECKING:
    from btmission.spec.mission import Mission
    from btmission.spec.source import Source


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
    mission: Mission,
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


def check_agent_trees(mission: Mission, src: Source) -> list[Diagnostic]:
    """Synthesise every (library, task type) pair and the default behaviour; report what fails."""
    out: list[Diagnostic] = []
    by_lib: dict[str, list[str]] = {}
    for a in mission.agents:
        by_lib.setdefault(a.library, []).append(a.id)
    doable: dict[str, list[str]] = {t: [] for t in mission.task_types}
    reported: set[tuple[str, str]] = set()

    def add(
        path: tuple[str | int, ...], message: str, code: str, sev: Severity = Severity.ERROR
    ) -> None:
        from btmission.spec.source import format_path

        key = (format_path(path), message)
        if key not in reported:
            reported.add(key)
            out.append(Diagnostic(sev, code, message, format_path(path), src.locate(path)))

    for ref, agent_ids in by_lib.items():
        loaded = mission.libraries.get(ref)
        if loaded is None:
            continue
        lib = loaded.library
        mt = build_mission_tree(mission, agent_ids[0])
        who = f"{', '.join(agent_ids)} (library {lib.name})"
        for tname, why in mt.skipped.items():
            add(
                ("task_types", tname, "goal"),
                f"agents {who} cannot do this task type: {why}",
                "cannot-do",
                Severity.INFO,
            )
        for tname, s in mt.branches.items():
            path: tuple[str | int, ...] = (
                ("default_behavior", "goal")
                if tname == "default"
                else ("task_types", tname, "goal")
            )
            for d in s.diagnostics:
                if d.severity is Severity.INFO:
                    continue
                add(path, f"for agents {who}: {d.message} [{d.where}]", d.code, d.severity)
            if tname == "default":
                free = list(s.inputs)
                if free:
                    add(
                        path,
                        f"the default behaviour has no task, but its goal uses {', '.join(free)}, "
                        f"which library '{lib.name}' does not declare as variables",
                        "undefined-parameter",
                    )
                continue
            doable[tname].extend(agent_ids)
            tt = mission.task_types[tname]
            if tt.commit_after is not None and not contains_condition(s.tree, tt.commit_after):
                add(
                    ("task_types", tname, "commit_after"),
                    f"'{tt.commit_after}' never occurs in the tree agents {who} synthesise for this type, "
                    "so they could never commit",
                    "commit-unreachable",
                )
        db = mission.default_behavior
        if db is not None and db.goals and can_do(lib, db.goals) is not None:
            add(
                ("default_behavior", "goal"),
                f"library '{lib.name}' (agents {', '.join(agent_ids)}) has no condition '{can_do(lib, db.goals)}'",
                "cannot-do",
            )
    for tname, agents in doable.items():
        if not agents:
            add(
                ("task_types", tname, "goal"),
                "no agent's library can achieve this goal",
                "no-capable-agent",
            )
    return out
