"""DPHR (seed 002 §3.2.4) on synthetic depth images of straight and bending tunnels."""

from __future__ import annotations

import math

import numpy as np
import pytest

from btmission.control.dphr import DphrConfig, choose_branch, deepest_point_heading
from btmission.control.scenes import DepthCamera, bending_tunnel, depth_image, straight_corridor

EYE = [0.0, 0.0, 1.5]


@pytest.mark.parametrize("bend, sign", [("left", 1.0), ("right", -1.0)])
@pytest.mark.parametrize("straight", [1.0, 3.0])
def test_turns_towards_the_open_side_of_a_bending_tunnel(
    bend: str, sign: float, straight: float
) -> None:
    img = depth_image(
        bending_tunnel(bend, straight_m=straight), EYE, noise_m=0.02, dropout=0.05, seed=3
    )
    res = deepest_point_heading(img)
    assert sign * res.yaw_rate > 0.02
    assert sign * res.offset < 0  # the deepest cluster sits on the bend's side of the image
    assert res.deepest_depth_m == pytest.approx(6.0, abs=0.2)  # the far opening, beyond range
    assert res.centers.size == 10


def test_earlier_bend_gives_a_stronger_turn() -> None:
    near = deepest_point_heading(depth_image(bending_tunnel("left", straight_m=0.5), EYE))
    far = deepest_point_heading(depth_image(bending_tunnel("left", straight_m=3.0), EYE))
    assert near.yaw_rate > far.yaw_rate > 0


def test_straight_tunnel_gives_no_turn_and_a_yawed_mav_turns_back() -> None:
    tunnel = straight_corridor(3.0, 3.0)
    assert abs(deepest_point_heading(depth_image(tunnel, EYE)).yaw_rate) < 0.01
    yawed_left = deepest_point_heading(depth_image(tunnel, EYE, yaw=0.3))
    assert yawed_left.yaw_rate < -0.05  # turn right, back along the tunnel
    yawed_right = deepest_point_heading(depth_image(tunnel, EYE, yaw=-0.3))
    assert yawed_right.yaw_rate == pytest.approx(-yawed_left.yaw_rate, abs=0.02)


def test_heading_loop_aligns_with_the_tunnel() -> None:
    """Integrate ψ̇ = DPHR(ψ) at 10 Hz from a 0.4 rad misalignment: the heading converges."""
    tunnel = straight_corridor(3.0, 3.0)
    cam = DepthCamera(width=160, height=120)
    psi = 0.4
    for _ in range(60):
        psi += (
            0.1
            * deepest_point_heading(
                depth_image(tunnel, EYE, psi, cam), DphrConfig(stride=1)
            ).yaw_rate
        )
    assert abs(psi) < 0.1


def test_morphological_close_removes_dropout_speckle() -> None:
    tunnel = bending_tunnel("right")
    clean = deepest_point_heading(depth_image(tunnel, EYE))
    noisy = deepest_point_heading(depth_image(tunnel, EYE, dropout=0.1, seed=5))
    assert noisy.offset == pytest.approx(clean.offset, abs=0.05)
    # without the close, dropout pixels (no return ⇒ "far") pull the centroid to the centre
    unclosed = deepest_point_heading(
        depth_image(tunnel, EYE, dropout=0.1, seed=5), DphrConfig(close_size=1)
    )
    assert abs(unclosed.offset - clean.offset) > abs(noisy.offset - clean.offset)


def test_limits_and_gain() -> None:
    img = np.full((48, 64), 2.0)
    img[:, :6] = 5.0  # deep on the far left edge
    res = deepest_point_heading(img, DphrConfig(stride=1, close_size=1, yaw_rate_max=0.3, gain=2.0))
    assert res.yaw_rate == pytest.approx(0.3)  # −l·s̄ = 2 · 0.92 clipped to the limit
    assert res.offset == pytest.approx((2.5 - 31.5) / 31.5)
    flat = deepest_point_heading(np.full((48, 64), 3.0))
    assert flat.yaw_rate == 0.0 and flat.offset == 0.0


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="2-D image"):
        deepest_point_heading(np.zeros(10))
    with pytest.raises(ValueError, match="principal_x"):
        deepest_point_heading(np.ones((10, 10)), principal_x=20)
    with pytest.raises(ValueError, match="clusters"):
        DphrConfig(clusters=1)
    with pytest.raises(ValueError, match="positive"):
        DphrConfig(yaw_rate_max=-math.pi)
    with pytest.raises(ValueError, match="bend"):
        bending_tunnel("up")


def _two_branches(left_cols: slice, right_cols: slice, right_depth: float = 6.0) -> np.ndarray:
    """A junction seen head-on: rock at 2 m, a branch opening on each side."""
    img = np.full((48, 64), 2.0)
    img[10:38, left_cols] = 6.0
    img[10:38, right_cols] = right_depth
    return img


def test_junction_branch_choice_is_explicit_and_deterministic() -> None:
    cfg = DphrConfig(stride=1, close_size=1)
    img = _two_branches(slice(4, 24), slice(44, 58))  # left opening 20 px wide, right 14 px
    res = deepest_point_heading(img, cfg)
    assert len(res.branches) == 2
    left, right = sorted(res.branches, key=lambda b: b.offset)
    assert left.offset < 0 < right.offset
    # the larger opening (the left one) is chosen, and the heading goes there — not to the rock
    # between the two, where the centroid of both would point
    assert res.branches[res.chosen] == left
    assert res.offset == pytest.approx(left.offset) and res.yaw_rate > 0
    union = (left.offset * left.pixels + right.offset * right.pixels) / (left.pixels + right.pixels)
    assert abs(res.offset - union) > 0.2
    assert deepest_point_heading(img, cfg).offset == res.offset  # same image, same choice
    # equal openings: the deeper one wins
    tie = deepest_point_heading(_two_branches(slice(4, 18), slice(44, 58), 5.5), cfg)
    assert tie.branches[tie.chosen].offset < 0


def test_committed_branch_is_kept_unless_another_is_much_larger() -> None:
    cfg = DphrConfig(stride=1, close_size=1)
    img = _two_branches(slice(4, 24), slice(44, 58))
    first = deepest_point_heading(img, cfg)
    right = max(first.branches, key=lambda b: b.offset)
    # committed to the right branch: kept, although the left one is larger (20 vs 14 px)
    kept = deepest_point_heading(img, cfg, prefer_offset=right.offset)
    assert kept.offset == pytest.approx(right.offset) and kept.yaw_rate < 0
    # a left branch more than switch_ratio times larger takes over
    wide = _two_branches(slice(0, 40), slice(48, 58))
    switched = deepest_point_heading(wide, cfg, prefer_offset=0.6)
    assert switched.offset < 0
    with pytest.raises(ValueError, match="no branch"):
        choose_branch([])


def test_dead_end_turns_round_and_speed_widens_the_yaw_rate_bound() -> None:
    from btmission.control.dphr import yaw_rate_limit_for_speed

    wall = np.full((48, 64), 1.2)  # a flat wall 1.2 m ahead fills the view
    wall[:, 40:] = 1.3  # slightly deeper on the right: the paper's rule turns right, barely
    plain = deepest_point_heading(wall, DphrConfig(stride=1, close_size=1))
    assert plain.yaw_rate <= 0
    dead = deepest_point_heading(wall, DphrConfig(stride=1, close_size=1, dead_end_m=2.0))
    assert dead.yaw_rate == pytest.approx(DphrConfig().yaw_rate_max)  # turns round (left)
    open_ = _two_branches(slice(4, 24), slice(44, 58))
    cfg = DphrConfig(stride=1, close_size=1, dead_end_m=2.0)
    assert (
        deepest_point_heading(open_, cfg).yaw_rate
        == deepest_point_heading(open_, DphrConfig(stride=1, close_size=1)).yaw_rate
    )  # an opening in view: the ordinary rule
    assert yaw_rate_limit_for_speed(0.5) == 0.5  # the floor: DphrConfig's default
    assert yaw_rate_limit_for_speed(1.0) == pytest.approx(1.0 / 1.5)
    assert yaw_rate_limit_for_speed(2.3) == pytest.approx(2.3 / 1.5)
    with pytest.raises(ValueError):
        yaw_rate_limit_for_speed(-1.0)
