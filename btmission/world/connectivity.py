"""26-connected components of a 3D boolean grid, in numpy alone (no scipy, no numba).

``btmission validate`` asks one question of a map: which voxels are connected to an agent's start
through voxels the planner may enter. :func:`components` answers it without importing
``scipy.ndimage`` (~0.2 s of imports for one call) by working on *runs*: the maximal stretches of
``True`` voxels along the grid's last (contiguous) axis. A mine's 2 million voxels hold ~20 000
runs, so the graph is small:

* two runs are 26-neighbours exactly when their rows are 8-neighbours in the first two axes and
  their intervals come within one voxel of each other (found with ``searchsorted``, row by row);
* runs are merged by min-label hooking of roots and pointer jumping (Shiloach–Vishkin style), a
  few vectorised passes over the run edges.

Labels are component ids, not scipy's numbering; :meth:`Components.label` answers "same component"
exactly as ``scipy.ndimage.label(mask, structure=np.ones((3, 3, 3)))`` does (a test compares them).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

IntArray = npt.NDArray[np.int64]

_FORWARD_ROWS = ((0, 1), (1, -1), (1, 0), (1, 1))
"""Row offsets (first axis, second axis) to the half of a row's 8 neighbours that come after it;
each undirected run edge is found once."""


@dataclass(frozen=True)
class Components:
    """The 26-connected components of a 3D boolean grid, stored per run along its last axis.

    Run ``q`` covers ``[start_key[q], end_key[q])`` in keys ``row * (n_last + 1) + index`` where
    ``row = i * shape[1] + j``; keys increase with ``q``. ``root[q]`` is the component of run ``q``
    (the smallest run index in it).
    """

    shape: tuple[int, int, int]
    start_key: IntArray
    end_key: IntArray
    root: IntArray

    def label(self, index: Sequence[int] | npt.NDArray[np.integer]) -> int:
        """The component of voxel ``index`` (i, j, k inside the grid); -1 for a ``False`` voxel."""
        i, j, k = (int(v) for v in index)
        key = (i * self.shape[1] + j) * (self.shape[2] + 1) + k
        q = int(np.searchsorted(self.start_key, key, side="right")) - 1
        if q < 0 or self.end_key[q] <= key:
            return -1
        return int(self.root[q])

    @property
    def count(self) -> int:
        """How many components there are."""
        return int(np.count_nonzero(self.root == np.arange(self.root.size)))


def _runs(mask: npt.NDArray[np.bool_]) -> tuple[IntArray, IntArray]:
    """Start and end keys of the runs of ``True`` along the last axis (see :class:`Components`)."""
    ni, nj, nk = mask.shape
    padded = np.zeros((ni * nj, nk + 2), np.int8)
    padded[:, 1:-1] = mask.reshape(ni * nj, nk)
    step = np.diff(padded, axis=1)  # row r, column k: +1 where a run starts at k, -1 where one ends
    return np.flatnonzero(step == 1), np.flatnonzero(step == -1)


def _run_edges(shape: tuple[int, int, int], start: IntArray, end: IntArray) -> IntArray:
    """Pairs (2, E) of runs that touch (26-neighbourhood), each pair once."""
    ni, nj, nk = shape
    width = nk + 1
    row = start // width
    first, stop = start - row * width, end - row * width
    i, j = row // nj, row % nj
    sources: list[IntArray] = []
    targets: list[IntArray] = []
    for di, dj in _FORWARD_ROWS:
        valid = (i + di < ni) & (j + dj >= 0) & (j + dj < nj)
        other = (row + di * nj + dj) * width
        # runs of the other row that reach back to `first` and begin no later than `stop`
        lo = np.searchsorted(end, other + first, side="left")
        hi = np.searchsorted(start, other + stop, side="right")
        count = np.where(valid, np.maximum(hi - lo, 0), 0)
        total = int(count.sum())
        if total == 0:
            continue
        src = np.repeat(np.arange(start.size), count)
        offset = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
        sources.append(src)
        targets.append(lo[src] + offset)
    if not sources:
        return np.zeros((2, 0), np.int64)
    return np.stack([np.concatenate(sources), np.concatenate(targets)])


def _roots(n: int, edges: IntArray) -> IntArray:
    """Component root (smallest member) of each of ``n`` nodes joined by ``edges`` (2, E)."""
    parent = np.arange(n)
    u, v = edges
    while True:
        ru, rv = parent[u], parent[v]
        apart = ru != rv
        if not apart.any():
            return parent
        u, v, ru, rv = u[apart], v[apart], ru[apart], rv[apart]
        # hook each larger root under the smallest root it touches, then jump to the roots
        np.minimum.at(parent, np.maximum(ru, rv), np.minimum(ru, rv))
        while True:
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand


def components(mask: npt.ArrayLike) -> Components:
    """The 26-connected components of the ``True`` voxels of the 3D array ``mask``."""
    grid = np.asarray(mask, dtype=bool)
    if grid.ndim != 3:
        raise ValueError(f"components needs a 3D array, got shape {grid.shape}")
    shape = (int(grid.shape[0]), int(grid.shape[1]), int(grid.shape[2]))
    start, end = _runs(grid)
    root = _roots(start.size, _run_edges(shape, start, end))
    return Components(shape, start, end, root)
