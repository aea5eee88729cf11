"""World ENU ↔ a MAVLink vehicle's local NED frame, yaw included, and the geodetic origin."""

from __future__ import annotations

import math

import numpy as np
import pytest

from btmission.backends.mavlink_frames import (
    GeodeticOrigin,
    LocalFrame,
    geodetic_to_world,
    world_to_geodetic,
    wrap_pi,
)


def test_a_world_whose_y_is_north_swaps_x_and_y_and_flips_z() -> None:
    f = LocalFrame((0.0, 0.0, 0.0))  # north = world +y (a mission laid out on a map)
    np.testing.assert_allclose(f.to_local((1.0, 0.0, 0.0)), [0.0, 1.0, 0.0], atol=1e-12)  # east
    np.testing.assert_allclose(f.to_local((0.0, 1.0, 0.0)), [1.0, 0.0, 0.0], atol=1e-12)  # north
    np.testing.assert_allclose(
        f.to_local((0.0, 0.0, 2.0)), [0.0, 0.0, -2.0], atol=1e-12
    )  # up = −down


def test_the_origin_and_a_rotated_north() -> None:
    f = LocalFrame((1.0, 1.0, 1.0), north_yaw=0.0)  # the vehicle took world +x as north
    np.testing.assert_allclose(f.to_local((3.0, 4.0, 5.0)), [2.0, -3.0, -4.0], atol=1e-12)
    np.testing.assert_allclose(f.to_world((2.0, -3.0, -4.0)), [3.0, 4.0, 5.0], atol=1e-12)
    f = LocalFrame((10.0, 0.0, 0.0), north_yaw=math.pi / 4)
    np.testing.assert_allclose(f.to_local((11.0, 1.0, 0.0)), [math.sqrt(2), 0.0, 0.0], atol=1e-12)


def test_points_vectors_and_yaws_round_trip() -> None:
    rng = np.random.default_rng(4)
    for _ in range(200):
        f = LocalFrame(tuple(rng.uniform(-50, 50, 3)), north_yaw=float(rng.uniform(-4, 4)))
        p = rng.uniform(-100, 100, 3)
        np.testing.assert_allclose(f.to_world(f.to_local(p)), p, atol=1e-9)
        np.testing.assert_allclose(f.vector_to_world(f.vector_to_local(p)), p, atol=1e-9)
        assert np.linalg.norm(f.vector_to_local(p)) == pytest.approx(np.linalg.norm(p))
        yaw = float(rng.uniform(-math.pi, math.pi))
        assert f.yaw_to_world(f.yaw_to_local(yaw)) == pytest.approx(yaw, abs=1e-12)


@pytest.mark.parametrize("north_yaw", [math.pi / 2, 0.0, 1.0, -2.5])
def test_a_heading_and_its_velocity_agree_in_both_frames(north_yaw: float) -> None:
    """Flying along world yaw ψ: the NED velocity points along the NED yaw (north = cos, east =
    sin), so setpoints built from one and the other never disagree."""
    f = LocalFrame((0.0, 0.0, 0.0), north_yaw)
    for psi in np.linspace(-math.pi, math.pi, 13):
        v_local = f.vector_to_local((math.cos(psi), math.sin(psi), 0.0))
        yaw_local = f.yaw_to_local(float(psi))
        np.testing.assert_allclose(v_local, [math.cos(yaw_local), math.sin(yaw_local), 0.0],
                                   atol=1e-12)  # fmt: skip
    assert f.yaw_rate_to_local(0.3) == -0.3 and f.yaw_rate_to_world(-0.3) == 0.3


def test_yaws_in_a_map_aligned_world() -> None:
    f = LocalFrame((0.0, 0.0, 0.0))
    assert f.yaw_to_local(math.pi / 2) == pytest.approx(0.0)  # facing north
    assert f.yaw_to_local(0.0) == pytest.approx(math.pi / 2)  # facing east
    assert f.yaw_to_local(math.pi) == pytest.approx(-math.pi / 2)  # facing west
    assert wrap_pi(-math.pi) == math.pi and wrap_pi(3 * math.pi) == pytest.approx(math.pi)


def test_geodetic_degrees_at_the_equator_and_round_trips() -> None:
    o = GeodeticOrigin(0.0, 0.0, 100.0)
    # one degree of longitude / latitude at the equator (WGS-84): 111,319.49 m / 110,574.27 m
    np.testing.assert_allclose(geodetic_to_world(0.0, 1.0, 100.0, o), [111319.49, 0.0, 0.0],
                               atol=0.01)  # fmt: skip
    np.testing.assert_allclose(geodetic_to_world(1.0, 0.0, 90.0, o), [0.0, 110574.27, -10.0],
                               atol=0.01)  # fmt: skip
    mine = GeodeticOrigin(-23.5, 133.9, 550.0)  # somewhere underground in the outback
    for p in ([0.0, 0.0, 0.0], [1200.0, -800.0, -300.0], [-35.5, 12.25, 4.0]):
        lat, lon, alt = world_to_geodetic(p, mine)
        np.testing.assert_allclose(geodetic_to_world(lat, lon, alt, mine), p, atol=1e-6)
    lat, lon, alt = world_to_geodetic((0.0, 1000.0, 0.0), mine)
    assert lat > mine.lat_deg and lon == mine.lon_deg and alt == 550.0


def test_a_bad_geodetic_origin_is_refused() -> None:
    with pytest.raises(ValueError, match=r"latitude must be in \(-90, 90\)"):
        GeodeticOrigin(91.0, 0.0)
    with pytest.raises(ValueError, match="longitude in"):
        GeodeticOrigin(0.0, 200.0)
