"""A small generated mine and its place database, built once per test session (shared by the
relocalization, BT-leaf and CLI tests)."""

from __future__ import annotations

from functools import cache

from btmission.localization.database import PlaceDatabase, build_database
from btmission.localization.relocalize import Relocalizer
from btmission.world.minegen import GeneratedMine, generate_mine

SEED = 1
SIZE = (60.0, 40.0, 8.0)
OTHER_SEED = 2


def small_mine(seed: int = SEED) -> GeneratedMine:
    return _mine(seed)


def small_database(seed: int = SEED) -> PlaceDatabase:
    return _database(seed)


def small_relocalizer(seed: int = SEED) -> Relocalizer:
    return _relocalizer(seed)


# (cached by the seed alone: ``functools.cache`` on the functions above would keep
# ``small_database()`` and ``small_database(1)`` apart and build the same database twice)
@cache
def _mine(seed: int) -> GeneratedMine:
    return generate_mine(seed, SIZE, 0.5)


@cache
def _database(seed: int) -> PlaceDatabase:
    return build_database(_mine(seed).map)


@cache
def _relocalizer(seed: int) -> Relocalizer:
    return Relocalizer(_database(seed))
