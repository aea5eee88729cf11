"""Map sensors: a vehicle's LiDAR and depth camera ray-cast through the mission map.

:class:`MapSensors` implements the :class:`~btmission.vehicles.base.Sensors` interface from a
:class:`~btmission.backends.simworld.SimWorld` (the voxel map and the mission's artifacts), the sensor
settings of a :class:`~btmission.backends.sim.SimConfig`, a seeded numpy generator, and two
callables: ``pose()``, where the vehicle is (anything with ``time_s``, ``position`` and ``yaw``,
world frame: a :class:`SensorPose` or a :class:`~btmission.vehicles.base.Telemetry`), and
``others()``, the body spheres of the other vehicles (:class:`Body`; :func:`body_at` makes one
from a reported position). It never looks at a
vehicle's truth, only at what those callables give:

* the embedded simulator's vehicles (:class:`~btmission.backends.sim.SimVehicle`) use it with
  their true pose and the other simulated vehicles;
* a real-autopilot provider (MAVLink SITL, tests) can use it with the pose the vehicle
  *reports* and the other agents' reported positions (or none) — what SITL users get from
  Gazebo's sensors.

What each sensor gives (the same as the simulator always did):

* :meth:`MapSensors.lidar` — the short-range view for obstacle avoidance: the rock faces within
  ``lidar_range_m`` (no occlusion), points on the body sphere of every other vehicle whose
  reference point (the bottom of its sphere) is within that range, and ``dust_points`` dust
  outliers near the vehicle; in the vehicle's yaw frame;
* :meth:`MapSensors.lidar_scan` — a full turn of an OS1-32-like 3D LiDAR mounted
  ``lidar_mount_m`` above the vehicle, gravity-aligned, with range noise (static map only);
  one scan per pose time;
* :meth:`MapSensors.camera` — a level, forward-looking depth camera 0.1 m above the vehicle, with
  the artifacts drawn as spheres and detected with noisy boxes; one frame per pose time.

Random draws (dust, scan noise, detection noise) come from the generator given, in that order
per call, so a seed gives the same readings.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np

from btmission.control.mav_model import world_to_yaw_frame
from btmission.localization.scan import OS1_32, LidarSensor, pose_matrix, simulate_scan
from btmission.types import CameraIntrinsics, Detection, FloatArray, Vec3
from btmission.vehicles.base import CameraFrame, LidarScan

if TYPE_CHECKING:
    from btmission.backends.sim import SimConfig
    from btmission.backends.simworld import Artifact, SimWorld

VEHICLE_POINTS = 200
"""Points another vehicle returns in a LiDAR scan (a 0.5 m drone 1-2 m away in a VLP-16 scan
gives hundreds)."""
LIDAR_MOUNT_M = 0.2
"""Height of the 3D LiDAR above the vehicle's reference point (the bottom of its body)."""
CAMERA_MOUNT_M = 0.1
"""Height of the depth camera above the vehicle's reference point."""


class PoseSource(Protocol):
    """Where a vehicle is: a :class:`SensorPose`, or a
    :class:`~btmission.vehicles.base.Telemetry` as an autopilot reports it."""

    @property
    def time_s(self) -> float: ...

    @property
    def position(self) -> FloatArray:
        """World position of the vehicle's reference point (the bottom of its body), m."""
        ...

    @property
    def yaw(self) -> float:
        """World yaw, rad, counter-clockwise from +x."""
        ...


class SensorPose(NamedTuple):
    """A vehicle's pose at a time (world frame)."""

    time_s: float
    position: FloatArray
    yaw: float


class Body(NamedTuple):
    """Another vehicle as the LiDAR sees it: a sphere resting on the vehicle's reference point."""

    centre: FloatArray
    """World position of the sphere's centre (m)."""
    radius: float


class Bodies(NamedTuple):
    """Other vehicles as arrays (what a simulator holding a whole fleet hands its sensors)."""

    centres: FloatArray
    """(m, 3) sphere centres (m)."""
    radii: FloatArray
    """(m,) radii (m)."""
    skip: int = -1
    """A row to leave out (the vehicle itself, in a table of the whole fleet); -1: none."""


def body_at(position: Vec3 | FloatArray, radius: float) -> Body:
    """The body sphere of a vehicle at ``position`` (its reference point, e.g. the position it
    reports): the sphere of ``radius`` resting on that point."""
    centre: FloatArray = np.asarray(position, dtype=float) + np.array([0.0, 0.0, radius])
    return Body(centre, radius)


def no_bodies() -> list[Body]:
    """No other vehicles (the default ``others``)."""
    return []


class MapSensors:
    """The :class:`~btmission.vehicles.base.Sensors` of one vehicle, ray-cast through a
    :class:`~btmission.backends.simworld.SimWorld` at the pose ``pose()`` gives (module docstring)."""

    def __init__(
        self,
        world: SimWorld,
        config: SimConfig,
        rng: np.random.Generator,
        pose: Callable[[], PoseSource],
        others: Callable[[], Iterable[Body] | Bodies] = no_bodies,
        *,
        scan_sensor: LidarSensor = OS1_32,
        lidar_mount_m: float = LIDAR_MOUNT_M,
    ) -> None:
        self.world = world
        self.config = config
        self.rng = rng
        self.pose = pose
        self.others = others
        self.scan_sensor = scan_sensor
        """The 3D LiDAR of :meth:`lidar_scan` (seed 000's platforms carry an Ouster OS1-32)."""
        self.lidar_mount_m = lidar_mount_m
        """Height of that LiDAR above the vehicle's reference point."""
        self._camera_cache: tuple[float, CameraFrame] | None = None
        self._scan_cache: LidarScan | None = None

    def lidar(self) -> FloatArray:
        """(N, 3) points relative to the vehicle, in its yaw frame (x forward, z up): rock faces
        and other vehicles' bodies within ``lidar_range_m``, plus dust."""
        cfg = self.config
        pose = self.pose()
        p = pose.position
        bodies = self.others()
        if not isinstance(bodies, Bodies):
            listed = list(bodies)
            bodies = Bodies(
                np.array([b.centre for b in listed]).reshape(-1, 3),
                np.array([b.radius for b in listed], dtype=float),
            )
        pts = self.world.scan_points(p, cfg.lidar_range_m, pose.yaw, bodies, _SPHERE)
        if cfg.dust_points:
            dust = self.rng.normal(0.0, 0.25, (cfg.dust_points, 3))
            pts = np.vstack([pts, world_to_yaw_frame(dust, pose.yaw)])
        return pts

    def lidar_scan(self) -> LidarScan:
        """A full turn of the 3D LiDAR at the pose: every beam of :attr:`scan_sensor` ray-cast
        through the voxel map (:func:`~btmission.localization.scan.simulate_scan`, with its range
        noise drawn from the generator, so a seed gives the same scans). The sensor sits
        :attr:`lidar_mount_m` above the vehicle and is gravity-aligned (x along the heading,
        z up): the points are what a LiDAR-inertial driver gives. Other vehicles are not in it
        (the voxel map is static). One scan per pose time: asking again at the same time returns
        the same scan."""
        pose = self.pose()
        cached = self._scan_cache
        if cached is not None and cached.time_s == pose.time_s:
            return cached
        p = pose.position
        at = pose_matrix(float(p[0]), float(p[1]), float(p[2]) + self.lidar_mount_m, pose.yaw)
        points = simulate_scan(self.world.map, at, self.scan_sensor, rng=self.rng)
        mount = pose_matrix(0.0, 0.0, self.lidar_mount_m)
        scan = LidarScan(pose.time_s, points, mount, self.scan_sensor.name)
        self._scan_cache = scan
        return scan

    def camera(self) -> CameraFrame:
        """Depth image (z-depth, 0 = no return) from a forward-looking level camera, with the
        artifacts in view detected (noisy box, probability 0.6-0.95). One frame per pose time."""
        pose = self.pose()
        if self._camera_cache is not None and self._camera_cache[0] == pose.time_s:
            return self._camera_cache[1]
        cfg = self.config
        rng = self.rng
        w, h = cfg.camera_size
        fx = (w / 2) / math.tan(math.radians(cfg.camera_hfov_deg) / 2)
        intr = CameraIntrinsics(fx, fx, (w - 1) / 2, (h - 1) / 2)
        p = pose.position + np.array([0.0, 0.0, CAMERA_MOUNT_M])
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        # optical frame (x right, y down, z forward) → world, for a level camera facing yaw
        rot = np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])
        uu, vv = np.meshgrid((np.arange(w) - intr.cx) / fx, (np.arange(h) - intr.cy) / fx)
        rays = np.column_stack([uu.ravel(), vv.ravel(), np.ones(w * h)]) @ rot.T
        norm = np.linalg.norm(rays, axis=1)
        dirs = rays / norm[:, None]
        dist = self.world.raycast(p, dirs, cfg.camera_range_m)
        seen: list[Artifact] = []
        for art in self.world.artifacts:
            d = _ray_sphere(p, dirs, np.asarray(art.position), art.size_m / 2)
            closer = d < dist
            if np.any(closer):
                dist = np.where(closer, d, dist)
                seen.append(art)
        z = dist / norm  # distance along the ray → depth along the optical axis
        depth = np.where(z <= cfg.camera_range_m, z, 0.0).reshape(h, w)
        dets: list[Detection] = []
        for art in seen:
            rel = rot.T @ (np.asarray(art.position) - p)
            if rel[2] <= 0.1:
                continue
            u = fx * rel[0] / rel[2] + intr.cx
            vpx = fx * rel[1] / rel[2] + intr.cy
            size_px = fx * art.size_m / rel[2]
            noise = rng.normal(0.0, cfg.detection_noise_px, 2)
            x0 = u - size_px / 2 + noise[0]
            y0 = vpx - size_px / 2 + noise[1]
            if not (0 <= u < w and 0 <= vpx < h):
                continue
            prob = float(rng.uniform(0.6, 0.95))
            dets.append(Detection(pose.time_s, art.label, prob, (x0, y0, size_px, size_px)))
        frame = CameraFrame(pose.time_s, depth, intr, rot, p, tuple(dets))
        self._camera_cache = (pose.time_s, frame)
        return frame


def _fibonacci_sphere(n: int) -> FloatArray:
    """``n`` points spread evenly on the unit sphere."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    r = np.sqrt(1 - z * z)
    phi = math.pi * (1 + 5**0.5) * k
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


_SPHERE = _fibonacci_sphere(VEHICLE_POINTS)


def sphere_points() -> FloatArray:
    """The unit points a vehicle's body gives in another's short-range LiDAR (scaled to its
    radius by the scan)."""
    return _SPHERE


def _ray_sphere(origin: FloatArray, dirs: FloatArray, centre: FloatArray, r: float) -> FloatArray:
    """Distance along each unit ray to a sphere (inf where it misses)."""
    oc = origin - centre
    b = dirs @ oc
    c = float(oc @ oc) - r * r
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc >= 0) & (t > 0), t, math.inf)
