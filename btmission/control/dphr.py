"""Deepest-point heading regulation, DPHR (seed 002 §3.2.4).

Turns the MAV towards the open, deep part of the tunnel ahead from one depth image:

1. a grey-scale morphological **close** (``scipy.ndimage.grey_closing``) removes the speckle of
   invalid (zero) pixels and fills the tunnel opening;
2. **k-means** with N_clusters = 10 on the depth values (``scipy.cluster.vq.kmeans2``) splits the
   image into depth layers; the cluster with the largest mean depth is the deepest part;
3. its pixel centroid s_x = (1/|C_m|) Σ_{(x,y) ∈ C_m} x is normalised about the principal point,
   s̄_x = (s_x − c_x) / c_x ∈ [−1, 1], and mapped linearly to a yaw-rate reference
   ψ̇_ref = −l · s̄_x, clipped to [−ψ̇_max, ψ̇_max] (l = ψ̇_max by default, so the image edge maps to
   the limit). The minus sign is the frame convention: image x grows to the right, yaw grows to
   the left (counter-clockwise, z up), so an opening on the right gives a negative (right) turn.

Choices the paper leaves open, and why:

* Pixels with no return (0, as a RealSense reports anything beyond its range) count as the
  sensor's maximum range *after* the close: a tunnel opening deeper than the range is the deepest
  thing in view, while isolated dropouts have already been closed away.
* For speed the image is first reduced by ``stride`` (default 4: 640×480 → 160×120) and k-means is
  fitted on a seeded random sample of ``sample_size`` pixels, after which every reduced pixel is
  assigned to its nearest centre. The heading only needs the centroid's column, which this keeps
  to within a few full-resolution pixels, and the whole step stays within a few milliseconds.
* k-means starts from N_clusters depths evenly spaced between the nearest and the farthest
  (deterministic, one centre per layer); a cluster that empties keeps its previous centre.
* **Branch choice at junctions.** At a junction the deepest cluster falls apart into several
  regions, one per branch, and the centroid of them all lies on the rock between them. The
  paper's rule is "the deepest cluster"; here it is applied explicitly to the branches: the
  deepest cluster's mask is split into connected regions (8-connectivity; regions below
  ``min_branch_fraction`` of it are noise), and one is chosen, deterministically: the largest
  (the widest opening, the deepest *cluster* of pixels), ties broken by the greater mean depth,
  then by the smaller offset (straighter on). To commit to a branch once chosen, a caller passes
  the previous choice's offset as ``prefer_offset``: the region nearest it is kept unless another
  is more than ``switch_ratio`` times its size (:func:`choose_branch`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from btmission.types import FloatArray

__all__ = [
    "Branch",
    "DphrConfig",
    "DphrResult",
    "choose_branch",
    "deepest_point_heading",
    "yaw_rate_limit_for_speed",
]

TURN_RADIUS_M = 1.5
"""Tightest turn the heading regulation must allow: about half a 3-4 m tunnel's width."""


def yaw_rate_limit_for_speed(
    speed_m_s: float, turn_radius_m: float = TURN_RADIUS_M, floor: float = 0.5
) -> float:
    """ψ̇_max for a cruise speed: max(floor, v / R). Seed 002 maps s̄_x linearly to
    ψ̇_ref ∈ [min, max] without giving the bounds; a fixed 0.5 rad/s turns a 2.3 m/s MAV on a
    4.6 m radius, wider than the tunnel it must follow round a bend, so the bound grows with the
    speed to keep the turn radius v/ψ̇_max within ``turn_radius_m``."""
    if speed_m_s < 0 or turn_radius_m <= 0 or floor <= 0:
        raise ValueError("need speed >= 0 and a positive turn radius and floor")
    return max(floor, speed_m_s / turn_radius_m)


@dataclass(frozen=True)
class DphrConfig:
    """DPHR parameters; ``clusters`` = 10 as in the paper, the rest are ours."""

    clusters: int = 10
    close_size: int = 3
    """Side of the square structuring element of the close, in pixels of the reduced image
    (3 at stride 4 = 12 full-resolution pixels); 1 = no close."""
    stride: int = 4
    sample_size: int = 4000
    iterations: int = 10
    max_range_m: float = 6.0
    """Depth given to pixels with no return (the camera's range)."""
    yaw_rate_max: float = 0.5
    """ψ̇_max (rad/s): the reference is clipped to ±ψ̇_max."""
    gain: float | None = None
    """l (rad/s per unit offset); None = ``yaw_rate_max``."""
    seed: int = 0
    min_branch_fraction: float = 0.1
    """A connected region of the deepest cluster smaller than this share of it is not a branch."""
    switch_ratio: float = 2.0
    """With ``prefer_offset``: leave the preferred branch only for one this many times larger."""
    dead_end_m: float = 0.0
    """When even the deepest cluster is nearer than this, nothing ahead is open (a dead end, a
    wall filling the view): turn at ψ̇_max to the left until an opening comes into view, instead
    of the paper's ψ̇ = l·s̄_x, which is ~0 on a flat wall. 0 = never."""

    def __post_init__(self) -> None:
        if self.clusters < 2:
            raise ValueError(f"clusters must be at least 2, got {self.clusters}")
        if self.close_size < 1 or self.stride < 1 or self.iterations < 1:
            raise ValueError("close_size, stride and iterations must be at least 1")
        if self.sample_size < self.clusters:
            raise ValueError("sample_size must be at least the number of clusters")
        if self.max_range_m <= 0 or self.yaw_rate_max <= 0:
            raise ValueError("max_range_m and yaw_rate_max must be positive")
        if not 0 <= self.min_branch_fraction < 1 or self.switch_ratio < 1:
            raise ValueError("need 0 <= min_branch_fraction < 1 and switch_ratio >= 1")


@dataclass(frozen=True)
class Branch:
    """One connected region of the deepest cluster: a way on."""

    pixels: int
    mean_depth_m: float
    offset: float
    """s̄_x of the region's centroid, in [−1, 1] (negative = left)."""


def choose_branch(
    branches: list[Branch], prefer_offset: float | None = None, switch_ratio: float = 2.0
) -> int:
    """Index of the branch to follow (module docstring): the largest, then the deepest, then the
    straightest; with ``prefer_offset``, the one nearest it unless another is more than
    ``switch_ratio`` times larger."""
    if not branches:
        raise ValueError("no branch to choose from")
    best = min(
        range(len(branches)),
        key=lambda i: (-branches[i].pixels, -branches[i].mean_depth_m, abs(branches[i].offset)),
    )
    if prefer_offset is None or len(branches) == 1:
        return best
    kept = min(range(len(branches)), key=lambda i: abs(branches[i].offset - prefer_offset))
    if branches[best].pixels > switch_ratio * branches[kept].pixels:
        return best
    return kept


@dataclass(frozen=True)
class DphrResult:
    """One DPHR step."""

    yaw_rate: float
    """ψ̇_ref (rad/s), positive = turn left."""
    offset: float
    """s̄_x ∈ [−1, 1]: normalised column of the deepest cluster's centroid (negative = left)."""
    centroid: tuple[float, float]
    """(s_x, s_y) in full-resolution pixel coordinates."""
    deepest_depth_m: float
    """Mean depth of the deepest cluster."""
    centers: FloatArray
    """The cluster centres (depths, ascending)."""
    mask: NDArray[np.bool_]
    """The chosen branch of the deepest cluster on the reduced image (the paper's Fig. 3,
    right)."""
    branches: tuple[Branch, ...] = ()
    """Every branch of the deepest cluster (more than one: a junction)."""
    chosen: int = 0
    """Index of the followed branch in :attr:`branches`."""


def deepest_point_heading(
    depth: ArrayLike,
    config: DphrConfig | None = None,
    principal_x: float | None = None,
    prefer_offset: float | None = None,
) -> DphrResult:
    """Yaw-rate reference towards the deepest region of ``depth`` (H, W metres, 0 = no return).

    ``principal_x`` is the principal point's column c_x (default: the image centre);
    ``prefer_offset`` the offset of the branch followed so far (see :func:`choose_branch`).
    """
    from scipy import ndimage
    from scipy.cluster.vq import kmeans2

    cfg = config or DphrConfig()
    img = np.asarray(depth, dtype=float)
    if img.ndim != 2 or img.shape[0] < 2 or img.shape[1] < 2:
        raise ValueError(f"depth must be a 2-D image, got shape {img.shape}")
    width = img.shape[1]
    cx = (width - 1) / 2 if principal_x is None else float(principal_x)
    if not 0 < cx < width - 1:
        raise ValueError(f"principal_x must lie inside the image (0, {width - 1}), got {cx}")
    small = np.nan_to_num(img[:: cfg.stride, :: cfg.stride], nan=0.0, posinf=0.0, neginf=0.0)
    small = np.clip(small, 0.0, None)
    size = cfg.close_size
    closed = ndimage.grey_closing(small, size=(size, size)) if size > 1 else small
    filled = np.where(closed > 0, np.minimum(closed, cfg.max_range_m), cfg.max_range_m)
    values = filled.ravel()

    rng = np.random.default_rng(cfg.seed)
    sample = values if values.size <= cfg.sample_size else rng.choice(values, cfg.sample_size)
    lo, hi = float(sample.min()), float(sample.max())
    flat = hi - lo < 1e-9
    if flat:  # nothing deeper than anything else
        init = np.array([lo])
        centers = init
        labels = np.zeros(values.size, dtype=int)
    else:
        init = np.linspace(lo, hi, cfg.clusters)
        with warnings.catch_warnings():  # an emptied cluster keeps its centre; that is fine
            warnings.simplefilter("ignore", UserWarning)
            centers, _ = kmeans2(sample, init, iter=cfg.iterations, minit="matrix")
        centers = np.sort(centers)
        # 1-D nearest centre = the interval between consecutive mid-points
        labels = np.searchsorted((centers[1:] + centers[:-1]) / 2, values)
    deepest = int(
        np.argmax(
            np.bincount(labels, weights=values, minlength=centers.size)
            / np.maximum(np.bincount(labels, minlength=centers.size), 1)
        )
    )
    deep = (labels == deepest).reshape(filled.shape)
    regions, count = ndimage.label(deep, structure=np.ones((3, 3), dtype=int))
    sizes = np.bincount(regions.ravel(), minlength=count + 1)[1:]
    keep = [k + 1 for k in range(count) if sizes[k] >= cfg.min_branch_fraction * deep.sum()]
    branches: list[Branch] = []
    for k in keep:
        r_mask = regions == k
        col = float(np.nonzero(r_mask)[1].mean()) * cfg.stride
        branches.append(
            Branch(
                pixels=int(sizes[k - 1]),
                mean_depth_m=float(filled[r_mask].mean()),
                offset=float(np.clip((col - cx) / cx, -1.0, 1.0)),
            )
        )
    chosen = choose_branch(branches, prefer_offset, cfg.switch_ratio) if branches else 0
    mask = regions == keep[chosen] if branches else deep
    rows, cols = np.nonzero(mask)
    s_x = float(cols.mean()) * cfg.stride
    s_y = float(rows.mean()) * cfg.stride
    offset = float(np.clip((s_x - cx) / cx, -1.0, 1.0))
    gain = cfg.yaw_rate_max if cfg.gain is None else cfg.gain
    if flat:
        offset = 0.0
    yaw_rate = float(np.clip(-gain * offset, -cfg.yaw_rate_max, cfg.yaw_rate_max))
    deepest_m = float(values[mask.ravel()].mean())
    if deepest_m < cfg.dead_end_m:
        yaw_rate = cfg.yaw_rate_max
    return DphrResult(
        yaw_rate=yaw_rate,
        offset=offset,
        centroid=(s_x, s_y),
        deepest_depth_m=deepest_m,
        centers=np.asarray(centers, dtype=float),
        mask=mask,
        branches=tuple(branches),
        chosen=chosen,
    )
