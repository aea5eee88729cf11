"""``btmission auction``: one auction round on a mission file — who gets what, and why."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from btmission.cli.common import BadInput, handle_spec_errors


def _json_cost(v: float) -> float | str | None:
    if math.isnan(v):
        return None
    return "inf" if math.isinf(v) else v


def _cost(v: float) -> str:
    if math.isnan(v):
        return "—"
    return "unreachable" if math.isinf(v) else f"{v:.2f}"


@click.command("auction")
@click.argument("mission_file", metavar="MISSION", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--at",
    "at_s",
    type=click.FloatRange(min=0),
    default=0.0,
    show_default=True,
    help="Mission time (s) of the round: tasks whose 'at' is later are not announced yet.",
)
@click.option(
    "--solver",
    type=click.Choice(["assignment", "ilp-scip"]),
    help="Override the mission's coordination.solver.",
)
@click.option("--bids", "show_bids", is_flag=True, help="Also print every agent's bids.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@handle_spec_errors
def auction(
    mission_file: Path, at_s: float, solver: str | None, show_bids: bool, as_json: bool
) -> None:
    """Run one auction round on MISSION with every agent at its start position.

    Agents bid the task types' cost expressions (seed 003 eq. 8-10) with straight-line path
    costs, on the tasks that have arrived by --at; the auctioneer assigns the most tasks at the
    least total cost, priorities first (eq. 6-7). Prints each agent's task and cost, and why
    every other task has no agent.

    \b
    Examples:
      btmission auction missions/mine_inspection.yaml
      btmission auction missions/mine_inspection.yaml --at 120 --bids
      btmission auction missions/pick_and_deliver.yaml --solver ilp-scip --json
    """
    from dataclasses import replace

    from btmission.allocation.auction import AuctionConfig, AuctionState, announce, auction_round
    from btmission.allocation.bidder import AgentState, Bidder, BidError
    from btmission.allocation.tasks import pool_from_mission
    from btmission.spec.mission import load_mission

    m = load_mission(mission_file)
    cfg = AuctionConfig.from_spec(m.spec.coordination)
    if solver is not None:
        cfg = replace(cfg, solver=solver)
    state = announce(AuctionState(cfg, pool_from_mission(m)), at_s)
    ann = state.announcement
    try:
        bids = [
            Bidder.for_agent(m, a.id).bid(ann, AgentState(a.id, a.start), at_s) for a in m.agents
        ]
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
        f"bidding from their start positions (straight-line costs), solver {report.method}"
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
    later = [t.id for t in state.pool if t.info.arrival_s > at_s]
    if later:
        click.echo(f"  not yet arrived: {', '.join(later)}")
    if show_bids and ann.ids:
        click.echo("")
        tw = max(8, *(len(t) for t in ann.ids))
        click.echo(" " * (width + 2) + "".join(f"{t:>{tw + 2}}" for t in ann.ids))
        for b in bids:
            click.echo(f"  {b.agent:<{width}}" + "".join(f"{_cost(c):>{tw + 2}}" for c in b.costs))
