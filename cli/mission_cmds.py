"""``btmission validate``, ``btmission mission tree`` and ``btmission schema``."""

from __future__ import annotations

import json
from pathlib import Path

import click

from btmission.cli.common import (
    BadInput,
    ChecksFailed,
    checking_imports,
    echo_diagnostics,
    handle_spec_errors,
    with_implementations_option,
    write_output,
)
from btmission.cli.synth_cmds import emit_tree, format_option, output_option
from btmission.diagnostics import Severity, SpecError, errors, promote
from btmission.missions import load_mission
from btmission.synthesis.mission_tree import build_mission_tree


@click.command()
@click.argument("mission_file", metavar="MISSION", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--strict", is_flag=True, help="Warnings (e.g. assumed conditions) fail the check (exit 1)."
)
@with_implementations_option
@handle_spec_errors
def validate(mission_file: Path, strict: bool, with_implementations: bool) -> None:
    """Validate a mission file without running it.

    Checks the schema, ids, libraries, task types, task fields, cost expressions, commit
    conditions, that every agent's trees synthesise, that its libraries' implementations load
    (unless a library is abstract: no `module:`) and its runtime settings are known and in range
    (as `run` does), and against the world map that agent starts
    and task locations are inside the map, not in rock and reachable from some agent. Every
    problem is reported with file:line:col. Exit status 2 when the mission is invalid.

    Libraries given by path are checked without importing their implementation modules;
    --with-implementations imports them.
    """
    from btmission.runtime.runcheck import run_problems
    from btmission.world.checks import check_mission_world

    with checking_imports(with_implementations):
        m = load_mission(mission_file)
        run_errors = run_problems(m, abstract_ok=True)  # what `run` refuses, validate refuses first
    if run_errors:
        raise SpecError(run_errors + m.diagnostics)
    map_diags = check_mission_world(m)
    if errors(map_diags):
        raise SpecError(
            errors(map_diags) + [d for d in map_diags if d.severity is not Severity.ERROR]
        )
    diags = promote(m.diagnostics + map_diags, strict)
    echo_diagnostics(diags)
    if errors(diags):
        raise ChecksFailed(f"{mission_file}: warnings are errors under --strict")
    libs = ", ".join(sorted({lb.library.name for lb in m.libraries.values()}))
    click.echo(
        f"{mission_file}: mission '{m.name}' OK — {len(m.agents)} agent(s) ({libs}), "
        f"{len(m.tasks)} task(s), {len(m.task_types)} task type(s)"
    )


@click.group()
def mission() -> None:
    """Inspect a mission's per-agent trees."""


@mission.command("tree")
@click.argument("mission_file", metavar="MISSION", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-a", "--agent", "agent_id", required=True, help="Agent id from the mission.")
@click.option(
    "-t",
    "--task-type",
    "task_types",
    multiple=True,
    help="Only this task type's branch (repeatable; default: every type the agent can do).",
)
@format_option
@output_option
@click.option(
    "--strict", is_flag=True, help="Assumed conditions and ambiguous achievers are errors."
)
@with_implementations_option
@handle_spec_errors
def tree_cmd(
    mission_file: Path,
    agent_id: str,
    task_types: tuple[str, ...],
    fmt: str | None,
    output: Path | None,
    strict: bool,
    with_implementations: bool,
) -> None:
    """Show an agent's mission tree, as in seed 000 Fig. 7.

    The root falls back from one branch per task type (task_assigned(type) → the back-chained
    subtree of the type's goal) to the default behaviour after the idle timeout, then to wait.
    """
    with checking_imports(with_implementations):
        m = load_mission(mission_file)
    ids = [a.id for a in m.agents]
    if agent_id not in ids:
        raise BadInput(f"{mission_file}: no agent '{agent_id}' (agents: {', '.join(ids)})")
    for t in task_types:
        if t not in m.task_types:
            raise BadInput(
                f"{mission_file}: no task type '{t}' (task types: {', '.join(m.task_types)})"
            )
    mt = build_mission_tree(m, agent_id, list(task_types) or None, strict=strict)
    for name, why in mt.skipped.items():
        click.echo(f"note: {agent_id} cannot do task type '{name}': {why}", err=True)
    echo_diagnostics([d for d in mt.diagnostics if d.severity is not Severity.INFO])
    emit_tree(
        mt.tree,
        fmt,
        output,
        f"{m.name}_{agent_id}",
        {"mission": m.name, "agent": agent_id, "branches": list(mt.branches)},
    )
    if errors(mt.diagnostics):
        raise ChecksFailed("synthesis reported errors")


@click.command()
@click.argument("kind", type=click.Choice(["library", "mission"]))
@output_option
def schema(kind: str, output: Path | None) -> None:
    """Print the JSON Schema of a library or mission file, for editor validation.

    \b
    For VS Code (YAML extension), add to settings.json:
      "yaml.schemas": {"./mission.schema.json": "missions/*.yaml"}
    """
    from btmission.spec.schema import json_schema

    write_output(json.dumps(json_schema(kind), indent=2) + "\n", output)
