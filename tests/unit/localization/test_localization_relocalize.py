"""One-scan global relocalization (seed 000 §IV-C1) on a generated mine: the issue's tests.

Success means what the issue asks: translation error < 0.3 m and yaw error < 3° against the pose
the scan was simulated at; every scan comes from the simulated OS1-32 with 3 cm range noise.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from btmission.localization.database import random_poses
from btmission.localization.relocalize import Relocalization, RelocConfig, pose_error
from btmission.localization.scan import add_dust, pose_matrix, simulate_scan, with_obstacle
from tests.reloc_helpers import OTHER_SEED, small_mine, small_relocalizer

N = 10


def assert_correct(result: Relocalization, truth: np.ndarray) -> None:
    assert result.localized, result.reason
    assert result.pose is not None
    dt, dyaw = pose_error(result.pose, truth)
    assert dt < 0.3 and dyaw < 3.0, (dt, dyaw, result.reason)
    assert result.confidence >= RelocConfig().min_confidence


def test_relocalizes_from_scans_at_random_poses() -> None:
    reloc = small_relocalizer()
    vm = small_mine().map
    for k, truth in enumerate(random_poses(vm, N, rng=11)):
        assert_correct(reloc.localize(simulate_scan(vm, truth, rng=k)), truth)


def test_a_scan_from_a_different_map_is_not_localised() -> None:
    reloc = small_relocalizer()
    other = small_mine(OTHER_SEED).map
    for k, pose in enumerate(random_poses(other, N, rng=12)):
        r = reloc.localize(simulate_scan(other, pose, rng=k))
        assert not r.localized, r.reason
        assert r.pose is None and r.reason.startswith("not localised")
        assert r.confidence < RelocConfig().min_confidence


def test_robust_to_five_percent_dust() -> None:
    reloc = small_relocalizer()
    vm = small_mine().map
    for k, truth in enumerate(random_poses(vm, N, rng=13)):
        scan = add_dust(simulate_scan(vm, truth, rng=k), 0.05, rng=k)
        assert_correct(reloc.localize(scan), truth)


def test_robust_to_a_partly_occluded_scan() -> None:
    """A 2 × 2 × 3 m object the map does not know stands 3 m from the sensor, blocking its
    longest view (the direction of its farthest return): ~30° of the scan ends at the object."""
    reloc = small_relocalizer()
    vm = small_mine().map
    for k, truth in enumerate(random_poses(vm, N, rng=14)):
        clear = simulate_scan(vm, truth, rng=k)
        far = clear[np.argmax(np.hypot(clear[:, 0], clear[:, 1]))]
        world = with_obstacle(vm, truth, distance_m=3.0, bearing=np.arctan2(far[1], far[0]))
        scan = simulate_scan(world, truth, rng=k)
        short = np.hypot(scan[:, 0], scan[:, 1]) < 5.0
        assert short.mean() > (np.hypot(clear[:, 0], clear[:, 1]) < 5.0).mean() + 0.03
        assert_correct(reloc.localize(scan), truth)


def test_the_result_reports_candidates_and_times() -> None:
    reloc = small_relocalizer()
    vm = small_mine().map
    truth = random_poses(vm, 1, rng=15)[0]
    r = reloc.localize(simulate_scan(vm, truth, rng=0))
    cfg = reloc.config
    assert 1 <= len(r.candidates) <= cfg.top_k
    assert sum(c.refined for c in r.candidates) == min(cfg.refine, len(r.candidates))
    scores = [c.score for c in r.candidates]
    assert scores[0] == max(scores)
    assert set(r.timings_ms) >= {"descriptors", "coarse_icp", "fine_icp", "total"}
    d = json.loads(json.dumps(r.to_dict()))
    assert d["localized"] and d["pose"]["x"] == pytest.approx(truth[0, 3], abs=0.3)
    assert r.position is not None and r.yaw is not None


def test_register_refines_a_close_guess_and_fails_from_far() -> None:
    reloc = small_relocalizer()
    vm = small_mine().map
    truth = random_poses(vm, 1, rng=16)[0]
    scan = simulate_scan(vm, truth, rng=1)
    near = truth.copy()
    near[:3, 3] += [0.6, -0.4, 0.2]
    c = reloc.register(scan, near)
    assert pose_error(c.pose, truth)[0] < 0.1 and c.fitness > 0.7
    far = reloc.register(scan, np.eye(4))  # the map's origin: in rock, nowhere near
    assert pose_error(far.pose, truth)[0] > 5.0
    assert far.fitness < 0.5 or far.conflict > RelocConfig().max_conflict


def test_scans_too_small_or_malformed() -> None:
    reloc = small_relocalizer()
    r = reloc.localize(np.zeros((3, 3)))
    assert not r.localized and "3 point(s)" in r.reason
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        reloc.localize(np.zeros((10, 2)))


def test_a_scan_from_inside_rock_is_not_localised() -> None:
    """Points all at one spot (nothing like a scan of tunnels)."""
    reloc = small_relocalizer()
    blob = np.random.default_rng(0).normal(0.0, 0.05, size=(500, 3)) + np.array([1.0, 0.0, 0.0])
    assert not reloc.localize(blob).localized


def test_confidence_drops_when_two_places_fit_alike() -> None:
    """The same scan, localised in a map where a second copy of its surroundings exists, has a
    rival pose: the distinctiveness factor must fall (here: the ambiguity margin is set so wide
    that any rival counts)."""
    reloc = small_relocalizer()
    vm = small_mine().map
    truth = random_poses(vm, 1, rng=17)[0]
    scan = simulate_scan(vm, truth, rng=2)
    sure = reloc.localize(scan)
    from btmission.localization.relocalize import Relocalizer

    wide = Relocalizer(reloc.db, RelocConfig(ambiguity_margin=10.0, min_confidence=0.0))
    unsure = wide.localize(scan)
    assert unsure.confidence < sure.confidence
    assert unsure.localized  # min_confidence 0: the pose is still given


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"top_k": 0}, "at least 1"),
        ({"registration": "NDT"}, "registration"),
        ({"fine_voxel_m": 0.0}, "voxel"),
        ({"min_fitness": 1.0}, "min_fitness"),
        ({"min_confidence": 2.0}, "min_confidence"),
    ],
)
def test_bad_settings_are_refused(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        RelocConfig(**kwargs)  # type: ignore[arg-type]


def test_pose_error_measures_translation_and_wrapped_yaw() -> None:
    a = pose_matrix(1.0, 2.0, 3.0, np.radians(179.0))
    b = pose_matrix(1.0, 2.3, 3.4, np.radians(-179.0))
    dt, dyaw = pose_error(a, b)
    assert dt == pytest.approx(0.5) and dyaw == pytest.approx(2.0)


@pytest.mark.slow
def test_relocalizes_in_a_200_m_mine() -> None:
    """The issue's scenario at full scale, 20 poses (~40 s). The rate itself (97 % of 200 poses)
    is the benchmark's to measure; 20 scans can only bound it: at least 18 right, none wrong."""
    from btmission.localization.database import build_database
    from btmission.localization.relocalize import Relocalizer
    from btmission.world.minegen import generate_mine

    vm = generate_mine(7, (200.0, 120.0, 12.0), 0.5).map
    reloc = Relocalizer(build_database(vm))
    right = wrong = 0
    for k, truth in enumerate(random_poses(vm, 20, rng=31)):
        r = reloc.localize(simulate_scan(vm, truth, rng=k))
        if r.pose is None:
            continue
        dt, dyaw = pose_error(r.pose, truth)
        right += dt < 0.3 and dyaw < 3.0
        wrong += not (dt < 0.3 and dyaw < 3.0)
    assert right >= 18 and wrong == 0, (right, wrong)
