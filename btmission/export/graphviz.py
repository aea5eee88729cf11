"""Render dot text to svg/png with Graphviz's ``dot`` binary (the only exporter running a program).

Graphviz is an optional system dependency: :func:`graphviz_available` tells whether it is there,
and :func:`render_graphviz` raises :class:`GraphvizMissing` with an actionable message when it is
not, so callers can suggest the text formats instead.
"""

from __future__ import annotations

import shutil
import subprocess
from typing import Literal

from btmission.errors import BtmissionError

__all__ = [
    "DEFAULT_TIMEOUT",
    "MISSING_MESSAGE",
    "GraphvizFailed",
    "GraphvizMissing",
    "graphviz_available",
    "render_graphviz",
]

DEFAULT_TIMEOUT = 120.0
"""Seconds ``dot`` may run; laying out a tree with tens of thousands of nodes takes a while."""

MISSING_MESSAGE = (
    "graphviz 'dot' was not found on PATH; install graphviz (e.g. apt-get install graphviz) "
    "or export as dot/xml/json/ascii"
)


class GraphvizMissing(BtmissionError, RuntimeError):
    """The ``dot`` executable is not on ``PATH``."""


class GraphvizFailed(BtmissionError, RuntimeError):
    """``dot`` ran but failed (non-zero exit, or timeout); the message carries its stderr."""


def _dot_executable() -> str | None:
    return shutil.which("dot")


def graphviz_available() -> bool:
    """True when the Graphviz ``dot`` executable is on ``PATH``."""
    return _dot_executable() is not None


def render_graphviz(
    dot_text: str, fmt: Literal["svg", "png"], timeout: float = DEFAULT_TIMEOUT
) -> bytes:
    """Run ``dot -T<fmt>`` on ``dot_text`` and return the rendered image.

    Raises:
        ValueError: ``fmt`` is neither ``"svg"`` nor ``"png"``.
        GraphvizMissing: ``dot`` is not installed / not on ``PATH``.
        GraphvizFailed: ``dot`` exited non-zero (message includes its stderr) or timed out.
    """
    if fmt not in ("svg", "png"):
        raise ValueError(f"unsupported graphviz format {fmt!r}; expected 'svg' or 'png'")
    executable = _dot_executable()
    if executable is None:
        raise GraphvizMissing(MISSING_MESSAGE)
    try:
        proc = subprocess.run(
            [executable, f"-T{fmt}"],
            input=dot_text.encode("utf-8"),
            capture_output=True,
            timeout=timeout,
            check=False,
        )
    except subprocess.TimeoutExpired as exc:
        raise GraphvizFailed(f"graphviz 'dot' timed out after {timeout:g} s") from exc
    except OSError as exc:  # found on PATH but not runnable
        raise GraphvizFailed(f"graphviz 'dot' could not be run ({executable}): {exc}") from exc
    if proc.returncode != 0:
        stderr = proc.stderr.decode("utf-8", errors="replace").strip()
        raise GraphvizFailed(
            f"graphviz 'dot -T{fmt}' failed with exit status {proc.returncode}: "
            f"{stderr or '(no error output)'}"
        )
    return proc.stdout
