"""Synthetic tunnels and the sensors that see them: a VLP-16-like LiDAR and a depth camera.

Used by the tests, the benchmarks and the documentation examples of :mod:`btmission.control`, so
the reactive modules are exercised on geometry rather than on hand-placed numbers. A tunnel is a
pair of wall polylines in the horizontal plane (world frame, metres) between a flat floor and
ceiling; sensors ray-cast against the vertical wall segments and the two planes, fully vectorised
(rays × segments), with no Python loop over rays.

Frames: world x forward/east, y left/north, z up; yaw ψ counter-clockwise about z. The LiDAR
returns points in the *body* frame (x forward, y left, z up) centred on the sensor. The depth
camera is a pinhole looking along body x, returning z-depth in metres (0 = no return) in an image
with u to the right and v downwards, as a RealSense publishes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from btmission.types import FloatArray

__all__ = [
    "DepthCamera",
    "Tunnel",
    "bending_tunnel",
    "box_distance",
    "depth_image",
    "lidar_scan",
    "shelf_outline",
    "straight_corridor",
]


@dataclass(frozen=True)
class Tunnel:
    """Walls as polylines ((K, 2) arrays of x, y), plus floor and ceiling heights (z)."""

    left: FloatArray
    right: FloatArray
    floor_z: float = 0.0
    ceiling_z: float = 3.0

    def segments(self) -> tuple[FloatArray, FloatArray]:
        """Start points and direction vectors of every wall segment, (S, 2) each."""
        starts = np.vstack([self.left[:-1], self.right[:-1]])
        ends = np.vstack([self.left[1:], self.right[1:]])
        return starts, ends - starts


def shelf_outline(x0: float, x1: float, y0: float, y1: float, step: float = 0.05) -> FloatArray:
    """(P, 2) points every ``step`` along the sides of the rectangle [x0, x1] × [y0, y1]: a shelf
    (or any box) as a planar LiDAR at the robot's height sees it, for the ground NMPC."""
    xs = np.arange(x0, x1 + 1e-9, step)
    ys = np.arange(y0, y1 + 1e-9, step)
    return np.vstack(
        [
            np.column_stack([xs, np.full_like(xs, y0)]),
            np.column_stack([xs, np.full_like(xs, y1)]),
            np.column_stack([np.full_like(ys, x0), ys]),
            np.column_stack([np.full_like(ys, x1), ys]),
        ]
    )


def box_distance(p: ArrayLike, box: tuple[float, float, float, float]) -> float:
    """Exact distance from the point ``p`` (x, y) to the filled rectangle ``box`` = (x0, x1, y0,
    y1) (0 inside)."""
    x0, x1, y0, y1 = box
    q = np.asarray(p, dtype=float)
    dx = max(x0 - float(q[0]), 0.0, float(q[0]) - x1)
    dy = max(y0 - float(q[1]), 0.0, float(q[1]) - y1)
    return math.hypot(dx, dy)


def straight_corridor(
    width_m: float = 3.0, height_m: float = 3.0, length_m: float = 200.0, start_x: float = -20.0
) -> Tunnel:
    """A straight corridor along +x, centred on y = 0, from ``start_x`` for ``length_m``."""
    xs = np.array([start_x, start_x + length_m])
    half = width_m / 2
    return Tunnel(
        left=np.column_stack([xs, np.full(2, half)]),
        right=np.column_stack([xs, np.full(2, -half)]),
        floor_z=0.0,
        ceiling_z=height_m,
    )


def bending_tunnel(
    bend: str,
    width_m: float = 3.5,
    height_m: float = 3.0,
    straight_m: float = 3.0,
    radius_m: float = 5.0,
    angle_deg: float = 90.0,
    exit_m: float = 20.0,
    pieces: int = 24,
) -> Tunnel:
    """A tunnel along +x from x = −5 that bends ``"left"`` or ``"right"`` after ``straight_m``.

    The centre line is straight to x = ``straight_m``, then an arc of ``radius_m`` through
    ``angle_deg``, then straight again for ``exit_m``; walls are offset ±width/2 from it.
    """
    if bend not in ("left", "right"):
        raise ValueError(f"bend must be 'left' or 'right', got '{bend}'")
    if not 0 < width_m / 2 < radius_m:
        raise ValueError("need 0 < width/2 < radius")
    side = 1.0 if bend == "left" else -1.0
    angles = np.radians(np.linspace(0.0, angle_deg, pieces + 1))
    centre = np.array([straight_m, side * radius_m])  # centre of the arc
    arc = centre + radius_m * np.column_stack([np.sin(angles), -side * np.cos(angles)])
    heading = side * angles  # tangent direction along the centre line
    exit_dir = np.array([math.cos(heading[-1]), math.sin(heading[-1])])
    line = np.vstack([[-5.0, 0.0], arc, arc[-1] + exit_m * exit_dir])
    tangent_angles = np.concatenate([[0.0], heading, [heading[-1]]])
    normal = np.column_stack([-np.sin(tangent_angles), np.cos(tangent_angles)])  # to the left
    half = width_m / 2
    return Tunnel(
        left=line + half * normal, right=line - half * normal, floor_z=0.0, ceiling_z=height_m
    )


_CHUNK = 16384
"""Rays per block: bounds the (rays × segments) temporaries to a few MB."""


def _raycast(tunnel: Tunnel, origin: FloatArray, dirs: FloatArray, max_range: float) -> FloatArray:
    """Ray parameter t of the first hit along ``origin + t·dirs`` (inf beyond ``max_range``)."""
    return np.concatenate(
        [
            _raycast_block(tunnel, origin, dirs[i : i + _CHUNK], max_range)
            for i in range(0, len(dirs), _CHUNK)
        ]
        or [np.zeros(0)]
    )


def _raycast_block(
    tunnel: Tunnel, origin: FloatArray, dirs: FloatArray, max_range: float
) -> FloatArray:
    starts, edges = tunnel.segments()
    rel = starts - origin[:2]  # (S, 2)
    dx, dy = dirs[:, 0:1], dirs[:, 1:2]  # (R, 1)
    denom = dx * edges[:, 1] - dy * edges[:, 0]  # d × e, (R, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (rel[:, 0] * edges[:, 1] - rel[:, 1] * edges[:, 0]) / denom  # (P × e)/(d × e)
        s = (rel[:, 0] * dy - rel[:, 1] * dx) / denom  # (P × d)/(d × e)
    hit = (t > 1e-9) & (s >= 0) & (s <= 1) & np.isfinite(t)
    t_wall = np.where(hit, t, np.inf).min(axis=1)
    dz = dirs[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(dz < 0, (tunnel.floor_z - origin[2]) / dz, np.inf)
        t_ceil = np.where(dz > 0, (tunnel.ceiling_z - origin[2]) / dz, np.inf)
    t_hit = np.minimum(t_wall, np.minimum(t_floor, t_ceil))
    reach = np.linalg.norm(dirs, axis=1)
    return np.where(t_hit * reach <= max_range, t_hit, np.inf)


def _yaw_matrix(yaw: float) -> FloatArray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def lidar_scan(
    tunnel: Tunnel,
    position: ArrayLike,
    yaw: float = 0.0,
    *,
    rings: int = 16,
    azimuth_steps: int = 1875,
    vertical_fov_deg: tuple[float, float] = (-15.0, 15.0),
    max_range_m: float = 100.0,
    noise_m: float = 0.0,
    seed: int = 0,
) -> FloatArray:
    """A spinning-LiDAR scan (default VLP-16: 16 rings × 1,875 azimuths = 30,000 rays).

    Returns the (M, 3) body-frame points of the rays that hit within ``max_range_m``, with optional
    Gaussian range noise.
    """
    origin = np.asarray(position, dtype=float)
    elev = np.radians(np.linspace(*vertical_fov_deg, rings))
    azim = np.linspace(-math.pi, math.pi, azimuth_steps, endpoint=False)
    el, az = np.meshgrid(elev, azim, indexing="ij")
    body = np.column_stack(
        [(np.cos(el) * np.cos(az)).ravel(), (np.cos(el) * np.sin(az)).ravel(), np.sin(el).ravel()]
    )
    world_dirs = body @ _yaw_matrix(yaw).T
    t = _raycast(tunnel, origin, world_dirs, max_range_m)
    keep = np.isfinite(t)
    rng_t = t[keep]
    if noise_m > 0:
        rng_t = rng_t + np.random.default_rng(seed).normal(0.0, noise_m, rng_t.shape)
    return np.asarray(body[keep] * rng_t[:, None], dtype=float)


@dataclass(frozen=True)
class DepthCamera:
    """Pinhole depth camera (defaults: a RealSense D455 depth stream, 86° × 57°, 6 m)."""

    width: int = 640
    height: int = 480
    hfov_deg: float = 86.0
    max_range_m: float = 6.0

    @property
    def fx(self) -> float:
        return (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def fy(self) -> float:
        return self.fx  # square pixels

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2


def depth_image(
    tunnel: Tunnel,
    position: ArrayLike,
    yaw: float = 0.0,
    camera: DepthCamera = DepthCamera(),
    *,
    noise_m: float = 0.0,
    dropout: float = 0.0,
    seed: int = 0,
) -> FloatArray:
    """The camera's z-depth image (H, W) in metres; 0 where nothing is within range.

    ``noise_m`` adds Gaussian depth noise and ``dropout`` zeroes that fraction of pixels at random
    (the speckle a morphological close is meant to remove).
    """
    origin = np.asarray(position, dtype=float)
    u = (np.arange(camera.width) - camera.cx) / camera.fx
    v = (np.arange(camera.height) - camera.cy) / camera.fy
    uu, vv = np.meshgrid(u, v)
    # camera (x right, y down, z forward) → body (x forward, y left, z up); z-depth = ray param
    body = np.column_stack([np.ones(uu.size), -uu.ravel(), -vv.ravel()])
    t = _raycast(tunnel, origin, body @ _yaw_matrix(yaw).T, math.inf)
    depth = np.where(t <= camera.max_range_m, t, 0.0).reshape(camera.height, camera.width)
    rng = np.random.default_rng(seed)
    if noise_m > 0:
        depth = np.where(depth > 0, depth + rng.normal(0.0, noise_m, depth.shape), 0.0)
    if dropout > 0:
        depth = np.where(rng.random(depth.shape) < dropout, 0.0, depth)
    return np.asarray(np.clip(depth, 0.0, None), dtype=float)
