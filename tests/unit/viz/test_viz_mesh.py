"""The viewer's geometry: the rock surface mesh of a voxel map and the risk layer's points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from btmission.missions import load_mission
from btmission.planning.risk import CostMap, RiskParams
from btmission.viz.mesh import SurfaceMesh, coarse_rock, risk_points, surface_mesh
from btmission.world.build import world_from_spec
from btmission.world.voxel import FREE, OCCUPIED, UNKNOWN, MapError, VoxelMap

ROOT = Path(__file__).resolve().parents[3]
MINE = ROOT / "missions" / "mine_inspection.yaml"


@pytest.fixture(scope="module")
def mine() -> VoxelMap:
    return world_from_spec(load_mission(MINE).spec.world, MINE.parent)


def normals(mesh: SurfaceMesh) -> npt.NDArray[np.float64]:
    """Each triangle's (e1 × e2) with its vertices in order: its front side by the right-hand rule
    (three.js: counter-clockwise seen from the front)."""
    v = mesh.vertices.astype(np.float64)[mesh.faces]
    return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])


def area(mesh: SurfaceMesh) -> float:
    return float(np.linalg.norm(normals(mesh), axis=1).sum() / 2)


def state_at(vm: VoxelMap, points: npt.NDArray[np.float64]) -> npt.NDArray[np.int64]:
    """The state of the voxel holding each point; -1 outside the map."""
    idx = vm.world_to_index(points)
    inside = vm.in_bounds(idx)
    out = np.full(len(points), -1, dtype=np.int64)
    i = idx[inside]
    out[inside] = vm.state[i[:, 0], i[:, 1], i[:, 2]]
    return out


def sides(mesh: SurfaceMesh, eps: float) -> tuple[npt.NDArray[np.float64], ...]:
    """Points just in front of and just behind each triangle's centroid."""
    n = normals(mesh)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = mesh.vertices.astype(np.float64)[mesh.faces].mean(axis=1)
    return c + eps * n, c - eps * n


# ------------------------------------------------------------------------------- small maps
def test_a_single_rock_voxel_is_a_cube_of_twelve_outward_triangles() -> None:
    vm = VoxelMap.empty((1.5, 1.5, 1.5), 0.5, origin=(1.0, -2.0, 3.0))
    vm.state[1, 1, 1] = OCCUPIED
    mesh = surface_mesh(vm)
    assert mesh.triangles == 12 and mesh.unit_faces == 6 and mesh.cell_m == 0.5
    assert mesh.vertices.dtype == np.float32 and mesh.faces.dtype == np.uint32
    assert mesh.colors.shape == mesh.vertices.shape and mesh.colors.dtype == np.float32
    assert area(mesh) == pytest.approx(6 * 0.25)
    centre = vm.index_to_world([1, 1, 1])
    centroids = mesh.vertices.astype(np.float64)[mesh.faces].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normals(mesh), centroids - centre) > 0)  # outward
    np.testing.assert_allclose(mesh.vertices.min(axis=0), centre - 0.25)
    np.testing.assert_allclose(mesh.vertices.max(axis=0), centre + 0.25)


def test_a_tunnel_has_walls_floor_and_roof_facing_in_and_nothing_on_the_map_edge() -> None:
    vm = VoxelMap.empty((4, 3, 3), 0.5, fill=OCCUPIED)  # 8 × 6 × 6 voxels of rock
    vm.state[:, 2:4, 2:4] = FREE  # a 2 × 2-voxel corridor along x, open at both ends of the map
    vm.state[3, 2, 2] = UNKNOWN  # unmapped space counts as open: no rock drawn around it
    mesh = surface_mesh(vm)
    assert mesh.triangles == 8  # floor, roof and two walls: one rectangle each
    assert area(mesh) == pytest.approx(4 * 4 * 1.0)  # 4 m long, 1 m wide faces
    front, back = sides(mesh, 0.01)
    assert np.all(np.isin(state_at(vm, front), (FREE, UNKNOWN)))  # every normal into the corridor
    assert np.all(state_at(vm, back) == OCCUPIED)
    v = mesh.vertices
    # corridor walls at y = 1 and 2 m, floor and roof at z = 1 and 2 m: no face on the map's box
    assert set(np.unique(v[:, 1])) == {1.0, 2.0} and set(np.unique(v[:, 2])) == {1.0, 2.0}
    n = normals(mesh)
    assert np.all(n[:, 0] == 0)  # no face across the corridor (its ends are the map's edge)


def test_a_flat_floor_merges_into_two_triangles() -> None:
    vm = VoxelMap.empty((5, 5, 1), 0.5)  # 10 × 10 × 2 voxels
    vm.state[:, :, 0] = OCCUPIED
    mesh = surface_mesh(vm)
    assert mesh.triangles == 2 and mesh.unit_faces == 100
    n = normals(mesh)
    assert np.all(n[:, :2] == 0) and np.all(n[:, 2] > 0)  # facing up, counter-clockwise from above
    assert area(mesh) == pytest.approx(25.0)
    np.testing.assert_allclose(mesh.vertices[:, 2], 0.5)


def test_no_rock_or_no_budget_gives_an_empty_mesh() -> None:
    vm = VoxelMap.empty((2, 2, 2), 0.5)
    for mesh in (surface_mesh(vm), surface_mesh(VoxelMap.empty((2, 2, 2), 0.5, fill=OCCUPIED))):
        assert mesh.triangles == 0 and mesh.vertices.shape == (0, 3) and mesh.faces.shape == (0, 3)
    vm.state[1:3, 1:3, 1:3] = OCCUPIED
    assert surface_mesh(vm, max_triangles=0).triangles == 0
    with pytest.raises(MapError):
        surface_mesh(vm, max_triangles=-1)


# ------------------------------------------------------------------------------- brute force
def boundary_faces(rock: npt.NDArray[np.bool_]) -> set[tuple[int, int, int, int, int]]:
    """Every rock/open cell face, brute force: (axis, sign of the normal, i, j, k) where (i, j, k)
    is the open cell the face's normal points into."""
    out: set[tuple[int, int, int, int, int]] = set()
    for i, j, k in np.argwhere(rock):
        for axis in range(3):
            for sign in (-1, 1):
                nb = [int(i), int(j), int(k)]
                nb[axis] += sign
                if 0 <= nb[axis] < rock.shape[axis] and not rock[tuple(nb)]:
                    out.add((axis, sign, nb[0], nb[1], nb[2]))
    return out


def check_against_brute_force(vm: VoxelMap, mesh: SurfaceMesh) -> None:
    """Every triangle lies on the rock/open boundary of the grid meshed (vertices on cell planes,
    facing the open side) and every boundary face is covered exactly once."""
    factor = round(mesh.cell_m / vm.resolution)
    rock = coarse_rock(vm, factor).astype(bool)
    assert all(s % factor == 0 for s in vm.shape)  # no partial coarse cells in these maps
    faces = boundary_faces(rock)
    cell = mesh.cell_m
    grid = (mesh.vertices.astype(np.float64) - np.asarray(vm.origin)) / cell
    np.testing.assert_allclose(grid, np.round(grid), atol=1e-4)  # vertices on cell planes
    assert mesh.unit_faces == len(faces)
    assert area(mesh) == pytest.approx(len(faces) * cell**2)
    n = normals(mesh)
    tri = np.round(grid).astype(np.int64)[mesh.faces]  # (M, 3 vertices, 3 coordinates)
    for t in range(mesh.triangles):
        axis = int(np.flatnonzero(n[t])[0])
        assert np.count_nonzero(n[t]) == 1  # axis-aligned
        sign = 1 if n[t, axis] > 0 else -1
        plane = int(tri[t, 0, axis])
        assert np.all(tri[t, :, axis] == plane)
        lo, hi = tri[t].min(axis=0), tri[t].max(axis=0)
        # every cell face in the triangle's bounding rectangle is a boundary face of its
        # orientation (the triangle is half of a greedy rectangle, so that rectangle is its box)
        ranges = [range(int(lo[a]), int(hi[a])) if a != axis else [0] for a in range(3)]
        for i in ranges[0]:
            for j in ranges[1]:
                for k in ranges[2]:
                    cellidx = [i, j, k]
                    cellidx[axis] = plane if sign > 0 else plane - 1
                    assert (axis, sign, *cellidx) in faces
    # each boundary face's sample point lies in exactly one triangle (no gap, no overlap)
    corners = mesh.vertices.astype(np.float64)[mesh.faces]
    offset = np.array([0.3, 0.618034, 0.41])  # off every rectangle's diagonal
    for axis, sign, i, j, k in faces:
        p = np.asarray(vm.origin) + (np.array([i, j, k]) + offset) * cell
        p[axis] = vm.origin[axis] + (i, j, k)[axis] * cell + (0 if sign > 0 else cell)
        same = (np.sign(n[:, axis]) == sign) & np.isclose(corners[:, 0, axis], p[axis])
        hits = sum(inside_triangle(p, corners[t], axis) for t in np.flatnonzero(same))
        assert hits == 1, (axis, sign, i, j, k)


def cross2(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def inside_triangle(p: npt.NDArray[np.float64], tri: npt.NDArray[np.float64], axis: int) -> bool:
    """Whether ``p`` is strictly inside ``tri``, both seen along ``axis``."""
    u, v = [a for a in range(3) if a != axis]
    a, b, c = (np.array([q[u], q[v]]) for q in tri)
    q = np.array([p[u], p[v]])
    d1, d2, d3 = (cross2(e1 - e0, q - e0) for e0, e1 in ((a, b), (b, c), (c, a)))
    return bool((d1 > 0 and d2 > 0 and d3 > 0) or (d1 < 0 and d2 < 0 and d3 < 0))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_random_map_is_meshed_exactly_and_facing_the_open_side(seed: int) -> None:
    rng = np.random.default_rng(seed)
    state = rng.choice([FREE, OCCUPIED, UNKNOWN], size=(8, 12, 8), p=[0.4, 0.5, 0.1])
    vm = VoxelMap(state.astype(np.uint8), 0.25, origin=(-3.0, 2.0, -0.5))
    mesh = surface_mesh(vm)
    assert mesh.cell_m == 0.25
    check_against_brute_force(vm, mesh)
    assert mesh.unit_faces > mesh.triangles / 2  # merged: fewer rectangles than faces
    front, back = sides(mesh, 0.01)
    assert np.all(np.isin(state_at(vm, front), (FREE, UNKNOWN)))
    assert np.all(state_at(vm, back) == OCCUPIED)


def test_over_budget_the_grid_is_coarsened_and_meshed_the_same_way() -> None:
    rng = np.random.default_rng(5)
    rock = rng.random((16, 16, 8)) < 0.9
    vm = VoxelMap(np.where(rock, OCCUPIED, FREE).astype(np.uint8), 0.5)
    full = surface_mesh(vm)
    mesh = surface_mesh(vm, max_triangles=full.triangles // 4)
    assert mesh.cell_m > vm.resolution and mesh.triangles <= full.triangles // 4
    check_against_brute_force(vm, mesh)


def test_coarse_cells_at_the_map_edge_end_at_the_map_edge() -> None:
    vm = VoxelMap.empty((3.5, 2.5, 1.5), 0.5, fill=OCCUPIED)  # 7 × 5 × 3 voxels
    vm.state[1:, 2, 2] = FREE  # along x to the map's end, under its top
    assert surface_mesh(vm).triangles == 8  # floor, two walls, the end at x = 0.5 m
    mesh = surface_mesh(vm, max_triangles=7)
    assert mesh.cell_m == 1.0 and mesh.triangles == 6  # the 1 m cells: floor and two walls
    lo, hi = vm.bounds
    assert np.all(mesh.vertices >= np.asarray(lo)) and np.all(mesh.vertices <= np.asarray(hi))
    assert mesh.vertices[:, 0].max() == hi[0] and mesh.vertices[:, 2].max() == hi[2]


# ------------------------------------------------------------------------------- the mine
def test_the_mine_fits_the_budget_and_coarsening_never_closes_a_passage(mine: VoxelMap) -> None:
    mesh = surface_mesh(mine)
    assert mesh.cell_m == mine.resolution and mesh.triangles <= 150_000
    assert 2 * mesh.unit_faces > 5 * mesh.triangles  # greedy merging: >5× fewer triangles
    assert np.all(mesh.colors >= 0) and np.all(mesh.colors <= 1)
    assert len(np.unique(mesh.colors.round(2), axis=0)) > 20  # shaded, not one flat colour
    open_centres = mine.index_to_world(np.argwhere(mine.state != OCCUPIED))
    for budget in (5_000, 1_000):
        coarse = surface_mesh(mine, max_triangles=budget)
        assert 0 < coarse.triangles <= budget and coarse.cell_m > mine.resolution
        factor = round(coarse.cell_m / mine.resolution)
        rock = coarse_rock(mine, factor)
        cell = np.floor((open_centres - np.asarray(mine.origin)) / coarse.cell_m).astype(int)
        assert not rock[cell[:, 0], cell[:, 1], cell[:, 2]].any()  # every open voxel stays open


# ------------------------------------------------------------------------------- risk points
def test_risk_points_are_the_free_voxels_near_rock_scaled_to_one_at_the_wall() -> None:
    vm = VoxelMap.empty((6, 4, 3), 0.5)
    vm.state[:, :2, :] = OCCUPIED  # a wall along y = 0..1 m
    vm.state[5, 2, 1] = UNKNOWN  # near the wall, but unknown: not a point
    params = RiskParams(radius_m=1.5, unknown_cost=10.0)
    pts, val = risk_points(vm, params)
    assert pts.dtype == np.float32 and val.dtype == np.float32 and len(pts) == len(val) > 0
    idx = vm.world_to_index(pts)
    assert np.all(vm.state[idx[:, 0], idx[:, 1], idx[:, 2]] == FREE)
    cost = CostMap(vm, params).voxel_cost[idx[:, 0], idx[:, 1], idx[:, 2]]
    assert np.all(cost > 0) and np.all((val > 0) & (val <= 1))
    np.testing.assert_allclose(val, cost / cost.max(), rtol=1e-6)  # the planner's own costs
    free = (vm.state == FREE) & (CostMap(vm, params).voxel_cost > 0)
    assert len(pts) == free.sum()  # every free voxel with a risk, each once
    assert np.all(idx[val == 1.0][:, 1] == 2)  # highest right next to the wall
    assert np.all(idx[:, 1] <= 3)  # nothing r = 1.5 m or more from it (y voxel 4 is 1.5 m away)


def test_risk_points_are_subsampled_deterministically(mine: VoxelMap) -> None:
    pts, val = risk_points(mine, max_points=5_000)
    again, val2 = risk_points(mine, max_points=5_000)
    assert len(pts) == 5_000
    np.testing.assert_array_equal(pts, again)
    np.testing.assert_array_equal(val, val2)
    full, _ = risk_points(mine, max_points=10**9)
    assert len(full) > 5_000
    assert len(np.unique(np.concatenate([full, pts]), axis=0)) == len(full)  # a subset
    assert risk_points(mine, max_points=0)[0].shape == (0, 3)
