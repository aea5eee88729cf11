"""The separation rule between drones (:data:`~btmission.runtime.navcontrol.AGENT_SEPARATION`),
flown: two simulated drones whose navigators share where they are and how they move on the
in-memory bus, as a run wires them — a take-off under a hovering drone waits its turn, two
drones meeting head-on pass each other, a follower stops behind a leader that stops dead."""

from __future__ import annotations

import math

import numpy as np

from btmission.backends.sim import Simulator
from btmission.links.bus import InMemoryAgentLink, InMemoryBus, neighbour_states
from btmission.runtime.navconfig import NavState
from btmission.runtime.navigation import Navigator
from btmission.vehicles.base import Mode
from btmission.world.voxel import OCCUPIED, VoxelMap

CONTACT_M = 0.5
"""Two 0.25 m drone bodies touch below this distance between their centres."""


def _room() -> VoxelMap:
    """A 24 m × 10 m × 6 m box of rock around open space, floor top at z = 0."""
    vm = VoxelMap.empty((24, 10, 6), 0.5, origin=(0.0, 0.0, -0.5))
    st = vm.state
    st[0, :, :] = st[-1, :, :] = OCCUPIED
    st[:, 0, :] = st[:, -1, :] = OCCUPIED
    st[:, :, 0] = st[:, :, -1] = OCCUPIED
    return vm


class Pair:
    """Drones in one simulator, each with a tracking navigator; ``shared``: whether they share
    their positions and velocities on a bus (without it neither sees the other)."""

    def __init__(self, starts: list[tuple[float, float, float]], shared: bool = True) -> None:
        self.sim = Simulator(_room(), seed=1)
        self.bus = InMemoryBus()
        self.t = 0.0
        self.min_distance = math.inf
        self.navs: list[Navigator] = []
        self.links: list[InMemoryAgentLink] = []
        for i, start in enumerate(starts):
            veh = self.sim.add_multirotor(f"R{i + 1}", start)
            link = self.bus.agent_link(f"R{i + 1}")

            def neighbours(agent: str, pos: np.ndarray, _link: InMemoryAgentLink = link):
                return neighbour_states(_link, self.t, 0.1, pos, 6.0)

            nav = Navigator(
                f"R{i + 1}", veh, veh, "track", neighbours=neighbours if shared else None
            )
            self.navs.append(nav)
            self.links.append(link)
        for _ in range(24):  # PX4: setpoints stream before OFFBOARD
            for nav in self.navs:
                nav.backend.set_position_setpoint(nav.backend.telemetry().position)
            self.step_sim()
        for nav in self.navs:
            assert nav.backend.arm() and nav.backend.set_mode(Mode.OFFBOARD)

    def step_sim(self) -> None:
        self.sim.step()
        self.t += self.sim.config.step_s
        p = [nav.backend.telemetry().position for nav in self.navs]
        for i in range(len(p)):
            for j in range(i + 1, len(p)):
                self.min_distance = min(self.min_distance, float(np.linalg.norm(p[i] - p[j])))

    def fly(self, seconds: float) -> None:
        for _ in range(round(seconds / self.sim.config.step_s)):
            for nav, link in zip(self.navs, self.links):
                nav.step(self.t)
                link.share_prediction(self.t, nav.prediction, nav.shared_velocity)
            self.step_sim()

    def position(self, i: int) -> np.ndarray:
        return self.navs[i].backend.telemetry().position


def _route(a: tuple[float, float, float], b: tuple[float, float, float]) -> np.ndarray:
    return np.linspace(a, b, 30)


def test_a_take_off_under_a_hovering_drone_waits_until_it_has_gone() -> None:
    """R1 hovers 1.6 m up beside R2's pad (0.3 m off its column); where R2's take-off ends
    (2 m up) is 0.5 m from R1. R2 climbs round R1 no closer than the stand-off and waits beside
    it; once R1 has flown off, R2 takes its place over its pad."""
    pair = Pair([(3.0, 5.0, 0.0), (6.3, 5.0, 0.0)])
    r1, r2 = pair.navs
    r1.takeoff(1.6)
    pair.fly(3.0)
    r1.follow(_route((3.0, 5.0, 1.6), (6.0, 5.0, 1.6)), (6.0, 5.0, 1.6), pair.t)
    pair.fly(6.0)
    assert r1.status.state is NavState.ARRIVED
    pair.min_distance = math.inf
    r2.takeoff(2.0)
    pair.fly(8.0)
    spot = np.array([6.3, 5.0, 2.0])
    assert float(np.linalg.norm(pair.position(1) - spot)) > 0.3  # not in its place
    assert pair.min_distance > 0.9
    r1.follow(_route((6.0, 5.0, 1.6), (16.0, 5.0, 1.6)), (16.0, 5.0, 1.6), pair.t)
    pair.fly(8.0)
    assert float(np.linalg.norm(pair.position(1) - spot)) < 0.2  # its turn came
    assert pair.min_distance > 0.9


def _head_on(shared: bool) -> Pair:
    pair = Pair([(3.0, 5.0, 0.0), (21.0, 5.0, 0.0)], shared)
    for nav in pair.navs:
        nav.takeoff(2.0)
    pair.fly(3.0)
    a, b = (3.0, 5.0, 2.0), (21.0, 5.0, 2.0)
    pair.navs[0].follow(_route(a, b), b, pair.t)
    pair.navs[1].follow(_route(b, a), a, pair.t)
    pair.fly(25.0)
    return pair


def test_two_drones_meeting_head_on_keep_apart_and_pass() -> None:
    """On one line towards each other at 1.5 m/s (closing at 3 m/s, the hardest meeting): they
    stay well clear of contact (0.72 m at the closest: the stand-off less what the velocity
    loop's lag costs), sidestep and both reach the other end. Without sharing where they are
    (no rule, no APF between them) the same flight is a collision."""
    pair = _head_on(shared=True)
    assert pair.min_distance > 0.65
    assert [nav.status.state for nav in pair.navs] == [NavState.ARRIVED, NavState.ARRIVED]
    blind = _head_on(shared=False)
    assert blind.min_distance < CONTACT_M


def test_a_follower_stops_behind_a_leader_that_stops_dead() -> None:
    """R2 follows R1 along a line 3 m behind it, both at cruise speed; R1 stops where it is: R2
    stops behind it, well clear of contact (0.74 m at the closest)."""
    pair = Pair([(6.0, 5.0, 0.0), (3.0, 5.0, 0.0)])
    for nav in pair.navs:
        nav.takeoff(2.0)
    pair.fly(3.0)
    end = (22.0, 5.0, 2.0)
    pair.navs[0].follow(_route((6.0, 5.0, 2.0), end), end, pair.t)
    pair.navs[1].follow(_route((3.0, 5.0, 2.0), end), end, pair.t)
    pair.fly(5.0)
    lead = pair.navs[0].backend.telemetry()
    assert float(np.linalg.norm(lead.velocity)) > 1.2  # both cruising
    pair.navs[0].hold()
    pair.fly(4.0)
    assert pair.min_distance > 0.65
    assert pair.position(1)[0] < pair.position(0)[0]  # still behind it
