"""Mission-scale budgets (:mod:`btmission.limits`), checked on the raw data of a mission file
before the schema and the (slow, per-agent) compilation run: the number of agents and tasks, and
the smallest simulator step."""

from __future__ import annotations

from btmission import limits
from btmission.diagnostics import Diagnostic, SpecError
from btmission.spec.source import Source


def check_mission_scale(src: Source) -> None:
    """Raise :class:`SpecError` when the mission in ``src`` exceeds a mission-scale budget."""
    data = src.data
    if not isinstance(data, dict):
        return  # the schema check says what a mission file must be
    problems: list[Diagnostic] = []
    for key, budget in (("agents", limits.MAX_AGENTS), ("tasks", limits.MAX_TASKS)):
        items = data.get(key)
        if isinstance(items, list) and len(items) > budget.limit:
            message = budget.exceeded(f"the number of {key}", len(items))
            problems.append(src.diag((key,), message, "too-many", key=True))
    runtime = data.get("runtime")
    sim = runtime.get("sim") if isinstance(runtime, dict) else None
    step = sim.get("step_s") if isinstance(sim, dict) else None
    if isinstance(step, (int, float)) and not isinstance(step, bool):
        least = limits.MIN_STEP_S
        if 0 < step < least.value:  # (≤ 0 and non-numbers are the schema's to report)
            message = (
                f"step_s is {step:g} s, below the smallest step {least.show()} s "
                f"(set {least.env} to change it)"
            )
            problems.append(src.diag(("runtime", "sim", "step_s"), message, "too-small"))
    if problems:
        raise SpecError(problems)
