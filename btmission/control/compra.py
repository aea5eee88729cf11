"""COMPRA reactive exploration, breadcrumb return and object localisation (seed 002 §3.2.4, §3.3,
Alg. 2).

**Exploration** (carrot chasing): the waypoint is always a constant step ahead along the body x
axis at the mission altitude, wp^B = [p_x^B + 1, p_y^B, p_z^m]; lateral motion comes only from the
APF and the heading from DPHR. The altitude is measured by the down-facing single-beam LiDAR,
p_z^T = R_sbl cos θ cos φ (:func:`altitude_from_range`), so the carrot's world height is the MAV's
height corrected by p_z^m − p_z^T.

**Breadcrumbs**: while T_mission^current ≤ T_mission^reference, the waypoints (with the heading)
are appended to the list BW at a user-chosen rate. After the time budget, the MAV turns round
(ψ_ref = ψ + π) and flies back to the last breadcrumb, removing it (BW \\ BW(k)) once within the
acceptance radius — and, as the paper's text adds, every other breadcrumb within that radius of the
MAV. An empty BW ends the mission: land (Alg. 2).

**Object localisation** (§3.3.1): detections (class, probability, pixel bounding box) from any
detector plus the aligned depth image are turned into 3-D positions: the depth of a 3×3 window at
the box centroid, back-projected with the camera intrinsics and transformed to the world frame.
Two-step outlier rejection fills a buffer: (1) probability ≥ Pr_threshold and inside a 5 m sphere,
(2) metric box width within the class's [Width_min, Width_max]. Once ``time_window_s`` has passed
since the last buffered observation, each class's buffer is clustered by Euclidean distance
(single linkage, ``scipy.cluster.hierarchy``), cluster means are merged with already known objects
of that class within ``merge_radius_m`` (running mean) or reported as new, and the buffer is
cleared. The result is the object list OL (the paper's leading 0₃ₓ₁ placeholder is omitted).

Everything here is pure state and arithmetic: no sensors, no I/O. The runtime feeds it
measurements and applies its outputs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from numpy.typing import ArrayLike

from btmission.control.mav_model import wrap_angle
from btmission.types import CameraIntrinsics, Detection, FloatArray  # re-exported (__all__)

__all__ = [
    "Breadcrumb",
    "BreadcrumbTrail",
    "CameraIntrinsics",
    "CompraConfig",
    "CompraExplorer",
    "Detection",
    "ExplorationCommand",
    "LocalizedObject",
    "LocalizerConfig",
    "Mode",
    "ObjectLocalizer",
    "altitude_from_range",
    "carrot_waypoint",
]


def altitude_from_range(range_m: float, roll: float, pitch: float) -> float:
    """p_z^T = R_sbl cos θ cos φ: height above ground from the down-facing single-beam range."""
    if not range_m >= 0:
        raise ValueError(f"range must be a non-negative number, got {range_m}")
    return range_m * math.cos(pitch) * math.cos(roll)


def carrot_waypoint(
    position: ArrayLike,
    yaw: float,
    altitude_m: float,
    mission_altitude_m: float,
    step_m: float = 1.0,
) -> FloatArray:
    """World-frame carrot wp = p + R_z(ψ)[step, 0, 0] with the height corrected to p_z^m.

    This is wp^B = [p_x^B + step, p_y^B, p_z^m] of seed 002 §3.2.4 expressed in the world frame:
    ``altitude_m`` is the measured height above ground (p_z^T), so the carrot sits
    ``mission_altitude_m − altitude_m`` above the MAV.
    """
    p = np.asarray(position, dtype=float)
    return np.array(
        [
            p[0] + step_m * math.cos(yaw),
            p[1] + step_m * math.sin(yaw),
            p[2] + (mission_altitude_m - altitude_m),
        ]
    )


@dataclass(frozen=True)
class Breadcrumb:
    """One entry of BW: a visited waypoint and the heading there."""

    position: tuple[float, float, float]
    yaw: float
    t: float


class BreadcrumbTrail:
    """BW of Alg. 2: recorded at ``rate_hz`` on the way in, consumed from the end on the way back."""

    def __init__(self, rate_hz: float = 1.0, radius_m: float = 0.75) -> None:
        if rate_hz <= 0 or radius_m <= 0:
            raise ValueError("rate_hz and radius_m must be positive")
        self.rate_hz = rate_hz
        self.radius_m = radius_m
        self._crumbs: list[Breadcrumb] = []
        self.recorded: list[Breadcrumb] = []
        """Every crumb ever recorded, in order (the outbound path; never consumed)."""

    def __len__(self) -> int:
        return len(self._crumbs)

    @property
    def crumbs(self) -> tuple[Breadcrumb, ...]:
        return tuple(self._crumbs)

    def record(self, t: float, position: ArrayLike, yaw: float) -> bool:
        """Append (position, yaw) if at least 1/rate has passed since the last crumb."""
        if self._crumbs and t - self._crumbs[-1].t < 1.0 / self.rate_hz - 1e-9:
            return False
        p = np.asarray(position, dtype=float)
        crumb = Breadcrumb((float(p[0]), float(p[1]), float(p[2])), float(yaw), t)
        self._crumbs.append(crumb)
        self.recorded.append(crumb)
        return True

    def target(self) -> Breadcrumb | None:
        """BW(k): the last crumb, the next one to fly back to (None when empty)."""
        return self._crumbs[-1] if self._crumbs else None

    def consume(self, position: ArrayLike) -> int:
        """Remove the crumbs within ``radius_m`` of ``position``; returns how many went.

        Only the reached tail is removed, plus any crumb along the way that is also within the
        radius, so a loop in the outbound path is not cut short.
        """
        if not self._crumbs:
            return 0
        p = np.asarray(position, dtype=float)
        pts = np.array([c.position for c in self._crumbs])
        near = np.linalg.norm(pts - p, axis=1) <= self.radius_m
        if not near[-1]:
            return 0
        before = len(self._crumbs)
        self._crumbs = [c for c, n in zip(self._crumbs, near) if not n]
        return before - len(self._crumbs)


class Mode(Enum):
    """Phases of the COMPRA workflow handled here (take-off and pre-flight are upstream)."""

    EXPLORE = "explore"
    RETURN = "return"
    LAND = "land"


@dataclass(frozen=True)
class CompraConfig:
    """Exploration and return parameters (seed 002 Alg. 2)."""

    mission_altitude_m: float = 1.5
    carrot_step_m: float = 1.0
    mission_time_s: float = 60.0
    """T_mission^reference: exploration time budget."""
    breadcrumb_rate_hz: float = 1.0
    breadcrumb_radius_m: float = 0.75

    def __post_init__(self) -> None:
        if self.mission_altitude_m <= 0 or self.carrot_step_m <= 0 or self.mission_time_s < 0:
            raise ValueError("altitude and carrot step must be positive, mission time >= 0")


@dataclass(frozen=True)
class ExplorationCommand:
    """What the explorer asks for this step (world frame)."""

    mode: Mode
    waypoint: FloatArray
    """The waypoint to hand to the APF (then to the NMPC); the current position when landing."""
    yaw_ref: float | None
    """A yaw to hold: on the return, the target crumb's heading + π (ψ_return^ref = ψ + π of
    Alg. 2, crumb by crumb); None while exploring (DPHR steers)."""
    yaw_rate_ref: float
    """The DPHR yaw rate passed through while exploring, 0 otherwise."""
    breadcrumbs: int


class CompraExplorer:
    """Alg. 2's exploration loop: explore → return along breadcrumbs → land."""

    def __init__(self, config: CompraConfig | None = None) -> None:
        self.config = cfg = config or CompraConfig()
        self.trail = BreadcrumbTrail(cfg.breadcrumb_rate_hz, cfg.breadcrumb_radius_m)
        self.mode = Mode.EXPLORE
        self._t0: float | None = None

    def step(
        self,
        t: float,
        position: ArrayLike,
        yaw: float,
        altitude_m: float,
        dphr_yaw_rate: float = 0.0,
    ) -> ExplorationCommand:
        """One tick at mission time ``t`` (s) with the MAV's world position, yaw and height.

        ``altitude_m`` is p_z^T (see :func:`altitude_from_range`); ``dphr_yaw_rate`` the DPHR
        reference, passed through while exploring.
        """
        cfg = self.config
        p = np.asarray(position, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"position must be three finite numbers, got {p.tolist()}")
        if self._t0 is None:
            self._t0 = t
        elapsed = t - self._t0
        if self.mode is Mode.EXPLORE and elapsed > cfg.mission_time_s:
            self.mode = Mode.RETURN
        if self.mode is Mode.EXPLORE:
            wp = carrot_waypoint(p, yaw, altitude_m, cfg.mission_altitude_m, cfg.carrot_step_m)
            self.trail.record(t, wp, yaw)
            return ExplorationCommand(Mode.EXPLORE, wp, None, dphr_yaw_rate, len(self.trail))
        if self.mode is Mode.RETURN:
            self.trail.consume(p)
            target = self.trail.target()
            if target is None:
                self.mode = Mode.LAND
            else:
                yaw_ref = wrap_angle(target.yaw + math.pi)
                return ExplorationCommand(
                    Mode.RETURN, np.array(target.position), yaw_ref, 0.0, len(self.trail)
                )
        return ExplorationCommand(Mode.LAND, p.copy(), None, 0.0, 0)


# ----------------------------------------------------------------------------------------------
# Object localisation (seed 002 §3.3.1)
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LocalizerConfig:
    """Object-localiser parameters (seed 002 §3.3.1; the 5 m sphere is the paper's)."""

    probability_threshold: float = 0.5
    max_range_m: float = 5.0
    width_bounds_m: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    """Per class [Width_min, Width_max] (m); a class not listed is not width-checked."""
    time_window_s: float = 2.0
    cluster_distance_m: float = 1.0
    merge_radius_m: float = 1.5
    window_px: int = 3

    def __post_init__(self) -> None:
        if not 0 <= self.probability_threshold <= 1:
            raise ValueError("probability_threshold must be within [0, 1]")
        if self.max_range_m <= 0 or self.time_window_s < 0:
            raise ValueError("max_range_m must be positive and time_window_s >= 0")
        if self.cluster_distance_m <= 0 or self.merge_radius_m <= 0 or self.window_px < 1:
            raise ValueError("cluster/merge distances must be positive and window_px >= 1")
        for label, (lo, hi) in self.width_bounds_m.items():
            if not 0 <= lo <= hi:
                raise ValueError(f"width bounds of '{label}' must satisfy 0 <= min <= max")


@dataclass
class LocalizedObject:
    """An entry of OL: a class, its world position (mean of its observations) and the count."""

    label: str
    position: FloatArray
    observations: int


@dataclass(frozen=True)
class _Observation:
    t: float
    label: str
    position: FloatArray


class ObjectLocalizer:
    """Buffer + processor of §3.3.1. Feed :meth:`add`; call :meth:`update` every tick."""

    def __init__(self, config: LocalizerConfig | None = None) -> None:
        self.config = config or LocalizerConfig()
        self._buffer: list[_Observation] = []
        self.objects: list[LocalizedObject] = []
        self.rejected: dict[str, int] = {"probability": 0, "depth": 0, "range": 0, "width": 0}

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def add(
        self,
        detection: Detection,
        depth: ArrayLike,
        camera: CameraIntrinsics,
        rotation: ArrayLike = np.eye(3),
        translation: ArrayLike = (0.0, 0.0, 0.0),
    ) -> bool:
        """Localise one detection and buffer it if it passes both outlier checks.

        ``depth`` is the aligned depth image (metres, 0 = invalid); ``rotation``/``translation``
        are ^W T_C = [R | t] (camera optical frame: x right, y down, z forward). Returns whether
        the observation was buffered; rejections are counted in :attr:`rejected`.
        """
        cfg = self.config
        if detection.probability < cfg.probability_threshold:
            self.rejected["probability"] += 1
            return False
        img = np.asarray(depth, dtype=float)
        x_min, y_min, wd, ht = detection.bbox
        if wd <= 0 or ht <= 0:
            raise ValueError(f"bounding box width and height must be positive: {detection.bbox}")
        u = x_min + wd / 2
        v = y_min + ht / 2
        half = cfg.window_px // 2
        ui, vi = round(u), round(v)
        window = img[max(vi - half, 0) : vi + half + 1, max(ui - half, 0) : ui + half + 1]
        valid = window[np.isfinite(window) & (window > 0)]
        if valid.size == 0:
            self.rejected["depth"] += 1
            return False
        z = float(np.median(valid))
        p_cam = np.array([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z])
        if float(np.linalg.norm(p_cam)) > cfg.max_range_m:
            self.rejected["range"] += 1
            return False
        bounds = cfg.width_bounds_m.get(detection.label)
        width_m = wd * z / camera.fx
        if bounds is not None and not bounds[0] <= width_m <= bounds[1]:
            self.rejected["width"] += 1
            return False
        p_world = np.asarray(rotation, dtype=float) @ p_cam + np.asarray(translation, dtype=float)
        self._buffer.append(_Observation(detection.t, detection.label, p_world))
        return True

    def update(self, t: float) -> list[LocalizedObject]:
        """Process the buffer if ``time_window_s`` has passed since its last observation.

        Returns the objects created or updated by this processing (empty if it did not run).
        """
        if not self._buffer or t - self._buffer[-1].t < self.config.time_window_s:
            return []
        return self.flush()

    def flush(self) -> list[LocalizedObject]:
        """Cluster the buffer per class, merge with known objects, clear it (§3.3.1)."""
        from scipy.cluster.hierarchy import fclusterdata

        cfg = self.config
        touched: list[LocalizedObject] = []
        for label in sorted({o.label for o in self._buffer}):
            pts = np.array([o.position for o in self._buffer if o.label == label])
            if len(pts) == 1:
                groups = np.ones(1, dtype=int)
            else:
                groups = fclusterdata(
                    pts, t=cfg.cluster_distance_m, criterion="distance", method="single"
                )
            for g in np.unique(groups):
                members = pts[groups == g]
                touched.append(self._merge(label, members.mean(axis=0), len(members)))
        self._buffer.clear()
        return touched

    def _merge(self, label: str, mean: FloatArray, count: int) -> LocalizedObject:
        known = [o for o in self.objects if o.label == label]
        if known:
            dists = [float(np.linalg.norm(o.position - mean)) for o in known]
            best = int(np.argmin(dists))
            if dists[best] <= self.config.merge_radius_m:
                obj = known[best]
                total = obj.observations + count
                obj.position = (obj.position * obj.observations + mean * count) / total
                obj.observations = total
                return obj
        obj = LocalizedObject(label, mean.copy(), count)
        self.objects.append(obj)
        return obj

    def object_list(self) -> list[tuple[str, FloatArray]]:
        """OL: (class, world position) of every localised object, in discovery order."""
        return [(o.label, o.position.copy()) for o in self.objects]
