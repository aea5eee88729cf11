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


@cache
def small_mine(seed: int = SEED) -> GeneratedMine:
    return generate_mine(seed, SIZE, 0.5)


@cache
def small_database(seed: int = SEED) -> PlaceDatabase:
    return build_database(small_mine(seed).map)


@cache
def small_relocalizer(seed: int = SEED) -> Relocalizer:
    return Relocalizer(small_database(seed))
