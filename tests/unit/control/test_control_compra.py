"""COMPRA exploration, breadcrumb return (seed 002 Alg. 2) and object localisation (§3.3.1)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from btmission.control.compra import (
    BreadcrumbTrail,
    CameraIntrinsics,
    CompraConfig,
    CompraExplorer,
    Detection,
    LocalizerConfig,
    Mode,
    ObjectLocalizer,
    altitude_from_range,
    carrot_waypoint,
)
from btmission.control.examples import explore_tunnel
from btmission.control.scenes import bending_tunnel


def test_altitude_and_carrot() -> None:
    assert altitude_from_range(2.0, 0.0, 0.0) == 2.0
    assert altitude_from_range(2.0, 0.1, 0.2) == pytest.approx(2.0 * math.cos(0.1) * math.cos(0.2))
    # yaw 90°, flying 0.3 m too low: the carrot is 1 m to the left (+y) and 0.3 m up
    wp = carrot_waypoint([5.0, 2.0, 1.2], math.pi / 2, altitude_m=1.2, mission_altitude_m=1.5)
    np.testing.assert_allclose(wp, [5.0, 3.0, 1.5], atol=1e-12)
    with pytest.raises(ValueError, match="range"):
        altitude_from_range(-1.0, 0.0, 0.0)


def test_breadcrumbs_recorded_at_rate_and_consumed_from_the_end() -> None:
    trail = BreadcrumbTrail(rate_hz=2.0, radius_m=0.5)
    recorded = [trail.record(t, [t, 0.0, 1.0], 0.0) for t in np.arange(0.0, 5.0, 0.1)]
    assert sum(recorded) == 10  # every 0.5 s over 5 s
    assert trail.target() is not None and trail.target().position == pytest.approx((4.5, 0.0, 1.0))
    assert trail.consume([2.0, 0.0, 1.0]) == 0  # near crumbs in the middle: not the tail, kept
    assert trail.consume([4.4, 0.0, 1.0]) == 2  # the tail and its neighbour within 0.5 m
    assert trail.target().position == pytest.approx((3.5, 0.0, 1.0))
    with pytest.raises(ValueError, match="positive"):
        BreadcrumbTrail(rate_hz=0.0)


def test_explore_then_return_along_breadcrumbs_then_land() -> None:
    """A point MAV follows the commands: out along a curve for the time budget, back, land."""
    cfg = CompraConfig(mission_time_s=20.0, breadcrumb_rate_hz=1.0, breadcrumb_radius_m=0.6)
    explorer = CompraExplorer(cfg)
    p = np.array([0.0, 0.0, 1.0])
    yaw = 0.0
    dt = 0.1
    t = 0.0
    outbound: list[np.ndarray] = []
    modes: list[Mode] = []
    while t < 120.0:
        cmd = explorer.step(t, p, yaw, altitude_m=p[2], dphr_yaw_rate=0.05)
        modes.append(cmd.mode)
        if cmd.mode is Mode.LAND:
            break
        if cmd.mode is Mode.EXPLORE:
            assert cmd.yaw_ref is None and cmd.yaw_rate_ref == 0.05
            yaw += cmd.yaw_rate_ref * dt  # DPHR turns the MAV slowly left
            outbound.append(p.copy())
        else:
            assert cmd.yaw_ref is not None
            yaw = cmd.yaw_ref
        # track the waypoint at up to 0.8 m/s
        err = cmd.waypoint - p
        p = p + err / max(1.0, np.linalg.norm(err) / (0.8 * dt))
        t += dt
    assert modes[0] is Mode.EXPLORE and Mode.RETURN in modes and modes[-1] is Mode.LAND
    first_return = modes.index(Mode.RETURN)
    assert first_return * dt == pytest.approx(cfg.mission_time_s, abs=dt * 1.5)
    assert np.linalg.norm(outbound[-1][:2]) > 8.0  # it did get away from the start
    assert p[2] == pytest.approx(1.5, abs=0.05)  # mission altitude held
    assert np.linalg.norm(p[:2]) < 1.0 + cfg.breadcrumb_radius_m  # back at the first crumb
    assert len(explorer.trail) == 0


# ----------------------------------------------------------------------------------------------
CAM = CameraIntrinsics(fx=400.0, fy=400.0, cx=320.0, cy=240.0)


def _scene(depth_m: float) -> np.ndarray:
    img = np.zeros((480, 640))
    img[200:280, 280:360] = depth_m  # the object
    return img


def _detection(
    t: float, label: str = "survivor", prob: float = 0.9, width_px: float = 80.0
) -> Detection:
    return Detection(
        t=t, label=label, probability=prob, bbox=(320 - width_px / 2, 200.0, width_px, 80.0)
    )


def test_localizer_back_projects_to_the_world() -> None:
    loc = ObjectLocalizer(LocalizerConfig(time_window_s=1.0))
    # camera 2 m along +x looking along world +x: optical z → world x, x → −y, y → −z
    rot = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert loc.add(_detection(0.0), _scene(3.0), CAM, rot, [2.0, 0.0, 1.0])
    assert loc.update(0.5) == []  # the time window has not passed
    objects = loc.update(1.2)
    assert len(objects) == 1
    np.testing.assert_allclose(objects[0].position, [5.0, 0.0, 1.0], atol=1e-9)
    assert loc.buffered == 0


def test_localizer_rejects_low_probability_out_of_range_and_wrong_width() -> None:
    cfg = LocalizerConfig(probability_threshold=0.6, width_bounds_m={"survivor": (0.3, 1.0)})
    loc = ObjectLocalizer(cfg)
    assert not loc.add(_detection(0.0, prob=0.5), _scene(3.0), CAM)
    assert not loc.add(_detection(0.0), _scene(7.0), CAM)  # beyond the 5 m sphere
    assert not loc.add(_detection(0.0, width_px=20.0), _scene(3.0), CAM)  # 0.15 m: too narrow
    assert not loc.add(_detection(0.0, width_px=200.0), _scene(3.0), CAM)  # 1.5 m: too wide
    assert not loc.add(_detection(0.0), np.zeros((480, 640)), CAM)  # no depth at the centroid
    assert loc.rejected == {"probability": 1, "range": 1, "width": 2, "depth": 1}
    assert loc.add(_detection(0.0), _scene(3.0), CAM)  # 0.6 m wide at 3 m: accepted
    assert loc.add(
        _detection(0.0, label="drill", width_px=20.0), _scene(3.0), CAM
    )  # unchecked class
    assert loc.buffered == 2


def test_localizer_clusters_and_merges_repeated_detections() -> None:
    loc = ObjectLocalizer(
        LocalizerConfig(time_window_s=1.0, cluster_distance_m=0.5, merge_radius_m=1.0)
    )
    rng = np.random.default_rng(0)
    # two survivors 3 m apart seen in one buffer session, plus a phone
    for k in range(6):
        loc.add(
            _detection(0.1 * k), _scene(3.0 + rng.normal(0, 0.03)), CAM, translation=[0.0, 0.0, 0.0]
        )
        loc.add(
            _detection(0.1 * k), _scene(3.0 + rng.normal(0, 0.03)), CAM, translation=[3.0, 0.0, 0.0]
        )
    loc.add(_detection(0.6, label="phone"), _scene(2.0), CAM)
    touched = loc.update(2.0)
    assert sorted((o.label, o.observations) for o in touched) == [
        ("phone", 1),
        ("survivor", 6),
        ("survivor", 6),
    ]
    assert len(loc.objects) == 3
    # a later session sees the first survivor again: merged, not a new object
    for k in range(4):
        loc.add(_detection(10.0 + 0.1 * k), _scene(3.1), CAM, translation=[0.05, 0.0, 0.0])
    (merged,) = loc.update(12.0)
    assert len(loc.objects) == 3
    assert merged.observations == 10
    first = next(o for o in loc.objects if o.label == "survivor" and o.position[0] < 1.0)
    assert first is merged
    np.testing.assert_allclose(first.position[2], (6 * 3.0 + 4 * 3.1) / 10, atol=0.05)
    assert [label for label, _ in loc.object_list()] == ["phone", "survivor", "survivor"]


def test_localizer_bad_inputs() -> None:
    with pytest.raises(ValueError, match="probability_threshold"):
        LocalizerConfig(probability_threshold=1.5)
    with pytest.raises(ValueError, match="width bounds of 'x'"):
        LocalizerConfig(width_bounds_m={"x": (1.0, 0.5)})
    with pytest.raises(ValueError, match="focal"):
        CameraIntrinsics(0.0, 1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="bounding box"):
        ObjectLocalizer().add(Detection(0.0, "a", 0.9, (1.0, 1.0, 0.0, 5.0)), _scene(2.0), CAM)
    with pytest.raises(ValueError, match="position"):
        CompraExplorer().step(0.0, [0.0, 0.0], 0.0, 1.0)
    with pytest.raises(ValueError, match="altitude and carrot step must be positive"):
        CompraConfig(mission_altitude_m=0.0)
    with pytest.raises(ValueError, match="time_window_s"):
        LocalizerConfig(time_window_s=-1.0)
    with pytest.raises(ValueError, match="width/2 < radius"):
        bending_tunnel("left", width_m=12.0, radius_m=5.0)


@pytest.mark.parametrize("bend", ["left", "right"])
def test_compra_explores_a_bending_tunnel_and_comes_back(bend: str) -> None:
    """Carrot + DPHR + APF out through the bend for the time budget, breadcrumbs back, land."""
    log = explore_tunnel(bend, mission_time_s=14.0)
    assert log.modes[0] == "explore" and log.modes[-1] == "land"
    side = 1.0 if bend == "left" else -1.0
    far = log.positions[np.argmax(np.linalg.norm(log.positions[:, :2], axis=1))]
    assert far[0] > 7.0 and side * far[1] > 3.0  # followed the tunnel round the bend
    last_explore = max(k for k, m in enumerate(log.modes) if m == "explore")
    assert side * log.yaws[last_explore] > 0.5  # heading turned with the tunnel
    assert np.max(side * log.yaw_rates) > 0  # DPHR turned it the bend's way
    assert log.clearance.min() >= 0.6  # APF r_c kept from the walls throughout
    assert np.linalg.norm(log.positions[-1, :2] - log.breadcrumbs[0, :2]) < 1.0  # landed at home
