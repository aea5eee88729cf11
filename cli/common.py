"""Shared CLI plumbing: exit codes, printing diagnostics, writing outputs safely."""

from __future__ import annotations

import contextlib
import errno
import functools
import math
import os
import stat
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, Literal, TypeVar

import click

from btmission.diagnostics import Diagnostic, Severity, SpecError
from btmission.errors import BtmissionError

EXIT_OK, EXIT_CHECKS_FAILED, EXIT_BAD_INPUT = 0, 1, 2
EXIT_INTERNAL_ERROR = 70  # EX_SOFTWARE (sysexits.h): a bug in btmission or a plugin
EXIT_INTERRUPTED = 130  # 128 + SIGINT

F = TypeVar("F", bound=Callable[..., Any])


class BadInput(BtmissionError, click.ClickException):
    """The input cannot be used (exit status 2)."""

    exit_code = EXIT_BAD_INPUT


class ChecksFailed(BtmissionError, click.ClickException):
    """The input is well-formed but a check failed (exit status 1)."""

    exit_code = EXIT_CHECKS_FAILED


# ------------------------------------------------------------------ last-resort error report
ErrorSink = Callable[[BaseException, str], "str | None"]
_ALSO_IN = "_btmission_traceback_also_in"  # where sinks wrote an exception's traceback


@contextlib.contextmanager
def internal_error_sink(sink: ErrorSink) -> Iterator[None]:
    """An unexpected exception leaving the block is given to ``sink(exc, traceback_text)`` at once.

    ``run`` uses this to put the traceback in its event log while the log is still open; the
    sink returns where it wrote it (named in the one-line message) or None. Expected ends (bad
    input, click's exits, signals) pass untouched, and a sink that fails is ignored.
    """
    try:
        yield
    except (click.exceptions.ClickException, click.exceptions.Exit, click.Abort, SpecError):
        raise
    except Exception as exc:
        try:
            shown = sink(exc, "".join(traceback.format_exception(exc)))
        except Exception:  # the report must not fail because a sink did
            shown = None
        if shown:
            setattr(exc, _ALSO_IN, [*getattr(exc, _ALSO_IN, []), shown])
        raise


def crash_dir() -> Path:
    """Where internal-error tracebacks go: ``$XDG_STATE_HOME/btmission`` (default
    ``~/.local/state/btmission``)."""
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state) / "btmission"


def _write_crash_file(text: str) -> Path | None:
    """Write ``text`` to a new file in :func:`crash_dir` (else the temp dir); None if neither works."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    for folder in (crash_dir(), Path(tempfile.gettempdir())):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, name = tempfile.mkstemp(
                prefix=f"btmission-crash-{stamp}-", suffix=".txt", dir=folder
            )
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(text)
            return Path(name)
        except OSError:
            continue
    return None


def report_internal_error(exc: BaseException, *, debug: bool = False) -> int:
    """Report an unexpected exception and return :data:`EXIT_INTERNAL_ERROR`.

    Without ``debug``: one line on stderr, ``internal error: <Type: message>; details in
    <file>``, with the full traceback written to that file (and to every
    :func:`internal_error_sink`). With ``debug``: the traceback on stderr.
    """
    from btmission import __version__

    trace = "".join(traceback.format_exception(exc))
    if debug:
        click.echo(trace.rstrip("\n"), err=True)
        return EXIT_INTERNAL_ERROR
    where: list[str] = list(getattr(exc, _ALSO_IN, []))
    header = (
        f"btmission {__version__} internal error\n"
        f"command: {' '.join(sys.argv)}\n"
        f"python: {sys.version.split()[0]} on {sys.platform}\n\n"
    )
    crash = _write_crash_file(header + trace)
    if crash is not None:
        where.insert(0, str(crash))
    what = " ".join(f"{type(exc).__name__}: {exc}".split())  # one line
    if len(what) > 300:
        what = what[:297] + "..."
    details = (
        f"details in {' and '.join(where)}"
        if where
        else "no traceback file could be written; rerun with --debug"
    )
    click.echo(f"internal error: {what}; {details}", err=True)
    return EXIT_INTERNAL_ERROR


# ------------------------------------------------------------------ checking is not running
def with_implementations_option(fn: F) -> F:
    """``--with-implementations`` for the checking commands, which otherwise never import the
    implementation module a library file names (see :func:`checking_imports`)."""
    return click.option(
        "--with-implementations",
        "with_implementations",
        is_flag=True,
        help="Also import the implementation modules of libraries given by path (this runs "
        "their code) to check and report what is implemented.",
    )(fn)


def checking_imports(with_implementations: bool) -> contextlib.AbstractContextManager[None]:
    """The import policy of a checking command: a library given by path is data, so its
    ``module:`` is imported only on request; installed libraries (entry points) are trusted."""
    from btmission.plugins import implementation_imports

    return implementation_imports("always" if with_implementations else "installed")


def echo_diagnostics(diags: Iterable[Diagnostic], *, show_info: bool = True) -> None:
    """Print findings to stderr, one per line, errors first as produced."""
    for d in diags:
        if d.severity is Severity.INFO and not show_info:
            continue
        colour = {"error": "red", "warning": "yellow", "info": None}[d.severity.value]
        click.secho(d.format(), err=True, fg=colour)


def handle_spec_errors(fn: F) -> F:
    """Turn :class:`SpecError` into one clear message per problem and exit status 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except SpecError as exc:
            echo_diagnostics(exc.diagnostics)
            n = len([d for d in exc.diagnostics if d.severity is Severity.ERROR])
            raise BadInput(f"{n} problem(s) found; nothing was run") from None

    return wrapper  # type: ignore[return-value]


def write_output(data: str | bytes, output: Path | None) -> None:
    """Write to ``output`` atomically (temp file + rename), or to stdout when it is None.

    Writing through a temporary file means an existing file is never left half-written. A target
    that is not a regular file (see :func:`check_output_target`) and a write that fails (disk full,
    permission denied) are :class:`BadInput` with the path and the reason.
    """
    if output is None:
        if isinstance(data, bytes) and sys.stdout.isatty():
            raise BadInput("this format is binary: give an output file with -o FILE")
        try:
            if isinstance(data, bytes):
                sys.stdout.buffer.write(data)
                sys.stdout.buffer.flush()
            else:
                click.echo(data, nl=not data.endswith("\n"))
                sys.stdout.flush()
        except BrokenPipeError:
            raise  # the reader went away: the CLI ends quietly
        except OSError as exc:
            raise BadInput(f"cannot write to standard output: {exc.strerror or exc}") from None
        return
    check_output_target(output)
    tmp: str | None = None
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{output.name}.", dir=output.parent)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data if isinstance(data, bytes) else data.encode("utf-8"))
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, output)
    except OSError as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise BadInput(f"cannot write {output}: {exc.strerror or exc}") from None
    except BaseException:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise
    click.echo(f"wrote {output}", err=True)


OutputKind = Literal["file", "dir"]


def _what_is(mode: int) -> str | None:
    """What a non-regular, non-directory file is, in words (None for a regular file/dir)."""
    if stat.S_ISLNK(mode):
        return "a symbolic link"
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return None


def check_output_target(path: Path | None, kind: OutputKind = "file") -> Path | None:
    """Refuse an output path btmission must not write to; return it unchanged otherwise.

    ``kind="file"``: the path is replaced by a new regular file, so an existing symlink, FIFO,
    device, socket or directory there is refused (replacing a device node or a link is never what
    the user meant; opening a FIFO would block). ``kind="dir"``: files are written into it, so
    it must be a directory (or a link to one) if it exists. Either way the nearest existing
    ancestor must be a writable directory. Raises :class:`BadInput` naming the path and the
    reason; nothing is opened, so a FIFO cannot block this check.
    """
    if path is None:
        return None
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    except OSError as exc:  # e.g. ENOTDIR: a parent is a file
        st = None
        if exc.errno != errno.ENOTDIR:
            raise BadInput(f"cannot write {path}: {exc.strerror}") from None
    if st is not None:
        if kind == "dir":
            if not stat.S_ISDIR(st.st_mode) and not path.is_dir():
                raise BadInput(
                    f"output directory {path} is {_what_is(st.st_mode) or 'a file'}, "
                    "not a directory"
                )
        else:
            what: str | None = "a directory" if stat.S_ISDIR(st.st_mode) else _what_is(st.st_mode)
            if what is not None:
                raise BadInput(
                    f"refusing to write {path}: it is {what}, not a regular file "
                    "(give the path of a regular file)"
                )
    parent = path.parent if kind == "file" or st is None else path
    while not parent.exists() and parent != parent.parent:
        if parent.is_symlink():  # a dangling link among the parents
            break
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise BadInput(f"cannot write {path}: {parent} is not a directory")
    if parent.is_dir() and not os.access(parent, os.W_OK | os.X_OK):
        raise BadInput(f"cannot write {path}: permission denied in {parent}")
    return path


def output_target(
    kind: OutputKind = "file",
) -> Callable[[click.Context, click.Parameter, Any], Any]:
    """A click option callback applying :func:`check_output_target` to the option's value."""

    def callback(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
        return check_output_target(value, kind)

    return callback


def output_file_option(*decls: str, help: str, required: bool = False) -> Callable[[F], F]:
    """An output file option: a ``Path`` checked by :func:`check_output_target`; None if not given."""
    return click.option(
        *decls,
        type=click.Path(dir_okay=False, path_type=Path),
        required=required,
        default=None,
        callback=output_target("file"),
        help=help,
    )


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


FORMAT_BY_SUFFIX = {
    ".svg": "svg",
    ".png": "png",
    ".xml": "xml",
    ".json": "json",
    ".dot": "dot",
    ".gv": "dot",
    ".txt": "ascii",
}


def infer_format(fmt: str | None, output: Path | None) -> str:
    if fmt:
        return fmt
    if output is not None and output.suffix:
        suffix = output.suffix.lower()
        if suffix not in FORMAT_BY_SUFFIX:
            known = ", ".join(sorted(FORMAT_BY_SUFFIX))
            raise BadInput(
                f"cannot tell the format from '{output.name}' (known suffixes: {known}); "
                "give --format"
            )
        return FORMAT_BY_SUFFIX[suffix]
    return "ascii"


# ------------------------------------------------------------------ option helpers
# One definition for the option shapes the commands repeat; each returns a plain
# ``click.option`` so --help reads exactly as a hand-written one would.


def int_option(
    *decls: str, default: int, help: str, min: int = 1, max: int | None = None
) -> Callable[[F], F]:
    """An integer option bounded below by ``min`` (and above by ``max``), default shown."""
    return click.option(
        *decls, default=default, show_default=True, type=click.IntRange(min, max), help=help
    )


def positive_float_option(*decls: str, default: float, help: str) -> Callable[[F], F]:
    """A float option that must be > 0, default shown."""
    return click.option(
        *decls,
        default=default,
        show_default=True,
        type=POSITIVE,
        help=help,
    )


def file_option(*decls: str, help: str, required: bool = False) -> Callable[[F], F]:
    """A file path option (``Path``; a directory is refused); None when not given."""
    return click.option(
        *decls,
        type=click.Path(dir_okay=False, path_type=Path),
        required=required,
        default=None,
        help=help,
    )


# ------------------------------------------------------------------ finite numbers
# Every number a command reads is finite: click's float types accept "nan", "inf" and "1e400"
# (and nan passes any range check), which would reach the algorithms as NaN or inf.


class FiniteFloat(click.FloatRange):
    """A finite float, optionally bounded like :class:`click.FloatRange` (nan, inf refused)."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return rv

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if (self.min, self.max) == (None, None):
            self.name = "float"  # unbounded: shown as FLOAT, like type=float

    def _describe_range(self) -> str:
        return super()._describe_range() if (self.min, self.max) != (None, None) else ""


FINITE = FiniteFloat()
"""Any finite float."""

POSITIVE = FiniteFloat(min=0, min_open=True)
"""A finite float > 0."""

NON_NEGATIVE = FiniteFloat(min=0)
"""A finite float ≥ 0."""

SEED = click.IntRange(min=0)
"""A random seed: an integer ≥ 0 (numpy refuses negative seeds)."""


def parse_numbers(text: str, count: int) -> tuple[float, ...] | None:
    """``"1, 2.5, 3"`` → ``(1.0, 2.5, 3.0)`` when it has ``count`` finite numbers, else None."""
    try:
        values = tuple(float(p) for p in text.split(","))
    except ValueError:
        return None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        return None
    return values
