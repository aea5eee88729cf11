"""A wall clock a test moves by hand (the ``wall`` fixture of ``tests/conftest.py`` puts it in
place of ``time.monotonic``)."""

from __future__ import annotations

from typing import Any


class WallClock:
    """``time.monotonic`` as the test sets it (the ``wall`` fixture puts it in place)."""

    def __init__(self) -> None:
        self._t = 1000.0
        self._read_on: list[Any] = []

    def __call__(self) -> float:
        return self._t

    @property
    def t(self) -> float:
        return self._t

    @t.setter
    def t(self, value: float) -> None:
        self._t = value
        for link in self._read_on:
            link.read_wall = value

    def read_on(self, link: Any) -> Any:
        """``link`` (a MAVLink provider's ``_Link``) is read to its end whenever the clock moves,
        as a running I/O thread reads it: its vehicle's silence counts up to now."""
        self._read_on.append(link)
        link.read_wall = self._t
        return link
