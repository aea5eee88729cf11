"""Build ``seed002_tunnel.npz``: the curving tunnel of seed 002's fast run (§4.3, Fig. 6, Fig. 19).

Run from the repository root: ``python missions/data/seed002_tunnel.py`` (writes
``missions/data/seed002_tunnel.npz``; the same file every time). ``--radius R --out FILE`` writes
the same tunnel with its bends at radius R (the curvature variants of ``btmission bench paper
--only seed002``). Every dimension and why it is what it is: ``missions/data/seed002_tunnel.md``.

The tunnel (x east, y north, z up, the floor at z = 0, rock 1 m below it and above the roof): one
drift 3.5 m wide (the paper's "slightly wider tunnels (~ 3.5 m) such as in Figure 6") and 4 m high
at its crown, closed behind the start, with no junction and no artifact; its centre line is
:data:`LAYOUT`: straights and bends of radius :data:`RADIUS_M` (left, right, left, right), ~200 m
long, so that 60 s at 2.3 m/s (~140 m) never reaches its far end.
"""

from __future__ import annotations

import argparse
import itertools
import math
from pathlib import Path

import numpy as np

from btmission.world.io import save_map
from btmission.world.minegen import FLOOR_ROCK_M, Tunnel, _carve
from btmission.world.voxel import OCCUPIED, VoxelMap

RESOLUTION_M = 0.5
WIDTH_M = 3.5
"""The paper's width of the Fig. 6 tunnel (§4.3: "slightly wider tunnels (~ 3.5 m)")."""
HEIGHT_M = 4.0
"""Crown height (3.2 m at the walls): an assumption, the paper gives no height."""
RADIUS_M = 20.0
"""Bend radius (centre line): an assumption, the paper gives none (see the .md)."""
START_BACK_M = 3.0
"""The MAV starts this far along the centre line from the tunnel's closed back end."""
MARGIN_M = 3.0
"""Rock kept around the tunnel's footprint up to the map's edge."""
STEP_M = 0.5
"""The centre line is carved as straight pieces this long (one voxel)."""
LAYOUT: tuple[tuple[str, float], ...] = (
    ("straight", 12.0),
    ("bend", 60.0),
    ("straight", 12.0),
    ("bend", -90.0),
    ("straight", 12.0),
    ("bend", 75.0),
    ("straight", 12.0),
    ("bend", -45.0),
    ("straight", 50.0),
)
"""Centre line from the back end, heading east: straights (m) and bends (degrees, left +)."""


def centre_line(radius_m: float = RADIUS_M) -> np.ndarray:
    """Points (x, y) every :data:`STEP_M` along :data:`LAYOUT` from (0, 0), heading east."""
    if radius_m <= WIDTH_M / 2:
        raise ValueError(f"the bend radius must exceed the half width ({WIDTH_M / 2} m)")
    pts = [(0.0, 0.0)]
    x = y = heading = 0.0
    for kind, value in LAYOUT:
        length = value if kind == "straight" else radius_m * math.radians(abs(value))
        n = max(1, round(length / STEP_M))
        turn = 0.0 if kind == "straight" else math.radians(value) / n
        step = length / n
        for _ in range(n):
            # a chord of the arc: heading at the middle of the piece
            heading += turn / 2
            x += step * math.cos(heading)
            y += step * math.sin(heading)
            heading += turn / 2
            pts.append((x, y))
    return np.asarray(pts)


def length_m(radius_m: float = RADIUS_M) -> float:
    """The centre line's length (m)."""
    c = centre_line(radius_m)
    return float(np.sum(np.hypot(*np.diff(c, axis=0).T)))


def build(radius_m: float = RADIUS_M) -> tuple[VoxelMap, tuple[float, float, float]]:
    """The voxel map (solid rock with the tunnel carved out) and the MAV's start on the floor,
    :data:`START_BACK_M` along the centre line; the map's corner is at (0, 0) so that every
    coordinate is positive."""
    c = centre_line(radius_m)
    lo = c.min(axis=0) - WIDTH_M / 2 - MARGIN_M
    hi = c.max(axis=0) + WIDTH_M / 2 + MARGIN_M
    c = c - lo
    size = (float(hi[0] - lo[0]), float(hi[1] - lo[1]), HEIGHT_M + 2 * FLOOR_ROCK_M)
    vm = VoxelMap.empty(size, RESOLUTION_M, (0.0, 0.0, -FLOOR_ROCK_M), fill=OCCUPIED)
    for a, b in itertools.pairwise(c):
        _carve(vm, Tunnel((a[0], a[1], 0.0), (b[0], b[1], 0.0), WIDTH_M, HEIGHT_M))
    k = round(START_BACK_M / STEP_M)
    vm.meta = {
        "generator": "missions/data/seed002_tunnel.py",
        "size": [round(v, 2) for v in size],
        "radius_m": radius_m,
        "length_m": round(length_m(radius_m), 1),
    }
    start = (round(float(c[k, 0]), 2), round(float(c[k, 1]), 2), 0.0)
    return vm, start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radius", type=float, default=RADIUS_M, help="bend radius (m)")
    ap.add_argument("--out", type=Path, default=Path(__file__).with_suffix(".npz"))
    args = ap.parse_args()
    if not math.isfinite(args.radius) or args.radius <= WIDTH_M / 2:
        ap.exit(2, f"error: --radius must be a number above {WIDTH_M / 2} m\n")
    vm, start = build(args.radius)
    path = save_map(vm, args.out)
    print(f"wrote {path} (start {list(start)}, {vm.meta['length_m']} m long)")


if __name__ == "__main__":
    main()
