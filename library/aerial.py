"""Implementations of the ``aerial`` capability library (spec: ``aerial.yaml``).

The runtime issue binds these actions to a backend; until then the library is abstract: it
synthesises, checks and exports, and ``IMPLEMENTATIONS`` is empty.
"""

from __future__ import annotations

from importlib.resources import files

from btmission.plugins import Implementations

SPEC = files(__package__).joinpath("aerial.yaml")
"""The library file; the ``btmission.libraries`` entry point ``aerial`` points here."""

IMPLEMENTATIONS = Implementations("aerial")
