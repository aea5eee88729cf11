"""Shared CLI plumbing: exit codes, printing diagnostics, writing outputs safely."""

from __future__ import annotations

import functools
import math
import os
import sys
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TypeVar

import click

from btmission.diagnostics import Diagnostic, Severity, SpecError

EXIT_OK, EXIT_CHECKS_FAILED, EXIT_BAD_INPUT = 0, 1, 2

F = TypeVar("F", bound=Callable[..., Any])


class BadInput(click.ClickException):
    """The input cannot be used (exit status 2)."""

    exit_code = EXIT_BAD_INPUT


class ChecksFailed(click.ClickException):
    """The input is well-formed but a check failed (exit status 1)."""

    exit_code = EXIT_CHECKS_FAILED


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

    Writing through a temporary file means an existing file is never left half-written.
    """
    if output is None:
        if isinstance(data, bytes):
            if sys.stdout.isatty():
                raise BadInput("this format is binary: give an output file with -o FILE")
            sys.stdout.buffer.write(data)
            sys.stdout.buffer.flush()
        else:
            click.echo(data, nl=not data.endswith("\n"))
        return
    output.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{output.name}.", dir=output.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data if isinstance(data, bytes) else data.encode("utf-8"))
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, output)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    click.echo(f"wrote {output}", err=True)


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
