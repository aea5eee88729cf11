"""The fake provider's refused arming (:meth:`FakeVehicle.refuse_arming`): what tests of the
runtime's retries make a vehicle do."""

from __future__ import annotations

import pytest

from btmission.backends.fake import SAME_REQUEST_S, FakeProvider, FakeVehicle
from btmission.vehicles.base import VehicleKind


def drone() -> tuple[FakeProvider, FakeVehicle]:
    provider = FakeProvider()
    vehicle = provider.attach("R1", VehicleKind.MULTIROTOR, (0.0, 0.0, 0.0)).backend
    assert isinstance(vehicle, FakeVehicle)
    return provider, vehicle


def test_the_first_requests_are_refused_then_arming_is_accepted() -> None:
    provider, v = drone()
    v.refuse_arming(2, "PreArm: estimator not ready")
    for _ in range(2):  # two requests, each asked again every tick for a second
        for _ in range(10):
            ack = v.arm()
            assert not ack and ack.transient and ack.reason == "PreArm: estimator not ready"
            provider.step(0.1)
        provider.step(SAME_REQUEST_S + 0.1)  # a pause: the next call is a new request
    assert v.arm() and v.telemetry().armed


def test_always_refused_and_a_final_refusal() -> None:
    provider, v = drone()
    v.refuse_arming(None, "battery too low (5%)", transient=False)
    for _ in range(5):
        ack = v.arm()
        assert not ack and not ack.transient
        provider.step(2.0)
    v.refuse_arming(0)  # stop refusing
    assert v.arm()


def test_a_negative_count_is_refused() -> None:
    _, v = drone()
    with pytest.raises(ValueError, match="requests must be ≥ 0 or None"):
        v.refuse_arming(-1)
