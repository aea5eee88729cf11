"""Seeded procedural underground mines, and the point cloud a LiDAR survey of one would give.

The mine is solid rock with tunnels carved out of it, in the shape of the ~200 m mine of seed 000
§V (Fig. 14): a network of 4-5 m wide, 4-5 m high drifts with junctions, at least one loop, dead
ends, ramps between floor heights, a launch area (the portal where the agents start) near the
origin, a few unknown patches (parts of the tunnels the survey did not see) and, optionally,
parked machines as clutter. When the map is at least 11 m high there is an upper level reached by a
long ramp.

Coordinates: x, y horizontal, z up; the main level's floor is at **z = 0** and the map starts 1 m
below it, so a generated map of ``size = (X, Y, Z)`` spans ``[0, X] × [0, Y] × [-1, Z - 1]``. A
drone at the launch area sits at z = 0 and flies at z ≈ 2 (2 m above the floor).

Everything is drawn from ``numpy.random.default_rng(seed)``: the same seed, size and resolution give
the same map, voxel for voxel. Carving works on the bounding box of each tunnel segment, so a
200 × 120 × 12 m mine at 0.5 m (~2 M voxels) takes a fraction of a second.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from btmission.types import Vec3
from btmission.world.voxel import FREE, OCCUPIED, UNKNOWN, MapError, VoxelMap, checked_shape

FLOOR_ROCK_M = 1.0
"""Rock below the main level's floor (the map starts at z = -FLOOR_ROCK_M)."""
UPPER_FLOOR_M = 6.0
"""Floor of the upper level, when the map is tall enough for one (Z ≥ 11 m)."""
LAUNCH_SIZE_M = (12.0, 8.0, 5.0)
"""Launch area (portal) at the origin corner: x, y extent and height."""
MIN_SIZE_M = (40.0, 30.0, 6.0)


@dataclass(frozen=True)
class Tunnel:
    """A straight drift from ``a`` to ``b`` (floor points, metres); ``width``/``height`` in metres."""

    a: Vec3
    b: Vec3
    width: float
    height: float
    kind: str = "drift"
    """drift, ramp, dead_end, launch or upper."""

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.subtract(self.b, self.a)[:2]))

    def point(self, t: float, above_floor: float = 0.0) -> Vec3:
        """The floor point at fraction ``t`` along the tunnel, raised by ``above_floor`` metres."""
        a, b = np.asarray(self.a), np.asarray(self.b)
        p = a + t * (b - a)
        return float(p[0]), float(p[1]), float(p[2] + above_floor)


@dataclass(frozen=True)
class Machine:
    """A parked machine (an occupied box): centre of its footprint on the floor, size, heading."""

    centre: Vec3
    size: Vec3
    heading: float


@dataclass
class GeneratedMine:
    """A generated mine: the voxel map and how it was laid out (for missions, tests, docs)."""

    map: VoxelMap
    seed: int
    launch: Vec3
    """Centre of the launch area's floor."""
    nodes: list[Vec3]
    """Junctions (floor points)."""
    tunnels: list[Tunnel]
    unknown_patches: list[tuple[Vec3, float]] = field(default_factory=list)
    """(centre, radius) of each patch whose free voxels were marked unknown."""
    machines: list[Machine] = field(default_factory=list)

    @property
    def dead_ends(self) -> list[Vec3]:
        return [t.b for t in self.tunnels if t.kind == "dead_end"]


# ------------------------------------------------------------------------------------ layout
def _check_size(size: Sequence[float], resolution: float) -> tuple[float, float, float]:
    if len(size) != 3:
        raise MapError(f"size must be three numbers [x, y, z] in metres, got {list(size)}")
    sx, sy, sz = (float(v) for v in size)
    lo = MIN_SIZE_M
    if not all(math.isfinite(v) for v in (sx, sy, sz)):
        raise MapError(f"size must be three finite numbers (m), got {sx:g} × {sy:g} × {sz:g}")
    if sx < lo[0] or sy < lo[1] or sz < lo[2]:
        raise MapError(
            f"a mine needs at least {lo[0]:g} × {lo[1]:g} × {lo[2]:g} m (got {sx:g} × {sy:g} × {sz:g})"
        )
    if not 0 < resolution <= 1.0:
        raise MapError(f"mine resolution must be in (0, 1] m, got {resolution:g}")
    checked_shape((sx, sy, sz), resolution)  # the voxel budget, before anything is laid out
    return sx, sy, sz


def check_seed(seed: int) -> int:
    """A generator seed: a whole number ≥ 0 (numpy's generators refuse negative ones)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise MapError(f"seed must be a whole number ≥ 0, got {seed!r}")
    return int(seed)


def _spanning_edges(
    rng: np.random.Generator, n_cols: int, n_rows: int
) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Random spanning tree over a lattice of junctions (Kruskal on shuffled edges) and the edges
    it left out."""

    def nid(i: int, j: int) -> int:
        return i * n_rows + j

    cand: list[tuple[int, int]] = []
    for i in range(n_cols):
        for j in range(n_rows):
            if i + 1 < n_cols:
                cand.append((nid(i, j), nid(i + 1, j)))
            if j + 1 < n_rows:
                cand.append((nid(i, j), nid(i, j + 1)))
    order = rng.permutation(len(cand))
    parent = list(range(n_cols * n_rows))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    tree: list[tuple[int, int]] = []
    rest: list[tuple[int, int]] = []
    for k in order:
        a, b = cand[int(k)]
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
            tree.append((a, b))
        else:
            rest.append((a, b))
    return tree, rest


def _clear_of(a: Vec3, b: Vec3, w: float, others: list[Tunnel], from_m: float) -> bool:
    """Whether the drift a → b (width w) stays 1.5 m of rock away, in plan view, from every drift
    in ``others``, ignoring its first ``from_m`` metres (where it leaves a junction)."""
    pa, pb = np.asarray(a[:2]), np.asarray(b[:2])
    length = float(np.linalg.norm(pb - pa))
    ts = np.arange(min(from_m, length), length + 1e-9, 0.5) / max(length, 1e-9)
    pts = pa[None, :] + ts[:, None] * (pb - pa)[None, :]
    # Drifts whose bounding box is farther than any clearance (plus 1 m to spare) from this one's
    # are skipped: same answer, without their numpy work (most of a mine's generation time).
    reach = (w + max((t.width for t in others), default=0.0)) / 2 + 1.5 + 1.0
    x0, x1 = min(a[0], b[0]) - reach, max(a[0], b[0]) + reach
    y0, y1 = min(a[1], b[1]) - reach, max(a[1], b[1]) + reach
    for t in others:
        if (
            max(t.a[0], t.b[0]) < x0
            or min(t.a[0], t.b[0]) > x1
            or max(t.a[1], t.b[1]) < y0
            or min(t.a[1], t.b[1]) > y1
        ):
            continue
        qa, qb = np.asarray(t.a[:2]), np.asarray(t.b[:2])
        d = qb - qa
        l2 = float(d @ d)
        u = np.clip(((pts - qa) @ d) / l2, 0.0, 1.0) if l2 > 0 else np.zeros(len(pts))
        dist = np.linalg.norm(pts - (qa + u[:, None] * d), axis=1)
        if np.any(dist < (w + t.width) / 2 + 1.5):
            return False
    return True


def _layout(
    rng: np.random.Generator, sx: float, sy: float, sz: float, clutter: bool
) -> tuple[list[Vec3], list[Tunnel], list[Machine], list[tuple[Vec3, float]], Vec3]:
    margin = 9.0
    spacing = 36.0
    n_cols = max(2, round((sx - 2 * margin) / spacing) + 1)
    n_rows = max(2, round((sy - 2 * margin) / spacing) + 1)
    xs = np.linspace(margin + 6.0, sx - margin, n_cols)
    ys = np.linspace(margin + 4.0, sy - margin, n_rows)
    jx = 0.2 * (xs[1] - xs[0]) if n_cols > 1 else 0.0
    jy = 0.2 * (ys[1] - ys[0]) if n_rows > 1 else 0.0
    has_upper = sz - FLOOR_ROCK_M >= UPPER_FLOOR_M + 5.0
    # Raised junctions make ramps; with an upper level they stay low enough (ceilings ≤ 5.5 m) to
    # leave rock under the upper floor (6 m), so upper drifts may pass over main-level ones.
    max_rise = 0.5 if has_upper else max(0.0, min(2.0, sz - FLOOR_ROCK_M - 5.5))
    nodes: list[Vec3] = []
    for i in range(n_cols):
        for j in range(n_rows):
            x = float(np.clip(xs[i] + rng.uniform(-jx, jx), margin, sx - margin))
            y = float(np.clip(ys[j] + rng.uniform(-jy, jy), margin, sy - margin))
            # Some junctions sit higher: the drifts to them are ramps.
            z = float(rng.choice([0.0, 0.0, max_rise])) if max_rise >= 0.5 else 0.0
            nodes.append((x, y, round(z, 1)))
    nodes[0] = (nodes[0][0], nodes[0][1], 0.0)  # the junction next to the portal is level

    def width() -> float:
        return float(rng.uniform(4.0, 5.0))

    def height() -> float:
        return float(rng.uniform(4.0, 5.0))

    tree, rest = _spanning_edges(rng, n_cols, n_rows)
    n_loops = max(1, len(rest) // 3)
    extra = [rest[int(k)] for k in rng.permutation(len(rest))[:n_loops]]
    tunnels: list[Tunnel] = []
    for a, b in tree + extra:
        kind = "ramp" if nodes[a][2] != nodes[b][2] else "drift"
        tunnels.append(Tunnel(nodes[a], nodes[b], width(), height(), kind))

    # Launch area (portal chamber at the origin corner) and the drift joining it to junction 0.
    lx, ly, lz = LAUNCH_SIZE_M
    launch: Vec3 = (1.0 + lx / 2, 1.0 + ly / 2, 0.0)
    tunnels.append(
        Tunnel(
            (1.0 + ly / 2, launch[1], 0.0), (1.0 + lx - ly / 2, launch[1], 0.0), ly, lz, "launch"
        )
    )
    tunnels.append(Tunnel(launch, nodes[0], width(), height(), "drift"))

    # Dead ends: short drifts from junctions that lead nowhere, kept inside the map.
    n_dead = max(2, len(nodes) // 4)
    for k in rng.permutation(len(nodes))[:n_dead]:
        x0, y0, z0 = nodes[int(k)]
        for _ in range(10):
            ang = rng.uniform(0, 2 * np.pi)
            length = rng.uniform(12.0, 22.0)
            x1, y1 = x0 + length * np.cos(ang), y0 + length * np.sin(ang)
            if margin - 4 <= x1 <= sx - margin + 4 and margin - 4 <= y1 <= sy - margin + 4:
                tunnels.append(
                    Tunnel(nodes[int(k)], (float(x1), float(y1), z0), width(), height(), "dead_end")
                )
                break

    # Upper level: a long ramp (about 1:7) from a main-level junction up to a few drifts.
    if has_upper:
        low = list(tunnels)  # the upper level must not cut into the main level's drifts
        for k in rng.permutation(np.arange(1, len(nodes))):
            start = nodes[int(k)]
            run = 7.0 * (UPPER_FLOOR_M - start[2])
            ramp_w = width()
            top: Vec3 | None = None
            ang = 0.0
            for _ in range(12):
                ang = rng.uniform(0, 2 * np.pi)
                x1, y1 = start[0] + run * np.cos(ang), start[1] + run * np.sin(ang)
                end: Vec3 = (float(x1), float(y1), UPPER_FLOOR_M)
                inside = margin <= x1 <= sx - margin and margin <= y1 <= sy - margin
                # leave the junction it starts from; from there on, rock around it
                if inside and _clear_of(start, end, ramp_w, low, from_m=ramp_w + 4.0):
                    top = end
                    break
            if top is None:
                continue
            tunnels.append(Tunnel(start, top, ramp_w, 4.5, "ramp"))
            for _ in range(2):
                a2 = ang + rng.uniform(-2.0, 2.0)
                ln = rng.uniform(15.0, 30.0)
                x2 = float(np.clip(top[0] + ln * np.cos(a2), margin, sx - margin))
                y2 = float(np.clip(top[1] + ln * np.sin(a2), margin, sy - margin))
                tunnels.append(Tunnel(top, (x2, y2, UPPER_FLOOR_M), width(), 4.5, "upper"))
            break

    # Parked machines: boxes against a wall of a level drift, leaving room to pass.
    machines: list[Machine] = []
    if clutter:
        drifts = [t for t in tunnels if t.kind == "drift" and t.length > 20.0 and t.a[2] == t.b[2]]
        for k in rng.permutation(len(drifts))[: min(3, len(drifts))]:
            t = drifts[int(k)]
            d = np.subtract(t.b, t.a)[:2] / max(t.length, 1e-9)
            nrm = np.array([-d[1], d[0]]) * rng.choice([-1.0, 1.0])
            mw, ml, mh = 2.4, 7.0, 2.8
            c = np.asarray(t.point(float(rng.uniform(0.35, 0.65)))[:2]) + nrm * (
                t.width / 2 - mw / 2 - 0.3
            )
            machines.append(
                Machine(
                    (float(c[0]), float(c[1]), t.a[2]), (ml, mw, mh), float(np.arctan2(d[1], d[0]))
                )
            )

    # Unknown patches: parts of drifts the survey missed (never the launch area).
    patches: list[tuple[Vec3, float]] = []
    cands = [t for t in tunnels if t.kind in ("drift", "dead_end", "ramp") and t.length > 15.0]
    for k in rng.permutation(len(cands))[: min(3, len(cands))]:
        t = cands[int(k)]
        patches.append((t.point(float(rng.uniform(0.3, 0.7)), 2.0), float(rng.uniform(2.5, 4.0))))
    return nodes, tunnels, machines, patches, launch


# ------------------------------------------------------------------------------------ carving
def _window(
    vm: VoxelMap, lo: npt.ArrayLike, hi: npt.ArrayLike
) -> tuple[
    tuple[slice, slice, slice],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
]:
    """Index slices covering world box [lo, hi] (clipped) and the voxel-centre coordinates there."""
    i0 = np.clip(vm.world_to_index(lo), 0, np.asarray(vm.shape))
    i1 = np.clip(vm.world_to_index(hi) + 1, 0, np.asarray(vm.shape))
    sl = (
        slice(int(i0[0]), int(i1[0])),
        slice(int(i0[1]), int(i1[1])),
        slice(int(i0[2]), int(i1[2])),
    )
    r, o = vm.resolution, vm.origin
    cx = o[0] + (np.arange(sl[0].start, sl[0].stop) + 0.5) * r
    cy = o[1] + (np.arange(sl[1].start, sl[1].stop) + 0.5) * r
    cz = o[2] + (np.arange(sl[2].start, sl[2].stop) + 0.5) * r
    return sl, cx.astype(np.float64), cy.astype(np.float64), cz.astype(np.float64)


def _carve(vm: VoxelMap, t: Tunnel) -> None:
    """Free the voxels inside tunnel ``t``: a horizontal capsule of half-width w/2 around the
    segment, from the (linearly interpolated) floor up to an arched roof of height h at the centre
    and h - 0.8 m at the walls."""
    a, b = np.asarray(t.a), np.asarray(t.b)
    half = t.width / 2
    lo = np.minimum(a, b) - np.array([half, half, 0.5])
    hi = np.maximum(a, b) + np.array([half, half, t.height + 0.5])
    sl, cx, cy, cz = _window(vm, lo, hi)
    if min(len(cx), len(cy), len(cz)) == 0:
        return
    dxy = (b - a)[:2]
    l2 = float(dxy @ dxy)
    px = cx[:, None] - a[0]
    py = cy[None, :] - a[1]
    tt = (
        np.clip((px * dxy[0] + py * dxy[1]) / l2, 0.0, 1.0)
        if l2 > 0
        else np.zeros((len(cx), len(cy)))
    )
    dist = np.hypot(px - tt * dxy[0], py - tt * dxy[1])
    floor = a[2] + tt * (b[2] - a[2])
    roof = floor + t.height - 0.8 * np.clip(dist / half, 0.0, 1.0) ** 2
    inside2d = dist <= half
    z = cz[None, None, :]
    inside = inside2d[:, :, None] & (z > floor[:, :, None]) & (z < roof[:, :, None])
    view = vm.state[sl]
    view[inside] = FREE


def _place_machine(vm: VoxelMap, m: Machine) -> None:
    ml, mw, mh = m.size
    rad = np.hypot(ml, mw) / 2
    c = np.asarray(m.centre)
    sl, cx, cy, cz = _window(vm, c - np.array([rad, rad, 0.0]), c + np.array([rad, rad, mh]))
    if min(len(cx), len(cy), len(cz)) == 0:
        return
    ch, sh = np.cos(m.heading), np.sin(m.heading)
    px = cx[:, None] - c[0]
    py = cy[None, :] - c[1]
    along = px * ch + py * sh
    across = -px * sh + py * ch
    foot = (np.abs(along) <= ml / 2) & (np.abs(across) <= mw / 2)
    z = cz[None, None, :]
    box = foot[:, :, None] & (z > c[2]) & (z < c[2] + mh)
    vm.state[sl][box] = OCCUPIED


def _mark_unknown(vm: VoxelMap, centre: Vec3, radius: float) -> None:
    c = np.asarray(centre)
    sl, cx, cy, cz = _window(vm, c - radius, c + radius)
    if min(len(cx), len(cy), len(cz)) == 0:
        return
    d2 = (
        (cx[:, None, None] - c[0]) ** 2
        + (cy[None, :, None] - c[1]) ** 2
        + (cz[None, None, :] - c[2]) ** 2
    )
    view = vm.state[sl]
    view[(d2 <= radius**2) & (view == FREE)] = UNKNOWN


def generate_mine(
    seed: int,
    size: Sequence[float] = (200.0, 120.0, 12.0),
    resolution: float = 0.5,
    *,
    clutter: bool = True,
    unknown: bool = True,
) -> GeneratedMine:
    """Generate the mine for ``seed`` (deterministic), ``size`` metres at ``resolution`` m.

    Raises :class:`MapError` for a size too small to hold a mine (below 40 × 30 × 6 m) or a
    resolution outside (0, 1] m.
    """
    seed = check_seed(seed)
    sx, sy, sz = _check_size(size, resolution)
    rng = np.random.default_rng(seed)
    nodes, tunnels, machines, patches, launch = _layout(rng, sx, sy, sz, clutter)
    vm = VoxelMap.empty((sx, sy, sz), resolution, (0.0, 0.0, -FLOOR_ROCK_M), fill=OCCUPIED)
    for t in tunnels:
        _carve(vm, t)
    for m in machines:
        _place_machine(vm, m)
    if unknown:
        for c, r in patches:
            _mark_unknown(vm, c, r)
    else:
        patches = []
    vm.meta = {
        "generator": "mine",
        "seed": int(seed),
        "size": [sx, sy, sz],
        "clutter": clutter,
    }
    return GeneratedMine(vm, int(seed), launch, nodes, tunnels, patches, machines)


# ------------------------------------------------------------------------------------ survey
def survey_point_cloud(
    vm: VoxelMap, seed: int = 0, points_per_face: int = 2, noise_m: float = 0.02
) -> npt.NDArray[np.float32]:
    """The point cloud a dense LiDAR survey of the free space would give: points scattered on every
    face between a free voxel and an occupied one (rock walls, floors, roofs, machines), with
    Gaussian range noise. Unknown voxels were not seen, so their faces give no points.

    Returns an ``(N, 3)`` float32 array in world coordinates.
    """
    rng = np.random.default_rng(int(seed))
    occ = vm.state == OCCUPIED
    free = vm.state == FREE
    r = vm.resolution
    chunks: list[npt.NDArray[np.float64]] = []
    for axis in range(3):
        for step in (1, -1):
            # occupied voxel whose neighbour along +axis (step 1) or -axis (step -1) is free
            n = occ.shape[axis]
            a = [slice(None)] * 3
            b = [slice(None)] * 3
            if step == 1:
                a[axis], b[axis] = slice(0, n - 1), slice(1, n)
            else:
                a[axis], b[axis] = slice(1, n), slice(0, n - 1)
            faces = occ[tuple(a)] & free[tuple(b)]
            idx = np.argwhere(faces)
            if step == -1:
                idx[:, axis] += 1
            if len(idx) == 0:
                continue
            idx = np.repeat(idx, points_per_face, axis=0)
            centre = vm.index_to_world(idx)
            jitter = rng.uniform(-0.5, 0.5, size=centre.shape) * r
            jitter[:, axis] = 0.5 * r * step
            pts = centre + jitter
            pts[:, axis] += rng.normal(0.0, noise_m, size=len(pts))
            chunks.append(pts)
    if not chunks:
        return np.zeros((0, 3), dtype=np.float32)
    return np.concatenate(chunks).astype(np.float32)


def empty_world(size: Sequence[float], resolution: float) -> VoxelMap:
    """Free space of ``size`` metres from the origin (the ``{generate: empty}`` world)."""
    vm = VoxelMap.empty(size, resolution)
    vm.meta = {"generator": "empty", "size": [float(v) for v in size]}
    return vm


def warehouse_world(size: Sequence[float], resolution: float, seed: int = 0) -> VoxelMap:
    """A warehouse floor like seed 003's lab (Fig. 1, Fig. 10): rows of shelves with aisles.

    Shelves are 1 m deep, full height, in rows along x separated by 2 m aisles; each row is cut
    into racks with 1.5 m cross-aisles between them (at seeded positions), and a 2.5 m open strip
    runs along each wall (the docks and drop-off area). No floor, walls or roof: the map is the
    free space the robots drive in, standing on z = 0. The same seed gives the same map.
    """
    seed = check_seed(seed)
    checked_shape(size, resolution)
    x, y, _ = (float(v) for v in size)
    if x < 8 or y < 8:
        raise MapError(f"a warehouse needs at least 8 × 8 m, got {x:g} × {y:g}")
    vm = VoxelMap.empty(size, resolution)
    rng = np.random.default_rng(seed)
    margin, depth, aisle, cross = 2.5, 1.0, 2.0, 1.5

    def cells(lo: float, hi: float, n: int) -> slice:
        return slice(max(0, round(lo / resolution)), min(n, round(hi / resolution)))

    nx, ny, _ = vm.shape
    y0 = margin
    while y0 + depth <= y - margin:
        x0 = margin
        while x0 < x - margin:
            length = float(rng.uniform(3.0, 6.0))
            x1 = min(x0 + length, x - margin)
            if x1 - x0 >= 1.0:
                vm.state[cells(x0, x1, nx), cells(y0, y0 + depth, ny), :] = OCCUPIED
            x0 = x1 + cross
        y0 += depth + aisle
    vm.meta = {"generator": "warehouse", "seed": seed, "size": [x, y, float(size[2])]}
    return vm
