"""Path post-processing: waypoint thinning that never adds risk and never cuts through rock.

A D*+ path is a chain of adjacent voxel centres (seed 000 §IV-C2: "a list of voxels that a UAV
must sequentially visit"). A tracker wants far fewer waypoints. :func:`thin_path` keeps a waypoint
only where a straight line would be worse: from each kept waypoint it extends the straight segment
along the path as far as the segment

* touches no occupied voxel (every voxel the segment passes through, including those it only
  grazes at an edge or a corner, is checked), and
* meets no voxel riskier than the riskiest voxel of the stretch of path it replaces, and the sum of
  the risk (+ unknown) costs of the voxels it touches is no more than that stretch's.

Both endpoints are kept; consecutive path voxels are always a valid step, so the result exists.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from btmission.planning.risk import CostMap


def _check(
    cost_map: CostMap, a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]
) -> tuple[float, float]:
    from btmission.planning import _kernels as K

    _, py, pz = cost_map.padded.shape
    origin_pad = np.asarray(cost_map.map.origin, dtype=np.float64) - cost_map.resolution
    worst, total = K.segment_cost(
        cost_map.flat_padded(), a, b, py * pz, pz, cost_map.resolution, origin_pad
    )
    return float(worst), float(total)


def segment_risk(cost_map: CostMap, a: npt.ArrayLike, b: npt.ArrayLike) -> tuple[float, float]:
    """(max, sum) of the voxel costs ``c_r + c_u·[unknown]`` over the voxels the straight segment
    ``a → b`` touches; (inf, inf) if it touches rock or leaves the map."""
    return _check(cost_map, np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))


def thin_path(cost_map: CostMap, path: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """The waypoints of ``path`` ((N, 3) world voxel centres, adjacent voxels) that a straight-line
    tracker needs; see the module docstring for the rules."""
    pts = np.asarray(path, dtype=np.float64).reshape(-1, 3)
    if len(pts) <= 2:
        return pts.copy()
    vm = cost_map.map
    idx = vm.world_to_index(pts)
    vc = cost_map.voxel_cost[idx[:, 0], idx[:, 1], idx[:, 2]]
    keep = [0]
    anchor = 0
    j = anchor + 2
    n = len(pts)
    while j < n:
        stretch = vc[anchor : j + 1]
        worst, total = _check(cost_map, pts[anchor], pts[j])
        if worst <= stretch.max() and total <= stretch.sum() + 1e-9:
            j += 1
            continue
        anchor = j - 1
        keep.append(anchor)
        j = anchor + 2
    keep.append(n - 1)
    return pts[keep]
