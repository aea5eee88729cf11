"""Place descriptors (btmission.localization.descriptor): yaw from the orientation part,
invariance of the location part, and the FFT shift scores against a direct computation."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btmission.localization.descriptor import (
    DescriptorParams,
    align,
    describe,
    floor_height,
    ring_key,
    shift_scores,
)
from btmission.localization.scan import from_record, pose_matrix, record, simulate_scan
from btmission.world.minegen import generate_mine

P = DescriptorParams()


@pytest.fixture(scope="module")
def mine():  # type: ignore[no-untyped-def]
    return generate_mine(1, (60.0, 40.0, 8.0), 0.5)


def rotate_z(points: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    out: np.ndarray = points @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    return out


def direct_scores(q: np.ndarray, cands: np.ndarray) -> np.ndarray:
    """Σ_j cos(q_j, c_{j+k}) / √(n_q n_c) by loops, the definition shift_scores implements."""

    def unit(w: np.ndarray) -> tuple[np.ndarray, int]:
        n = np.linalg.norm(w, axis=0)
        return np.divide(w, n, out=np.zeros_like(w), where=n > 0), int((n > 0).sum())

    uq, nq = unit(q)
    out = np.zeros((len(cands), q.shape[1]))
    for m, c in enumerate(cands):
        uc, nc = unit(c)
        for k in range(q.shape[1]):
            out[m, k] = sum(uq[:, j] @ uc[:, (j + k) % q.shape[1]] for j in range(q.shape[1]))
        out[m] /= np.sqrt(max(nq * nc, 1))
    return out


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 1000), sparse=st.floats(0.0, 0.9))
def test_fft_shift_scores_equal_the_direct_sum(seed: int, sparse: float) -> None:
    rng = np.random.default_rng(seed)
    q = rng.random((5, 12)) * (rng.random((5, 12)) > sparse)
    cands = rng.random((3, 5, 12)) * (rng.random((3, 5, 12)) > sparse)
    np.testing.assert_allclose(
        shift_scores(q, cands), np.clip(direct_scores(q, cands), 0, 1), atol=1e-9
    )


@settings(max_examples=20, deadline=None)
@given(k=st.integers(0, 59))
def test_rotating_a_scan_by_whole_sectors_rolls_its_image(k: int) -> None:
    """Turning the sensor by k sectors shifts the columns by k, keeps the ring key, and the
    image of the turned scan matches the original at shift k with similarity 1."""
    rng = np.random.default_rng(k)
    pts = rng.uniform(-40, 40, size=(4000, 3))
    pts[:, 2] = rng.uniform(-1.5, 1.0, size=4000)
    pts[:50] = [[1.0, 0.0, -2.0]]  # a floor 2 m down, seen by the lowest points
    base = describe(pts, P)
    # sensor turned by +kΔ: the world appears turned by -kΔ in its frame; nudge off the bin edges
    turned = describe(rotate_z(pts, -k * P.sector_rad), P)
    np.testing.assert_allclose(turned.ring_key, base.ring_key, atol=1e-6)
    sc = shift_scores(turned.polar, base.polar[None])[0]
    assert sc[k % P.sectors] == pytest.approx(1.0, abs=1e-6)


def test_align_finds_the_heading_between_two_scans_of_one_place(mine) -> None:  # type: ignore[no-untyped-def]
    vm = mine.map
    x, y, z = mine.tunnels[0].point(0.5, 2.0)
    ref = describe(simulate_scan(vm, pose_matrix(x, y, z, 0.0)), P)
    # from the same spot within half a sector; from half a metre away within one sector (ICP
    # refines it)
    for dx, dy, tol in ((0.0, 0.0, 3.0), (0.4, -0.3, 6.0)):
        for yaw in (0.3, 1.7, -2.9, 3.1):
            q = describe(simulate_scan(vm, pose_matrix(x + dx, y + dy, z, yaw), rng=5), P)
            sim, est = align(q.polar, ref.polar[None], P)
            err = abs((est[0] - yaw + np.pi) % (2 * np.pi) - np.pi)
            assert np.degrees(err) < tol, (yaw, est)
            assert sim[0] > 0.8


def test_two_peaks_give_a_second_heading_a_quarter_turn_away(mine) -> None:  # type: ignore[no-untyped-def]
    vm = mine.map
    x, y, z = mine.tunnels[0].point(0.5, 2.0)
    d = describe(simulate_scan(vm, pose_matrix(x, y, z, 0.0)), P)
    sim, yaw = align(d.polar, d.polar[None], P, peaks=2)
    assert sim.shape == yaw.shape == (1, 2)
    assert abs(yaw[0, 0]) < 1e-9 and sim[0, 0] == pytest.approx(1.0)
    assert abs(yaw[0, 1]) >= np.pi / 2 - P.sector_rad and sim[0, 1] <= sim[0, 0]
    with pytest.raises(ValueError, match="peaks"):
        align(d.polar, d.polar[None], P, peaks=3)


@pytest.mark.parametrize("height", [1.0, 2.0, 3.0])
def test_floor_height_is_seen_in_the_scan(mine, height: float) -> None:  # type: ignore[no-untyped-def]
    x, y, _ = mine.tunnels[0].point(0.5)
    pts = simulate_scan(mine.map, pose_matrix(x, y, height, 0.7), rng=1)
    assert floor_height(pts, P) == pytest.approx(height, abs=0.1)
    assert np.isnan(floor_height(np.zeros((0, 3)), P))


def test_heights_change_the_image_little(mine) -> None:  # type: ignore[no-untyped-def]
    """The wall image is nearly the same from 1 m and 3 m above the same spot (its purpose)."""
    x, y, _ = mine.tunnels[0].point(0.5)
    lo = describe(simulate_scan(mine.map, pose_matrix(x, y, 1.0)), P)
    hi = describe(simulate_scan(mine.map, pose_matrix(x, y, 3.0)), P)
    far = describe(simulate_scan(mine.map, pose_matrix(*mine.tunnels[-1].point(0.5, 2.0))), P)
    same = align(lo.polar, hi.polar[None], P)[0][0]
    other = align(lo.polar, far.polar[None], P)[0][0]
    assert same > 0.8 and same > other


def test_ring_key_ignores_unseen_sectors() -> None:
    img = np.zeros((4, 8), dtype=np.float32)
    img[1, :4] = 1.0
    img[3, :4] = 0.5
    np.testing.assert_allclose(ring_key(img), [0.0, 1.0, 0.0, 0.5])
    stack = np.stack([img, np.roll(img, 3, axis=1)])
    np.testing.assert_allclose(ring_key(stack)[0], ring_key(stack)[1])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"rings": 0}, "ring"),
        ({"min_radius_m": 50.0}, "radii"),
        ({"band_m": (3.0, 1.0)}, "band_m"),
        ({"floor_percentile": 120.0}, "floor_percentile"),
    ],
)
def test_bad_descriptor_settings_are_refused(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        DescriptorParams(**kwargs)  # type: ignore[arg-type]


def test_params_round_trip_through_a_record() -> None:
    p = DescriptorParams(rings=10, band_m=(0.5, 2.5))
    assert from_record(DescriptorParams, json.loads(json.dumps(record(p)))) == p
