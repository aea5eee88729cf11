"""The ``btmission`` console script: start the CLI, quietly even if Ctrl-C comes during start-up.

Importing a command (numpy, scipy, pydantic, py_trees ... behind it) takes up to a second; a
Ctrl-C in that second would otherwise print a ``KeyboardInterrupt`` traceback. This module imports nothing
heavy itself (``import btmission`` is lazy), so the window before our handling is milliseconds.
"""

from __future__ import annotations

import sys

EXIT_INTERRUPTED = 130  # 128 + SIGINT, as cli.common says


def main() -> None:
    """Console-script entry point (also ``python -m btmission``)."""
    try:
        from btmission.cli.main import main as cli_main
    except KeyboardInterrupt:
        sys.stderr.write("\ninterrupted\n")
        sys.exit(EXIT_INTERRUPTED)
    cli_main()


if __name__ == "__main__":  # pragma: no cover
    main()
