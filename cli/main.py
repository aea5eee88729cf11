"""The ``btmission`` command: a thin click layer over btmission's Python API.

Exit status: 0 ok, 1 checks failed, 2 bad input (unreadable or invalid files, unknown names),
70 internal error (a bug: one line on stderr, the traceback in a file), 130 interrupted.
"""

from __future__ import annotations

import errno
import os
import sys
from typing import Any, NoReturn

import click

from btmission import __version__
from btmission.cli import (
    auction_cmds,
    bench_cmds,
    console_cmds,
    control_cmds,
    dispatch_cmds,
    library_cmds,
    map_cmds,
    mavsim_cmds,
    mission_cmds,
    process_cmds,
    reloc_cmds,
    run_cmds,
    synth_cmds,
    view_cmds,
)
from btmission.cli.common import EXIT_BAD_INPUT, EXIT_INTERRUPTED, report_internal_error

# An OSError with one of these numbers is the environment refusing (disk full, no permission,
# read-only file system ...), not a bug: a clear message and exit status 2, no traceback file.
_ENVIRONMENT_ERRNOS = frozenset(
    {
        errno.ENOSPC,
        errno.EDQUOT,
        errno.EACCES,
        errno.EPERM,
        errno.EROFS,
        errno.EFBIG,
        errno.EISDIR,
        errno.ENOTDIR,
        errno.EMFILE,
        errno.ENFILE,
        errno.ENOENT,
        errno.ENAMETOOLONG,
        errno.ELOOP,
    }
)
_EXIT_BROKEN_PIPE = 141  # what a shell reports for a command ended by SIGPIPE (128 + 13)


def _silence_stdout() -> None:
    """After a broken pipe: point stdout at /dev/null so the final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # no real file descriptor (e.g. under CliRunner)
        pass


def _environment_message(exc: OSError, what: str | None = None) -> str:
    """``FILE: reason`` (like other Unix tools), or just the reason when no file is known."""
    where = what or exc.filename
    reason = exc.strerror or str(exc)
    return f"{where}: {reason}" if where else reason


class _Cli(click.Group):
    """The top-level group; its :meth:`invoke` is btmission's last-resort error handler."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.Abort, SystemExit):
            raise
        except KeyboardInterrupt:
            click.echo("\ninterrupted", err=True)
            ctx.exit(EXIT_INTERRUPTED)
        except BrokenPipeError:  # `btmission library list | head -1`
            _silence_stdout()
            ctx.exit(_EXIT_BROKEN_PIPE)
        except OSError as exc:
            if exc.errno not in _ENVIRONMENT_ERRNOS:
                _internal_error(ctx, exc)
            click.echo(f"Error: {_environment_message(exc)}", err=True)
            ctx.exit(EXIT_BAD_INPUT)
        except Exception as exc:
            _internal_error(ctx, exc)


def _internal_error(ctx: click.Context, exc: BaseException) -> NoReturn:
    debug = bool(ctx.params.get("debug"))
    ctx.exit(report_internal_error(exc, debug=debug))


@click.group(
    cls=_Cli,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
)
@click.version_option(__version__, "--version", "-V", prog_name="btmission")
@click.option(
    "--debug",
    is_flag=True,
    envvar="BTMISSION_DEBUG",
    help="On an internal error, show the Python traceback (also: BTMISSION_DEBUG=1).",
)
def cli(debug: bool) -> None:
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

    Exit status: 0 ok, 1 checks failed, 2 bad input, 70 internal error, 130 interrupted.
    """


cli.add_command(library_cmds.library)
cli.add_command(synth_cmds.synth)
cli.add_command(mission_cmds.validate)
cli.add_command(mission_cmds.mission)
cli.add_command(process_cmds.coordinator_cmd)
cli.add_command(process_cmds.agent_cmd)
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
cli.add_command(mavsim_cmds.mavsim)
cli.add_command(view_cmds.view_cmd)
cli.add_command(console_cmds.task_group)
cli.add_command(console_cmds.status_cmd)
cli.add_command(console_cmds.fleet_group)


def main() -> None:
    """Console-script entry point (also ``python -m btmission``)."""
    try:
        cli.main(prog_name="btmission")
    except SystemExit as stop:
        code = stop.code
    else:  # pragma: no cover - click's standalone mode always exits
        code = 0
    try:  # a pipe closed or a disk filled while the last output was buffered
        sys.stdout.flush()
    except BrokenPipeError:
        _silence_stdout()
        code = _EXIT_BROKEN_PIPE
    except OSError as exc:
        _silence_stdout()
        click.echo(f"Error: {_environment_message(exc, 'standard output')}", err=True)
        code = EXIT_BAD_INPUT
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    main()
