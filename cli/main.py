"""The ``btmission`` command: a thin click layer over btmission's Python API.

Exit status: 0 ok, 1 checks failed, 2 bad input (unreadable or invalid files, unknown names),
70 internal error (a bug: one line on stderr, the traceback in a file), 130 interrupted.
"""

from __future__ import annotations

import errno
import importlib
import os
import sys
from collections.abc import Iterator
from typing import Any, NoReturn

import click

from btmission import __version__
from btmission.cli.common import EXIT_BAD_INPUT, EXIT_INTERRUPTED, report_internal_error

COMMANDS: dict[str, tuple[str, str, str]] = {
    "library": ("library_cmds", "library", "Capability libraries: list, show, check, scaffold a plugin."),
    "synth": ("synth_cmds", "synth", "Synthesise the behaviour tree that achieves --goal from library REF (name or YAML path)."),
    "validate": ("mission_cmds", "validate", "Validate a mission file without running it."),
    "mission": ("mission_cmds", "mission", "Inspect a mission's per-agent trees."),
    "coordinator": ("process_cmds", "coordinator_cmd", "Run a mission's coordinator: the auction, the task pool and the event log, for agents in other processes or on other machines (btmission agent), over Zenoh."),
    "agent": ("process_cmds", "agent_cmd", "Run agents of a mission (their trees, bids, navigation and vehicles) in this process, linked to the mission's coordinator (btmission coordinator) over Zenoh."),
    "schema": ("mission_cmds", "schema", "Print the JSON Schema of a library or mission file, for editor validation."),
    "bench": ("bench_cmds", "bench", "Run benchmarks; each prints a table and writes it under --out (default benchmarks/results)."),
    "control": ("control_cmds", "control", "Reactive navigation: NMPC, APF, DPHR and COMPRA exploration (seed 002, seed 003)."),
    "auction": ("auction_cmds", "auction", "Run one auction round on MISSION (agents at their start positions unless moved)."),
    "map": ("map_cmds", "map_group", "Voxel maps: generate a mine, show a map (summary and top-view picture)."),
    "plan": ("map_cmds", "plan_cmd", "Plan the D*+ risk-aware path between two points of a map (seed 000 eq."),
    "dispatch": ("dispatch_cmds", "dispatch", "GA fleet dispatch for haul trucks on topological mine maps (seed 004)."),
    "run": ("run_cmds", "run_cmd", "Run a mission and print its report."),
    "report": ("run_cmds", "report_cmd", "Print the report of a run from its event log (seed 000 Tables III and II)."),
    "reloc": ("reloc_cmds", "reloc", "Global relocalization: find an agent in the shared map from one LiDAR scan (seed 000 §IV-C1: place descriptors, then coarse-to-fine ICP)."),
    "mavsim": ("mavsim_cmds", "mavsim", "Simulated MAVLink vehicles for flying missions without hardware."),
    "view": ("view_cmds", "view_cmd", "Replay a finished run in the browser, from its event log alone."),
    "task": ("console_cmds", "task_group", "Add, cancel or reprioritise a task of a running mission."),
    "status": ("console_cmds", "status_cmd", "Show the agents and tasks of the running mission at URL (a table; --json for scripts)."),
    "fleet": ("console_cmds", "fleet_group", "Recall, exclude or include an agent, cut its link (simulator drills), pause or resume allocation, or stop a running mission (its console at URL; see btmission task)."),
}  # fmt: skip
"""Every top-level command: name → (module under ``btmission.cli``, attribute, short help).

A command's module (numpy, pydantic, scipy, py_trees ... behind it) is imported only when the
command runs or is looked up, so ``btmission --help`` and ``--version`` start in a tenth of a
second. The short help is the command's own (``get_short_help_str``); a test keeps them equal."""

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


class _LazyCommands(dict[str, click.Command]):
    """``Group.commands`` that imports a command's module on first access (see :data:`COMMANDS`).

    A dict of name → command like click's own, so ``cli.commands[name]``, ``.get``, ``.items``
    and ``.values`` work as before; only the import is deferred."""

    def __init__(self) -> None:
        super().__init__()
        self._pending = dict(COMMANDS)

    def _load(self, name: str) -> click.Command:
        module, attr, _ = self._pending.pop(name)
        command = getattr(importlib.import_module(f"btmission.cli.{module}"), attr)
        assert isinstance(command, click.Command)
        dict.__setitem__(self, name, command)
        return command

    def __getitem__(self, name: str) -> click.Command:
        if name in self._pending:
            return self._load(name)
        return dict.__getitem__(self, name)

    def __contains__(self, name: object) -> bool:
        return name in self._pending or dict.__contains__(self, name)

    def __iter__(self) -> Iterator[str]:
        return iter([*dict.keys(self), *self._pending])

    def __len__(self) -> int:
        return dict.__len__(self) + len(self._pending)

    def keys(self) -> Any:
        return list(self)

    def get(self, name: str, default: Any = None) -> Any:
        return self[name] if name in self else default

    def values(self) -> Any:
        return [self[n] for n in list(self)]

    def items(self) -> Any:
        return [(n, self[n]) for n in list(self)]

    def short_help(self, name: str) -> str | None:
        """The command's short help without importing it (None once it is loaded)."""
        spec = self._pending.get(name)
        return None if spec is None else spec[2]


class _Cli(click.Group):
    """The top-level group; its :meth:`invoke` is btmission's last-resort error handler.

    Its commands are :class:`_LazyCommands`: ``--help`` lists them from :data:`COMMANDS`
    without importing any."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.commands = _LazyCommands()

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        lazy = self.commands
        assert isinstance(lazy, _LazyCommands)
        rows = []
        limit = formatter.width - 6 - max((len(n) for n in lazy), default=0)
        for name in self.list_commands(ctx):
            text = lazy.short_help(name)
            if text is None:
                command = lazy[name]
                if command.hidden:
                    continue
                text = command.get_short_help_str(limit)
            else:
                text = click.Command(name, help=text).get_short_help_str(limit)
            rows.append((name, text))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)

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
