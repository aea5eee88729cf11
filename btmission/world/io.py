"""Reading and writing voxel maps and point clouds: ``.npz`` (our own), ``.ply`` and ``.pcd``.

Formats
-------
``.npz``  btmission's own lossless format (``numpy.savez_compressed``): ``format`` =
          ``"btmission-voxelmap"``, ``version`` = 1, ``state`` (uint8 x·y·z grid, 0 free / 1 occupied
          / 2 unknown), ``resolution`` (m), ``origin`` (world corner of voxel 0,0,0) and ``meta``
          (JSON text).
``.ply``  read and written with `plyfile` (ASCII or binary, either endianness). Only the
          ``vertex`` element is used (meshes' faces are ignored).
``.pcd``  read and written with `pypcd4` (ASCII, binary and binary_compressed).

A point cloud becomes a voxel map in one of two ways:

* **With a per-point ``state`` field** (what :func:`save_map` writes): every point is a voxel centre
  with its state; the grid spans the points' bounding box and voxels without a point are free. The
  two corner voxels are always written, so a save/load round trip gives back the same grid.
* **Plain x, y, z** (a LiDAR survey, an OctoMap export...): voxels holding a point are occupied and
  the others are filled by ``fill``: ``"free"`` (default), ``"unknown"``, or ``"enclosed"`` (free
  inside the closed surfaces, unknown outside them: the part of the empty space that touches the
  grid's border is unknown). The grid is the points' bounding box snapped to multiples of the
  resolution, plus one voxel on every side. ``resolution`` must be given (or be in a PLY comment
  ``btmission resolution R``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from btmission.world.voxel import FREE, OCCUPIED, UNKNOWN, MapError, VoxelMap

NPZ_FORMAT = "btmission-voxelmap"
NPZ_VERSION = 1
MAP_SUFFIXES = (".npz", ".ply", ".pcd")
Fill = Literal["free", "unknown", "enclosed"]
FILLS: tuple[str, ...] = ("free", "unknown", "enclosed")

Columns = dict[str, npt.NDArray[np.generic]]


# ------------------------------------------------------------------------------------ clouds
def read_cloud(path: str | Path) -> tuple[Columns, list[str]]:
    """Read a ``.ply`` or ``.pcd`` point cloud: its per-point columns (``x``, ``y``, ``z``, ...) and
    header comments. Raises :class:`MapError` naming the file and the problem."""
    p = Path(path)
    suffix = p.suffix.lower()
    if not p.is_file():
        raise MapError(f"{p}: no such file")
    if suffix == ".ply":
        cols, comments = _read_ply(p)
    elif suffix == ".pcd":
        cols, comments = _read_pcd(p)
    else:
        raise MapError(f"{p}: not a point cloud (expected .ply or .pcd)")
    missing = [c for c in ("x", "y", "z") if c not in cols]
    if missing:
        raise MapError(
            f"{p}: the points have no {', '.join(missing)} field(s) (fields: {', '.join(cols) or 'none'})"
        )
    xyz = np.stack([np.asarray(cols[c], dtype=np.float64) for c in "xyz"], axis=1)
    if xyz.size and not np.all(np.isfinite(xyz)):
        bad = int(np.sum(~np.all(np.isfinite(xyz), axis=1)))
        raise MapError(f"{p}: {bad} point(s) have NaN or infinite coordinates")
    return cols, comments


def _read_ply(p: Path) -> tuple[Columns, list[str]]:
    from plyfile import PlyData

    try:
        ply = PlyData.read(str(p))
    except Exception as exc:  # plyfile raises PlyHeaderParseError, ValueError, struct.error...
        raise MapError(f"{p}: not a readable PLY file ({exc})") from None
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise MapError(f"{p}: PLY file has no 'vertex' element (elements: {', '.join(names)})")
    data = ply["vertex"].data
    cols: Columns = {name: np.asarray(data[name]) for name in data.dtype.names or ()}
    return cols, [str(c) for c in ply.comments]


def _read_pcd(p: Path) -> tuple[Columns, list[str]]:
    from pypcd4 import PointCloud

    try:
        pc = PointCloud.from_path(p)
    except Exception as exc:  # pydantic.ValidationError for bad headers, ValueError for data...
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise MapError(f"{p}: not a readable PCD file ({first})") from None
    cols: Columns = {name: np.asarray(pc.pc_data[name]).ravel() for name in pc.fields}
    return cols, []


def write_cloud(
    path: str | Path,
    columns: Columns,
    *,
    ascii: bool = False,
    comments: list[str] | None = None,
) -> None:
    """Write per-point ``columns`` (at least ``x``, ``y``, ``z``) as ``.ply`` or ``.pcd``.

    PCD files lose the comments (PCL's format has no place for them that readers keep)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if not all(c in columns for c in "xyz"):
        raise MapError("a point cloud needs x, y and z columns")
    n = len(columns["x"])
    if any(len(v) != n for v in columns.values()):
        raise MapError("point cloud columns differ in length")
    p.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".ply":
        from plyfile import PlyData, PlyElement

        rec = np.empty(n, dtype=[(k, np.asarray(v).dtype) for k, v in columns.items()])
        for k, v in columns.items():
            rec[k] = v
        el = PlyElement.describe(rec, "vertex")
        PlyData([el], text=ascii, comments=list(comments or [])).write(str(p))
    elif suffix == ".pcd":
        from pypcd4 import Encoding, PointCloud

        names = list(columns)
        arrays = [np.asarray(columns[k]) for k in names]
        pc = PointCloud.from_points(arrays, names, [a.dtype for a in arrays])
        pc.save(p, encoding=Encoding.ASCII if ascii else Encoding.BINARY)
    else:
        raise MapError(f"{p}: cannot write a point cloud as '{suffix}' (use .ply or .pcd)")


# ------------------------------------------------------------------------------------ voxelize
def voxelize(
    points: npt.ArrayLike,
    resolution: float,
    *,
    states: npt.ArrayLike | None = None,
    fill: Fill = "free",
) -> VoxelMap:
    """Turn points into a voxel map (see the module docstring for the two conventions)."""
    if not resolution > 0:
        raise MapError(f"resolution must be > 0, got {resolution}")
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise MapError("the point cloud is empty")
    if fill not in FILLS:
        raise MapError(f"unknown fill '{fill}' (expected one of: {', '.join(FILLS)})")
    lo = pts.min(axis=0)
    if states is not None:
        st = np.asarray(states).ravel()
        if len(st) != len(pts):
            raise MapError("the state field has a different length from the points")
        bad = ~np.isin(st, (FREE, OCCUPIED, UNKNOWN))
        if np.any(bad):
            raise MapError(
                f"voxel state {st[bad][0]!r} is not one of 0 (free), 1 (occupied), 2 (unknown)"
            )
        idx = np.rint((pts - lo) / resolution).astype(np.int64)
        shape = tuple(int(v) + 1 for v in idx.max(axis=0))
        grid = np.zeros(shape, dtype=np.uint8)
        grid[idx[:, 0], idx[:, 1], idx[:, 2]] = st.astype(np.uint8)
        origin = lo - resolution / 2
        return VoxelMap(grid, resolution, (origin[0], origin[1], origin[2]))
    origin = np.floor(lo / resolution) * resolution - resolution
    idx = np.floor((pts - origin) / resolution).astype(np.int64)
    shape = tuple(int(v) + 2 for v in idx.max(axis=0))
    grid = np.zeros(shape, dtype=np.uint8)
    grid[idx[:, 0], idx[:, 1], idx[:, 2]] = OCCUPIED
    if fill == "unknown":
        grid[grid != OCCUPIED] = UNKNOWN
    elif fill == "enclosed":
        _mark_outside_unknown(grid)
    return VoxelMap(grid, resolution, (origin[0], origin[1], origin[2]))


def _mark_outside_unknown(grid: npt.NDArray[np.uint8]) -> None:
    """Set to unknown every empty voxel connected to the grid's border through faces.

    Face connectivity, not the planner's 26: a surveyed wall puts a point in at least one of the
    two voxels on either side of each of its faces, so no face-connected route crosses it, while
    edge- and corner-connected ones slip through the staircase of a slanted wall."""
    from scipy import ndimage

    empty = grid != OCCUPIED
    labels, _ = ndimage.label(empty)
    border = np.concatenate(
        [
            labels[0].ravel(),
            labels[-1].ravel(),
            labels[:, 0].ravel(),
            labels[:, -1].ravel(),
            labels[:, :, 0].ravel(),
            labels[:, :, -1].ravel(),
        ]
    )
    outside = np.unique(border[border > 0])
    grid[np.isin(labels, outside)] = UNKNOWN


# ------------------------------------------------------------------------------------ maps
def load_map(path: str | Path, resolution: float | None = None, *, fill: Fill = "free") -> VoxelMap:
    """Load a voxel map from ``.npz``, ``.ply`` or ``.pcd``.

    ``resolution`` is required for point clouds without a ``btmission resolution`` comment; for
    ``.npz`` maps it is checked against the file's own when given. Raises :class:`MapError`.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in MAP_SUFFIXES:
        raise MapError(f"{p}: unknown map format '{suffix}' (expected .npz, .ply or .pcd)")
    if not p.is_file():
        raise MapError(f"{p}: no such file")
    if suffix == ".npz":
        vm = _load_npz(p)
        if resolution is not None and not np.isclose(resolution, vm.resolution):
            raise MapError(
                f"{p}: the map's resolution is {vm.resolution:g} m, not {resolution:g} m "
                "(set the same resolution, or convert the map)"
            )
        return vm
    cols, comments = read_cloud(p)
    own = _comment_resolution(comments)
    if own is not None and resolution is not None and not np.isclose(own, resolution):
        raise MapError(
            f"{p}: the map's resolution is {own:g} m, not {resolution:g} m "
            "(set the same resolution, or convert the map)"
        )
    res = resolution if resolution is not None else own
    if res is None:
        raise MapError(f"{p}: give the voxel resolution for this point cloud (e.g. 0.5 m)")
    xyz = np.stack([np.asarray(cols[c], dtype=np.float64) for c in "xyz"], axis=1)
    states = cols.get("state")
    vm = voxelize(xyz, res, states=states, fill=fill)
    vm.meta = {"source": str(p), "points": len(xyz)}
    return vm


def _comment_resolution(comments: list[str]) -> float | None:
    for c in comments:
        parts = c.split()
        if len(parts) == 3 and parts[0] == "btmission" and parts[1] == "resolution":
            try:
                return float(parts[2])
            except ValueError:
                return None
    return None


def read_npz(p: Path) -> dict[str, npt.NDArray[Any]]:
    """Every array of an ``.npz`` file (no pickles); :class:`MapError` when it cannot be read."""
    try:
        with p.open("rb") as fh, np.load(fh, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # zipfile.BadZipFile, ValueError, OSError...
        raise MapError(f"{p}: not a readable .npz file ({exc})") from None


def _load_npz(p: Path) -> VoxelMap:
    data = read_npz(p)
    fmt = str(data.get("format", ""))
    if fmt != NPZ_FORMAT:
        raise MapError(f"{p}: not a btmission voxel map (format '{fmt or 'missing'}')")
    version = int(data["version"]) if "version" in data else None
    if version != NPZ_VERSION:
        raise MapError(
            f"{p}: unsupported map version {version} (this btmission reads {NPZ_VERSION})"
        )
    missing = [k for k in ("state", "resolution", "origin") if k not in data]
    if missing:
        raise MapError(f"{p}: the map lacks {', '.join(missing)}")
    meta = json.loads(str(data["meta"])) if "meta" in data else {}
    origin = np.asarray(data["origin"], dtype=np.float64).ravel()
    if origin.shape != (3,):
        raise MapError(f"{p}: origin must hold three numbers")
    return VoxelMap(
        data["state"], float(data["resolution"]), (origin[0], origin[1], origin[2]), meta
    )


def save_map(vm: VoxelMap, path: str | Path, *, ascii: bool = False) -> Path:
    """Write ``vm`` as ``.npz`` (lossless, compressed) or as a ``.ply``/``.pcd`` cloud of voxel
    centres with a ``state`` field (non-free voxels and the two corner voxels)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in MAP_SUFFIXES:
        raise MapError(f"{p}: unknown map format '{suffix}' (expected .npz, .ply or .pcd)")
    p.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".npz":
        with p.open("wb") as fh:
            np.savez_compressed(
                fh,
                format=np.array(NPZ_FORMAT),
                version=np.array(NPZ_VERSION),
                state=vm.state,
                resolution=np.array(vm.resolution),
                origin=np.asarray(vm.origin, dtype=np.float64),
                meta=np.array(json.dumps(vm.meta, default=str)),
            )
        return p
    mask = vm.state != FREE
    mask[0, 0, 0] = mask[-1, -1, -1] = True
    idx = np.argwhere(mask)
    centres = vm.index_to_world(idx)
    cols: Columns = {
        "x": centres[:, 0].astype(np.float64),
        "y": centres[:, 1].astype(np.float64),
        "z": centres[:, 2].astype(np.float64),
        "state": vm.state[mask].astype(np.uint8),
    }
    comments = [
        f"btmission resolution {vm.resolution:.17g}",
        "btmission voxel map: state 0 free, 1 occupied, 2 unknown",
    ]
    write_cloud(p, cols, ascii=ascii, comments=comments)
    return p
