"""``btmission synth``: back-chain a goal over a library, export the tree, or dry-run it."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from btmission.cli.common import (
    BadInput,
    ChecksFailed,
    checking_imports,
    echo_diagnostics,
    handle_spec_errors,
    infer_format,
    output_target,
    with_implementations_option,
    write_output,
)
from btmission.diagnostics import errors
from btmission.export import FORMATS
from btmission.plugins import load_library
from btmission.spec.library import require_usable
from btmission.synthesis.backchain import Synthesizer, parse_goals
from btmission.synthesis.tree import Node, leaf_signatures

if TYPE_CHECKING:
    from btmission.synthesis.dryrun import DryRunResult

format_option = click.option(
    "-f",
    "--format",
    "fmt",
    type=click.Choice(FORMATS),
    default=None,
    help="Output format (default: from the -o suffix, else ascii). svg/png need graphviz.",
)
output_option = click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    callback=output_target("file"),
    help="Write to FILE instead of stdout (written atomically).",
)


def emit_tree(
    tree: Node,
    fmt: str | None,
    output: Path | None,
    name: str,
    extra: dict[str, object] | None = None,
    *,
    unicode: bool = True,
) -> None:
    """Export ``tree`` in ``fmt`` to ``output`` or stdout, with clear errors for graphviz."""
    from btmission.export import GraphvizFailed, GraphvizMissing, export_tree

    if any(leaf_name == name for _, leaf_name in leaf_signatures(tree)):
        name = f"{name}_tree"  # a BT.CPP tree ID must differ from every node type's ID
    try:
        data = export_tree(tree, infer_format(fmt, output), name=name, unicode=unicode, extra=extra)
    except GraphvizMissing as exc:
        raise BadInput(str(exc)) from None
    except GraphvizFailed as exc:
        raise ChecksFailed(str(exc)) from None
    except ValueError as exc:  # a tree the target format cannot represent (e.g. BT.CPP names)
        raise BadInput(f"cannot export as {infer_format(fmt, output)}: {exc}") from None
    write_output(data, output)


@click.command()
@click.argument("ref")
@click.option(
    "-g",
    "--goal",
    "goals",
    multiple=True,
    metavar="COND",
    help="Goal condition, e.g. 'at_goal(goal)'. Repeat for several goals (ticked in order).",
)
@format_option
@output_option
@click.option(
    "--strict", is_flag=True, help="Assumed conditions and ambiguous achievers are errors."
)
@click.option(
    "--dry-run", is_flag=True, help="Tick the tree in a symbolic world and print the trace."
)
@click.option(
    "--true",
    "true_conds",
    multiple=True,
    metavar="COND",
    help="Dry run: a condition that holds at the start, e.g. --true has_home. Repeatable.",
)
@click.option(
    "--action-ticks",
    default=2,
    show_default=True,
    type=click.IntRange(1, 100),
    help="Dry run: ticks each action stays RUNNING before it succeeds.",
)
@click.option(
    "--max-ticks",
    default=1000,
    show_default=True,
    type=click.IntRange(1),
    help="Dry run: give up after this many ticks.",
)
@click.option("--ascii-only", is_flag=True, help="Plain ASCII tree guides and trace marks.")
@with_implementations_option
@handle_spec_errors
def synth(
    ref: str,
    goals: tuple[str, ...],
    fmt: str | None,
    output: Path | None,
    strict: bool,
    dry_run: bool,
    true_conds: tuple[str, ...],
    action_ticks: int,
    max_ticks: int,
    ascii_only: bool,
    with_implementations: bool,
) -> None:
    """Synthesise the behaviour tree that achieves --goal from library REF (name or YAML path).

    Back-chaining (seed 000 Alg. 1, 2): every condition an action can achieve is replaced by
    Fallback(condition, Sequence(preconditions…, action)) until nothing is left to expand.
    Choices between several achievers and assumed conditions are reported on stderr.

    \b
    Examples:
      btmission synth aerial --goal 'at_goal(goal)'
      btmission synth aerial --goal landed_at_home -o default.svg
      btmission synth ground --goal 'delivered(pickup, dropoff)' -f xml -o pick.xml
      btmission synth aerial --goal 'at_goal(goal)' --dry-run --true has_home

    Exit status: 0 ok; 1 synthesis checks failed (cycles; with --strict also assumed or
    ambiguous) or the dry run did not reach the goal; 2 bad input.
    """
    with checking_imports(with_implementations):
        loaded = load_library(ref)
    lib = require_usable(loaded.library, loaded.diagnostics)
    if not goals:
        hint = f" (this library declares: {', '.join(map(str, lib.goals))})" if lib.goals else ""
        raise BadInput(
            f"give a goal with --goal, e.g. --goal '{lib.goals[0] if lib.goals else 'name(arg)'}'{hint}"
        )
    atoms = parse_goals(goals, lib)
    result = Synthesizer(lib).synthesize(atoms, strict=strict)
    echo_diagnostics(result.diagnostics)
    if dry_run:
        from btmission.synthesis.dryrun import conditions_in

        initial = {str(a): True for a in parse_goals(true_conds, lib, option="--true")}
        in_tree = set(conditions_in(result.tree))
        for cond in initial:
            if cond not in in_tree:
                click.echo(
                    f"note: --true {cond}: no such condition in this tree (ignored)", err=True
                )
        try:
            run = dry_run_fn(
                result.tree, lib, initial, action_ticks=action_ticks, max_ticks=max_ticks
            )
        except RecursionError:  # py_trees recurses per level; the limit raised for it is capped
            raise BadInput(
                f"the tree is too deep to dry-run ({result.size} nodes); export it with -o instead"
            ) from None
        click.echo(run.format_trace(unicode=not ascii_only))
        if output is not None:
            emit_tree(result.tree, fmt, output, lib.name, unicode=not ascii_only)
        if not result.ok:
            raise ChecksFailed("synthesis reported errors")
        if not run.success or run.violations:
            raise ChecksFailed("the dry run did not reach the goal cleanly")
        return
    meta: dict[str, object] = {
        "library": lib.name,
        "goals": [str(g) for g in atoms],
        "inputs": list(result.inputs),
    }
    emit_tree(result.tree, fmt, output, lib.name, meta, unicode=not ascii_only)
    click.echo(f"{result.size} nodes; inputs: {', '.join(result.inputs) or 'none'}", err=True)
    if errors(result.diagnostics):
        raise ChecksFailed("synthesis reported errors")


def dry_run_fn(*args: Any, **kwargs: Any) -> DryRunResult:
    """:func:`btmission.synthesis.dryrun.dry_run` (tests replace this); py_trees is imported only
    when a dry run happens."""
    from btmission.synthesis.dryrun import dry_run

    return dry_run(*args, **kwargs)
