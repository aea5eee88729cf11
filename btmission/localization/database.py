"""The place database of a map: descriptors at places sampled along its free space.

Seed 000 §IV-C1: "Using a point cloud map M_pcd and its corresponding trajectory Tr, 3DEG [...]
starts by partitioning the map and deriving the set of n descriptive vectors Q = {q_1 … q_n} [...]
and W = {w_1 … w_n}". Here the places are either

* **sampled along the free space** (:func:`sample_positions`): a lattice of ``spacing_m`` over every
  floor of the voxel map (the top face of rock with free space above it, so ramps and an upper
  level count), at ``height_m`` above the floor, where the sensor has ``clearance_m`` of free space
  around it; or
* **along a given trajectory** (:func:`positions_from_trajectory`), e.g. the mapping run's, resampled
  every ``spacing_m`` metres of path.

At each place the map's own voxel grid is "scanned" by the same simulated LiDAR the agents carry
(:func:`~btmission.localization.scan.simulate_scan`, noise-free, heading 0 = world +x), so the
map descriptors see what a real scan sees (walls hide what lies behind them), and the scan is
described by :func:`~btmission.localization.descriptor.describe`: ``Q`` are the ring keys (location
part) and ``W`` the polar images (orientation part). The database also keeps the map itself — the
voxel grid (to check a pose against free space) and the point cloud (the ICP target) — so that one
file is all a relocalization needs.

File format (``.npz``, written with ``numpy.savez_compressed``): ``format`` =
``"btmission-reloc-db"``, ``version`` = 1, ``positions`` (n × 3 sensor positions, m), ``floor_z``
(n), ``ring_keys`` (n × rings, float32), ``polar`` (n × rings × sectors, float32), ``cloud``
(m × 3 map points, float32), the voxel map as in :mod:`btmission.world.io` (``state``,
``resolution``, ``origin``, ``map_meta``), and JSON texts ``descriptor`` (the
:class:`~btmission.localization.descriptor.DescriptorParams`), ``sensor`` (the
:class:`~btmission.localization.scan.LidarSensor` the places were scanned with) and ``meta``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from btmission import limits
from btmission.errors import BtmissionError
from btmission.localization.descriptor import DescriptorParams, describe
from btmission.localization.scan import (
    OS1_32,
    LidarSensor,
    drop_see_through,
    from_record,
    pose_matrix,
    record,
    simulate_scan,
)
from btmission.types import FloatArray
from btmission.world.io import (
    MAP_FIELDS,
    NUMBER,
    TEXT,
    NpzField,
    json_field,
    read_npz,
    require_file,
)
from btmission.world.voxel import FREE, OCCUPIED, MapError, VoxelMap

DB_FORMAT = "btmission-reloc-db"
DB_VERSION = 1

F32Array = npt.NDArray[np.float32]


class DatabaseError(BtmissionError, ValueError):
    """A place database cannot be built, read or used."""


# ------------------------------------------------------------------------------------ places
def sample_positions(
    vm: VoxelMap, spacing_m: float = 1.0, height_m: float = 2.0, clearance_m: float = 0.5
) -> tuple[FloatArray, FloatArray]:
    """Sensor positions ``(n, 3)`` on a ``spacing_m`` lattice over every floor of ``vm``, at
    ``height_m`` above it, and the floors' heights ``(n,)``.

    A floor is the top face of an occupied voxel with free voxels above it; a place is kept when
    every voxel from the floor up to the sensor is free and the sensor is at least ``clearance_m``
    from the nearest occupied voxel. Raises :class:`DatabaseError` when no place qualifies.
    """
    from scipy import ndimage

    if not (spacing_m > 0 and height_m > 0 and clearance_m >= 0):
        raise DatabaseError("spacing and height must be > 0 and clearance ≥ 0")
    res = vm.resolution
    occ = vm.state == OCCUPIED
    free = vm.state == FREE
    nx, ny, nz = vm.shape
    up = int(np.floor(height_m / res)) + 1  # voxels from the floor to the one holding the sensor
    if up >= nz:
        raise DatabaseError(
            f"the map is {nz * res:g} m high: no room for a sensor {height_m:g} m up"
        )
    step = max(1, round(spacing_m / res))
    off = step // 2
    lattice = np.zeros((nx, ny), dtype=bool)
    lattice[off::step, off::step] = True
    cand = occ[:, :, : nz - up] & lattice[:, :, None]
    for j in range(1, up + 1):
        cand &= free[:, :, j : nz - up + j]
    if clearance_m > 0 and np.any(cand):
        dist = ndimage.distance_transform_edt(~occ) * res
        cand &= dist[:, :, up:nz] >= clearance_m
    idx = np.argwhere(cand)
    if len(idx) == 0:
        raise DatabaseError(
            f"no place of the map has a floor with {height_m:g} m of free space above it "
            f"(and {clearance_m:g} m of clearance): is the map's free space marked free?"
        )
    floor_z = vm.origin[2] + (idx[:, 2] + 1) * res
    xy = vm.index_to_world(idx)[:, :2]
    pos = np.column_stack([xy, floor_z + height_m])
    return pos.astype(np.float64), floor_z.astype(np.float64)


def positions_from_trajectory(
    vm: VoxelMap, trajectory: npt.ArrayLike, spacing_m: float = 1.0, height_m: float = 2.0
) -> tuple[FloatArray, FloatArray]:
    """Places every ``spacing_m`` metres along a trajectory ``(k, 3)`` of sensor positions (a
    polyline), with the floor under each (the top of the first occupied voxel below it; ``z -
    height_m`` where there is none). Points outside the map or in rock are dropped."""
    tr = np.asarray(trajectory, dtype=np.float64)
    if tr.ndim != 2 or tr.shape[1] != 3 or len(tr) == 0 or not np.all(np.isfinite(tr)):
        raise DatabaseError("a trajectory is a non-empty list of finite x, y, z positions")
    if not spacing_m > 0:
        raise DatabaseError("spacing must be > 0")
    seg = np.linalg.norm(np.diff(tr, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    stations = np.arange(0.0, s[-1] + 1e-9, spacing_m)
    pos = np.column_stack([np.interp(stations, s, tr[:, i]) for i in range(3)])
    idx = vm.world_to_index(pos)
    inside = vm.in_bounds(idx)
    pos, idx = pos[inside], idx[inside]
    ok = vm.state[tuple(idx.T)] != OCCUPIED
    pos, idx = pos[ok], idx[ok]
    if len(pos) == 0:
        raise DatabaseError("no point of the trajectory lies in the map's free space")
    floor_z = pos[:, 2] - height_m
    occ = vm.state == OCCUPIED
    for n, (i, j, k) in enumerate(idx):
        below = np.flatnonzero(occ[i, j, : k + 1])
        if len(below):
            floor_z[n] = vm.origin[2] + (below[-1] + 1) * vm.resolution
    return pos, floor_z


# ------------------------------------------------------------------------------------ database
@dataclass(eq=False)
class PlaceDatabase:
    """Descriptors of a map's places (``Q`` = ring keys, ``W`` = polar images) with the map."""

    positions: FloatArray
    floor_z: FloatArray
    ring_keys: F32Array
    polar: F32Array
    cloud: F32Array
    voxel_map: VoxelMap
    params: DescriptorParams = DescriptorParams()
    sensor: LidarSensor = OS1_32
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.positions)
        r, s = self.params.rings, self.params.sectors
        checks = [
            (self.positions.shape == (n, 3), f"positions {self.positions.shape} ≠ ({n}, 3)"),
            (self.floor_z.shape == (n,), f"floor_z {self.floor_z.shape} ≠ ({n},)"),
            (
                self.ring_keys.shape == (n, self.params.key_size),
                f"ring_keys {self.ring_keys.shape} ≠ ({n}, {self.params.key_size})",
            ),
            (self.polar.shape == (n, r, s), f"polar {self.polar.shape} ≠ ({n}, {r}, {s})"),
            (self.cloud.ndim == 2 and self.cloud.shape[1] == 3, f"cloud {self.cloud.shape}"),
            (n > 0, "no places"),
            (len(self.cloud) > 0, "an empty map cloud"),
        ]
        for name in ("positions", "floor_z", "ring_keys", "polar", "cloud"):
            values = getattr(self, name)
            if values.dtype.kind == "f" and not np.isfinite(values).all():
                checks.append((False, f"{name} has NaN or infinite values"))
        bad = [msg for ok, msg in checks if not ok]
        if bad:
            raise DatabaseError("inconsistent place database: " + "; ".join(bad))

    def __len__(self) -> int:
        return len(self.positions)

    def describe(self) -> str:
        vm = self.voxel_map
        ex = vm.extent
        return (
            f"{len(self):,} places, {self.params.rings}×{self.params.sectors} descriptors "
            f"(rings × sectors, {self.params.max_radius_m:g} m), {len(self.cloud):,} map points, "
            f"map {ex[0]:g} × {ex[1]:g} × {ex[2]:g} m at {vm.resolution:g} m, sensor {self.sensor.name}"
        )


def build_database(
    vm: VoxelMap,
    cloud: npt.ArrayLike | None = None,
    positions: tuple[FloatArray, FloatArray] | None = None,
    *,
    spacing_m: float = 1.0,
    height_m: float = 2.0,
    clearance_m: float = 0.5,
    sensor: LidarSensor = OS1_32,
    params: DescriptorParams = DescriptorParams(),
    progress: Callable[[int, int], object] | None = None,
) -> PlaceDatabase:
    """Scan and describe ``vm`` at its places (``positions`` = (sensor positions, floor heights),
    or :func:`sample_positions` with ``spacing_m``/``height_m``/``clearance_m``).

    ``cloud`` is the map's point cloud (the ICP target: a survey, in world coordinates); without
    one, the faces between free and occupied voxels are used
    (:func:`~btmission.world.minegen.survey_point_cloud` without noise). ``progress(done, total)``
    is called as places are scanned.
    """
    from btmission.world.minegen import survey_point_cloud

    if positions is None:
        positions = sample_positions(vm, spacing_m, height_m, clearance_m)
    pos, floor_z = (np.asarray(a, dtype=np.float64) for a in positions)
    if cloud is None:
        pts = survey_point_cloud(vm, seed=0, points_per_face=2, noise_m=0.0)
    else:
        pts = np.asarray(cloud, dtype=np.float32).reshape(-1, 3)
    if len(pts) == 0:
        raise DatabaseError("the map has no surface points (no face between free and occupied)")
    exact = replace(sensor, range_noise_m=0.0, dropout=0.0)
    n = len(pos)
    polar = np.zeros((n, params.rings, params.sectors), dtype=np.float32)
    keys = np.zeros((n, params.key_size), dtype=np.float32)
    every = max(1, n // 50)
    for i in range(n):
        scan = drop_see_through(simulate_scan(vm, pose_matrix(*pos[i]), exact, rng=None))
        d = describe(scan, params)
        polar[i], keys[i] = d.polar, d.ring_key
        if progress is not None and (i + 1 == n or (i + 1) % every == 0):
            progress(i + 1, n)
    meta = {"map": dict(vm.meta), "spacing_m": spacing_m, "height_m": height_m}
    return PlaceDatabase(
        pos,
        floor_z,
        keys,
        polar,
        np.asarray(pts, dtype=np.float32),
        vm,
        params,
        sensor,
        meta,
    )


# ------------------------------------------------------------------------------------ files
def save_database(db: PlaceDatabase, path: str | Path) -> Path:
    """Write ``db`` as a compressed ``.npz`` (see the module docstring for the fields)."""
    p = Path(path)
    if p.suffix.lower() != ".npz":
        raise DatabaseError(f"{p}: a place database is saved as .npz")
    p.parent.mkdir(parents=True, exist_ok=True)
    vm = db.voxel_map
    with p.open("wb") as fh:
        np.savez_compressed(
            fh,
            format=np.array(DB_FORMAT),
            version=np.array(DB_VERSION),
            positions=db.positions,
            floor_z=db.floor_z,
            ring_keys=db.ring_keys,
            polar=db.polar,
            cloud=db.cloud,
            state=vm.state,
            resolution=np.array(vm.resolution),
            origin=np.asarray(vm.origin, dtype=np.float64),
            map_meta=np.array(json.dumps(vm.meta, default=str)),
            descriptor=np.array(json.dumps(record(db.params))),
            sensor=np.array(json.dumps(record(db.sensor))),
            meta=np.array(json.dumps(db.meta, default=str)),
        )
    return p


_FIELDS = ("positions", "floor_z", "ring_keys", "polar", "cloud", "state", "resolution", "origin")
DB_FIELDS: tuple[NpzField, ...] = (
    *(f for f in MAP_FIELDS if f.name != "meta"),
    NpzField("positions", NUMBER, 2, "n × 3 sensor positions", 3),
    NpzField("floor_z", NUMBER, 1, "n floor heights"),
    NpzField("ring_keys", NUMBER, 2, "n × rings ring keys"),
    NpzField("polar", NUMBER, 3, "n × rings × sectors polar images"),
    NpzField("cloud", NUMBER, 2, "m × 3 map points", 3),
    NpzField("map_meta", TEXT, 0, "a JSON text"),
    NpzField("descriptor", TEXT, 0, "a JSON text"),
    NpzField("sensor", TEXT, 0, "a JSON text"),
    NpzField("meta", TEXT, 0, "a JSON text"),
)


def load_database(path: str | Path) -> PlaceDatabase:
    """Read a database written by :func:`save_database`; :class:`DatabaseError` names the file and
    what is wrong with it."""
    p = Path(path)
    try:
        require_file(p)
        data = read_npz(p, DB_FIELDS)
        fmt = str(data["format"]) if "format" in data else ""
        if fmt != DB_FORMAT:
            hint = (
                " (a voxel map: build a database from it with `btmission reloc build`)"
                if (fmt == "btmission-voxelmap")
                else ""
            )
            raise DatabaseError(
                f"{p}: not a btmission place database (format '{fmt or 'missing'}'){hint}"
            )
        version = int(data["version"]) if "version" in data else None
        if version != DB_VERSION:
            raise DatabaseError(
                f"{p}: unsupported place database version {version} "
                f"(this btmission reads {DB_VERSION})"
            )
        missing = [k for k in _FIELDS if k not in data]
        if missing:
            raise DatabaseError(f"{p}: the database lacks {', '.join(missing)}")
        if len(data["cloud"]) > limits.MAX_POINTS.limit:
            raise DatabaseError(
                f"{p}: field 'cloud': "
                + limits.MAX_POINTS.exceeded("its number of points", len(data["cloud"]))
            )
        records = {k: json_field(p, data, k) for k in ("descriptor", "sensor", "meta", "map_meta")}
    except MapError as exc:
        raise DatabaseError(str(exc)) from None
    field_name = "descriptor"
    try:
        params = from_record(DescriptorParams, records["descriptor"])
        field_name = "sensor"
        sensor = from_record(LidarSensor, records["sensor"])
        if sensor.channels * sensor.azimuths > limits.MAX_POINTS.limit:
            raise ValueError(
                limits.MAX_POINTS.exceeded("its beams (channels × azimuths)", sensor.beams)
            )
        field_name = ""
        origin = np.asarray(data["origin"], dtype=np.float64).ravel()
        vm = VoxelMap(data["state"], float(data["resolution"]), tuple(origin), records["map_meta"])  # type: ignore[arg-type]
        return PlaceDatabase(
            np.asarray(data["positions"], dtype=np.float64),
            np.asarray(data["floor_z"], dtype=np.float64),
            np.asarray(data["ring_keys"], dtype=np.float32),
            np.asarray(data["polar"], dtype=np.float32),
            np.asarray(data["cloud"], dtype=np.float32),
            vm,
            params,
            sensor,
            records["meta"],
        )
    except (KeyError, TypeError, ValueError, MapError) as exc:
        where = f"field '{field_name}': " if field_name else ""
        raise DatabaseError(f"{p}: {where}{exc}") from None


def random_poses(
    vm: VoxelMap,
    n: int,
    rng: np.random.Generator | int = 0,
    *,
    heights_m: tuple[float, float] = (1.0, 3.0),
    clearance_m: float = 0.7,
) -> list[FloatArray]:
    """``n`` random sensor poses (4×4) in the free space of ``vm``: uniformly over the floor area
    (every floor, as in :func:`sample_positions`), at a uniform height in ``heights_m`` above the
    floor, with a uniform heading; the benchmark's and the tests' query poses."""
    g = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(int(rng))
    lo, hi = heights_m
    if not 0 < lo <= hi:
        raise DatabaseError(f"heights must satisfy 0 < low ≤ high, got {heights_m}")
    pos, floor_z = sample_positions(vm, vm.resolution, hi, clearance_m)
    pick = g.integers(0, len(pos), size=n)
    jitter = g.uniform(-0.5, 0.5, size=(n, 2)) * vm.resolution
    h = g.uniform(lo, hi, size=n)
    yaw = g.uniform(-np.pi, np.pi, size=n)
    return [
        pose_matrix(pos[i, 0] + jitter[k, 0], pos[i, 1] + jitter[k, 1], floor_z[i] + h[k], yaw[k])
        for k, i in enumerate(pick)
    ]
