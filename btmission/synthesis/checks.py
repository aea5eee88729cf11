"""Whole-library checks (``btmission library check``), DESIGN.md §4.2.

Beyond the reference checks done while loading (undefined conditions and parameters, wrong argument
lists, unbound parameters), the checker back-chains

* every goal the library declares (``goals:``),
* every postcondition and every precondition of every action, as written (the action's own
  parameter names as symbols),

with one memoising :class:`Synthesizer`, so each ground condition is expanded once and the check is
linear in the library size. It reports cycles (errors, with the chain of names), conditions that
are needed but that no action achieves (*assumed*), ambiguous achievers, and actions that can
never be used: with no postcondition, always beaten by a cheaper achiever, or (when the library
declares goals) not used by any goal. ``strict`` turns every warning into an error.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from btmission.diagnostics import Diagnostic, Severity, errors, promote
from btmission.spec.library import Library
from btmission.synthesis.backchain import Synthesizer
from btmission.synthesis.tree import Kind, Node, Role, walk_distinct


@dataclass
class CheckReport:
    library: Library
    diagnostics: list[Diagnostic]

    @property
    def ok(self) -> bool:
        return not errors(self.diagnostics)

    def counts(self) -> dict[str, int]:
        out = {s.value: 0 for s in Severity}
        for d in self.diagnostics:
            out[d.severity.value] += 1
        return out


def check_library(
    library: Library, load_diagnostics: Sequence[Diagnostic] = (), *, strict: bool = False
) -> CheckReport:
    """Run every check on ``library``; ``load_diagnostics`` are the findings from loading it."""
    diags: list[Diagnostic] = list(load_diagnostics)
    synth = Synthesizer(library)
    goal_trees_used: set[str] = set()
    for goal, where in zip(library.goals, library.goal_where):
        tree = synth.expand(goal, where)
        goal_trees_used.update(n.name for _, n in walk_distinct(tree) if n.kind is Kind.ACTION)
    # every condition as some action achieves it (its postconditions as written, the action's
    # own parameters as symbols), and every action's preconditions as written
    for act in library.actions.values():
        for p in act.post:
            synth.expand(p, act.where)
        for p, w in zip(act.pre, act.pre_where):
            synth.expand(p, w)
    everything = Node(Kind.SEQUENCE, "all", (), synth.expansions(), Role.ACHIEVE)
    res_all = synth.result(everything, (), max_nodes=None)
    diags.extend(res_all.diagnostics)

    if errors(load_diagnostics):
        # items with errors were left out of the model: reachability and use would only add noise
        return CheckReport(library, _sorted(promote(_unique(diags), strict)))

    # actions that back-chaining never picks
    chosen: set[str] = set(res_all.used_actions)
    for act in library.actions.values():
        if not act.post:
            continue  # reported at load time
        if act.name not in chosen and not _ever_best(library, act):
            better = sorted(
                {
                    a.name
                    for p in act.post
                    for a, _ in library.achievers.get(p.name, ())
                    if a is not act
                }
            )
            diags.append(
                Diagnostic(
                    Severity.WARNING,
                    "unreachable-action",
                    f"action '{act.name}' is never chosen: {', '.join(better)} achieve(s) its postconditions "
                    "at lower cost or earlier in the file",
                    f"actions.{act.name}",
                    act.where,
                )
            )
        elif library.goals and act.name not in goal_trees_used:
            diags.append(
                Diagnostic(
                    Severity.WARNING,
                    "unreachable-action",
                    f"action '{act.name}' is not used by any of the library's goals "
                    f"({', '.join(str(g) for g in library.goals)})",
                    f"actions.{act.name}",
                    act.where,
                )
            )
    referenced = {p.name for a in library.actions.values() for p in (*a.pre, *a.post)} | {
        g.name for g in library.goals
    }
    for cname, cond in library.conditions.items():
        if cname not in referenced:
            diags.append(
                Diagnostic(
                    Severity.INFO,
                    "unused-condition",
                    f"condition '{cname}' is declared but no action or goal refers to it",
                    f"conditions.{cname}",
                    cond.where,
                )
            )
    return CheckReport(library, _sorted(promote(_unique(diags), strict)))


def _ever_best(library: Library, act: object) -> bool:
    """Is ``act`` the first-ranked achiever of at least one of its postconditions' names?"""
    for lst in library.achievers.values():
        if lst and lst[0][0] is act:
            return True
    return False


def _unique(diags: list[Diagnostic]) -> list[Diagnostic]:
    seen: set[tuple[str, str, str]] = set()
    out = []
    for d in diags:
        key = (d.code, d.item, d.message)
        if key not in seen:
            seen.add(key)
            out.append(d)
    return out


_ORDER = {Severity.ERROR: 0, Severity.WARNING: 1, Severity.INFO: 2}


def _sorted(diags: list[Diagnostic]) -> list[Diagnostic]:
    return sorted(diags, key=lambda d: (_ORDER[d.severity], d.where.line or 0, d.where.col or 0))
