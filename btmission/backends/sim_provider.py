"""The embedded simulator as a vehicle provider: the ``sim`` scheme of ``btmission.providers``.

:func:`sim_provider` (the entry point) builds a :class:`~btmission.backends.sim.Simulator` of the
mission's world with its ``runtime.sim`` settings (:func:`sim_config`) and artifacts
(:func:`mission_artifacts`), seeded with the run's seed, and wraps it in a :class:`SimProvider`:
vehicles spawned at their start, the simulator's time, its physics stepped by the run. Its
:class:`SimFleetSensing` lets the fleet control step compute the drones' LiDAR scans itself, and
:func:`warm_simulator` loads the simulator's kernels while the run is built.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from typing import TYPE_CHECKING, cast

import numpy as np

from btmission.backends.sim import SimConfig, Simulator, SimVehicle, _BodyTable
from btmission.backends.simworld import Artifact
from btmission.spec.common import config_from
from btmission.spec.vehicleref import SIM, VehicleRef
from btmission.types import FloatArray, Vec3
from btmission.vehicles.base import Backend, Sensors, VehicleKind
from btmission.vehicles.provider import (
    AttachOptions,
    FleetSensing,
    ProviderBase,
    Vehicle,
    VehicleEvent,
)

if TYPE_CHECKING:
    from btmission.spec.mission import Mission
    from btmission.world.voxel import VoxelMap


class SimProvider(ProviderBase):
    """The embedded simulator as the run's
    :class:`~btmission.vehicles.provider.VehicleProvider` (scheme ``sim``): vehicles are spawned
    at their start, time is the simulator's (:class:`~btmission.vehicles.clock.SimClock`), and
    :meth:`step` integrates the physics. Wrapping changes nothing: the same seed gives the same
    run as driving the :class:`Simulator` directly."""

    realtime = False

    def __init__(self, sim: Simulator) -> None:
        from btmission.vehicles.clock import SimClock

        self.sim = sim
        self.clock = SimClock(sim)

    def warm_up(self) -> None:
        """The simulator's kernels, through a throwaway simulator with the run's settings
        (:func:`warm_simulator`): the run's own is untouched."""
        warm_simulator(self.sim.config)

    def attach(
        self,
        agent_id: str,
        kind: VehicleKind,
        start: Vec3,
        ref: VehicleRef = SIM,
        options: AttachOptions = AttachOptions(),
    ) -> Vehicle:
        """Spawn ``agent_id``'s vehicle at ``start``, heading ``options.yaw`` (a ground robot
        at most at ``options.v_max``: :meth:`Simulator.add_ground`)."""
        yaw = float(options.yaw)
        if kind is VehicleKind.GROUND:
            backend = self.sim.add_ground(agent_id, start, yaw, v_max=options.v_max)
        else:
            backend = self.sim.add_multirotor(agent_id, start, yaw)
        truth = self.sim.vehicle(agent_id)
        return Vehicle(
            agent_id,
            kind,
            backend,
            backend,
            odometer_m=lambda: truth.odometer_m,
            clearance_m=partial(self.sim.take_clearance, agent_id),
        )

    def step(self, dt: float) -> list[VehicleEvent]:
        """Advance by ``dt``: a whole number of the simulator's fixed steps."""
        step_s = self.sim.config.step_s
        n = round(dt / step_s)
        if n < 1 or abs(n * step_s - dt) > 1e-9:
            raise ValueError(f"dt must be a multiple of the simulator's step {step_s} s, got {dt}")
        out: list[VehicleEvent] = []
        for _ in range(n):
            out.extend(self.sim.step())
        return out

    def close(self) -> None:
        """Nothing to release: the simulator lives in this process."""

    def fleet_sensing(self) -> FleetSensing | None:
        """The simulator's offer to the fleet control step (:class:`SimFleetSensing`); None
        with dust in the LiDAR, which draws from the simulator's generator vehicle by vehicle."""
        return None if self.sim.config.dust_points else SimFleetSensing(self.sim)


class SimFleetSensing:
    """What the fleet control step needs of the simulator to compute its drones' LiDAR scans
    itself, exactly as each drone's :class:`~btmission.backends.mapsensors.MapSensors` would
    (:class:`~btmission.vehicles.provider.FleetSensing`)."""

    def __init__(self, sim: Simulator) -> None:
        from btmission.backends.mapsensors import sphere_points

        self.sim = sim
        cells = sim.world.cells
        self.cells = (cells.points, cells.starts, cells.lo, float(cells.cell), cells.dims)
        self.lidar_range_m = float(sim.config.lidar_range_m)
        self.sphere = sphere_points()

    def covers(self, backend: Backend, sensors: Sensors | None) -> bool:
        """A multirotor of this simulator whose navigator reads its own, unreplaced LiDAR."""
        if type(backend) is not SimVehicle:
            return False
        return (
            backend.kind is VehicleKind.MULTIROTOR
            and backend.sim is self.sim
            and sensors is backend
            and backend.owns_sensors
        )

    def bodies(self) -> _BodyTable:
        return self.sim.bodies()

    def true_poses(self, backends: Sequence[Backend]) -> FloatArray:
        vehicles = [cast(SimVehicle, b).vehicle for b in backends]
        poses = np.empty((len(vehicles), 4))
        poses[:, 0:3] = [v.x[:3] for v in vehicles]
        poses[:, 3] = [v.yaw for v in vehicles]
        return poses


_warmed = False


def warm_simulator(config: SimConfig) -> None:
    """Load the kernels a simulated run's loop calls (from numba's cache; compiled if
    missing), once per process: a throwaway :class:`Simulator` with ``config`` — a floor and a
    wall, more drones than :data:`~btmission.backends.sim.SMALL_FLEET` — scans one drone's
    LiDAR (the rock faces and another drone's body:
    :mod:`btmission.world._surface_kernels`) and steps once (the multirotors' model, the
    clearance to the walls, the contact tests of a fleet:
    :mod:`btmission.backends._multirotor_kernels`). Its vehicles are real simulated ones, so
    the kernels get the arrays — and the signatures — of a run's."""
    global _warmed
    if _warmed:
        return
    from btmission.backends.sim import SMALL_FLEET
    from btmission.world.voxel import OCCUPIED, VoxelMap

    vmap = VoxelMap.empty((4.0, 4.0, 3.0), 0.5)
    vmap.state[:, :, 0] = OCCUPIED  # a floor
    vmap.state[:, 7, :] = OCCUPIED  # and a wall
    sim = Simulator(vmap, config)
    drone = sim.add_multirotor("A", (1.0, 1.0, 0.5))
    sim.add_multirotor("B", (2.0, 1.5, 0.5))
    for i in range(SMALL_FLEET):  # a fleet's contact test (past SMALL_FLEET vehicles)
        sim.add_multirotor(f"F{i}", (0.5 + 0.5 * i, 2.5, 0.5))
    drone.set_position_setpoint((1.0, 1.0, 1.0))
    drone.lidar()
    sim.step()
    _warmed = True


def sim_config(mission: Mission) -> SimConfig:
    """The simulator (and map-sensor) settings of a mission's ``runtime.sim`` section."""
    return config_from(SimConfig, mission.spec.runtime.sim)


def mission_artifacts(mission: Mission) -> list[Artifact]:
    """The objects a mission places in the world for the cameras (``runtime.sim.artifacts``)."""
    return [Artifact(a.label, a.position, a.size_m) for a in mission.spec.runtime.sim.artifacts]


def sim_provider(mission: Mission, voxel_map: VoxelMap, seed: int) -> SimProvider:
    """The ``sim`` entry point of ``btmission.providers``: a simulator of the mission's world
    with its ``runtime.sim`` settings and artifacts, seeded with the run's seed."""
    config = sim_config(mission)
    artifacts = mission_artifacts(mission)
    return SimProvider(Simulator(voxel_map, config, seed=seed, artifacts=artifacts))
