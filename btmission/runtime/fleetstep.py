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
(:meth:`FleetFollow.build`): one process whose vehicle provider computes its vehicles' LiDAR
itself and offers it (:class:`~btmission.vehicles.provider.FleetSensing`: the embedded
simulator without dust, which draws from the simulator's generator in the agents' order), with
the in-memory bus, every agent a drone under the tracking controller whose LiDAR that provider
covers. Each step it also needs
every agent to have shared where it is on the bus (none a trajectory; an agent killed since
leaves a row no query returns, as on the bus); otherwise, and with fewer than
:data:`MIN_BATCH` drones following routes, the loop is the per-drone one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, cast

import numpy as np
from numpy.typing import NDArray

from btmission.links.bus import InMemoryAgentLink, InMemoryBus
from btmission.runtime.navcommands import _Follow
from btmission.runtime.navcontrol import AGENT_APF, AGENT_SEPARATION, CARROT_WINDOW
from btmission.runtime.navigation import POSITION_GAIN, SETTLED_M_S, Navigator
from btmission.types import FloatArray
from btmission.vehicles.base import Backend, VehicleKind
from btmission.vehicles.provider import BodyTable, FleetSensing

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
        sensing: FleetSensing,
    ) -> None:
        self.sides = list(sides)
        self.sensing = sensing
        self._members: list[tuple[AgentRuntime, Agent, Navigator, Backend]] = []
        for side in self.sides:
            nav = side.agent.navigator
            self._members.append((side, side.agent, nav, nav.backend))
        self._agent_list = [m[1] for m in self._members]
        self._navs = [m[2] for m in self._members]
        self._backends = [m[3] for m in self._members]
        self._ranks = np.arange(len(self._members), dtype=np.int64)
        """Each agent's place in the loop (its rank for the rows it shares)."""
        self._own_row: NDArray[np.int64] | None = None
        self._body = np.zeros(0, dtype=np.int64)
        self._bodies_for = -1
        self._cmds_key: tuple[int, ...] = ()
        self._cmds: list[_Follow] = []
        self._targets = np.zeros((0, 3))
        self._ground = np.zeros(0, dtype=np.bool_)
        self.bus = bus
        self.within_m = float(within_m)
        self._cells = sensing.cells
        self._radius = float(sensing.lidar_range_m)
        self._sphere = sensing.sphere
        nav = self._navs[0]  # (build checked: every navigator has the same settings)
        cfg = nav.config
        self._look = float(cfg.lookahead_m)
        self._tol = float(cfg.tolerance_m)
        self._speed = float(cfg.speed_m_s)
        assert nav._apf is not None
        self._field = nav._apf.config.packed
        self._agents = AGENT_APF[VehicleKind.MULTIROTOR].packed
        self._separation = AGENT_SEPARATION[VehicleKind.MULTIROTOR].packed
        self._table = np.zeros((0, 9))
        self._offsets = np.zeros(1, dtype=np.int64)
        self.batched = 0
        """Drone control steps computed in the batch (the rest took the per-drone path)."""
        self._warm_up()

    @classmethod
    def build(
        cls,
        sides: Sequence[AgentRuntime],
        bus: InMemoryBus,
        within_m: float,
        sensing: FleetSensing | None,
    ) -> FleetFollow | None:
        """A :class:`FleetFollow` for these agents, with what their vehicles' provider offers
        (``sensing``), or None where it does not apply (module docstring)."""
        if sensing is None or len(sides) < MIN_BATCH:
            return None
        configs = set()
        for side in sides:
            a = side.agent
            nav = a.navigator
            if nav.controller != "track" or not sensing.covers(nav.backend, nav.sensors):
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
        if len(configs) != 1:
            return None
        return cls(sides, bus, within_m, sensing)

    def control(self, now: float) -> None:
        """This step's setpoints for every agent, in the loop's order (module docstring)."""
        bus = self.bus
        members = self._members
        n = len(bus._row_names)
        if bus._trajectories or n != len(members):
            return self._each(now)
        navs = self._navs
        alive = [a.alive for a in self._agent_list]
        batch = [
            k for k, nav in enumerate(navs) if alive[k] and type(nav._cmd) is _Follow
        ]  # (every navigator here is a tracking multirotor's: build checked)
        if len(batch) < MIN_BATCH:
            return self._each(now)
        prev = bus._starts[:n]  # (a killed agent's row is NaN: never a neighbour, as on the bus)
        vprev = bus._vel[:n]
        if self._own_row is None:  # (rows never change once the bus has them all)
            rows = {name: r for r, name in enumerate(bus._row_names)}
            self._own_row = np.array([rows[a.id] for a in self._agent_list], dtype=np.int64)
        own_row = self._own_row
        tels = [b.telemetry() for b in self._backends]
        pos = np.array([t.position for t in tels])
        pos.flags.writeable = False  # (its rows are the drones' shared positions: (1, 3) views)
        where = pos.reshape(-1, 1, 3)
        xy = pos[:, :2].tolist()
        vel = np.array([t.velocity for t in tels])  # (shared with the positions)
        rank = np.full(n, len(members), dtype=np.int64)
        cur = prev.copy()
        vcur = vprev.copy()
        if all(alive):
            rank[own_row] = self._ranks
            cur[own_row] = pos
            vcur[own_row] = vel
        else:
            live = np.array(alive, dtype=bool)
            rank[own_row[live]] = self._ranks[live]
            cur[own_row[live]] = pos[live]
            vcur[own_row[live]] = vel[live]
        table = self.sensing.bodies()
        if table.key[1] != self._bodies_for:
            index = table.index
            self._body = np.array([index[a.id] for a in self._agent_list], dtype=np.int64)
            self._bodies_for = table.key[1]
        cmds = cast(list[_Follow], [navs[k]._cmd for k in batch])
        key = tuple(map(id, cmds))
        if key != self._cmds_key:  # new routes: their tables, targets and ground flags
            self._cmds_key = key
            self._cmds = cmds  # (kept: their ids stay theirs)
            self._table = np.ascontiguousarray(np.concatenate([c.route._table for c in cmds]))
            lengths = [len(c.route._table) for c in cmds]
            self._offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
            self._targets = np.array([c.target for c in cmds], dtype=float)
            self._ground = np.array([c.ground_goal for c in cmds], dtype=np.bool_)
        sel = np.array(batch, dtype=np.int64)
        states = np.empty((len(batch), 7))
        states[:, 0:3] = pos[sel]
        states[:, 3:6] = vel[sel]
        states[:, 6] = [tels[k].yaw for k in batch]
        poses = self.sensing.true_poses([self._backends[k] for k in batch])
        out = self._follow(
            np.array([c.seg for c in cmds], dtype=np.int64), states, poses, self._body[sel],
            np.array([navs[k]._apf_previous for k in batch], dtype=float),
            table, prev, cur, vprev, vcur, rank, own_row[sel], sel,
        )  # fmt: skip
        rows = out.tolist()  # (Python floats: the per-row reads cost less, same values)
        apf = out[:, 9:12]
        shares: list[tuple[str, FloatArray]] = []
        first = 0  # (the members sharing: first, first + 1, ... — consecutive, as flushed)
        j = 0
        for k, (side, a, nav, _) in enumerate(members):
            if j < len(batch) and batch[j] == k:
                done = nav.finish_batch(now, rows[j], apf[j], where[k], xy[k], vel[k])
                j += 1
                if done:
                    if not shares:
                        first = k
                    shares.append((a.id, where[k]))
                    continue
            if shares:  # the agents before this one have shared where they are
                self._share(now, shares, first, pos, vel)
                shares = []
            side.control(now)
        if shares:
            self._share(now, shares, first, pos, vel)
        return None

    def _follow(
        self,
        seg0: NDArray[np.int64],
        states: FloatArray,
        poses: FloatArray,
        body: NDArray[np.int64],
        apf_prev: FloatArray,
        table: BodyTable,
        prev: FloatArray,
        cur: FloatArray,
        vprev: FloatArray,
        vcur: FloatArray,
        rank: NDArray[np.int64],
        own_row: NDArray[np.int64],
        own_rank: NDArray[np.int64],
    ) -> FloatArray:
        """The batch's rows of :func:`~btmission.runtime._fleet_kernels.fleet_follow`, with
        the routes of :attr:`_cmds` and this fleet's settings."""
        from btmission.runtime._fleet_kernels import fleet_follow

        out: FloatArray = fleet_follow(
            self._table, self._offsets, seg0, states, poses, body, self._targets, self._ground,
            apf_prev, *self._cells, self._radius, table.centres, table.radii, self._sphere,
            prev, cur, vprev, vcur, rank, own_row, own_rank,
            self.within_m, CARROT_WINDOW, self._look, self._tol, SETTLED_M_S, self._speed,
            POSITION_GAIN, self._field, self._agents, self._separation,
        )  # fmt: skip
        return out

    def _warm_up(self) -> None:
        """Load the compiled step (from numba's cache; compiled if missing) now, while the run
        is built, not at the loop's first batch: :meth:`_follow` for no drone, with arrays made
        as :meth:`control` makes them and the provider's own (``sensing``) — the signature of
        the run's calls."""
        none = np.zeros(0, dtype=np.int64)
        n = len(self.bus._row_names)
        prev = self.bus._starts[:n]
        vprev = self.bus._vel[:n]
        self._follow(
            none, np.empty((0, 7)), np.empty((0, 4)), none, np.zeros((0, 3)),
            self.sensing.bodies(), prev, prev.copy(), vprev, vprev.copy(),
            np.zeros(n, dtype=np.int64), none, none,
        )  # fmt: skip

    def _share(
        self,
        now: float,
        shares: list[tuple[str, FloatArray]],
        first: int,
        pos: FloatArray,
        vel: FloatArray,
    ) -> None:
        """Share the positions and velocities of the consecutive members ``first``,
        ``first + 1``, ... of ``shares`` on the bus, their rows, positions and velocities as
        blocks."""
        end = first + len(shares)
        assert self._own_row is not None
        self.bus.share_positions(
            now, shares, (self._own_row[first:end], pos[first:end]), vel[first:end]
        )
        self.batched += len(shares)

    def _each(self, now: float) -> None:
        for side in self.sides:
            side.control(now)
