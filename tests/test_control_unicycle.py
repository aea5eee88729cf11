"""Ground-robot NMPC with set-exclusion avoidance (seed 003 eq. 11-12)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from btmission.control.examples import head_on
from btmission.control.unicycle_nmpc import (
    UnicycleConfig,
    UnicycleNmpc,
    exclusion_violation,
    shift_prediction,
    unicycle_dynamics,
    unicycle_step,
)

R_OBS = 0.3


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
    with pytest.raises(ValueError, match="penalty_growth"):
        UnicycleConfig(penalty_growth=1.0)
    with pytest.raises(ValueError, match="v_min"):
        UnicycleConfig(v_min=0.5)
