"""The viewer's static scene as meshcat commands: the mine's surface, the risk layer, the look.

meshcat's Python package encodes scene objects as three.js JSON packed with msgpack (typed
arrays as msgpack extensions); its browser viewer (``MeshCat.Viewer``) decodes exactly those
bytes (``handle_command_bytearray``). The viewer page fetches the scene once as
:func:`pack_commands`' bytes — each command prefixed by its length — and everything that moves
(agents, tasks, trails, routes, scans) it draws itself from the run's records (``viewer.js``).

Paths in the meshcat scene tree: ``/mine`` (the rock surface, from
:func:`~btmission.viz.mesh.surface_mesh`), ``/risk`` (free voxels with a D*+ risk cost, hidden
until asked for), and meshcat's own ``/Background``, ``/Grid`` and ``/Axes``.
"""

from __future__ import annotations

import struct
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import numpy.typing as npt

from btmission.planning.risk import RiskParams
from btmission.viz.mesh import SurfaceMesh, risk_points, surface_mesh
from btmission.world.voxel import VoxelMap

MAX_TRIANGLES = 150_000
"""The mine surface's triangle budget: a 200 m mine loads in a browser in about a second."""
MAX_RISK_POINTS = 100_000
BACKGROUND = ((0.20, 0.22, 0.26), (0.04, 0.04, 0.06))
"""Top and bottom colours of the background gradient (a dark mine, not meshcat's sky)."""


def _meshcat() -> Any:
    """meshcat's geometry and commands modules. Importing meshcat imports its zmq server,
    whose pyzmq warns of deprecated modules: not ours to fix, and not to fail a run on."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import meshcat.commands
        import meshcat.geometry
        import meshcat.path
        import umsgpack
    return meshcat, umsgpack


@dataclass(frozen=True)
class Scene:
    """The packed commands and what the page needs to know of them."""

    commands: list[bytes]
    info: dict[str, Any]
    """``bounds`` ([[x, y, z] low, high]), ``resolution``, ``triangles``, ``cell_m``,
    ``risk_points``."""

    def packed(self) -> bytes:
        """The commands as :func:`pack_commands` gives them (made once: every page asks)."""
        return self._packed

    @cached_property
    def _packed(self) -> bytes:
        return pack_commands(self.commands)


def pack_commands(commands: Iterable[bytes]) -> bytes:
    """Commands as one byte string: each a 4-byte big-endian length, then its msgpack bytes."""
    return b"".join(struct.pack(">I", len(c)) + c for c in commands)


def unpack_commands(data: bytes) -> list[bytes]:
    """The inverse of :func:`pack_commands`."""
    out = []
    i = 0
    while i < len(data):
        (n,) = struct.unpack_from(">I", data, i)
        out.append(data[i + 4 : i + 4 + n])
        i += 4 + n
    return out


def risk_colors(values: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Risk in [0, 1] → RGB from pale yellow (the lowest there is) to red (the highest: next to
    rock), ``(N, 3)``."""
    v = np.clip(np.asarray(values, dtype=np.float32), 0.0, 1.0)
    if len(v) and float(v.max() - v.min()) > 1e-6:  # the ramp over the values there are
        v = (v - v.min()) / (v.max() - v.min())
    v = v[:, None]
    low = np.array([1.0, 0.93, 0.45], dtype=np.float32)
    high = np.array([0.86, 0.1, 0.08], dtype=np.float32)
    out: npt.NDArray[np.float32] = (low + (high - low) * v).astype(np.float32)
    return out


def build_scene(
    vmap: VoxelMap,
    *,
    risk: RiskParams | None = None,
    max_triangles: int = MAX_TRIANGLES,
    max_risk_points: int = MAX_RISK_POINTS,
) -> Scene:
    """The static scene of a mission's map (module docstring)."""
    mc, umsgpack = _meshcat()
    g, c, P = mc.geometry, mc.commands, mc.path.Path
    mesh: SurfaceMesh = surface_mesh(vmap, max_triangles=max_triangles)
    commands: list[dict[str, Any]] = []
    if len(mesh.faces):
        commands.append(
            c.SetObject(
                g.TriangularMeshGeometry(mesh.vertices, mesh.faces, color=mesh.colors),
                g.MeshLambertMaterial(color=0xFFFFFF, vertexColors=True, side=0),  # FrontSide:
                path=P(("mine",)),  # seen from outside, the near rock is culled (a cutaway)
            ).lower()
        )
    points, values = risk_points(vmap, risk, max_points=max_risk_points)
    if len(points):
        size = float(vmap.resolution) * 0.6
        risk_cmd = c.SetObject(
            g.PointsGeometry(points.T, risk_colors(values).T),
            g.PointsMaterial(size=size),
            path=P(("risk",)),
        ).lower()
        for material in risk_cmd["object"]["materials"]:  # see-through: tasks and trails show
            material.update({"transparent": True, "opacity": 0.35, "depthWrite": False})
        commands.append(risk_cmd)
        commands.append(c.SetProperty("visible", False, P(("risk",))).lower())
    for name in ("Grid", "Axes"):  # meshcat's 20 m grid at the origin: not the mine's floor
        commands.append(c.SetProperty("visible", False, P((name,))).lower())
    top, bottom = BACKGROUND
    commands.append(c.SetProperty("top_color", list(top), P(("Background",))).lower())
    commands.append(c.SetProperty("bottom_color", list(bottom), P(("Background",))).lower())
    lo, hi = vmap.bounds
    info = {
        "bounds": [list(map(float, lo)), list(map(float, hi))],
        "resolution": float(vmap.resolution),
        "triangles": len(mesh.faces),
        "cell_m": float(mesh.cell_m),
        "risk_points": len(points),
    }
    return Scene([umsgpack.packb(cmd) for cmd in commands], info)
