"""A wall clock a test moves by hand (the ``wall`` fixture of ``tests/conftest.py`` puts it in
place of ``time.monotonic``)."""

from __future__ import annotations


class WallClock:
    """``time.monotonic`` as the test sets it (the ``wall`` fixture puts it in place)."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t
