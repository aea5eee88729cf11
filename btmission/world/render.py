"""Top-view pictures of a voxel map shaded by a cost per voxel, and a path (like seed 000 Fig. 5).

The costs are the caller's: a plain array of the map's shape, e.g. the planner's risk layer
(``btmission.planning.risk.CostMap.voxel_cost``, what ``btmission map show`` and ``btmission plan``
draw); this module knows the map, not how the costs were made.

Colours: rock black; free space shaded by the cost of the voxel (green = 0, through yellow to red
= highest); columns holding only unknown voxels purple. Without ``z`` each (x, y) column shows its
*cheapest* non-rock voxel (with the risk layer a tunnel reads as its safe centre line); with ``z``
the horizontal slice at that height. Matplotlib is imported here only.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from btmission.world.voxel import FREE, OCCUPIED, UNKNOWN, VoxelMap

Marker = tuple[str, Sequence[float], str]
"""(label, world point, colour)."""


def top_view_png(
    voxel_map: VoxelMap,
    voxel_cost: npt.NDArray[np.float64],
    *,
    cost_label: str = "voxel cost",
    path: npt.ArrayLike | None = None,
    markers: Sequence[Marker] = (),
    z: float | None = None,
    title: str = "",
    dpi: int = 100,
) -> bytes:
    """PNG bytes of the top view of ``voxel_map`` shaded by ``voxel_cost`` (same shape as the
    map; its values in rock are not read), with ``cost_label`` under the colour bar; ``path``
    (N, 3) drawn as a line, ``markers`` as labelled dots."""
    if np.shape(voxel_cost) != voxel_map.shape:
        raise ValueError(
            f"voxel costs of shape {np.shape(voxel_cost)} for a map of shape {voxel_map.shape}"
        )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LinearSegmentedColormap

    vm = voxel_map
    st = vm.state
    vc = voxel_cost
    if z is not None:
        k = int(np.clip(vm.world_to_index((0.0, 0.0, z))[2], 0, vm.shape[2] - 1))
        layer_state = st[:, :, k]
        shade = np.where(layer_state == OCCUPIED, np.nan, vc[:, :, k])
        only_unknown = layer_state == UNKNOWN
    else:
        passable = st != OCCUPIED
        shade = np.where(passable, vc, np.inf).min(axis=2)
        shade = np.where(np.isfinite(shade), shade, np.nan)
        only_unknown = passable.any(axis=2) & ~(st == FREE).any(axis=2)
    cmax = max(float(np.nanmax(shade)) if np.isfinite(np.nanmax(shade, initial=0.0)) else 1.0, 1e-9)
    ex = vm.extent
    lo = vm.origin
    aspect = ex[1] / max(ex[0], 1e-9)
    fig, ax = plt.subplots(figsize=(10, max(3.0, 10 * aspect) + 0.6))
    ax.set_facecolor("black")
    cmap = LinearSegmentedColormap.from_list("cost", ["#2ca02c", "#ffdd33", "#d62728"])
    extent = (lo[0], lo[0] + ex[0], lo[1], lo[1] + ex[1])
    img = ax.imshow(
        shade.T,
        origin="lower",
        extent=extent,
        cmap=cmap,
        vmin=0.0,
        vmax=cmax,
        interpolation="nearest",
    )
    if only_unknown.any():
        ov = np.zeros((*only_unknown.T.shape, 4))
        ov[only_unknown.T] = (0.55, 0.25, 0.75, 1.0)
        ax.imshow(ov, origin="lower", extent=extent, interpolation="nearest")
    fig.colorbar(img, ax=ax, fraction=0.03, pad=0.01, label=cost_label)
    if path is not None:
        p = np.asarray(path, dtype=np.float64).reshape(-1, 3)
        if len(p):
            ax.plot(p[:, 0], p[:, 1], color="white", lw=1.6)
            ax.plot(p[0, 0], p[0, 1], "o", color="#1f77b4", ms=9, mec="white")
            ax.plot(p[-1, 0], p[-1, 1], "o", color="#d62728", ms=9, mec="white")
    for label, pt, colour in markers:
        ax.plot(pt[0], pt[1], "o", color=colour, ms=6, mec="white")
        ax.annotate(
            label,
            (pt[0], pt[1]),
            xytext=(4, 4),
            textcoords="offset points",
            color="white",
            fontsize=8,
        )
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    where = f"slice z = {z:g} m" if z is not None else "cheapest voxel of each column"
    ax.set_title(
        title or f"{vm.shape[0]}×{vm.shape[1]}×{vm.shape[2]} at {vm.resolution:g} m — {where}"
    )
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()
