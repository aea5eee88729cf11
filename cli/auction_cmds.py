"""``btmission auction``: one auction round on a mission file — who gets what, and why."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import click

from btmission.cli.common import NON_NEGATIVE, BadInput, handle_spec_errors, parse_numbers


def _json_cost(v: float) -> float | str | None:
    if math.isnan(v):
        return None
    return "inf" if math.isinf(v) else v


def _cost(v: float) -> str:
    if math.isnan(v):
        return "—"
    return "unreachable" if math.isinf(v) else f"{v:.2f}"


def _pair(text: str, option: str, agents: Mapping[str, object]) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not value:
        raise BadInput(f"{option} {text}: expected AGENT=VALUE")
    if name not in agents:
        raise BadInput(f"{option} {text}: no agent '{name}' (agents: {', '.join(agents)})")
    return name, value


@click.command("auction")
@click.argument("mission_file", metavar="MISSION", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--at",
    "at_s",
    type=NON_NEGATIVE,
    default=0.0,
    show_default=True,
    help="Mission time (s) of the round: tasks whose 'at' is later are not announced yet.",
)
@click.option(
    "--solver",
    type=click.Choice(["assignment", "ilp-scip"]),
    help="Override the mission's coordination.solver.",
)
@click.option(
    "--agent-at",
    "moves",
    multiple=True,
    metavar="AGENT=X,Y,Z",
    help="Put an agent somewhere else than its start (repeatable).",
)
@click.option(
    "--holding",
    multiple=True,
    metavar="AGENT=TASK",
    help="The agent is executing TASK before the round (repeatable).",
)
@click.option(
    "--committed",
    multiple=True,
    metavar="AGENT=TASK",
    help="The agent is past TASK's commit point (k_bt = 0): it keeps the task (repeatable).",
)
@click.option("--bids", "show_bids", is_flag=True, help="Also print every agent's bids.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@handle_spec_errors
def auction(
    mission_file: Path,
    at_s: float,
    solver: str | None,
    moves: tuple[str, ...],
    holding: tuple[str, ...],
    committed: tuple[str, ...],
    show_bids: bool,
    as_json: bool,
) -> None:
    """Run one auction round on MISSION (agents at their start positions unless moved).

    Agents bid the task types' cost expressions (seed 003 eq. 8-10) with straight-line path
    costs, on the tasks that have arrived by --at; the auctioneer assigns the most tasks at the
    least total cost, priorities first (eq. 6-7). Prints each agent's task and cost, and why
    every other task has no agent.

    \b
    Examples:
      btmission auction missions/mine_inspection.yaml
      btmission auction missions/mine_inspection.yaml --at 120 --bids
      btmission auction missions/pick_and_deliver.yaml --at 40 --committed G1=P1
      btmission auction missions/pick_and_deliver.yaml --solver ilp-scip --json
    """
    from dataclasses import replace

    from btmission.allocation.auction import AuctionConfig, AuctionState, announce, auction_round
    from btmission.allocation.bidder import AgentState, BidError
    from btmission.allocation.tasks import TaskState
    from btmission.missions import load_mission
    from btmission.runtime.mission_auction import bidder_for_agent, pool_from_mission

    m = load_mission(mission_file)
    cfg = AuctionConfig.from_spec(m.spec.coordination)
    if solver is not None:
        cfg = replace(cfg, solver=solver)
    agents = {a.id: AgentState(a.id, a.start) for a in m.agents}
    pool = pool_from_mission(m)
    for text in moves:
        name, value = _pair(text, "--agent-at", agents)
        xyz = parse_numbers(value, 3)
        if xyz is None:
            raise BadInput(f"--agent-at {text}: expected AGENT=X,Y,Z (e.g. R1=60,10,2)")
        agents[name] = replace(agents[name], position=xyz)  # type: ignore[arg-type]
    for option, given, commit in (("--holding", holding, False), ("--committed", committed, True)):
        for text in given:
            name, tid = _pair(text, option, agents)
            task = pool.get(tid)
            if task is None:
                raise BadInput(f"{option} {text}: no task '{tid}' in the mission")
            if task.info.arrival_s > at_s:
                raise BadInput(
                    f"{option} {text}: task '{tid}' arrives at {task.info.arrival_s:g} s, "
                    f"after --at {at_s:g}"
                )
            if commit and not task.info.multi_stage:
                raise BadInput(f"{option} {text}: task type '{task.info.type}' has no commit_after")
            if agents[name].task not in (None, tid) or (task.agent not in (None, name)):
                raise BadInput(f"{option} {text}: an agent holds one task and a task one agent")
            state_ = TaskState.COMMITTED if commit else TaskState.ASSIGNED
            pool = pool.with_tasks({tid: task.moved(at_s, state_, name, f"given by {option}")})
            agents[name] = replace(agents[name], task=tid, committed=commit)
    state = announce(AuctionState(cfg, pool), at_s)
    ann = state.announcement
    try:
        bids = [bidder_for_agent(m, a).bid(ann, g, at_s) for a, g in agents.items()]
    except BidError as exc:
        raise BadInput(f"{mission_file}: {exc}") from None
    assignments, state, report = auction_round(state, bids, at_s)
    by_agent = {b.agent: b for b in bids}
    if as_json:
        out = {
            "mission": m.name,
            "time_s": at_s,
            "solver": report.method,
            "announced": list(ann.ids),
            "assignments": {
                a: None if t is None else {"task": t, "cost": _json_cost(by_agent[a].cost_of(t))}
                for a, t in assignments.items()
            },
            "unassigned": report.unassigned,
            "bids": {
                b.agent: {t: _json_cost(float(c)) for t, c in zip(b.tasks, b.costs)} for b in bids
            },
        }
        click.echo(json.dumps(out, indent=2))
        return
    click.echo(
        f"{m.name} at t = {at_s:g} s: {len(ann)} task(s) announced, {len(bids)} agent(s) "
        f"bidding (straight-line costs), solver {report.method}"
    )
    width = max((len(a) for a in assignments), default=5)
    for a, t in assignments.items():
        shown = (
            "— (no task: default behaviour)"
            if t is None
            else f"{t}  cost {_cost(by_agent[a].cost_of(t))}"
        )
        click.echo(f"  {a:<{width}}  {shown}")
    for t, why in report.unassigned.items():
        click.echo(f"  {t} unassigned: {why}")
    for c in report.changes:
        if c.before is not None:
            click.echo(f"  {c.task}: {c.before} → {c.after or '—'} ({c.reason})")
    later = [t.id for t in state.pool if t.info.arrival_s > at_s]
    if later:
        click.echo(f"  not yet arrived: {', '.join(later)}")
    if show_bids and ann.ids:
        click.echo("")
        tw = max(8, *(len(t) for t in ann.ids))
        click.echo(" " * (width + 2) + "".join(f"{t:>{tw + 2}}" for t in ann.ids))
        for b in bids:
            click.echo(f"  {b.agent:<{width}}" + "".join(f"{_cost(c):>{tw + 2}}" for c in b.costs))
