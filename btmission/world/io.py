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
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from btmission import limits
from btmission.world.voxel import FREE, OCCUPIED, UNKNOWN, MapError, VoxelMap, check_grid

NPZ_FORMAT = "btmission-voxelmap"
NPZ_VERSION = 1
MAP_SUFFIXES = (".npz", ".ply", ".pcd")
Fill = Literal["free", "unknown", "enclosed"]
FILLS: tuple[str, ...] = ("free", "unknown", "enclosed")

Columns = dict[str, npt.NDArray[np.generic]]


# ------------------------------------------------------------------------------------ clouds
def require_file(p: Path) -> None:
    """:class:`MapError` unless ``p`` is a regular file (a FIFO or a device is never opened)."""
    if not p.is_file():
        raise MapError(f"{p}: not a regular file" if p.exists() else f"{p}: no such file")


def read_cloud(path: str | Path) -> tuple[Columns, list[str]]:
    """Read a ``.ply`` or ``.pcd`` point cloud: its per-point columns (``x``, ``y``, ``z``, ...) and
    header comments. Raises :class:`MapError` naming the file and the problem."""
    p = Path(path)
    suffix = p.suffix.lower()
    require_file(p)
    if suffix not in (".ply", ".pcd"):
        raise MapError(f"{p}: not a point cloud (expected .ply or .pcd)")
    declared = _declared_points(p)
    if declared > limits.MAX_POINTS.limit:
        raise MapError(f"{p}: " + limits.MAX_POINTS.exceeded("its number of points", declared))
    cols, comments = _read_ply(p) if suffix == ".ply" else _read_pcd(p)
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


def _declared_points(p: Path) -> int:
    """The number of items a ``.ply`` header (every element) or a ``.pcd`` header (``POINTS``, or
    ``WIDTH`` × ``HEIGHT``) declares; 0 when the header cannot be read (the reader then says why)."""
    with p.open("rb") as fh:
        head = fh.read(65536)
    total, width, height = 0, 1, 1
    for raw in head.split(b"\n"):
        words = raw.split()
        if not words:
            continue
        key = words[0].lower()
        try:
            if key == b"element" and len(words) >= 3:
                total += int(words[2])
            elif key == b"points" and len(words) >= 2:
                total = max(total, int(words[1]))
            elif key == b"width" and len(words) >= 2:
                width = int(words[1])
            elif key == b"height" and len(words) >= 2:
                height = int(words[1])
        except ValueError:
            continue
        if key in (b"end_header", b"data"):
            break
    if p.suffix.lower() == ".pcd":
        total = max(total, width * height)
    return total


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
    held = min((len(v) for v in cols.values()), default=0)
    if held != pc.metadata.points:  # pypcd4 reads a cut-off ASCII body without a word
        raise MapError(
            f"{p}: the header declares {pc.metadata.points:,} points but the file holds {held:,} "
            "(cut off?)"
        )
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
    if not (math.isfinite(resolution) and resolution > 0):
        raise MapError(f"resolution must be a finite number > 0, got {resolution}")
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
        span = np.rint((pts.max(axis=0) - lo) / resolution)
        shape = tuple(int(v) + 1 for v in span)
        check_grid(shape, f"{len(pts):,} points at {resolution:g} m")
        idx = np.rint((pts - lo) / resolution).astype(np.int64)
        grid = np.zeros(shape, dtype=np.uint8)
        grid[idx[:, 0], idx[:, 1], idx[:, 2]] = st.astype(np.uint8)
        origin = lo - resolution / 2
        return VoxelMap(grid, resolution, (origin[0], origin[1], origin[2]))
    origin = np.floor(lo / resolution) * resolution - resolution
    span = np.floor((pts.max(axis=0) - origin) / resolution)
    shape = tuple(int(v) + 2 for v in span)
    check_grid(shape, f"{len(pts):,} points spanning {_span(pts)} m at {resolution:g} m")
    idx = np.floor((pts - origin) / resolution).astype(np.int64)
    grid = np.zeros(shape, dtype=np.uint8)
    grid[idx[:, 0], idx[:, 1], idx[:, 2]] = OCCUPIED
    if fill == "unknown":
        grid[grid != OCCUPIED] = UNKNOWN
    elif fill == "enclosed":
        _mark_outside_unknown(grid)
    return VoxelMap(grid, resolution, (origin[0], origin[1], origin[2]))


def _span(pts: npt.NDArray[np.float64]) -> str:
    ext = pts.max(axis=0) - pts.min(axis=0)
    return " × ".join(f"{v:g}" for v in ext)


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
    require_file(p)
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
    try:
        vm = voxelize(xyz, res, states=states, fill=fill)
    except MapError as exc:
        raise MapError(f"{p}: {exc}") from None
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


@dataclass(frozen=True)
class NpzField:
    """What one array of an ``.npz`` file must be, checked from its npy header before any data is
    decompressed: the dtype kinds accepted (numpy's ``dtype.kind`` letters), the number of
    dimensions, the length of the last axis, and what to call it in messages."""

    name: str
    kinds: str
    ndim: int | None
    expected: str
    width: int | None = None

    def problem(self, shape: tuple[int, ...], dtype: np.dtype[Any]) -> str | None:
        """Why an array of ``shape`` and ``dtype`` cannot be this field (None when it can)."""
        if dtype.hasobject or dtype.kind not in self.kinds:
            return f"expected {self.expected}, found {_describe(shape, dtype)}"
        if (self.ndim is not None and len(shape) != self.ndim) or (
            self.width is not None and (not shape or shape[-1] != self.width)
        ):
            return f"expected {self.expected}, found {_describe(shape, dtype)}"
        n = math.prod(shape)
        if dtype.kind == "U":
            chars = n * (dtype.itemsize // 4)
            if chars > limits.MAX_TEXT_CHARS.limit:
                return limits.MAX_TEXT_CHARS.exceeded("its length (characters)", chars)
        elif n > limits.MAX_VOXELS.limit:
            dims = " × ".join(f"{d:,}" for d in shape)
            return limits.MAX_VOXELS.exceeded(f"its size ({dims} values)", n)
        return None


def _describe(shape: tuple[int, ...], dtype: np.dtype[Any]) -> str:
    one, many = {
        "U": ("a text", "texts"),
        "i": ("a whole number", "whole numbers"),
        "u": ("a whole number", "whole numbers"),
        "f": ("a number", "numbers"),
        "b": ("a true/false value", "true/false values"),
    }.get(dtype.kind, (f"a {dtype} value", f"{dtype} values"))
    return f"{many} of shape {shape}" if shape else one


TEXT = "U"
NUMBER = "iuf"
WHOLE = "iu"
MAP_FIELDS: tuple[NpzField, ...] = (
    NpzField("format", TEXT, 0, "a text"),
    NpzField("version", WHOLE, 0, "a whole number"),
    NpzField("state", WHOLE + "b", 3, "a 3D grid of voxel states (0, 1, 2)"),
    NpzField("resolution", NUMBER, 0, "a number (m)"),
    NpzField("origin", NUMBER, 1, "three numbers [x, y, z]", 3),
    NpzField("meta", TEXT, 0, "a JSON text"),
)
MAX_NPZ_MEMBERS = 64


def read_npz(p: Path, fields: Sequence[NpzField] = MAP_FIELDS) -> dict[str, npt.NDArray[Any]]:
    """The arrays ``fields`` of an ``.npz`` file (those present; others are not read).

    Every field's npy header (shape, dtype) is checked before any data is decompressed, against
    the field and the budgets :data:`~btmission.limits.MAX_VOXELS` (values per array) and
    :data:`~btmission.limits.MAX_TEXT_CHARS` (texts), so a zip bomb is refused in milliseconds.
    Raises :class:`MapError` naming the file, the field and what was expected."""
    import zipfile

    try:
        with p.open("rb") as fh, zipfile.ZipFile(fh) as zf:
            infos = zf.infolist()
            if len(infos) > MAX_NPZ_MEMBERS:
                raise MapError(f"{p}: {len(infos):,} arrays in the file, expected at most "
                               f"{MAX_NPZ_MEMBERS}")  # fmt: skip
            members = {i.filename[: -len(".npy")]: i for i in infos if i.filename.endswith(".npy")}
            present = [f for f in fields if f.name in members]
            for f in present:
                with zf.open(members[f.name]) as stream:
                    shape, dtype = _npy_header(p, f.name, stream)
                problem = f.problem(shape, dtype)
                if problem:
                    raise MapError(f"{p}: field '{f.name}': {problem}")
            out: dict[str, npt.NDArray[Any]] = {}
            for f in present:
                with zf.open(members[f.name]) as stream:
                    out[f.name] = np.lib.format.read_array(stream, allow_pickle=False)
            return out
    except MapError:
        raise
    except Exception as exc:  # zipfile.BadZipFile, ValueError, OSError, EOFError, zlib.error...
        raise MapError(f"{p}: not a readable .npz file ({exc or type(exc).__name__})") from None


def read_npy(p: Path, field: NpzField) -> npt.NDArray[Any]:
    """The array of a ``.npy`` file, its header checked against ``field`` and the budgets first."""
    try:
        with p.open("rb") as fh:
            shape, dtype = _npy_header(p, field.name, fh)
            problem = field.problem(shape, dtype)
            if problem:
                raise MapError(f"{p}: {problem}")
            fh.seek(0)
            return np.load(fh, allow_pickle=False)  # type: ignore[no-any-return]
    except MapError:
        raise
    except Exception as exc:  # ValueError, OSError, EOFError...
        raise MapError(f"{p}: not a readable .npy file ({exc or type(exc).__name__})") from None


def _npy_header(p: Path, name: str, stream: Any) -> tuple[tuple[int, ...], np.dtype[Any]]:
    fmt = np.lib.format
    try:
        version = fmt.read_magic(stream)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(stream)
        elif version == (2, 0):
            shape, _, dtype = fmt.read_array_header_2_0(stream)
        else:
            raise ValueError(f"npy format version {version} is not supported")
    except ValueError as exc:
        raise MapError(f"{p}: field '{name}' is not a readable array ({exc})") from None
    return tuple(int(d) for d in shape), np.dtype(dtype)


def _load_npz(p: Path) -> VoxelMap:
    data = read_npz(p, MAP_FIELDS)
    fmt = str(data["format"]) if "format" in data else ""
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
    meta = json_field(p, data, "meta")
    origin = np.asarray(data["origin"], dtype=np.float64).ravel()
    res = float(data["resolution"])
    if not (math.isfinite(res) and res > 0):
        raise MapError(f"{p}: field 'resolution': expected a number > 0 (m), found {res:g}")
    try:
        return VoxelMap(data["state"], res, (origin[0], origin[1], origin[2]), meta)
    except MapError as exc:  # the grid's own checks (origin, empty grid, states): name the file
        raise MapError(f"{p}: {exc}") from None


def json_field(p: Path, data: dict[str, npt.NDArray[Any]], name: str) -> dict[str, Any]:
    """The JSON object in text field ``name`` (``{}`` when absent); :class:`MapError` otherwise."""
    if name not in data:
        return {}
    try:
        value = json.loads(str(data[name]))
    except ValueError as exc:  # json.JSONDecodeError, and too deep nesting (RecursionError is not)
        raise MapError(f"{p}: field '{name}': expected a JSON text ({exc})") from None
    except RecursionError:
        raise MapError(f"{p}: field '{name}': the JSON text is nested too deeply") from None
    if not isinstance(value, dict):
        raise MapError(f"{p}: field '{name}': expected a JSON object {{...}}, found "
                       f"{type(value).__name__}")  # fmt: skip
    return value


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
