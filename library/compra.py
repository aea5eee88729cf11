"""Implementations of the ``compra`` capability library (spec: ``compra.yaml``).

The runtime issue binds these actions to a backend; until then the library is abstract: it
synthesises, checks and exports, and ``IMPLEMENTATIONS`` is empty.
"""

from __future__ import annotations

from importlib.resources import files

from btmission.plugins import Implementations

SPEC = files(__package__).joinpath("compra.yaml")
"""The library file; the ``btmission.libraries`` entry point ``compra`` points here."""

IMPLEMENTATIONS = Implementations("compra")
