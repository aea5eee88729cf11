"""``btmission reloc build|query|scan|try``: global relocalization in a point-cloud map."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import click
import numpy as np

from btmission.cli.common import (
    FINITE,
    SEED,
    BadInput,
    ChecksFailed,
    FiniteFloat,
    file_option,
    handle_spec_errors,
    output_file_option,
    parse_numbers,
)
from btmission.cli.map_cmds import (
    _xyz,
    fill_option,
    load_map_arg,
    map_argument,
    resolution_option,
)

SCAN_SUFFIXES = (".ply", ".pcd", ".npy")


def _pose4(
    ctx: click.Context, param: click.Parameter, value: str | None
) -> tuple[float, float, float, float] | None:
    if value is None:
        return None
    pose = parse_numbers(value, 4)
    if pose is None:
        raise click.BadParameter(
            f"expected X,Y,Z,YAW (metres and degrees, four finite numbers), got '{value}'"
        )
    x, y, z, yaw = pose
    return x, y, z, yaw


def _sensor(name: str) -> Any:
    from btmission.localization.scan import SENSORS

    return SENSORS[name]


sensor_option = click.option(
    "--sensor",
    type=click.Choice(["os1-32", "vlp-16"]),
    default="os1-32",
    show_default=True,
    help="Simulated LiDAR (Ouster OS1-32-like or Velodyne VLP-16-like).",
)


def read_points(path: Path, what: str = "scan") -> np.ndarray:
    """x, y, z points of a .ply/.pcd/.npy file (a scan or a trajectory); BadInput when unusable."""
    from btmission.world.io import read_cloud
    from btmission.world.voxel import MapError

    suffix = path.suffix.lower()
    if not path.is_file():
        raise BadInput(f"{path}: not a regular file" if path.exists() else f"{path}: no such file")
    if suffix == ".npy":
        from btmission.world.io import NUMBER, NpzField, read_npy

        try:
            pts = read_npy(path, NpzField(what, NUMBER, None, "an array of numbers"))
        except MapError as exc:
            raise BadInput(str(exc)) from None
    elif suffix in (".ply", ".pcd"):
        try:
            cols, _ = read_cloud(path)
        except MapError as exc:
            raise BadInput(str(exc)) from None
        pts = np.stack([np.asarray(cols[c], dtype=np.float64) for c in "xyz"], axis=1)
    elif suffix in (".csv", ".txt") and what == "trajectory":
        from btmission import limits
        from btmission.spec.source import read_regular_file

        try:
            data = read_regular_file(path, limits.MAX_FILE_BYTES)
        except OSError as exc:
            raise BadInput(f"{path}: {exc}") from None
        try:
            text = data.decode("utf-8").replace(",", " ")
            rows = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
            pts = np.array([[float(v) for v in r[:3]] for r in rows if len(r) >= 3])
        except ValueError as exc:  # (UnicodeDecodeError too)
            raise BadInput(f"{path}: expected lines of x, y, z numbers ({exc})") from None
    else:
        known = ".ply, .pcd, .npy" + (", .csv, .txt" if what == "trajectory" else "")
        raise BadInput(f"{path}: cannot read a {what} from '{suffix}' (expected {known})")
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise BadInput(f"{path}: a {what} is an N × 3 array of x, y, z, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise BadInput(f"{path}: the {what} has NaN or infinite coordinates")
    return pts


def _plain_cloud(path: Path) -> np.ndarray | None:
    """The points of a .ply/.pcd map that is a plain survey (no per-point state), else None."""
    if path.suffix.lower() not in (".ply", ".pcd"):
        return None
    from btmission.world.io import read_cloud
    from btmission.world.voxel import MapError

    try:
        cols, _ = read_cloud(path)
    except MapError:
        return None
    if "state" in cols:
        return None
    return np.stack([np.asarray(cols[c], dtype=np.float64) for c in "xyz"], axis=1)


def _build(
    vm: Any,
    map_file: Path,
    cloud: Path | None,
    trajectory: Path | None,
    spacing: float,
    height: float,
    clearance: float,
    sensor: str,
    *,
    show_progress: bool = True,
) -> Any:
    """The place database of ``vm`` (loaded from ``map_file``), shared by ``build`` and ``try``."""
    from contextlib import nullcontext

    from btmission.localization.database import (
        DatabaseError,
        build_database,
        positions_from_trajectory,
    )

    points = read_points(cloud, "cloud") if cloud is not None else _plain_cloud(map_file)
    places = None
    bar_cm: Any = nullcontext()
    if show_progress:
        bar_cm = click.progressbar(length=1, label="scanning places", file=sys.stderr)
    try:
        if trajectory is not None:
            places = positions_from_trajectory(
                vm, read_points(trajectory, "trajectory"), spacing, height
            )
        with bar_cm as bar:
            seen = [0]

            def progress(done: int, total: int) -> None:
                if bar is not None:
                    bar.length = total
                    bar.update(done - seen[0])
                    seen[0] = done

            return build_database(
                vm,
                points,
                places,
                spacing_m=spacing,
                height_m=height,
                clearance_m=clearance,
                sensor=_sensor(sensor),
                progress=progress,
            )
    except DatabaseError as exc:
        hint = ""
        if points is not None and cloud is None and trajectory is None:
            hint = (
                " (a survey with holes lets the outside in, so its tunnels are not enclosed: "
                "give the mapping run's path with --trajectory, or a voxel map)"
            )
        raise BadInput(f"{map_file}: {exc}{hint}") from None


def _load_db(path: Path) -> Any:
    from btmission.localization.database import DatabaseError, load_database

    try:
        return load_database(path)
    except DatabaseError as exc:
        raise BadInput(str(exc)) from None


def _report(result: Any, truth: tuple[float, float, float, float] | None, as_json: bool) -> bool:
    """Print a relocalization (and its error against ``truth``); whether it counts as a success."""
    from btmission.localization.relocalize import pose_error
    from btmission.localization.scan import pose_matrix

    ok = bool(result.localized)
    err: tuple[float, float] | None = None
    if truth is not None and result.pose is not None:
        x, y, z, yaw = truth
        err = pose_error(result.pose, pose_matrix(x, y, z, np.radians(yaw)))
        ok = ok and err[0] < 0.3 and err[1] < 3.0
    if as_json:
        d = result.to_dict()
        if err is not None:
            d["error"] = {"translation_m": round(err[0], 4), "yaw_deg": round(err[1], 3)}
        click.echo(json.dumps(d, indent=2))
        return ok
    if result.pose is not None:
        p = result.pose
        click.echo(
            f"localised at x {p[0, 3]:.2f}, y {p[1, 3]:.2f}, z {p[2, 3]:.2f} m, "
            f"yaw {np.degrees(result.yaw):.1f}°  (confidence {result.confidence:.2f})"
        )
    click.echo(result.reason)
    t = result.timings_ms
    if "total" in t:
        click.echo(
            f"time {t['total']:.0f} ms (descriptors {t.get('descriptors', 0):.0f}, coarse ICP "
            f"{t.get('coarse_icp', 0):.0f}, fine ICP {t.get('fine_icp', 0):.0f}); "
            f"{len(result.candidates)} candidate pose(s) registered"
        )
    if err is not None:
        click.echo(
            f"error against the true pose: {err[0]:.3f} m, {err[1]:.2f}° "
            f"({'within' if err[0] < 0.3 and err[1] < 3.0 else 'outside'} 0.3 m / 3°)"
        )
    return ok


# ------------------------------------------------------------------------------------ commands
@click.group("reloc")
def reloc() -> None:
    """Global relocalization: find an agent in the shared map from one LiDAR scan (seed 000
    §IV-C1: place descriptors, then coarse-to-fine ICP). See docs/relocalization.md.

    \b
    Examples:
      btmission reloc build missions/mine_inspection.yaml -o mine_db.npz
      btmission reloc scan missions/mine_inspection.yaml --at 60,10,2 --yaw 30 -o scan.ply
      btmission reloc query mine_db.npz scan.ply
      btmission reloc try docs/examples/reloc_mine.yaml --at 32,15,2 --yaw 40
    """


def _metres(name: str, default: float, text: str, *, positive: bool = True) -> Any:
    return click.option(
        name,
        type=FiniteFloat(min=0, min_open=positive),
        default=default,
        show_default=True,
        help=text,
    )


def build_options(fn: Any) -> Any:
    """Options that say where the database's places go (shared by build and try)."""
    for opt in reversed(
        [
            _metres("--spacing", 1.0, "Distance between places (m)."),
            _metres("--height", 2.0, "Sensor height above the floor at the places (m)."),
            _metres("--clearance", 0.5, "Places keep this far from rock (m).", positive=False),
            sensor_option,
            resolution_option,
            fill_option("enclosed", "For plain point clouds: what the voxels without points are."),
        ]
    ):
        fn = opt(fn)
    return fn


@reloc.command("build")
@map_argument
@output_file_option("-o", "--output", required=True, help="The database file (.npz).")
@file_option(
    "--cloud",
    help="The map's point cloud for ICP (.ply/.pcd/.npy; default: MAP's own points if it is a "
    "plain survey, else the faces between free and occupied voxels).",
)
@file_option(
    "--trajectory",
    help="Put places along this path (.csv/.txt/.npy/.ply/.pcd of x, y, z) instead of all over "
    "the free space.",
)
@build_options
@handle_spec_errors
def build_cmd(
    map_file: Path,
    output: Path,
    cloud: Path | None,
    trajectory: Path | None,
    spacing: float,
    height: float,
    clearance: float,
    sensor: str,
    resolution: float | None,
    fill: str,
) -> None:
    """Build the place database of MAP: descriptors of simulated scans at places sampled along the
    free space (or a trajectory), with the map itself, in one .npz file.

    MAP: a voxel map (.npz, .ply/.pcd with a state field), a plain survey point cloud (.ply/.pcd;
    its free space is what its closed walls enclose) or a mission file (.yaml: its world).

    \b
    Examples:
      btmission reloc build missions/mine_inspection.yaml -o mine_db.npz
      btmission reloc build survey.ply --resolution 0.5 -o survey_db.npz
      btmission reloc build mine.npz --trajectory mapping_run.csv --spacing 2 -o mine_db.npz
    """
    from btmission.localization.database import DatabaseError, save_database

    if output.suffix.lower() != ".npz":
        raise BadInput(f"{output}: a place database is written as .npz")
    vm, _ = load_map_arg(map_file, resolution, fill)
    t0 = time.perf_counter()
    db = _build(vm, map_file, cloud, trajectory, spacing, height, clearance, sensor)
    dt = time.perf_counter() - t0
    try:
        save_database(db, output)
    except (DatabaseError, OSError) as exc:
        raise BadInput(f"{output}: cannot write the database ({exc})") from None
    click.echo(f"{db.describe()}; built in {dt:.1f} s")
    click.echo(f"wrote {output}", err=True)


@reloc.command("query")
@click.argument("database", metavar="DB", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("scan", metavar="SCAN", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--truth",
    callback=_pose4,
    metavar="X,Y,Z,YAW",
    default=None,
    help="The scan's true pose (m, degrees): also print the error (exit 1 beyond 0.3 m / 3°).",
)
@click.option("--top-k", type=click.IntRange(1), default=None, help="Candidate poses to register.")
@click.option(
    "--min-confidence",
    type=FiniteFloat(0, 1),
    default=None,
    help="Below this the scan is 'not localised' (default 0.2).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
def query_cmd(
    database: Path,
    scan: Path,
    truth: tuple[float, float, float, float] | None,
    top_k: int | None,
    min_confidence: float | None,
    as_json: bool,
) -> None:
    """Localise one LiDAR SCAN (.ply/.pcd/.npy, x y z in the sensor frame, gravity-aligned) in
    the map of the place database DB, with no initial guess.

    Exit status: 0 localised, 1 not localised (or, with --truth, off by more than 0.3 m / 3°),
    2 bad input.

    \b
    Example:
      btmission reloc query mine_db.npz scan.ply --truth 60,10,2,30
    """
    from dataclasses import replace

    from btmission.localization.relocalize import Relocalizer, RelocConfig

    db = _load_db(database)
    points = read_points(scan)
    cfg = RelocConfig()
    if top_k is not None:
        cfg = replace(cfg, top_k=top_k)
    if min_confidence is not None:
        cfg = replace(cfg, min_confidence=min_confidence)
    result = Relocalizer(db, cfg).localize(points)
    if not _report(result, truth, as_json):
        raise ChecksFailed("not localised" if not result.localized else "pose error too large")


def _check_pose(vm: Any, at: tuple[float, float, float], yaw: float) -> Any:
    from btmission.localization.scan import pose_matrix
    from btmission.world.voxel import OCCUPIED

    state = vm.state_at(at)
    if state is None:
        lo, hi = vm.bounds
        raise BadInput(
            f"--at {at[0]:g},{at[1]:g},{at[2]:g} is outside the map "
            f"[{lo[0]:g}, {hi[0]:g}] × [{lo[1]:g}, {hi[1]:g}] × [{lo[2]:g}, {hi[2]:g}]"
        )
    if state == OCCUPIED:
        raise BadInput(f"--at {at[0]:g},{at[1]:g},{at[2]:g} is inside rock")
    return pose_matrix(at[0], at[1], at[2], np.radians(yaw))


scan_pose_options = [
    click.option(
        "--at",
        "at",
        required=True,
        callback=_xyz,
        metavar="X,Y,Z",
        help="Sensor position in the map (m).",
    ),
    click.option("--yaw", type=FINITE, default=0.0, show_default=True, help="Heading (degrees)."),
    click.option(
        "--dust",
        type=FiniteFloat(0, 1),
        default=0.0,
        show_default=True,
        help="Fraction of the returns replaced by dust.",
    ),
    click.option("--seed", type=SEED, default=0, show_default=True, help="Noise seed."),
]


def _with_options(options: list[Any]) -> Any:
    def deco(fn: Any) -> Any:
        for opt in reversed(options):
            fn = opt(fn)
        return fn

    return deco


def _simulate(
    vm: Any, at: tuple[float, float, float], yaw: float, sensor: str, dust: float, seed: int
) -> tuple[Any, np.ndarray]:
    from btmission.localization.scan import add_dust, simulate_scan

    pose = _check_pose(vm, at, yaw)
    points = simulate_scan(vm, pose, _sensor(sensor), rng=seed)
    if dust > 0:
        points = add_dust(points, dust, rng=seed)
    return pose, points


@reloc.command("scan")
@map_argument
@_with_options(scan_pose_options)
@sensor_option
@output_file_option(
    "-o",
    "--output",
    required=True,
    help="The scan: .ply, .pcd or .npy (points in the sensor frame).",
)
@resolution_option
@handle_spec_errors
def scan_cmd(
    map_file: Path,
    at: tuple[float, float, float],
    yaw: float,
    dust: float,
    seed: int,
    sensor: str,
    output: Path,
    resolution: float | None,
) -> None:
    """Simulate the LiDAR scan a sensor at --at/--yaw would take in MAP (ray casting through its
    voxels; free and unknown ones are transparent) and write it in the sensor frame.

    \b
    Example:
      btmission reloc scan missions/mine_inspection.yaml --at 60,10,2 --yaw 30 -o scan.ply
    """
    from btmission.world.io import write_cloud
    from btmission.world.voxel import MapError

    if output.suffix.lower() not in SCAN_SUFFIXES:
        raise BadInput(f"{output}: write a scan as .ply, .pcd or .npy")
    vm, _ = load_map_arg(map_file, resolution)
    _, points = _simulate(vm, at, yaw, sensor, dust, seed)
    try:
        if output.suffix.lower() == ".npy":
            output.parent.mkdir(parents=True, exist_ok=True)
            np.save(output, points)
        else:
            write_cloud(
                output,
                {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]},
                comments=[f"btmission {sensor} scan at {at[0]:g},{at[1]:g},{at[2]:g} yaw {yaw:g}"],
            )
    except (MapError, OSError) as exc:
        raise BadInput(f"{output}: cannot write the scan ({exc})") from None
    click.echo(
        f"{len(points):,} points from {sensor} at ({at[0]:g}, {at[1]:g}, {at[2]:g}), yaw {yaw:g}°"
    )
    click.echo(f"wrote {output}", err=True)


@reloc.command("try")
@map_argument
@_with_options(scan_pose_options)
@file_option(
    "--db", "database", help="Use this place database of MAP instead of building one in memory."
)
@build_options
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
@handle_spec_errors
def try_cmd(
    map_file: Path,
    at: tuple[float, float, float],
    yaw: float,
    dust: float,
    seed: int,
    database: Path | None,
    spacing: float,
    height: float,
    clearance: float,
    sensor: str,
    resolution: float | None,
    fill: str,
    as_json: bool,
) -> None:
    """Simulate a scan at --at/--yaw in MAP, relocalise it with no initial guess and compare with
    the true pose: how well relocalization works at that spot of your map.

    Exit status: 0 localised within 0.3 m and 3°, 1 otherwise, 2 bad input.

    \b
    Examples:
      btmission reloc try docs/examples/reloc_mine.yaml --at 32,15,2 --yaw 40
      btmission reloc try mine.npz --db mine_db.npz --at 60,10,2 --yaw -120 --dust 0.05
    """
    from btmission.localization.relocalize import Relocalizer

    vm, _ = load_map_arg(map_file, resolution, fill)
    _, points = _simulate(vm, at, yaw, sensor, dust, seed)
    if database is not None:
        db = _load_db(database)
    else:
        db = _build(
            vm, map_file, None, None, spacing, height, clearance, sensor, show_progress=False
        )
    result = Relocalizer(db).localize(points)
    if not _report(result, (at[0], at[1], at[2], yaw), as_json):
        raise ChecksFailed("not localised within 0.3 m and 3°")
