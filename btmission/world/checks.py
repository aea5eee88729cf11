"""Mission checks against the map: agent starts and task locations inside rock, outside the map,
or unreachable from every agent (DESIGN §4.3: "a location inside rock or outside the map" is bad
input).

A task's positions are the fields its type reads (goal and cost symbols) whose value is a list of
three numbers. Reachable means exactly "the planner finds a path" from some valid agent start
(through free or unknown voxels, never through rock): :func:`reachable_from` labels the planner's
26-connected components (:mod:`btmission.world.connectivity`) instead of searching.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from btmission.diagnostics import Diagnostic, Location, Severity
from btmission.world.connectivity import components
from btmission.world.voxel import OCCUPIED, UNKNOWN, VoxelMap


def _position(value: Any) -> tuple[float, float, float] | None:
    if (
        isinstance(value, (list, tuple))
        and len(value) == 3
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    ):
        return float(value[0]), float(value[1]), float(value[2])
    return None


def _fmt(p: Sequence[float] | np.ndarray) -> str:
    return "[" + ", ".join(f"{v:g}" for v in p) + "]"


def point_problem(vm: VoxelMap, p: tuple[float, float, float]) -> tuple[str, str] | None:
    """(code, message) when ``p`` cannot be used: outside the map or inside rock."""
    state = vm.state_at(p)
    if state is None:
        return "outside-map", f"{_fmt(p)} is outside the map ({vm.bounds_text()})"
    if state == OCCUPIED:
        near = vm.nearest_free(p, 10.0)
        hint = (
            f"; the nearest free voxel is at {_fmt(np.round(near, 2))}" if near is not None else ""
        )
        return "in-rock", f"{_fmt(p)} is inside rock (an occupied voxel){hint}"
    return None


def reachable_from(
    voxel_map: VoxelMap,
    starts: Sequence[tuple[float, float, float]],
    points: Sequence[tuple[float, float, float]],
) -> list[bool]:
    """Whether each of ``points`` has a D*+ path from one of ``starts`` (all inside the map).

    The planner moves between 26-neighbours and enters any voxel that is not rock (unknown ones
    at a cost, eq. 4), so a path exists exactly when both lie in one 26-connected component of
    the non-rock voxels. :func:`~btmission.world.connectivity.components` labels them from the
    map's runs with numpy alone (no numba kernels to load, no scipy to import) and gives the same
    answer as a one-to-all search (a test compares the two).
    """
    comps = components(voxel_map.state != OCCUPIED)

    def label(p: tuple[float, float, float]) -> int:
        return comps.label(voxel_map.world_to_index(p))

    ours = {label(s) for s in starts} - {-1}
    return [label(p) in ours for p in points]


def check_mission_map(mission: Any, voxel_map: VoxelMap) -> list[Diagnostic]:
    """Every agent start and task position checked against ``voxel_map``; one diagnostic each.

    Errors: ``outside-map``, ``in-rock``, ``unreachable`` (no path from any agent's start).
    Warning: ``unknown-voxel`` (a position the map has not seen; paths there pay c_u).
    """
    diags: list[Diagnostic] = []

    def add(sev: Severity, code: str, item: str, message: str, where: Location) -> None:
        diags.append(Diagnostic(sev, code, message, item, where))

    starts: list[tuple[float, float, float]] = []
    for i, a in enumerate(mission.agents):
        item = f"agents[{i}].start"
        problem = point_problem(voxel_map, a.start)
        if problem:
            add(Severity.ERROR, problem[0], item, f"agent {a.id} starts at {problem[1]}", a.where)
            continue
        if voxel_map.state_at(a.start) == UNKNOWN:
            add(
                Severity.WARNING,
                "unknown-voxel",
                item,
                f"agent {a.id} starts in an unknown voxel",
                a.where,
            )
        starts.append(tuple(float(v) for v in a.start))  # type: ignore[arg-type]

    positions: list[tuple[str, str, tuple[float, float, float], Location]] = []
    for i, t in enumerate(mission.tasks):
        tt = mission.task_types.get(t.type)
        names = tt.fields if tt is not None else tuple(t.fields)
        for name in names:
            p = _position(t.fields.get(name))
            if p is None:
                continue
            item = f"tasks[{i}].{name}"
            problem = point_problem(voxel_map, p)
            if problem:
                add(Severity.ERROR, problem[0], item, f"task {t.id}: {name} {problem[1]}", t.where)
                continue
            if voxel_map.state_at(p) == UNKNOWN:
                add(
                    Severity.WARNING,
                    "unknown-voxel",
                    item,
                    f"task {t.id}: {name} {_fmt(p)} is in an unknown voxel",
                    t.where,
                )
            positions.append((item, f"task {t.id}: {name} {_fmt(p)}", p, t.where))

    if not positions or not starts:
        return diags
    reachable = reachable_from(voxel_map, starts, [p for _, _, p, _ in positions])
    for (item, what, _, where), ok in zip(positions, reachable, strict=True):
        if not ok:
            add(
                Severity.ERROR,
                "unreachable",
                item,
                f"{what} cannot be reached from any agent's start (no path avoids rock)",
                where,
            )
    return diags


def check_mission_world(mission: Any) -> list[Diagnostic]:
    """Build the mission's world and run :func:`check_mission_map` on it.

    A world that cannot be built (unreadable map file, a mine too small...) is one ``bad-map``
    error located at the mission's ``world.map`` (``mission.locate``: the mission keeps the file
    it was read from, with every item's line).
    """
    from btmission.world.build import world_from_spec
    from btmission.world.voxel import MapError

    try:
        vm = world_from_spec(mission.spec.world, mission.base_dir)
    except MapError as exc:
        where = mission.locate(("world", "map"))
        return [Diagnostic(Severity.ERROR, "bad-map", str(exc), "world.map", where)]
    return check_mission_map(mission, vm)
