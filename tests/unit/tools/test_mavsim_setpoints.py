"""The simulator's reading of SET_ATTITUDE_TARGET is the inverse of the provider's writing."""

from __future__ import annotations

import math

import pytest

from btmission.backends.mavlink_frames import LocalFrame
from btmission.backends.mavlink_setpoints import (
    G,
    attitude_from_target,
    attitude_target,
    euler_to_quaternion,
    quaternion_to_euler,
)

MAP = LocalFrame((10.0, 5.0, 0.0))  # north = world +y
TILTED = LocalFrame((0.0, 0.0, 0.0), north_yaw=0.3)


@pytest.mark.parametrize("frame", [MAP, TILTED])
@pytest.mark.parametrize(
    ("thrust", "roll", "pitch", "yaw", "yaw_rate"),
    [
        (G, 0.0, 0.0, 0.0, 0.0),
        (1.2 * G, 0.2, -0.15, 1.0, 0.4),
        (0.7 * G, -0.3, 0.25, -2.5, -0.8),
        (1.5 * G, 0.05, 0.4, math.pi - 0.01, 1.2),
    ],
)
@pytest.mark.parametrize("hover", [0.5, 0.35])
def test_attitude_round_trip(
    frame: LocalFrame, thrust: float, roll: float, pitch: float, yaw: float, yaw_rate: float,
    hover: float,
) -> None:  # fmt: skip
    target = attitude_target(frame, thrust, roll, pitch, yaw, yaw_rate, hover=hover)
    back = attitude_from_target(frame, target, hover=hover)
    assert back == pytest.approx((thrust, roll, pitch, yaw_rate), abs=1e-9)


def test_thrust_beyond_full_throttle_reads_back_as_full_throttle() -> None:
    target = attitude_target(MAP, 5 * G, 0.0, 0.0, 0.0, hover=0.5)
    assert target.thrust == 1.0
    assert attitude_from_target(MAP, target, hover=0.5)[0] == pytest.approx(2 * G)


def test_a_positive_pitch_is_nose_down_in_frd() -> None:
    """Seed 002's +θ pushes forward: the FRD body pitch in the quaternion is negative."""
    target = attitude_target(MAP, G, 0.0, 0.2, math.pi / 2)
    assert quaternion_to_euler(target.q)[1] == pytest.approx(-0.2)


def test_quaternion_to_euler_inverts_euler_to_quaternion() -> None:
    for angles in [(0.1, -0.2, 0.3), (-1.0, 1.2, -3.0), (0.0, 0.0, math.pi / 2)]:
        assert quaternion_to_euler(euler_to_quaternion(*angles)) == pytest.approx(angles)


def test_a_bad_hover_throttle_is_refused() -> None:
    target = attitude_target(MAP, G, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="hover throttle"):
        attitude_from_target(MAP, target, hover=0.0)
