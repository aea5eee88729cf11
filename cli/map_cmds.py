"""``btmission map generate|show`` and ``btmission plan``: voxel maps and D*+ paths."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from btmission.cli.common import (
    FINITE,
    NON_NEGATIVE,
    POSITIVE,
    SEED,
    BadInput,
    ChecksFailed,
    FiniteFloat,
    handle_spec_errors,
    output_file_option,
    parse_numbers,
    write_output,
)

if TYPE_CHECKING:
    from btmission.planning.risk import CostMap

F = TypeVar("F", bound=Callable[..., Any])
MAP_HELP = "A map file (.npz, .ply, .pcd) or a mission file (.yaml: its world)."


def _xyz(
    ctx: click.Context, param: click.Parameter, value: str | None
) -> tuple[float, float, float] | None:
    if value is None:
        return None
    xyz = parse_numbers(value, 3)
    if xyz is None:
        raise click.BadParameter(f"expected X,Y,Z in metres (three finite numbers), got '{value}'")
    x, y, z = xyz
    return x, y, z


resolution_option = click.option(
    "--resolution",
    type=POSITIVE,
    default=None,
    help="Voxel size (m) for point clouds without one (default 0.5).",
)
map_argument = click.argument(
    "map_file", metavar="MAP", type=click.Path(dir_okay=False, path_type=Path)
)


def fill_option(default: str, help: str) -> Callable[[F], F]:
    """--fill: for a plain point cloud, what the voxels without points are."""
    return click.option(
        "--fill",
        type=click.Choice(["free", "unknown", "enclosed"]),
        default=default,
        show_default=True,
        help=help,
    )


map_fill_option = fill_option(
    "free", "For plain point clouds: what the voxels without points are (see docs/planner.md)."
)


def risk_options(fn: F) -> F:
    """--risk-radius and --unknown-cost: r and c_u of eq. 3-4."""
    from btmission.planning.risk import DEFAULT_RADIUS_M, DEFAULT_UNKNOWN_COST

    fn = click.option(
        "--unknown-cost",
        type=NON_NEGATIVE,
        default=None,
        help=f"c_u of eq. 3-4 (default {DEFAULT_UNKNOWN_COST:g}).",
    )(fn)
    return click.option(
        "--risk-radius",
        type=NON_NEGATIVE,
        default=None,
        help=f"r of eq. 3 in metres (default {DEFAULT_RADIUS_M:g}).",
    )(fn)


def size_option(default: tuple[float, float, float]) -> Callable[[F], F]:
    """--size X Y Z of a generated mine, in metres."""
    return click.option(
        "--size",
        nargs=3,
        type=POSITIVE,
        default=default,
        show_default=True,
        metavar="X Y Z",
        help="Extent in metres.",
    )


mine_resolution_option = click.option(
    "--resolution",
    type=FiniteFloat(min=0, max=1, min_open=True),
    default=0.5,
    show_default=True,
    help="Voxel size (m).",
)


def load_map_arg(path: Path, resolution: float | None, fill: str = "free") -> tuple[Any, list[Any]]:
    """(VoxelMap, markers) from a map file or a mission's world; MapError → exit 2."""
    from btmission.world.voxel import MapError

    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            from btmission.missions import load_mission
            from btmission.world.build import world_from_spec

            m = load_mission(path)
            vm = world_from_spec(m.spec.world, m.base_dir)
            markers: list[Any] = [(a.id, a.start, "#1f77b4") for a in m.agents]
            for t in m.tasks:
                for v in t.fields.values():
                    if isinstance(v, list) and len(v) == 3:
                        markers.append((t.id, v, "#d62728"))
            return vm, markers
        from btmission.world.io import load_map

        res = resolution
        if res is None and path.suffix.lower() in (".ply", ".pcd"):
            res = 0.5 if not _has_resolution_comment(path) else None
        return load_map(path, res, fill=fill), []  # type: ignore[arg-type]
    except MapError as exc:
        raise BadInput(str(exc)) from None


def _has_resolution_comment(path: Path) -> bool:
    if path.suffix.lower() != ".ply" or not path.is_file():
        return False
    with path.open("rb") as fh:
        head = fh.read(4096)
    return b"comment btmission resolution" in head


@click.group("map")
def map_group() -> None:
    """Voxel maps: generate a mine, show a map (summary and top-view picture).

    \b
    Examples:
      btmission map generate --seed 7 --size 200 120 12 -o mine.npz
      btmission map generate --seed 7 --size 200 120 12 -o mine.npz --survey mine_scan.ply
      btmission map show mine.npz --png mine.png
      btmission map show missions/mine_inspection.yaml --png mission.png
    """


@map_group.command("generate")
@click.option(
    "--seed", type=SEED, default=0, show_default=True, help="Random seed (same seed, same mine)."
)
@size_option((200.0, 120.0, 12.0))
@mine_resolution_option
@click.option(
    "--clutter/--no-clutter",
    default=True,
    show_default=True,
    help="Parked machines in some drifts.",
)
@click.option(
    "--unknown/--no-unknown", default=True, show_default=True, help="A few unknown patches."
)
@output_file_option(
    "-o", "--output", required=True, help="Map file: .npz (recommended), .ply or .pcd."
)
@output_file_option("--survey", help="Also write the LiDAR survey point cloud (.ply or .pcd).")
@click.option("--ascii", "ascii_", is_flag=True, help="ASCII .ply/.pcd instead of binary.")
def generate_cmd(
    seed: int,
    size: tuple[float, float, float],
    resolution: float,
    clutter: bool,
    unknown: bool,
    output: Path,
    survey: Path | None,
    ascii_: bool,
) -> None:
    """Generate a seeded underground mine (drifts, junctions, ramps, a loop, dead ends).

    The main level's floor is at z = 0; the map spans [0, X] × [0, Y] × [-1, Z-1]. Agents start in
    the launch area near (7, 5, 0).

    \b
    Example:
      btmission map generate --seed 7 --size 200 120 12 -o mine.npz
    """
    from btmission.world.io import MAP_SUFFIXES, save_map, write_cloud
    from btmission.world.minegen import generate_mine, survey_point_cloud
    from btmission.world.voxel import MapError

    if output.suffix.lower() not in MAP_SUFFIXES:
        raise BadInput(
            f"{output}: unknown map format '{output.suffix}' (expected .npz, .ply or .pcd)"
        )
    if survey is not None and survey.suffix.lower() not in (".ply", ".pcd"):
        raise BadInput(f"{survey}: a survey is a point cloud: use .ply or .pcd")
    try:
        t0 = time.perf_counter()
        mine = generate_mine(seed, size, resolution, clutter=clutter, unknown=unknown)
        dt = time.perf_counter() - t0
        save_map(mine.map, output, ascii=ascii_)
        click.echo(f"mine seed {seed}: {mine.map.describe()} (generated in {dt * 1000:.0f} ms)")
        click.echo(
            f"  {len(mine.nodes)} junctions, {len(mine.tunnels)} drifts "
            f"({sum(t.kind == 'ramp' for t in mine.tunnels)} ramps, {len(mine.dead_ends)} dead ends), "
            f"{len(mine.machines)} parked machines, {len(mine.unknown_patches)} unknown patches; "
            f"launch area at ({mine.launch[0]:g}, {mine.launch[1]:g}, 0)"
        )
        click.echo(f"wrote {output}", err=True)
        if survey is not None:
            pts = survey_point_cloud(mine.map, seed)
            write_cloud(
                survey,
                {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]},
                ascii=ascii_,
                comments=[f"btmission survey of mine seed {seed}"],
            )
            click.echo(f"wrote {survey} ({len(pts):,} points)", err=True)
    except MapError as exc:
        raise BadInput(str(exc)) from None


@map_group.command("show")
@map_argument
@output_file_option("--png", help="Write a top view with risk shading.")
@click.option(
    "--z",
    type=FINITE,
    default=None,
    help="Show the horizontal slice at this height instead of the whole column.",
)
@risk_options
@resolution_option
@map_fill_option
@handle_spec_errors
def show_cmd(
    map_file: Path,
    png: Path | None,
    z: float | None,
    risk_radius: float | None,
    unknown_cost: float | None,
    resolution: float | None,
    fill: str,
) -> None:
    """Summarise a map (size, voxel counts, risk layer); optionally draw its top view.

    MAP is a .npz/.ply/.pcd map or a mission file (its world, with agents and tasks marked).

    \b
    Example:
      btmission map show missions/mine_inspection.yaml --png mission.png
    """
    import numpy as np

    from btmission.planning.risk import CostMap

    vm, markers = load_map_arg(map_file, resolution, fill)
    if z is not None:
        (_, _, z0), (_, _, z1) = vm.bounds
        if png is None:
            raise BadInput("--z selects the slice drawn by --png; give --png FILE too")
        if not z0 <= z < z1:
            raise BadInput(f"--z {z:g} is outside the map (z from {z0:g} to {z1:g} m)")
    cm = CostMap(vm, _params(risk_radius, unknown_cost))
    click.echo(f"{map_file}: {vm.describe()}")
    vc = cm.voxel_cost[np.isfinite(cm.voxel_cost)]
    risky = int(np.count_nonzero(vc > 0))
    click.echo(
        f"risk layer: r = {cm.params.radius_m:g} m, c_u = {cm.params.unknown_cost:g}; "
        f"{risky:,} of {vc.size:,} enterable voxels carry risk or unknown cost"
        + (f" (max {vc.max():.2f})" if vc.size else "")
    )
    if png is not None:
        write_output(_top_view(cm, markers=markers, z=z, title=f"{map_file.name}"), png)


def _top_view(cm: CostMap, **kw: Any) -> bytes:
    """The top view of a cost map's voxel map, shaded by its risk layer (eq. 4 without the step)."""
    from btmission.world.render import top_view_png

    return top_view_png(cm.map, cm.voxel_cost, cost_label="voxel cost c_r + c_u·unknown", **kw)


def _params(risk_radius: float | None, unknown_cost: float | None) -> Any:
    from btmission.planning.risk import DEFAULT_RADIUS_M, DEFAULT_UNKNOWN_COST, RiskParams
    from btmission.world.voxel import MapError

    try:
        return RiskParams(
            DEFAULT_RADIUS_M if risk_radius is None else risk_radius,
            DEFAULT_UNKNOWN_COST if unknown_cost is None else unknown_cost,
        )
    except MapError as exc:
        raise BadInput(str(exc)) from None


@click.command("plan")
@map_argument
@click.option(
    "--from", "start", required=True, callback=_xyz, metavar="X,Y,Z", help="Start point (m)."
)
@click.option("--to", "goal", required=True, callback=_xyz, metavar="X,Y,Z", help="Goal point (m).")
@click.option(
    "--snap",
    is_flag=True,
    help="Move a start/goal in rock or outside the map to the nearest free voxel.",
)
@risk_options
@output_file_option("--png", help="Write a top view with the path.")
@click.option(
    "--json",
    "as_json",
    is_flag=True,
    help="Print the result as JSON (path, waypoints, cost, length).",
)
@resolution_option
@map_fill_option
@handle_spec_errors
def plan_cmd(
    map_file: Path,
    start: tuple[float, float, float],
    goal: tuple[float, float, float],
    snap: bool,
    risk_radius: float | None,
    unknown_cost: float | None,
    png: Path | None,
    as_json: bool,
    resolution: float | None,
    fill: str,
) -> None:
    """Plan the D*+ risk-aware path between two points of a map (seed 000 eq. 3-4).

    Prints the path's cost (length + risk + unknown costs of the voxels entered), its length and
    the thinned waypoints. Exit status 2 when a point is outside the map or in rock (unless
    --snap), 1 when no path exists.

    \b
    Examples:
      btmission plan missions/mine_inspection.yaml --from 7,5,0 --to 64.4,9.6,2.5
      btmission plan mine.npz --from 7,5,2 --to 187.7,62.9,2 --png path.png --json
    """
    from btmission.planning.dstar import Planner, PlanningError
    from btmission.planning.paths import thin_path
    from btmission.planning.risk import CostMap

    vm, markers = load_map_arg(map_file, resolution, fill)
    cm = CostMap(vm, _params(risk_radius, unknown_cost))
    planner = Planner(cm)
    try:
        res = planner.plan(start, goal, snap=snap)
    except PlanningError as exc:
        raise BadInput(str(exc)) from None
    # time a second, identical search: the first one also loads the compiled kernels
    t0 = time.perf_counter()
    planner.plan(res.start, res.goal)
    dt = time.perf_counter() - t0
    for w in res.warnings:
        click.secho(f"warning: {w}", err=True, fg="yellow")
    if not res.found:
        raise ChecksFailed(
            f"no path from ({_f(res.start)}) to ({_f(res.goal)}): rock separates them"
        )
    waypoints = thin_path(cm, res.path)
    if as_json:
        out = {
            "start": list(res.start),
            "goal": list(res.goal),
            "cost": res.cost,
            "length_m": res.length_m,
            "voxels": len(res.path),
            "expanded": res.expanded,
            "waypoints": [[round(float(v), 4) for v in p] for p in waypoints],
            "path": [[round(float(v), 4) for v in p] for p in res.path],
            "risk_radius_m": cm.params.radius_m,
            "unknown_cost": cm.params.unknown_cost,
            "warnings": list(res.warnings),
        }
        click.echo(json.dumps(out, indent=1))
    else:
        click.echo(
            f"path ({_f(res.start)}) → ({_f(res.goal)}): cost {res.cost:.2f}, length {res.length_m:.2f} m, "
            f"{len(res.path)} voxels → {len(waypoints)} waypoints; {res.expanded:,} voxels expanded "
            f"in {dt * 1000:.1f} ms"
        )
        for p in waypoints:
            click.echo(f"  {_f(p)}")
    if png is not None:
        title = f"{map_file.name}: cost {res.cost:.1f}, length {res.length_m:.1f} m"
        write_output(_top_view(cm, path=res.path, markers=markers, title=title), png)


def _f(p: Any) -> str:
    return ", ".join(f"{float(v):g}" for v in p)
