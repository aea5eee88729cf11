"""Build ``seed000_field.npz``: the mine section of the seed 000 field test, reconstructed.

Run from the repository root: ``python missions/data/seed000_field.py`` (writes
``missions/data/seed000_field.npz``; the same file every time). Every dimension and why it is
what it is: ``missions/data/seed000_field.md``.

The section (x east, y north, z up, the floor at z = 0, rock 1 m below it and above the roofs):

* a main drift along y = 10 from x = 2 to x = 188 (the paper's "environment of almost
  200 meters", abstract and Fig. 11a), with the launch area in its middle (x ≈ 95);
* seven crosscuts to the north, 25 m apart (x = 20 ... 170), 40 m long, joined at their far
  ends by a parallel drift along y = 50: the "interconnected tunnels" of §VI-A;
* every tunnel 6 m wide and 5 m high at its crown (4.2 m at the walls).
"""

from __future__ import annotations

from pathlib import Path

from btmission.world.io import save_map
from btmission.world.minegen import FLOOR_ROCK_M, Tunnel, _carve
from btmission.world.voxel import OCCUPIED, VoxelMap

SIZE_M = (190.0, 56.0, 7.0)
"""x, y, z extent (the map spans [0, 190] × [0, 56] × [-1, 6])."""
RESOLUTION_M = 0.5
WIDTH_M = 6.0
HEIGHT_M = 5.0
DRIFT_Y = 10.0
BACK_DRIFT_Y = 50.0
CROSSCUTS_X = (20.0, 45.0, 70.0, 95.0, 120.0, 145.0, 170.0)


def tunnels() -> list[Tunnel]:
    """The section's drifts and crosscuts (floor points)."""
    out = [
        Tunnel(
            (2.0 + WIDTH_M / 2, DRIFT_Y, 0.0),
            (188.0 - WIDTH_M / 2, DRIFT_Y, 0.0),
            WIDTH_M,
            HEIGHT_M,
        ),
        Tunnel(
            (CROSSCUTS_X[0], BACK_DRIFT_Y, 0.0),
            (CROSSCUTS_X[-1], BACK_DRIFT_Y, 0.0),
            WIDTH_M,
            HEIGHT_M,
        ),
    ]
    out += [
        Tunnel((x, DRIFT_Y, 0.0), (x, BACK_DRIFT_Y, 0.0), WIDTH_M, HEIGHT_M) for x in CROSSCUTS_X
    ]
    return out


def build() -> VoxelMap:
    """The voxel map: solid rock with :func:`tunnels` carved out."""
    vm = VoxelMap.empty(SIZE_M, RESOLUTION_M, (0.0, 0.0, -FLOOR_ROCK_M), fill=OCCUPIED)
    for t in tunnels():
        _carve(vm, t)
    vm.meta = {"generator": "missions/data/seed000_field.py", "size": list(SIZE_M)}
    return vm


if __name__ == "__main__":
    path = save_map(build(), Path(__file__).with_suffix(".npz"))
    print(f"wrote {path}")
