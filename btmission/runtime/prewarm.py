"""Load the run loop's compiled kernels while the run is built, not at its first steps.

The planner, the navigator and the bus run numba kernels (``cache=True``): each is compiled on
its first call for the types of its arguments, or loaded from numba's cache on disk. Left to
the loop, that loading falls on its first auction round (the path costs, the bids, the routes)
and first control steps — a stall of a second or more, which a real-time run would take as
missed deadlines. :func:`prewarm_run`, which
:class:`~btmission.runtime.runner.MissionRun` calls while it builds, runs every kernel the
runtime owns once, on tiny inputs, through the code a run uses — so that the argument types,
and so the signatures, are those of the run (another dtype, layout or read-only flag is another
signature, compiled again at the first step) — and has the vehicle provider load its own
(:meth:`VehicleProvider.warm_up <btmission.vehicles.provider.VehicleProvider.warm_up>`: the
simulator's model and LiDAR, a MAVLink provider's map sensors). The fleet control step's kernel
is loaded when that step is built, with the provider's arrays
(:class:`~btmission.runtime.fleetstep.FleetFollow`).

The install-time warm-up (``python -m btmission.warmup``, a tool) runs these too.
"""

from __future__ import annotations

import numpy as np

from btmission.types import FloatArray, Vec3
from btmission.vehicles.base import (
    ACCEPTED,
    Ack,
    CameraFrame,
    LandedState,
    LidarScan,
    Mode,
    Telemetry,
    VehicleKind,
)
from btmission.vehicles.provider import VehicleProvider

_warmed = False


def prewarm_run(provider: VehicleProvider) -> None:
    """Load the kernels a run's loop calls and the assignment's scipy module (module
    docstring): the runtime's once per process, then ``provider``'s
    (:meth:`~btmission.vehicles.provider.VehicleProvider.warm_up`)."""
    global _warmed
    if not _warmed:
        import scipy.optimize  # noqa: F401  (the assignment's linear_sum_assignment)

        warm_planner()
        warm_navigator()
        _warmed = True
    provider.warm_up()


def warm_planner() -> None:
    """A run's path costs and route on a tiny map (:class:`btmission.runtime.paths.PathCosts`:
    backward one-to-all D*+ searches with a risk layer, the gather of bids and their range
    check, a path), and an A* query."""
    from btmission.allocation.auction import Bid
    from btmission.planning.risk import RiskParams
    from btmission.runtime.paths import PathCosts
    from btmission.world.voxel import VoxelMap

    paths = PathCosts(VoxelMap.empty((3.0, 2.0, 1.0), 0.5), RiskParams(), clearance_m=0.25)
    start, goal = (0.25, 0.25, 0.25), (2.75, 1.75, 0.75)
    costs = paths.path_costs(start, (goal, (2.75, 0.25, 0.25)))
    Bid("A", 0.0, ("T1", "T2"), np.asarray(costs, dtype=np.float64)).problem()  # its check
    paths.route(start, goal)
    paths.planner.plan(start, goal)


def warm_navigator() -> None:
    """A drone's navigator, wired to the in-memory bus as a run wires it
    (:func:`~btmission.runtime.assembly.build_agents`), following a route for one step: the
    carrot (:mod:`btmission.runtime._route_kernels`), the neighbours past
    :data:`~btmission.links.bus.SMALL_FLEET` agents (:mod:`btmission.links._neighbour_kernels`)
    and the APF on its LiDAR with their push and the separation rule
    (:mod:`btmission.control._apf_kernels`), then a take-off under that rule — on a
    stand-in vehicle (:class:`StandInDrone`), the runtime having none of its own."""
    from btmission.links.bus import SMALL_FLEET, InMemoryBus, neighbour_states
    from btmission.runtime.assembly import NEIGHBOUR_RANGE_M
    from btmission.runtime.navigation import Navigator

    bus = InMemoryBus()
    for i in range(SMALL_FLEET + 1):  # a fleet: the neighbours' compiled query
        bus.share_prediction(f"V{i}", 0.0, np.array([[1.0 + 0.5 * i, 1.5, 1.0]]), np.zeros(3))
    link = bus.agent_link("V0")

    def neighbours(agent: str, pos: FloatArray) -> FloatArray:
        return neighbour_states(link, 0.0, 0.1, pos, NEIGHBOUR_RANGE_M)

    drone = StandInDrone()
    nav = Navigator("V0", drone, drone, "track", neighbours=neighbours)
    nav.follow(np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 1.0]]), np.array([3.0, 3.0, 1.0]), 0.0)
    nav.step(0.0)
    nav.takeoff()  # a take-off's and a hold's setpoint under the separation rule
    nav.step(0.0)


class StandInDrone:
    """A drone hovering at (1, 1, 1) that accepts every command: the vehicle (backend and
    sensors) of :func:`warm_navigator`. What it gives the navigator's kernels must be typed as
    a provider's vehicle's is, or they would be compiled for other signatures than a run's:
    telemetry as a :class:`~btmission.vehicles.base.Telemetry` of float64 arrays, and a LiDAR
    scan as :class:`~btmission.backends.mapsensors.MapSensors` returns it (the scan kernel's
    result) — a new, writable, C-contiguous float64 (n, 3) array."""

    kind = VehicleKind.MULTIROTOR

    def __init__(self) -> None:
        self._telemetry = Telemetry(
            time_s=0.0,
            position=np.array([1.0, 1.0, 1.0]),
            velocity=np.zeros(3),
            yaw=0.0,
            roll=0.0,
            pitch=0.0,
            yaw_rate=0.0,
            mode=Mode.OFFBOARD,
            armed=True,
            landed=False,
            landed_state=LandedState.IN_AIR,
            battery=1.0,
            ground_z=0.0,
        )

    def arm(self) -> Ack:
        return ACCEPTED

    def disarm(self) -> Ack:
        return ACCEPTED

    def set_mode(self, mode: Mode) -> Ack:
        return ACCEPTED

    def takeoff(self, altitude_m: float) -> Ack:
        return ACCEPTED

    def land(self) -> Ack:
        return ACCEPTED

    def set_position_setpoint(
        self,
        position: Vec3 | FloatArray,
        velocity: Vec3 | FloatArray | None = None,
        yaw: float | None = None,
    ) -> None:
        """Taken and forgotten."""

    def set_velocity_setpoint(self, velocity: Vec3 | FloatArray, yaw_rate: float = 0.0) -> None:
        """Taken and forgotten."""

    def set_attitude_setpoint(
        self, thrust: float, roll: float, pitch: float, yaw_rate: float = 0.0
    ) -> None:
        """Taken and forgotten."""

    def telemetry(self) -> Telemetry:
        return self._telemetry

    def lidar(self) -> FloatArray:
        """A rock face ahead and a point of another drone's body (yaw frame)."""
        return np.array([[1.2, 0.0, 0.0], [1.2, 0.3, 0.2], [0.0, -1.5, 0.4]])

    def lidar_scan(self) -> LidarScan | None:
        """No full scan (the navigator reads none)."""
        return None

    def camera(self) -> CameraFrame:
        raise RuntimeError("the warm-up's stand-in drone has no camera")
