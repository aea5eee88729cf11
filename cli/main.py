"""The ``btmission`` command: a thin click layer over btmission's Python API.

Exit status: 0 ok, 1 checks failed, 2 bad input (unreadable or invalid files, unknown names).
"""

from __future__ import annotations

import click

from btmission import __version__
from btmission.cli import (
    auction_cmds,
    bench_cmds,
    control_cmds,
    dispatch_cmds,
    library_cmds,
    map_cmds,
    mission_cmds,
    reloc_cmds,
    run_cmds,
    synth_cmds,
)


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, "--version", "-V", prog_name="btmission")
def cli() -> None:
    """Multi-robot missions from declarative capability libraries.

    A library declares a platform's actions with pre- and postconditions; btmission synthesises
    each agent's behaviour tree by back-chaining from a task's goal, checks it before deployment,
    and exports it (ascii, dot, svg, png, BehaviorTree.CPP XML, JSON).

    \b
    Quick start:
      btmission library list
      btmission synth aerial --goal 'at_goal(goal)'
      btmission synth aerial --goal 'at_goal(goal)' --dry-run
      btmission validate missions/mine_inspection.yaml
      btmission mission tree missions/mine_inspection.yaml --agent R1 -o r1.svg
      btmission run missions/mine_inspection.yaml --controller track

    Exit status: 0 ok, 1 checks failed, 2 bad input.
    """


cli.add_command(library_cmds.library)
cli.add_command(synth_cmds.synth)
cli.add_command(mission_cmds.validate)
cli.add_command(mission_cmds.mission)
cli.add_command(mission_cmds.schema)
cli.add_command(bench_cmds.bench)
cli.add_command(control_cmds.control)
cli.add_command(auction_cmds.auction)
cli.add_command(map_cmds.map_group)
cli.add_command(map_cmds.plan_cmd)
cli.add_command(dispatch_cmds.dispatch)
cli.add_command(run_cmds.run_cmd)
cli.add_command(run_cmds.report_cmd)
cli.add_command(reloc_cmds.reloc)


def main() -> None:
    """Console-script entry point."""
    cli(prog_name="btmission")


if __name__ == "__main__":  # pragma: no cover
    main()
