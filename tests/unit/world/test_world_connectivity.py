"""26-connected components by runs (btmission.world.connectivity) against scipy.ndimage.label."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage

from btmission.world.connectivity import components
from btmission.world.minegen import generate_mine
from btmission.world.voxel import OCCUPIED

FULL = np.ones((3, 3, 3), bool)


def assert_same_partition(mask: np.ndarray) -> None:
    """Same components as scipy's 26-connected labelling: same count, same voxels together."""
    expected, n = ndimage.label(mask, structure=FULL)
    comps = components(mask)
    ours = np.array([comps.label(idx) for idx in np.ndindex(*mask.shape)]).reshape(mask.shape)
    np.testing.assert_array_equal(ours == -1, expected == 0)
    assert comps.count == n
    pairs = set(zip(expected[mask].tolist(), ours[mask].tolist(), strict=True))
    assert len(pairs) == n  # a bijection between scipy's labels and ours


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    arrays(
        bool,
        st.tuples(st.integers(1, 7), st.integers(1, 7), st.integers(1, 7)),
        elements=st.booleans(),
    )
)
def test_components_are_scipys_26_connected_labels(mask: np.ndarray) -> None:
    assert_same_partition(mask)


@pytest.mark.parametrize("density", [0.3, 0.55, 0.75])
def test_components_of_larger_random_grids(density: float) -> None:
    rng = np.random.default_rng(int(density * 100))
    assert_same_partition(rng.random((23, 17, 11)) < density)


@pytest.mark.parametrize(
    "a, b, touching",
    [
        ((2, 2, 2), (3, 3, 3), True),  # corner to corner: a 26-neighbour
        ((2, 2, 2), (3, 1, 1), True),
        ((2, 2, 2), (2, 4, 2), False),  # one voxel of rock between
        ((2, 2, 2), (4, 2, 3), False),
        ((0, 4, 2), (1, 0, 2), False),  # far apart rows must not wrap around into each other
        ((1, 4, 0), (2, 0, 0), False),
        ((0, 0, 4), (0, 1, 0), False),
    ],
)
def test_single_voxels_touch_only_as_26_neighbours(
    a: tuple[int, int, int], b: tuple[int, int, int], touching: bool
) -> None:
    mask = np.zeros((5, 5, 5), bool)
    mask[a] = mask[b] = True
    comps = components(mask)
    assert (comps.label(a) == comps.label(b)) is touching
    assert comps.count == (1 if touching else 2)
    assert comps.label((4, 4, 4)) == -1  # a False voxel is in no component


def test_a_generated_mine_is_labelled_like_scipy_does() -> None:
    vm = generate_mine(seed=3, size=(60, 40, 8), resolution=1.0).map
    passable = vm.state != OCCUPIED
    expected, n = ndimage.label(passable, structure=FULL)
    comps = components(passable)
    assert comps.count == n
    idx = np.argwhere(passable)[:: max(1, int(passable.sum()) // 400)]
    ours = [comps.label(i) for i in idx]
    theirs = expected[tuple(idx.T)].tolist()
    assert len(set(zip(ours, theirs, strict=True))) == len(set(theirs))


def test_components_needs_a_3d_grid() -> None:
    with pytest.raises(ValueError, match="3D"):
        components(np.ones((4, 4), bool))
    assert components(np.zeros((2, 3, 4), bool)).count == 0
