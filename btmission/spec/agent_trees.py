"""The checks a mission's agent trees must pass, when the mission is loaded.

For each library the agents use, every task type's tree and the default behaviour's are
synthesised (:func:`btmission.synthesis.mission_tree.build_mission_tree`); what fails is reported
at the task type's (or the default behaviour's) line: a goal no agent's library can achieve, a
commit condition that never occurs in the tree (seed 003: the agent could never commit), a
default goal that uses parameters nobody gives it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from btmission.diagnostics import Diagnostic, Severity
from btmission.spec.source import format_path
from btmission.synthesis.mission_tree import build_mission_tree, can_do, contains_condition

if TYPE_CHECKING:
    from btmission.spec.mission import Mission
    from btmission.spec.source import Source


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
