"""The control step of a simulated fleet, its route-following drones computed together.

A mission's control loop asks every agent, in turn, for this step's setpoints
(:meth:`Agent.control_step <btmission.runtime.agent.Agent.control_step>`). A drone following a
route (most of a fleet's drones, most of the time) makes four compiled calls — the carrot on its
route, the LiDAR scan, the neighbours on the bus, the APF — with Python between them; at 30 drones
that Python was most of the step. :class:`FleetFollow` makes those calls for all such drones in
one (:func:`~btmission.runtime._fleet_kernels.fleet_follow`), then walks the agents in the loop's order: a drone of the batch takes its result
(:meth:`Navigator.finish_batch <btmission.runtime.navigation.Navigator.finish_batch>`) and shares
where it is; every other agent — and a drone whose step needs its map (it may have arrived, or
its route ends on the ground) or has stopped making progress — runs its own step, as before.

The result is the per-drone loop's, to the bit: the same kernels on the same numbers, and each
drone sees its neighbours as that loop shows them (those before it in the loop already moved on
the bus, those after it not yet: :mod:`btmission.runtime._fleet_kernels`).

It applies only where that equivalence is plain, checked when the run is built
(:meth:`FleetFollow.build`): one process on the embedded simulator with the in-memory bus,
every agent a drone under the tracking controller whose LiDAR is the simulator's without dust
(dust draws from the simulator's generator, in the agents' order). Each step it also needs
every agent on the bus sharing where it is (no trajectories, no agent gone); otherwise, and with
fewer than :data:`MIN_BATCH` drones following routes, the loop is the per-drone one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from btmission.backends.base import VehicleKind
from btmission.backends.mapsensors import sphere_points
from btmission.backends.sim import SimVehicle
from btmission.runtime.bus import InMemoryAgentLink, InMemoryBus
from btmission.runtime.navigation import (
    AGENT_APF,
    CARROT_WINDOW,
    POSITION_GAIN,
    SETTLED_M_S,
    Navigator,
)
from btmission.types import FloatArray

if TYPE_CHECKING:
    from btmission.runtime.agent import Agent
    from btmission.runtime.loops import AgentRuntime

MIN_BATCH = 2
"""Drones following routes below which a step takes the per-drone loop (nothing to share)."""


class FleetFollow:
    """The control step of a fleet (module docstring); :meth:`build` decides whether it applies."""

    def __init__(
        self,
        sides: Sequence[AgentRuntime],
        bus: InMemoryBus,
        within_m: float,
    ) -> None:
        self.sides = list(sides)
        self._members: list[tuple[AgentRuntime, Agent, Navigator, SimVehicle]] = []
        for side in self.sides:
            b = side.agent.navigator.backend
            assert isinstance(b, SimVehicle)
            self._members.append((side, side.agent, side.agent.navigator, b))
        self.bus = bus
        self.within_m = float(within_m)
        first = self.sides[0].agent
        backend = first.navigator.backend
        assert isinstance(backend, SimVehicle)
        self.sim = backend.sim
        cells = self.sim.world.cells
        self._cells = (cells.points, cells.starts, cells.lo, float(cells.cell), cells.dims)
        self._radius = float(self.sim.config.lidar_range_m)
        self._sphere = sphere_points()
        nav = first.navigator
        cfg = nav.config
        self._look = float(cfg.lookahead_m)
        self._tol = float(cfg.tolerance_m)
        self._speed = float(cfg.speed_m_s)
        assert nav._apf is not None
        self._field = nav._apf.config.packed
        self._agents = AGENT_APF[VehicleKind.MULTIROTOR].packed
        self._routes: tuple[object, ...] = ()
        self._table = np.zeros((0, 9))
        self._offsets = np.zeros(1, dtype=np.int64)
        self.batched = 0
        """Drone control steps computed in the batch (the rest took the per-drone path)."""

    @classmethod
    def build(
        cls, sides: Sequence[AgentRuntime], bus: InMemoryBus, within_m: float
    ) -> FleetFollow | None:
        """A :class:`FleetFollow` for these agents, or None where it does not apply (module
        docstring)."""
        if len(sides) < MIN_BATCH:
            return None
        sim = None
        configs = set()
        for side in sides:
            a = side.agent
            nav = a.navigator
            b = nav.backend
            if type(b) is not SimVehicle or b.kind is not VehicleKind.MULTIROTOR:
                return None
            if sim is None:
                sim = b.sim
            if b.sim is not sim or nav.controller != "track":
                return None
            if nav.sensors is not b or not b.owns_sensors:  # its LiDAR: the simulator's
                return None
            link = a.link
            if not isinstance(link, InMemoryAgentLink) or link.bus is not bus:
                return None
            if nav._apf is None:
                return None
            c = nav.config
            configs.add(
                (c.lookahead_m, c.tolerance_m, c.speed_m_s, nav._apf.config.packed.tobytes())
            )
        assert sim is not None
        if sim.config.dust_points or len(configs) != 1:
            return None
        return cls(sides, bus, within_m)

    def _route_table(self, routes: Sequence[object], tables: Sequence[FloatArray]) -> None:
        """The batch's route tables, stacked (rebuilt when a drone's route changed)."""
        key = tuple(routes)
        if key == self._routes:
            return
        self._routes = key
        self._table = np.ascontiguousarray(np.concatenate(tables))
        self._offsets = np.concatenate([[0], np.cumsum([len(t) for t in tables])]).astype(np.int64)

    def control(self, now: float) -> None:
        """This step's setpoints for every agent, in the loop's order (module docstring)."""
        bus = self.bus
        n = len(bus._row_names)
        if bus._trajectories or n != len(self.sides):
            return self._each(now)
        members = self._members
        batch = []
        for k, (_, a, nav, _) in enumerate(members):
            if a.alive:
                cmd = nav.batch_route()
                if cmd is not None:
                    batch.append((k, cmd))
        if len(batch) < MIN_BATCH:
            return self._each(now)
        prev = bus._starts[:n]
        if np.isnan(prev).any():  # an agent gone, or one that shares a 2D position
            return self._each(now)
        from btmission.runtime._fleet_kernels import fleet_follow

        rows = bus._rows
        rank = np.full(n, len(members), dtype=np.int64)
        cur = prev.copy()
        tels = []
        for k, (_, a, _, b) in enumerate(members):
            tel = b.telemetry()
            tels.append(tel)
            if a.alive:
                r = rows[a.id]
                rank[r] = k
                cur[r] = tel.position
        table = self.sim.bodies()
        index = table.index
        states, poses, targets, tables, routes = [], [], [], [], []
        seg, body, ground, own_row, own_rank, prev_f = [], [], [], [], [], []
        for k, cmd in batch:
            _, a, nav, b = members[k]
            tel = tels[k]
            states.append([*tel.position.tolist(), *tel.velocity.tolist(), tel.yaw])
            veh = b.vehicle
            x = veh.x
            poses.append((x[0], x[1], x[2], veh.yaw))
            targets.append(cmd.target)
            routes.append(cmd.route)
            tables.append(cmd.route._table)
            seg.append(cmd.seg)
            body.append(index[a.id])
            ground.append(cmd.ground_goal)
            own_row.append(rows[a.id])
            own_rank.append(k)
            prev_f.append(nav._apf_previous)
        self._route_table(routes, tables)
        out = fleet_follow(
            self._table, self._offsets, np.array(seg, dtype=np.int64),
            np.array(states, dtype=float), np.array(poses, dtype=float),
            np.array(body, dtype=np.int64), np.array(targets, dtype=float),
            np.array(ground, dtype=np.bool_), np.array(prev_f, dtype=float),
            *self._cells, self._radius, table.centres, table.radii, self._sphere,
            prev, cur, rank, np.array(own_row, dtype=np.int64), np.array(own_rank, dtype=np.int64),
            self.within_m, CARROT_WINDOW, self._look, self._tol, SETTLED_M_S, self._speed,
            POSITION_GAIN, self._field, self._agents,
        )  # fmt: skip
        j = 0
        for k, (side, a, nav, _) in enumerate(members):
            if j < len(batch) and batch[j][0] == k:
                if nav.finish_batch(now, tels[k], out[j]):
                    assert nav.prediction is not None
                    a.link.share_prediction(now, nav.prediction)
                    self.batched += 1
                else:
                    side.control(now)
                j += 1
            else:
                side.control(now)
        return None

    def _each(self, now: float) -> None:
        for side in self.sides:
            side.control(now)
