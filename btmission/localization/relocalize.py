"""One-scan global relocalization: descriptors → candidate poses → coarse-then-fine ICP → best fit.

Seed 000 §IV-C1: the current scan's descriptor ``q_t`` is matched against the map's ``Q`` (eq. 2,
``q_t* = argmin_{q_i ∈ Q} f(q_i, q_t)``), the matched place's orientation vector ``w_i*`` gives the
yaw, "which are together used to construct the initial guess transform T_0", and "the two-step ICP
algorithm" refines it. A single nearest neighbour is brittle in self-similar tunnels, so
:meth:`Relocalizer.localize` keeps several:

1. **retrieve** — the ``retrieve`` nearest ring keys in a KD-tree (eq. 2 with ``f`` = Euclidean
   distance over the yaw-invariant location part);
2. **rank** — each retrieved place's polar image is compared with the scan's at every circular
   shift (:func:`~btmission.localization.descriptor.align`): the best shift is the similarity and
   the yaw; places are ranked by similarity and thinned so that kept ones are ``separation_m``
   apart;
3. **initial guesses** — for the ``top_k`` best, ``T_0`` = the place's x, y, its floor plus the
   sensor's height above the floor seen in the scan, and the yaw;
4. **coarse ICP** from every ``T_0`` on clouds thinned to ``coarse_voxel_m`` with a wide
   correspondence radius, then **fine ICP** from the ``refine`` best coarse results on
   ``fine_voxel_m`` clouds with a tight radius — both GICP from `small_gicp`
   (``registration = "GICP"``; ``"ICP"`` and ``"PLANE_ICP"`` are the alternatives);
5. **score** — each pose gets a *fitness*, the fraction of scan points within ``inlier_m`` of a map
   point, and a *conflict*, the fraction of scan points the map says cannot be seen: the beam to
   them crosses rock more than ``conflict_margin_m`` before reaching them (a scan from elsewhere
   "sees through" the map's walls; dust and objects missing from the map only give *short*
   returns, which cost fitness but never conflict). The best pose maximises fitness − conflict.

The **confidence** (0-1) is the product of how well the best pose fits, ``(fitness −
min_fitness) / (1 − min_fitness) × (1 − conflict / max_conflict)``, and how clearly it beats the
best *different* pose (more than ``distinct_m`` or ``distinct_deg`` away): ``min(1, (score_best −
score_other) / ambiguity_margin)``. The result is **not localised** (``localized = False``, no
pose) when the best pose explains less than ``min_fitness`` of the scan, sees through rock with
more than ``max_conflict`` of it, or has a confidence below ``min_confidence`` — the last is how a
scan from another map, or from a place the map cannot tell from another, is turned down.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from btmission.localization.database import PlaceDatabase
from btmission.localization.descriptor import align, describe
from btmission.localization.scan import (
    cast,
    drop_see_through,
    pose_matrix,
    transform_points,
    yaw_of,
)
from btmission.types import FloatArray

REGISTRATIONS = ("GICP", "ICP", "PLANE_ICP")


@dataclass(frozen=True)
class RelocConfig:
    """Tuning of :class:`Relocalizer` (defaults measured on generated 200 m mines)."""

    retrieve: int = 200
    """Nearest ring keys fetched from the KD-tree (then ranked by their polar images)."""
    top_k: int = 40
    """Candidates registered by coarse ICP."""
    separation_m: float = 3.0
    """Candidates registered are at least this far apart."""
    refine: int = 2
    """Best coarse results refined by fine ICP."""
    registration: str = "GICP"
    coarse_voxel_m: float = 1.5
    coarse_max_corr_m: float = 2.5
    coarse_iterations: int = 10
    fine_voxel_m: float = 0.5
    fine_max_corr_m: float = 0.8
    fine_iterations: int = 30
    see_through_m: float = 1.0
    """Scan points more than this in front of another return in their direction cell are dropped
    as dust (:func:`~btmission.localization.scan.drop_see_through`; 0: keep every point)."""
    inlier_m: float = 0.3
    quick_points: int = 400
    """Scan points scored after coarse ICP (all points are scored after fine ICP)."""
    conflict_margin_m: float = 0.5
    conflict_margin_rel: float = 0.1
    """A scan point conflicts when its beam meets rock more than ``conflict_margin_m +
    conflict_margin_rel × range`` before reaching it (the relative part forgives beams that graze
    the floor far away, where a centimetre of pose error moves the entry point by metres)."""
    min_fitness: float = 0.5
    max_conflict: float = 0.05
    min_confidence: float = 0.2
    """Below this confidence the result is "not localised" (ambiguous or poorly fitting)."""
    distinct_m: float = 1.0
    distinct_deg: float = 10.0
    ambiguity_margin: float = 0.1

    def __post_init__(self) -> None:
        problems = []
        if min(self.retrieve, self.top_k, self.refine) < 1:
            problems.append("retrieve, top_k and refine must be at least 1")
        if self.registration not in REGISTRATIONS:
            problems.append(
                f"registration must be one of {', '.join(REGISTRATIONS)}, got '{self.registration}'"
            )
        if min(self.coarse_voxel_m, self.fine_voxel_m, self.inlier_m, self.ambiguity_margin) <= 0:
            problems.append("voxel sizes, inlier_m and ambiguity_margin must be > 0")
        if not (0 <= self.min_fitness < 1 and 0 < self.max_conflict <= 1):
            problems.append("min_fitness must be in [0, 1) and max_conflict in (0, 1]")
        if not 0 <= self.min_confidence <= 1:
            problems.append("min_confidence must be in [0, 1]")
        if problems:
            raise ValueError("relocalization settings: " + "; ".join(problems))


@dataclass(frozen=True, eq=False)
class Candidate:
    """One initial guess and what ICP made of it."""

    place: int
    """Index of the database place (-1 for a guess given by the caller)."""
    similarity: float
    """Descriptor similarity of the place (0-1)."""
    initial: FloatArray
    """``T_0`` (4×4, sensor in world)."""
    pose: FloatArray
    """After ICP (4×4)."""
    fitness: float
    conflict: float
    refined: bool
    """Whether fine ICP ran on it (else the pose is the coarse one)."""
    rmse_m: float = float("nan")
    """RMS distance of its inlier points to the map (m)."""

    @property
    def score(self) -> float:
        return self.fitness - self.conflict


@dataclass(frozen=True, eq=False)
class Relocalization:
    """The answer to one scan: a pose ``T_world_sensor`` (or None) and how far to trust it."""

    localized: bool
    pose: FloatArray | None
    confidence: float
    fitness: float
    conflict: float
    rmse_m: float
    """RMS distance of the inlier points to the map (m)."""
    reason: str
    """One line saying why the scan is (not) localised."""
    candidates: tuple[Candidate, ...] = ()
    timings_ms: dict[str, float] = field(default_factory=dict)

    @property
    def position(self) -> FloatArray | None:
        return None if self.pose is None else np.asarray(self.pose[:3, 3], dtype=np.float64)

    @property
    def yaw(self) -> float | None:
        return None if self.pose is None else yaw_of(self.pose)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (pose as x, y, z, yaw in degrees and the 4×4 matrix)."""
        out: dict[str, Any] = {
            "localized": self.localized,
            "confidence": round(self.confidence, 4),
            "fitness": round(self.fitness, 4),
            "conflict": round(self.conflict, 4),
            "rmse_m": round(self.rmse_m, 4),
            "reason": self.reason,
            "timings_ms": {k: round(v, 2) for k, v in self.timings_ms.items()},
        }
        if self.pose is not None:
            p = self.pose
            out["pose"] = {
                "x": round(float(p[0, 3]), 4),
                "y": round(float(p[1, 3]), 4),
                "z": round(float(p[2, 3]), 4),
                "yaw_deg": round(float(np.degrees(yaw_of(p))), 3),
                "matrix": [[round(float(v), 6) for v in row] for row in p],
            }
        out["candidates"] = [
            {
                "place": c.place,
                "similarity": round(c.similarity, 4),
                "x": round(float(c.pose[0, 3]), 3),
                "y": round(float(c.pose[1, 3]), 3),
                "yaw_deg": round(float(np.degrees(yaw_of(c.pose))), 2),
                "fitness": round(c.fitness, 4),
                "conflict": round(c.conflict, 4),
                "refined": c.refined,
            }
            for c in self.candidates
        ]
        return out


class _Source:
    """A scan prepared for registration: coarse and fine small_gicp clouds."""

    def __init__(self, points: FloatArray, cfg: RelocConfig) -> None:
        import small_gicp

        self.coarse, _ = small_gicp.preprocess_points(points, cfg.coarse_voxel_m)
        self.fine, _ = small_gicp.preprocess_points(points, cfg.fine_voxel_m)
        self.fine_xyz = np.asarray(self.fine.points())[:, :3]


class Relocalizer:
    """Localises single scans in the map of a :class:`PlaceDatabase` (see the module docstring).

    Building one prepares the map for registration (thinned clouds, normals/covariances and
    KD-trees: ~0.3 s for a 200 m mine); :meth:`localize` is then a pure function of the scan.
    """

    def __init__(self, db: PlaceDatabase, config: RelocConfig = RelocConfig()) -> None:
        import small_gicp
        from scipy.spatial import cKDTree

        self.db = db
        self.config = config
        self._keys = cKDTree(np.asarray(db.ring_keys, dtype=np.float64))
        cloud = np.asarray(db.cloud, dtype=np.float64)
        self._coarse, self._coarse_tree = small_gicp.preprocess_points(cloud, config.coarse_voxel_m)
        self._fine, self._fine_tree = small_gicp.preprocess_points(cloud, config.fine_voxel_m)
        self._dense_tree = small_gicp.KdTree(cloud)
        self._default_height = float(np.median(db.positions[:, 2] - db.floor_z))
        # first calls load the compiled ray caster and scipy.ndimage: pay them here, not per scan
        cast(db.voxel_map, db.positions[0], [[1.0, 0.0, 0.0]], 1.0)
        describe(np.array([[5.0, 0.0, 0.0], [0.0, 5.0, -1.0]]), db.params)

    # ---------------------------------------------------------------- building blocks
    def clean(self, points: FloatArray) -> FloatArray:
        """The scan without its see-through returns (dust), as the database's scans were."""
        if self.config.see_through_m <= 0:
            return points
        return drop_see_through(points, margin_m=self.config.see_through_m)

    def evaluate(
        self, source: _Source, pose: FloatArray, *, quick: bool = False
    ) -> tuple[float, float, float]:
        """(fitness, conflict, inlier RMSE in m) of the prepared scan at ``pose`` (``quick``: on
        at most ``quick_points`` of its points, evenly picked)."""
        cfg = self.config
        xyz = source.fine_xyz
        if quick and len(xyz) > cfg.quick_points:
            xyz = xyz[:: int(np.ceil(len(xyz) / cfg.quick_points))]
        world = transform_points(pose, xyz)
        _, sq = self._dense_tree.batch_nearest_neighbor_search(world)
        d = np.sqrt(np.asarray(sq, dtype=np.float64))
        inl = d < cfg.inlier_m
        fitness = float(inl.mean()) if len(d) else 0.0
        rmse = float(np.sqrt(np.mean(d[inl] ** 2))) if np.any(inl) else float("nan")
        vm = self.db.voxel_map
        origin = pose[:3, 3]
        if not bool(vm.contains(origin)):
            return fitness, 1.0, rmse
        vec = world - origin
        rng = np.linalg.norm(vec, axis=1)
        reach = rng * (1.0 - cfg.conflict_margin_rel) - cfg.conflict_margin_m
        ok = reach > 0
        if not np.any(ok):
            return fitness, 0.0, rmse
        hit = cast(vm, origin, vec[ok] / rng[ok, None], reach[ok])
        conflict = float(np.isfinite(hit).sum() / len(d))
        return fitness, conflict, rmse

    def _icp(self, source: _Source, init: FloatArray, fine: bool) -> FloatArray:
        import small_gicp

        cfg = self.config
        if fine:
            tgt, tree, src = self._fine, self._fine_tree, source.fine
            corr, iters = cfg.fine_max_corr_m, cfg.fine_iterations
        else:
            tgt, tree, src = self._coarse, self._coarse_tree, source.coarse
            corr, iters = cfg.coarse_max_corr_m, cfg.coarse_iterations
        res = small_gicp.align(
            tgt,
            src,
            tree,
            init_T_target_source=init,
            registration_type=cfg.registration,
            max_correspondence_distance=corr,
            max_iterations=iters,
        )
        return np.asarray(res.T_target_source, dtype=np.float64)

    def register(self, points: npt.ArrayLike, initial: npt.ArrayLike) -> Candidate:
        """Coarse-then-fine ICP of a scan from one initial guess (no descriptors): the plain-ICP
        peer of the benchmark, and a way to re-check a pose known from elsewhere."""
        cfg = self.config
        src = _Source(self.clean(_as_points(points)), cfg)
        t0 = np.asarray(initial, dtype=np.float64)
        t = self._icp(src, self._icp(src, t0, fine=False), fine=True)
        f, c, rmse = self.evaluate(src, t)
        return Candidate(-1, float("nan"), t0, t, f, c, True, rmse)

    def initial_guesses(self, points: npt.ArrayLike) -> list[tuple[int, float, FloatArray]]:
        """Steps 1-3: ``(place, similarity, T_0)`` of the ``top_k`` best hypotheses, best first.

        Every retrieved place gives two yaw hypotheses (the best column shift and the best one a
        quarter turn or more away from it); hypotheses are kept in order of similarity unless one
        already kept is within ``separation_m`` and a quarter turn of it."""
        cfg = self.config
        db = self.db
        desc = describe(_as_points(points), db.params)  # callers pass cleaned scans
        k = min(cfg.retrieve, len(db))
        _, idx = self._keys.query(np.asarray(desc.ring_key, dtype=np.float64), k=k)
        idx = np.atleast_1d(idx)
        sim, yaw = align(desc.polar, db.polar[idx], db.params, peaks=2)
        h = desc.height_above_floor
        if not np.isfinite(h) or h <= 0:
            h = self._default_height
        kept: list[tuple[int, float, FloatArray]] = []
        kept_yaw: list[float] = []
        flat = np.argsort(-sim, axis=None, kind="stable")
        for j, peak in zip(*np.unravel_index(flat, sim.shape)):
            i = int(idx[j])
            p = db.positions[i]
            y = float(yaw[j, peak])
            if any(
                np.linalg.norm(p - db.positions[q]) < cfg.separation_m
                and abs((y - ky + np.pi) % (2 * np.pi) - np.pi) < np.pi / 2
                for (q, _, _), ky in zip(kept, kept_yaw)
            ):
                continue
            kept.append((i, float(sim[j, peak]), pose_matrix(p[0], p[1], db.floor_z[i] + h, y)))
            kept_yaw.append(y)
            if len(kept) == cfg.top_k:
                break
        return kept

    # ---------------------------------------------------------------- the query
    def localize(self, points: npt.ArrayLike) -> Relocalization:
        """Localise one gravity-aligned scan ``(N, 3)`` (sensor frame) with no initial guess."""
        cfg = self.config
        t_start = time.perf_counter()
        pts = _as_points(points)
        timings: dict[str, float] = {}
        if len(pts) < 10:
            return Relocalization(
                False,
                None,
                0.0,
                0.0,
                0.0,
                float("nan"),
                f"not localised: the scan has {len(pts)} point(s)",
            )
        pts = self.clean(pts)
        t_clean = time.perf_counter()
        timings["clean"] = (t_clean - t_start) * 1000
        guesses = self.initial_guesses(pts)
        t_desc = time.perf_counter()
        timings["descriptors"] = (t_desc - t_clean) * 1000
        src = _Source(pts, cfg)
        coarse: list[Candidate] = []
        for place, sim, initial in guesses:
            pose = self._icp(src, initial, fine=False)
            fit, conflict, rmse = self.evaluate(src, pose, quick=True)
            coarse.append(Candidate(place, sim, initial, pose, fit, conflict, False, rmse))
        t_coarse = time.perf_counter()
        timings["coarse_icp"] = (t_coarse - t_desc) * 1000
        coarse.sort(key=lambda c: -c.score)
        ranked: list[Candidate] = []
        for c in coarse[: cfg.refine]:
            pose = self._icp(src, c.pose, fine=True)
            fit, conflict, rmse = self.evaluate(src, pose)
            ranked.append(
                Candidate(c.place, c.similarity, c.initial, pose, fit, conflict, True, rmse)
            )
        ranked += coarse[cfg.refine :]
        ranked.sort(key=lambda c: -c.score)
        timings["fine_icp"] = (time.perf_counter() - t_coarse) * 1000
        timings["total"] = (time.perf_counter() - t_start) * 1000
        return self._verdict(ranked, timings)

    def _verdict(self, ranked: list[Candidate], timings: dict[str, float]) -> Relocalization:
        cfg = self.config
        best = ranked[0]
        others = [c for c in ranked[1:] if _distinct(best.pose, c.pose, cfg)]
        other_score = max((c.score for c in others), default=0.0)
        quality = max(0.0, (best.fitness - cfg.min_fitness) / (1.0 - cfg.min_fitness))
        quality *= max(0.0, 1.0 - best.conflict / cfg.max_conflict)
        margin = min(1.0, max(0.0, (best.score - other_score) / cfg.ambiguity_margin))
        confidence = float(min(1.0, quality) * margin)
        if best.fitness < cfg.min_fitness:
            reason = (
                f"not localised: the best pose explains {best.fitness:.0%} of the scan "
                f"(needs {cfg.min_fitness:.0%})"
            )
        elif best.conflict > cfg.max_conflict:
            reason = (
                f"not localised: at the best pose {best.conflict:.0%} of the scan sees through "
                f"the map's rock (at most {cfg.max_conflict:.0%} allowed)"
            )
        elif confidence < cfg.min_confidence:
            rival = next((c for c in others if c.score == other_score), None)
            where = (
                f"; a pose {np.linalg.norm(rival.pose[:3, 3] - best.pose[:3, 3]):.1f} m away "
                f"scores {other_score:.2f} vs {best.score:.2f}"
                if rival is not None
                else ""
            )
            reason = (
                f"not localised: confidence {confidence:.2f} is below {cfg.min_confidence:g} "
                f"(fitness {best.fitness:.0%}, {best.conflict:.1%} through rock{where})"
            )
        else:
            reason = (
                f"localised: {best.fitness:.0%} of the scan within {cfg.inlier_m:g} m of the map, "
                f"{best.conflict:.1%} through rock, confidence {confidence:.2f}"
            )
        ok = reason.startswith("localised")
        return Relocalization(
            ok,
            best.pose if ok else None,
            confidence,
            best.fitness,
            best.conflict,
            best.rmse_m,
            reason,
            tuple(ranked),
            timings,
        )


def _distinct(a: FloatArray, b: FloatArray, cfg: RelocConfig) -> bool:
    dp = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    dyaw = abs((yaw_of(a) - yaw_of(b) + np.pi) % (2 * np.pi) - np.pi)
    return dp > cfg.distinct_m or np.degrees(dyaw) > cfg.distinct_deg


def _as_points(points: npt.ArrayLike) -> FloatArray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"a scan is an (N, 3) array of points, got shape {p.shape}")
    out: FloatArray = np.ascontiguousarray(p[np.all(np.isfinite(p), axis=1)])
    return out


def pose_error(estimate: npt.ArrayLike, truth: npt.ArrayLike) -> tuple[float, float]:
    """(translation error in m, absolute yaw error in degrees) between two 4×4 poses."""
    a = np.asarray(estimate, dtype=np.float64)
    b = np.asarray(truth, dtype=np.float64)
    dt = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    dyaw = (yaw_of(a) - yaw_of(b) + np.pi) % (2 * np.pi) - np.pi
    return dt, float(abs(np.degrees(dyaw)))
