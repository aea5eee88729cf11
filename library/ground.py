"""Implementations of the ``ground`` capability library (spec: ``ground.yaml``).

The runtime issue binds these actions to a backend; until then the library is abstract: it
synthesises, checks and exports, and ``IMPLEMENTATIONS`` is empty.
"""

from __future__ import annotations

from importlib.resources import files

from btmission.plugins import Implementations

SPEC = files(__package__).joinpath("ground.yaml")
"""The library file; the ``btmission.libraries`` entry point ``ground`` points here."""

IMPLEMENTATIONS = Implementations("ground")
