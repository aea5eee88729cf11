"""Backend setpoints as MAVLink targets: masks, frames, and the NMPC's attitude (seed 002)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation

from btmission.backends.mavlink_frames import LocalFrame
from btmission.backends.mavlink_setpoints import (
    G,
    attitude_target,
    euler_to_quaternion,
    position_target,
    velocity_target,
)
from btmission.control.mav_model import MavParams, mav_dynamics

MAP = LocalFrame((10.0, 5.0, 0.0))  # north = world +y


def test_attitude_targets_ignore_no_body_rate() -> None:
    """ArduCopter discards an attitude target whose mask ignores some body rates but not all
    (seen on ArduCopter SITL with mask 3); PX4 reads attitude and yaw rate with mask 0."""
    a = attitude_target(LocalFrame((0.0, 0.0, 0.0)), 9.81, 0.1, 0.0, 0.0, 0.2)
    assert a.type_mask == 0


def test_the_masks_are_the_dialects_bits() -> None:
    bits = {v.name: k for k, v in mavlink.enums["POSITION_TARGET_TYPEMASK"].items()}
    pos = position_target(MAP, (10.0, 5.0, 2.0))
    assert (
        pos.type_mask
        == (
            bits["POSITION_TARGET_TYPEMASK_VX_IGNORE"]
            | bits["POSITION_TARGET_TYPEMASK_VY_IGNORE"]
            | bits["POSITION_TARGET_TYPEMASK_VZ_IGNORE"]
            | bits["POSITION_TARGET_TYPEMASK_AX_IGNORE"]
            | bits["POSITION_TARGET_TYPEMASK_AY_IGNORE"]
            | bits["POSITION_TARGET_TYPEMASK_AZ_IGNORE"]
            | bits["POSITION_TARGET_TYPEMASK_YAW_IGNORE"]
            | bits["POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE"]
        )
        == 0b1101_1111_1000
    )  # position only: 3576, what PX4's offboard guide sends
    vel = velocity_target(MAP, (1.0, 0.0, 0.0), 0.2)
    assert vel.type_mask == 0b0101_1100_0111  # velocity + yaw rate: 1479
    full = position_target(MAP, (11.0, 5.0, 2.0), (0.5, 0.0, 0.0), yaw=0.0)
    assert full.type_mask == 0b1001_1100_0000  # position, velocity, yaw: 2496


def test_positions_velocities_and_yaws_go_to_the_local_frame() -> None:
    t = position_target(MAP, (11.0, 7.0, 3.0), (0.0, 1.0, -0.5), yaw=0.0)
    np.testing.assert_allclose(t.position, (2.0, 1.0, -3.0), atol=1e-12)  # north 2, east 1, up 3
    np.testing.assert_allclose(t.velocity, (1.0, 0.0, 0.5), atol=1e-12)
    assert t.yaw == pytest.approx(math.pi / 2)  # facing world +x = east
    v = velocity_target(MAP, (1.0, 0.0, 0.0), yaw_rate=0.3)
    np.testing.assert_allclose(v.velocity, (0.0, 1.0, 0.0), atol=1e-12)
    assert v.yaw_rate == -0.3  # counter-clockwise in the world is anticlockwise = negative in NED


def test_the_targets_encode_as_mavlink_messages() -> None:
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    t = position_target(MAP, (11.0, 7.0, 3.0), yaw=math.pi / 2)
    msg = mav.set_position_target_local_ned_encode(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, t.type_mask, *t.position, *t.velocity,
        0.0, 0.0, 0.0, t.yaw, t.yaw_rate,
    )  # fmt: skip
    back = mav.decode(bytearray(msg.pack(mav)))
    assert back.type_mask == t.type_mask and back.x == pytest.approx(2.0)
    a = attitude_target(MAP, G, 0.1, 0.2, 0.0, 0.1)
    msg = mav.set_attitude_target_encode(0, 1, 1, a.type_mask, a.q, 0.0, 0.0, a.body_yaw_rate,
                                         a.thrust)  # fmt: skip
    back = mav.decode(bytearray(msg.pack(mav)))
    np.testing.assert_allclose(back.q, a.q, atol=1e-6)
    assert back.thrust == pytest.approx(0.5)  # hover thrust at T = g


@pytest.mark.parametrize("north_yaw", [math.pi / 2, 0.0, 2.0])
@pytest.mark.parametrize(("phi", "theta", "yaw"), [(0.2, 0.0, 0.0), (0.0, 0.3, 0.0),
                                                   (-0.15, 0.25, 1.0), (0.1, -0.2, -2.5)])  # fmt: skip
def test_the_attitude_accelerates_as_the_seed_002_model_says(
    north_yaw: float, phi: float, theta: float, yaw: float
) -> None:
    """Thrust along the FRD body's −z, rotated by the target quaternion into NED and back to the
    world, equals the seed 002 model's acceleration (yaw frame, rotated by the heading)."""
    frame = LocalFrame((0.0, 0.0, 0.0), north_yaw)
    thrust = 11.0
    a = attitude_target(frame, thrust, phi, theta, yaw)
    w, x, y, z = a.q
    ned = Rotation.from_quat([x, y, z, w]).apply([0.0, 0.0, -thrust])  # thrust up the body
    world = frame.vector_to_world(ned) - np.array([0.0, 0.0, G])
    p = MavParams(drag=(0.0, 0.0, 0.0))
    state = np.array([0, 0, 0, 0, 0, 0, phi, theta], dtype=float)
    acc_yaw_frame = mav_dynamics(state, [thrust, phi, theta], p)[3:6]
    c, s = math.cos(yaw), math.sin(yaw)
    want = np.array([c * acc_yaw_frame[0] - s * acc_yaw_frame[1],
                     s * acc_yaw_frame[0] + c * acc_yaw_frame[1], acc_yaw_frame[2]])  # fmt: skip
    np.testing.assert_allclose(world, want, atol=1e-9)


def test_thrust_is_normalised_and_clipped() -> None:
    assert attitude_target(MAP, 2 * G, 0, 0, 0, hover=0.4).thrust == pytest.approx(0.8)
    assert attitude_target(MAP, 4 * G, 0, 0, 0).thrust == 1.0
    assert attitude_target(MAP, -1.0, 0, 0, 0).thrust == 0.0
    with pytest.raises(ValueError, match=r"hover throttle must be in \(0, 1\]"):
        attitude_target(MAP, G, 0, 0, 0, hover=0.0)
    assert euler_to_quaternion(0.0, 0.0, 0.0) == (1.0, 0.0, 0.0, 0.0)
