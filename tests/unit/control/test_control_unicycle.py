"""Ground-robot NMPC with set-exclusion avoidance (seed 003 eq. 11-12) and a safe corridor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from btmission.control.examples import head_on
from btmission.control.scenes import box_distance, shelf_outline
from btmission.control.unicycle_nmpc import (
    UnicycleConfig,
    UnicycleNmpc,
    exclusion_violation,
    obstacle_violation,
    safe_halfspaces,
    shift_prediction,
    unicycle_dynamics,
    unicycle_step,
)

R_OBS = 0.3
R_STATIC = 0.3
SHELF = (1.5, 2.5, 0.1, 1.1)
"""x0, x1, y0, y1 of a 1 m shelf whose corner the straight line y = 0 passes 0.1 m from."""


def drive_past_shelf(
    obstacles: np.ndarray | None, steps: int = 160, shelf: tuple[float, float, float, float] = SHELF
) -> tuple[np.ndarray, float, list[float]]:
    """A forward-only robot (as the navigator runs it) from the origin to (4, 0), the way-point
    straight ahead; returns the final state, the closest approach to SHELF and the static
    violations the NMPC reported."""
    nmpc = UnicycleNmpc(UnicycleConfig(v_min=0.0, q_heading=0.5))
    x = np.zeros(3)
    goal = np.array([4.0, 0.0])
    closest = math.inf
    violations: list[float] = []
    for _ in range(steps):
        d = goal - x[:2]
        heading = math.atan2(d[1], d[0]) if np.hypot(*d) > 0.05 else x[2]
        r = nmpc.solve(x, [goal[0], goal[1], heading], obstacles=obstacles)
        assert r.success
        violations.append(r.static_violation_m)
        x = unicycle_step(x, r.u, 0.1)
        closest = min(closest, box_distance(x, shelf))
    return x, closest, violations


def test_shelf_corner_is_kept_at_the_safety_distance() -> None:
    """The straight line to the way-point passes 0.1 m from a shelf's corner: with the shelf's
    outline as obstacle points the robot swings round it at ≥ r_static (0.3 m) to the shelf
    itself (not only to the sampled points) and still reaches the way-point."""
    x, closest, violations = drive_past_shelf(shelf_outline(*SHELF))
    assert closest >= R_STATIC
    assert max(violations) <= UnicycleConfig().violation_tol_m
    assert np.linalg.norm(x[:2] - [4.0, 0.0]) < 0.1


def test_without_the_corridor_it_would_clip_the_shelf() -> None:
    """The same drive with no obstacle points: a 0.15 m-radius robot would hit the corner."""
    x, closest, _ = drive_past_shelf(None)
    assert closest < 0.15
    assert np.linalg.norm(x[:2] - [4.0, 0.0]) < 0.1


def test_a_shelf_across_the_path_stops_the_robot_at_the_safety_distance() -> None:
    """A shelf straight across the line to the way-point: the robot stops in front of it at
    ≥ r_static (finding a way round is the planner's job: a local minimum of the tracking cost);
    without the corridor it drives through the shelf."""
    across = (1.5, 2.5, -0.4, 0.6)
    x, closest, _ = drive_past_shelf(shelf_outline(*across), steps=80, shelf=across)
    assert closest >= R_STATIC
    assert x[0] < across[0]  # still in front of it
    _, closest, _ = drive_past_shelf(None, steps=80, shelf=across)
    assert closest == 0.0  # inside it


def test_robots_pass_head_on_in_an_aisle_between_shelves() -> None:
    """Eq. 12 and the safe corridor together: two robots meet head-on in a 1.6 m aisle between
    two shelves; they pass each other at ≥ r_obs and keep ≥ r_static from both shelves."""
    lower, upper = (-1.0, 5.0, -1.8, -0.8), (-1.0, 5.0, 0.8, 1.8)
    shelves = np.vstack([shelf_outline(*lower), shelf_outline(*upper)])
    cfg = UnicycleConfig(v_min=0.0, q_heading=0.5)
    a, b = UnicycleNmpc(cfg), UnicycleNmpc(cfg)
    xa, xb = np.array([0.0, -0.05, 0.0]), np.array([4.0, 0.05, math.pi])
    goals = (np.array([4.0, 0.0]), np.array([0.0, 0.0]))
    pa = np.tile(xa[:2], (cfg.horizon + 1, 1))
    pb = np.tile(xb[:2], (cfg.horizon + 1, 1))
    closest, wall = math.inf, math.inf
    for _ in range(200):
        refs = []
        for x, g in ((xa, goals[0]), (xb, goals[1])):
            d = g - x[:2]
            refs.append([g[0], g[1], math.atan2(d[1], d[0]) if np.hypot(*d) > 0.05 else x[2]])
        ra = a.solve(xa, refs[0], [shift_prediction(pb)], obstacles=shelves)
        rb = b.solve(xb, refs[1], [shift_prediction(pa)], obstacles=shelves)
        assert ra.success and rb.success
        pa, pb = ra.predicted_positions, rb.predicted_positions
        xa, xb = unicycle_step(xa, ra.u, 0.1), unicycle_step(xb, rb.u, 0.1)
        closest = min(closest, float(np.linalg.norm(xa[:2] - xb[:2])))
        wall = min(wall, *(box_distance(x, s) for x in (xa, xb) for s in (lower, upper)))
    assert closest >= R_OBS
    assert wall >= R_STATIC
    assert np.linalg.norm(xa[:2] - goals[0]) < 0.15
    assert np.linalg.norm(xb[:2] - goals[1]) < 0.15


def test_safe_halfspaces_keep_every_point_at_r() -> None:
    """Any position inside a step's corridor is ≥ r from every obstacle point within the query
    radius (the half-spaces are a conservative inner approximation); the corridor contains the
    linearisation point when that point is ≥ r from the obstacles."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-2.0, 2.0, (300, 2))
    points = points[np.hypot(*points.T) > 0.6]  # a free disc round the origin
    centres = np.array([[0.0, 0.0], [0.1, -0.2]])
    planes = safe_halfspaces(centres, points, 0.3, 8, query_radius=1.5)
    assert planes.shape == (2, 8, 3)
    samples = rng.uniform(-1.0, 1.0, (20000, 2))
    for c, rows in zip(centres, planes):
        inside = np.all(samples @ rows[:, :2].T <= rows[:, 2], axis=1)
        assert inside.any()
        assert np.all(c @ rows[:, :2].T <= rows[:, 2])
        near = points[np.hypot(*(points - c).T) <= 1.5]
        dist = np.min(np.hypot(*(samples[inside][:, None, :] - near[None]).transpose(2, 0, 1)), 1)
        assert dist.min() >= 0.3 - 1e-9
    empty = safe_halfspaces(centres, np.zeros((0, 2)), 0.3, 4)
    np.testing.assert_array_equal(empty[..., 2], 1.0)  # 0·p ≤ 1: no constraint
    ours = np.array([[0.0, 0.0], [0.5, 0.0]])
    assert obstacle_violation(ours, [[0.7, 0.0], [3.0, 3.0]], R_STATIC) == pytest.approx(0.1)
    assert obstacle_violation(ours, np.zeros((0, 2)), R_STATIC) == 0.0


@pytest.mark.parametrize("offset", [0.05, 0.0])
def test_head_on_unicycles_keep_r_obs_and_reach_their_goals(offset: float) -> None:
    log = head_on(steps=110, offset=offset)
    cfg = UnicycleConfig()
    assert log.success.all()
    assert log.distance.min() >= R_OBS  # seed 003 reports at most 0.04 m violation; we keep none
    assert np.linalg.norm(log.a[-1, :2] - log.goals[0]) < 0.1
    assert np.linalg.norm(log.b[-1, :2] - log.goals[1]) < 0.1
    for u in (log.inputs_a, log.inputs_b):  # inputs within bounds
        assert np.all((u[:, 0] >= cfg.v_min - 1e-9) & (u[:, 0] <= cfg.v_max + 1e-9))
        assert np.all(np.abs(u[:, 1]) <= cfg.omega_max + 1e-9)


def test_without_avoidance_they_would_collide() -> None:
    """The same scenario with no shared predictions: the test above is not passing by luck."""
    log = head_on(steps=60, offset=0.05, avoid=False)
    assert log.distance.min() < 0.1


def test_static_obstacle_on_the_path_is_avoided() -> None:
    nmpc = UnicycleNmpc()
    obstacle = np.tile([1.0, 0.02], (nmpc.config.horizon + 1, 1))
    x = np.zeros(3)
    closest = math.inf
    for _ in range(60):
        r = nmpc.solve(x, [2.0, 0.0], [obstacle])
        assert r.violation_m <= nmpc.config.violation_tol_m
        x = unicycle_step(x, r.u, 0.1)
        closest = min(closest, float(np.linalg.norm(x[:2] - obstacle[0])))
    assert closest >= R_OBS
    assert np.linalg.norm(x[:2] - [2.0, 0.0]) < 0.15


def test_model_and_helpers() -> None:
    np.testing.assert_allclose(
        unicycle_dynamics(np.array([0, 0, math.pi / 2]), [1.0, 0.2]), [0, 1, 0.2], atol=1e-12
    )
    # a constant turn: RK4 lands on the circle of radius v/ω
    x = unicycle_step([0.0, 0.0, 0.0], [0.5, 0.5], math.pi, substeps=50)
    np.testing.assert_allclose(x, [1.0, 1.0, math.pi / 2], atol=1e-6)  # (R sin ψ, R(1 − cos ψ))
    traj = np.arange(12.0).reshape(6, 2)
    shifted = shift_prediction(traj)
    np.testing.assert_array_equal(shifted[:-1], traj[1:])
    np.testing.assert_array_equal(shifted[-1], traj[-1])
    ours = np.array([[0.0, 0.0], [0.5, 0.0], [1.0, 0.0]])
    theirs = np.array([[2.0, 0.0], [0.6, 0.1], [3.0, 0.0]])
    brute = max(0.0, max(R_OBS - float(np.linalg.norm(p - q)) for p, q in zip(ours, theirs)))
    assert exclusion_violation(ours, theirs, R_OBS) == pytest.approx(brute)


def test_bad_inputs() -> None:
    nmpc = UnicycleNmpc()
    with pytest.raises(ValueError, match="state x"):
        nmpc.solve([0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="x_ref"):
        nmpc.solve([0.0, 0.0, 0.0], [1.0, math.nan])
    with pytest.raises(ValueError, match=r"expected an \(51, 2\) predicted trajectory"):
        nmpc.solve([0.0, 0.0, 0.0], [1.0, 1.0], [np.zeros((10, 2))])
    with pytest.raises(ValueError, match="max_agents=4"):
        nmpc.solve([0.0, 0.0, 0.0], [1.0, 1.0], [np.zeros((51, 2))] * 5)
    with pytest.raises(ValueError, match="obstacles must be finite"):
        nmpc.solve([0.0, 0.0, 0.0], [1.0, 1.0], obstacles=np.zeros(4))
    with pytest.raises(ValueError, match="r_static_m"):
        UnicycleConfig(r_static_m=0.0)
    with pytest.raises(ValueError, match="penalty_growth"):
        UnicycleConfig(penalty_growth=1.0)
    with pytest.raises(ValueError, match="v_min"):
        UnicycleConfig(v_min=0.5)
