"""APF (seed 002 eq. 3, Alg. 1): brute-force reference, dust rule, Alg. 1 bounds, corridor flight."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from btmission.control.apf import ApfConfig, PotentialField, repulsive_force, shape_force
from btmission.control.examples import corridor_flight
from btmission.control.nmpc import NmpcConfig
from btmission.control.scenes import lidar_scan, straight_corridor

CFG = ApfConfig(gain=(0.05, 0.08, 0.03), gain_critical=0.4, dust_points=2)


def _eq3_by_loop(points: np.ndarray, cfg: ApfConfig) -> np.ndarray:
    """Seed 002 eq. 3 written literally, one point at a time."""
    force = np.zeros(3)
    critical = []
    for rho in points:
        d = math.sqrt(float(rho @ rho))
        if d == 0 or d > cfg.r_influence_m:
            continue
        force += np.asarray(cfg.gain) * (1 - d / cfg.r_influence_m) ** 2 * (-rho / d)
        if d <= cfg.r_critical_m:
            critical.append(-rho / d)
    if len(critical) > cfg.dust_points:
        force += cfg.gain_critical * np.sum(critical, axis=0)
    return force


vec3 = arrays(np.float64, 3, elements=st.floats(-3, 3, allow_nan=False))
clouds = arrays(
    np.float64,
    st.tuples(st.integers(0, 60), st.just(3)),
    elements=st.floats(-2, 2, allow_nan=False),
)


@settings(max_examples=60, deadline=None)
@given(clouds)
def test_repulsive_force_matches_eq_3_point_by_point(points: np.ndarray) -> None:
    force, n_rf, n_rc, ignored = repulsive_force(points, CFG)
    np.testing.assert_allclose(force, _eq3_by_loop(points, CFG), atol=1e-9)
    d = np.linalg.norm(points, axis=1)
    assert n_rf == int(((d <= CFG.r_influence_m) & (d > 0)).sum())
    assert n_rc == int(((d <= CFG.r_critical_m) & (d > 0)).sum())
    assert ignored == (0 < n_rc <= CFG.dust_points)


def test_dust_inside_r_c_is_ignored_but_a_real_obstacle_is_not() -> None:
    cfg = ApfConfig()  # n = 3
    wall = np.array([[0.0, 1.2, z] for z in np.linspace(-0.3, 0.3, 20)])  # outside r_c
    dust = np.array([[0.3, 0.0, 0.1], [0.2, -0.1, 0.0], [0.1, 0.3, -0.1]])  # n points in r_c
    base, *_ = repulsive_force(wall, cfg)
    with_dust, _, n_rc, ignored = repulsive_force(np.vstack([wall, dust]), cfg)
    assert n_rc == 3 and ignored
    # only the small r_F terms of the dust points are added, no static r_c potential
    np.testing.assert_allclose(with_dust - base, _eq3_by_loop(dust, cfg), atol=1e-12)
    assert np.linalg.norm(with_dust - base) < 0.01
    obstacle = np.vstack([dust, [[0.35, 0.05, 0.0]]])  # n + 1 points: a thin obstacle
    force, _, n_rc, ignored = repulsive_force(obstacle, cfg)
    assert n_rc == 4 and not ignored
    assert np.linalg.norm(force) > cfg.gain_critical  # the static potential is on
    assert force[0] < 0  # and it pushes away from the obstacle (ahead, +x)


def test_nan_and_origin_points_are_dropped_and_bad_shapes_rejected() -> None:
    pts = np.array([[math.nan, 0, 0], [0, 0, 0], [1.0, 0, 0]])
    force, n_rf, _, _ = repulsive_force(pts, CFG)
    assert n_rf == 1
    np.testing.assert_allclose(force, _eq3_by_loop(pts[2:], CFG))
    assert repulsive_force(np.zeros((0, 3)), CFG)[0].tolist() == [0, 0, 0]
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        repulsive_force(np.zeros((4, 2)), CFG)
    with pytest.raises(ValueError, match="r_critical_m < r_influence_m"):
        ApfConfig(r_critical_m=2.0)
    with pytest.raises(ValueError, match="dust_points"):
        ApfConfig(dust_points=-1)
    with pytest.raises(ValueError, match="waypoint"):
        PotentialField().step(np.zeros((0, 3)), [1.0, math.inf, 0])


@settings(max_examples=200)
@given(vec3, vec3, vec3)
def test_alg_1_saturation_rate_and_normalisation(
    raw: np.ndarray, prev: np.ndarray, fa: np.ndarray
) -> None:
    cfg = ApfConfig(force_max=1.5, force_rate_max=0.3)
    if np.linalg.norm(prev) > cfg.force_max:  # a previous output always satisfies the bound
        prev = prev / np.linalg.norm(prev) * cfg.force_max
    total, fr, fa_n = shape_force(raw * 10, prev, fa, cfg)
    assert np.linalg.norm(total) <= 1 + 1e-12
    assert np.linalg.norm(fr) <= cfg.force_max + 1e-12
    assert np.linalg.norm(fr - prev) <= cfg.force_rate_max + 1e-12
    assert np.linalg.norm(fa_n) <= 1 + 1e-12
    # direction preserved by each step of Alg. 1
    if np.linalg.norm(fa) > 1:
        np.testing.assert_allclose(fa_n, fa / np.linalg.norm(fa))
    s = fr + fa_n
    if np.linalg.norm(s) > 1:
        np.testing.assert_allclose(total, s / np.linalg.norm(s))
    else:
        np.testing.assert_allclose(total, s)


def test_alg_1_small_forces_pass_unchanged() -> None:
    cfg = ApfConfig()
    total, fr, fa = shape_force([0.1, 0, 0], [0.05, 0, 0], [0.5, 0.2, 0], cfg)
    np.testing.assert_allclose(fr, [0.1, 0, 0])
    np.testing.assert_allclose(fa, [0.5, 0.2, 0])
    np.testing.assert_allclose(total, [0.6, 0.2, 0])


def test_corridor_flight_keeps_r_c_from_walls_ignores_dust_and_respects_alg_1() -> None:
    """NMPC + APF fly down a 2.4 m corridor, the carrot pulled into the left wall, already
    drifting towards it at 0.5 m/s, with two dust points near the MAV on every other scan."""
    cfg = ApfConfig()
    log = corridor_flight(steps=140, width_m=2.4, pull=(1.0, 1.0, 0.0), dust=True)
    assert log.flight.success.all()
    assert log.clearance.min() >= cfg.r_critical_m
    assert np.all(np.linalg.norm(log.forces, axis=1) <= 1 + 1e-12)
    assert np.all(np.linalg.norm(log.repulsive, axis=1) <= cfg.force_max + 1e-12)
    changes = np.diff(np.vstack([np.zeros(3), log.repulsive]), axis=0)
    assert np.all(np.linalg.norm(changes, axis=1) <= cfg.force_rate_max + 1e-12)
    assert log.dust_ignored[1::2].all() and not log.dust_ignored[::2].any()
    final = log.flight.states[-1]
    assert final[0] > 2.0  # the MAV kept moving down the corridor
    assert log.width_m / 2 - final[1] < 1.0  # pressed towards the wall it is pulled to, held off
    # eq. 4 in the loop: the position weight dropped while the wall pushed back
    assert log.q_position.min() < 0.6 * NmpcConfig().q_position[0]


def test_corridor_flight_without_apf_would_hit_the_wall() -> None:
    """The same pull with a vanishing repulsion: the clearance check above is not vacuous."""
    weak = ApfConfig(gain=(1e-9, 1e-9, 1e-9), gain_critical=1e-9)
    log = corridor_flight(steps=60, width_m=2.4, pull=(1.0, 1.0, 0.0), apf_config=weak)
    assert log.clearance.min() < 0.0


def test_lidar_scan_is_vlp16_like_and_hits_the_walls() -> None:
    tunnel = straight_corridor(3.0, 3.0)
    pts = lidar_scan(tunnel, [0.0, 0.5, 1.5])
    assert pts.shape == (30_000, 3)  # a closed tunnel: every ray hits
    world = pts + np.array([0.0, 0.5, 1.5])
    on_wall = np.isclose(np.abs(world[:, 1]), 1.5, atol=1e-9)
    on_floor_or_ceiling = np.isclose(world[:, 2], 0.0, atol=1e-9) | np.isclose(
        world[:, 2], 3.0, atol=1e-9
    )
    assert np.all(on_wall | on_floor_or_ceiling)
    elev = np.degrees(np.arcsin(pts[:, 2] / np.linalg.norm(pts, axis=1)))
    assert elev.min() == pytest.approx(-15) and elev.max() == pytest.approx(15)


def test_braking_distance_and_stopping_speed_are_inverse() -> None:
    from btmission.control.apf import braking_distance, stopping_speed

    for v in (0.0, 0.5, 1.0, 2.3, 4.0):
        d = braking_distance(v, 3.6, 0.4)
        assert d == pytest.approx(v * 0.4 + v * v / 7.2)
        assert stopping_speed(d, 3.6, 0.4) == pytest.approx(v, abs=1e-9)
    assert stopping_speed(-0.1, 3.6, 0.4) == 0.0
    with pytest.raises(ValueError):
        braking_distance(1.0, 0.0, 0.4)


def test_influence_radius_grows_with_speed_only_past_the_configured_one() -> None:
    from btmission.control.apf import influence_radius_for_speed

    cfg = ApfConfig()
    assert influence_radius_for_speed(1.0, cfg, 3.6, 0.4) == cfg.r_influence_m
    fast = influence_radius_for_speed(2.3, cfg, 3.6, 0.4)
    assert fast == pytest.approx(cfg.r_critical_m + 2.3 * 0.4 + 2.3**2 / 7.2)
    assert fast > cfg.r_influence_m


def test_approach_speed_is_limited_towards_rock_but_not_along_it() -> None:
    from btmission.control.apf import limit_approach_speed, stopping_speed

    wall_ahead = np.array([[1.0, y, 0.0] for y in np.linspace(-1, 1, 9)])
    v = limit_approach_speed([2.3, 0.0, 0.0], wall_ahead, 0.6, 3.6, 0.4)
    assert v[0] <= stopping_speed(0.4, 3.6, 0.4) + 1e-9  # 1 m to the wall, 0.6 m stand-off
    # sliding along a wall beside the MAV (1.25 m off, a 2.5 m tunnel's centre) is untouched, and so
    # is moving away from it
    wall_left = np.array([[x, 1.25, 0.0] for x in np.linspace(-3, 3, 25)])
    np.testing.assert_allclose(limit_approach_speed([2.3, 0, 0], wall_left, 0.6, 3.6, 0.4)[0], 2.3)
    np.testing.assert_allclose(
        limit_approach_speed([0, -1.0, 0], wall_left, 0.6, 3.6, 0.4), [0, -1.0, 0]
    )
    # approaching it: no faster than can stop 0.6 m short of it; inside the stand-off, not at all
    limit = stopping_speed(1.25 - 0.6, 3.6, 0.4)
    assert limit_approach_speed([0, 2.0, 0], wall_left, 0.6, 3.6, 0.4)[1] <= limit + 1e-9
    close = wall_left * [1.0, 0.4, 1.0]
    assert limit_approach_speed([0, 1.0, 0], close, 0.6, 3.6, 0.4)[1] <= 1e-9


def test_approach_bound_ignores_rock_off_the_line_of_motion() -> None:
    """Flying level 1.5 m over a floor, with a wall 2 m ahead: only the wall counts once the
    corridor is set — without it, the floor ahead-below looks like an approach and slows the MAV."""
    from btmission.control.apf import limit_approach_speed, stopping_speed

    floor = np.array([[x, y, -1.5] for x in np.linspace(-3, 3, 13) for y in np.linspace(-2, 2, 9)])
    v = np.array([2.3, 0.0, 0.0])
    free = limit_approach_speed(v, floor, 0.7, 1.5, 0.6, corridor_m=1.0)
    np.testing.assert_allclose(free, v)
    assert limit_approach_speed(v, floor, 0.7, 1.5, 0.6)[0] < 2.3  # no corridor: slowed
    wall = np.array([[2.0, y, z] for y in np.linspace(-1, 1, 5) for z in np.linspace(-1, 1, 5)])
    limited = limit_approach_speed(v, np.vstack([floor, wall]), 0.7, 1.5, 0.6, corridor_m=1.0)
    assert limited[0] <= stopping_speed(2.0 - 0.7, 1.5, 0.6) + 1e-9
    # a wall beside the way the MAV actually moves (``heading``) counts too
    side = np.array([[x, 1.5, 0.0] for x in np.linspace(0.2, 2.0, 10)])
    turned = limit_approach_speed(
        [0, 2.0, 0], side, 0.7, 1.5, 0.6, corridor_m=0.5, heading=[1, 1, 0]
    )
    assert turned[1] < 2.0


def test_adaptive_speed_scale_is_eq4_normalised() -> None:
    from btmission.control.nmpc import NmpcConfig, adaptive_position_weight
    from btmission.runtime.navcontrol import adaptive_speed_scale

    cfg = NmpcConfig()
    assert adaptive_speed_scale(0.0) == pytest.approx(1.0)
    for f in (0.1, 0.5, 1.0, 3.0):
        q = adaptive_position_weight(f, cfg.q_position_min[0], cfg.q_position[0], cfg.force_gain)
        assert adaptive_speed_scale(f) == pytest.approx(float(q) / cfg.q_position[0])
    assert adaptive_speed_scale(0.5) > adaptive_speed_scale(1.0) > cfg.q_position_min[0] / 4.0


def test_separation_bound_keeps_each_agent_to_half_the_gap() -> None:
    """Towards another agent a vehicle goes no faster than it can stop within its half of the
    gap beyond the stand-off (its stop: reaction, then deceleration); along it and away from it
    nothing changes; inside the stand-off it does not approach at all."""
    from btmission.control.apf import SeparationConfig, separation_bound, stopping_speed

    cfg = SeparationConfig(stand_off_m=1.0, decel_m_s2=3.6, reaction_s=0.85)
    ahead = np.array([[3.0, 0.0, 0.0]])
    v = separation_bound([1.5, 0.0, 0.0], ahead, cfg)
    assert v[0] == pytest.approx(stopping_speed(0.5 * (3.0 - 1.0), 3.6, 0.85))
    assert v[0] < 1.5
    # passing beside it and moving away are kept; an approach at an angle loses only its approach
    np.testing.assert_allclose(separation_bound([0.0, 1.5, 0.0], ahead, cfg), [0.0, 1.5, 0.0])
    np.testing.assert_allclose(separation_bound([-1.5, 0.0, 0.0], ahead, cfg), [-1.5, 0.0, 0.0])
    oblique = separation_bound([1.5, 1.5, 0.0], ahead, cfg)
    assert oblique[1] == pytest.approx(1.5) and oblique[0] == pytest.approx(v[0])
    # inside the stand-off: no approach; far away: untouched
    assert separation_bound([1.0, 0.0, 0.0], [[0.8, 0.0, 0.0]], cfg)[0] == pytest.approx(0.0)
    np.testing.assert_allclose(separation_bound([1.5, 0, 0], [[20.0, 0, 0]], cfg), [1.5, 0, 0])
    # the most constraining of several neighbours rules
    two = separation_bound([1.5, 0.0, 0.0], [[3.0, 0.0, 0.0], [2.0, 0.0, 0.0]], cfg)
    assert two[0] == pytest.approx(stopping_speed(0.5, 3.6, 0.85))
    # stopping from the bounded speed (v·t_r + v²/2a) never takes it past its half of the gap
    for d in (1.2, 2.0, 3.0, 5.0):
        s = separation_bound([3.0, 0.0, 0.0], [[d, 0.0, 0.0]], cfg)[0]
        assert s * 0.85 + s * s / 7.2 <= 0.5 * (d - 1.0) + 1e-9


def test_a_neighbour_moving_away_gives_back_the_room_it_covers_when_it_brakes() -> None:
    """A leader moving away at w adds w²/(2·a_j) to the follower's room; one moving towards it
    or one whose velocity is not shared (NaN) adds nothing."""
    from btmission.control.apf import SeparationConfig, separation_bound, stopping_speed

    cfg = SeparationConfig(stand_off_m=1.0, decel_m_s2=3.6, reaction_s=0.85, lead_decel_m_s2=0.8)
    ahead = [[3.0, 0.0, 0.0]]
    alone = separation_bound([3.0, 0.0, 0.0], ahead, cfg)[0]
    away = separation_bound([3.0, 0.0, 0.0], ahead, cfg, [[1.0, 0.0, 0.0]])[0]
    assert away == pytest.approx(stopping_speed(1.0 + 1.0 / 1.6, 3.6, 0.85)) and away > alone
    towards = separation_bound([3.0, 0.0, 0.0], ahead, cfg, [[-1.0, 0.0, 0.0]])[0]
    unknown = separation_bound([3.0, 0.0, 0.0], ahead, cfg, [[np.nan] * 3])[0]
    assert towards == pytest.approx(alone) and unknown == pytest.approx(alone)
    # still approaching faster than allowed (the velocity loop lags): the command drops by the
    # excess again, to bring the approach down to the bound sooner
    late = separation_bound([3.0, 0.0, 0.0], ahead, cfg, current=[alone + 0.4, 0.0, 0.0])[0]
    assert late == pytest.approx(alone - 0.4)
    with pytest.raises(ValueError, match="velocities"):
        separation_bound([1.0, 0, 0], ahead, cfg, np.zeros((2, 3)))
    with pytest.raises(ValueError):
        SeparationConfig(share=0.0)
