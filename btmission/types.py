"""Value types shared across layers: one definition each, no behaviour.

Everything here is plain data that both the vehicle interface (:mod:`btmission.vehicles.base`)
and the algorithms (:mod:`btmission.control`, :mod:`btmission.localization` ...) use, so that the
interface does not have to import an algorithm to name its types:

* :data:`FloatArray` — a NumPy array of ``float64`` (positions, velocities, point clouds);
* :data:`Vec3` — a world-frame 3-vector as a plain tuple (metres, z up);
* :class:`CameraIntrinsics` and :class:`Detection` — what a depth camera and an object detector
  deliver (the inputs of the seed 002 object localiser, :mod:`btmission.control.compra`);
* :func:`recorder` and :func:`record` — a frozen dataclass built without its per-field
  assignment (records a run builds by the thousand per second): a performance shortcut, so it
  lives in :mod:`btmission.fastpaths.records` with the others and is re-exported here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from btmission.fastpaths.records import record, recorder

__all__ = ["CameraIntrinsics", "Detection", "FloatArray", "Vec3", "record", "recorder"]

FloatArray = NDArray[np.float64]
"""A NumPy array of float64."""

Vec3 = tuple[float, float, float]
"""A 3-vector (x, y, z) as a plain tuple."""


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of the depth image the boxes are aligned to (pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError("focal lengths must be positive")


@dataclass(frozen=True)
class Detection:
    """One detector output: class, probability Pr_CL and BB = (x_min, y_min, Wd, Ht) in pixels."""

    t: float
    label: str
    probability: float
    bbox: tuple[float, float, float, float]
