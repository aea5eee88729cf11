"""Build a mission's world (the ``world:`` key of a mission file) as a :class:`VoxelMap`.

``{generate: mine, seed, size}`` → :func:`~btmission.world.minegen.generate_mine`;
``{generate: empty, size}`` → free space from the origin; ``{generate: warehouse, seed, size}``
→ :func:`~btmission.world.minegen.warehouse_world` (shelves and aisles); ``{file: path}`` → a ``.npz``, ``.ply`` or
``.pcd`` map relative to the mission file (:func:`~btmission.world.io.load_map`), at the mission's
``resolution``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from btmission.world.voxel import MapError, VoxelMap


def world_from_spec(world_spec: Any, base_dir: str | Path = ".") -> VoxelMap:
    """The voxel map a mission's ``world`` describes. Raises :class:`MapError` when it cannot be
    built (unreadable file, size too small for a mine...)."""
    from btmission.world.io import load_map
    from btmission.world.minegen import empty_world, generate_mine, warehouse_world

    spec = world_spec.map
    res = float(world_spec.resolution)
    if hasattr(spec, "file"):
        return load_map(Path(base_dir) / spec.file, res)
    kind = spec.generate
    if kind == "mine":
        return generate_mine(spec.seed, spec.size, res).map
    if kind == "empty":
        return empty_world(spec.size, res)
    if kind == "warehouse":
        return warehouse_world(spec.size, res, spec.seed)
    raise MapError(f"unknown map generator '{kind}' (expected mine, empty or warehouse)")
