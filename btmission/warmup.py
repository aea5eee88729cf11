"""Compile btmission's numba kernels ahead of their first use (``make install`` runs this).

The D*+ planner, the GA dispatcher's evaluator, the LiDAR ray casters and the pruned assignment
solver are numba functions compiled on their first call and cached on disk (``cache=True``, next
to their modules). On a fresh install the first mission, planner query or dispatch would otherwise
pay that compilation (about half a minute on a 2-core machine) in the middle of its work. This module runs each of
them once, on tiny inputs, through the same code paths a run uses, so that the argument types —
and so the compiled signatures — are exactly those of real use: a command where one runs the kernel,
else the function that does (:func:`_calls`)::

    python -m btmission.warmup          # prints what it compiled and how long it took

It needs no network, writes only into the numba cache and a temporary directory, and is safe to
run again (it then takes a second or two: everything is cached).
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from btmission.backends.sim import Simulator
    from btmission.links.bus import InMemoryBus
    from btmission.runtime.navigation import Navigator


def _commands(tmp: Path) -> list[tuple[str, list[str]]]:
    root = Path(__file__).resolve().parents[1]
    missions = root / "missions"
    steps = [
        ("D*+ planner", ["bench", "planner", "--size", "60", "40", "6", "--repeat", "1",
                         "--queries", "2", "--no-peers", "--out", str(tmp / "bench")]),
        ("GA dispatch", ["dispatch", "static", "--map", "static_npr", "--vehicles", "2",
                         "--runs", "1", "--budget", "0.2"]),
    ]  # fmt: skip
    if (missions / "pick_and_deliver.yaml").is_file():  # a source checkout (make install)
        steps.append(
            ("simulator LiDAR", ["run", str(missions / "pick_and_deliver.yaml"), "--controller",
                                 "track", "--until", "2", "--quiet", "--no-png", "--log",
                                 str(tmp / "runs")]),
        )  # fmt: skip
        steps.append(
            ("simulator depth camera", ["run", str(missions / "compra_sar.yaml"), "--until", "4",
                                        "--quiet", "--no-png", "--log", str(tmp / "runs")]),
        )  # fmt: skip
        reloc = root / "docs" / "examples" / "reloc_mine.yaml"
        if reloc.is_file():
            steps.append(("relocalization ray casting",
                          ["reloc", "try", str(reloc), "--at", "32,15,2", "--yaw", "40"]))  # fmt: skip
    return steps


def _viewer_mesh() -> None:
    """The viewer's greedy meshing (:mod:`btmission.viz.mesh`), on a one-voxel rock."""
    from btmission.viz.mesh import surface_mesh
    from btmission.world.voxel import OCCUPIED, VoxelMap

    vmap = VoxelMap.empty((1.5, 1.5, 1.5), 0.5)
    vmap.state[1, 1, 1] = OCCUPIED
    surface_mesh(vmap)


def _pruned_assignment() -> None:
    """The pruned assignment solver (:mod:`btmission.allocation.pruned`), which ``auto`` picks
    only for large bid matrices, on a small one (the same argument types)."""
    import numpy as np

    from btmission.allocation.pruned import solve_pruned
    from btmission.allocation.solvers import AssignmentProblem

    costs = np.arange(12.0).reshape(3, 4)
    for bonus in (None, np.ones(4)):  # compiled apart: with and without priorities
        solve_pruned(AssignmentProblem.dense(costs, bonus=bonus, incumbent=[0, -1, 2]))


def _vehicle_control() -> None:
    """A simulated drone's control step: its short-range LiDAR (rock faces and another
    vehicle), the APF on it with the other agents' push, carrot chasing on a route and the
    simulator's step (the multirotors' model, clearance to the walls) — the kernels of
    :mod:`btmission.world._surface_kernels`, :mod:`btmission.backends._multirotor_kernels`,
    :mod:`btmission.control._apf_kernels` and :mod:`btmission.runtime._route_kernels`, through
    the simulator and the navigator."""
    import numpy as np

    from btmission.backends.sim import SimConfig, Simulator
    from btmission.control.apf import PotentialField
    from btmission.runtime.navigation import Navigator
    from btmission.world.voxel import OCCUPIED, VoxelMap

    vmap = VoxelMap.empty((4.0, 4.0, 3.0), 0.5)
    vmap.state[:, :, 0] = OCCUPIED  # a floor
    vmap.state[:, 7, :] = OCCUPIED  # and a wall
    sim = Simulator(vmap, SimConfig(lidar_range_m=3.0))
    a = sim.add_multirotor("A", (1.0, 1.0, 0.5))
    sim.add_multirotor("B", (2.0, 1.5, 0.5))
    from btmission.backends.sim import SMALL_FLEET

    for i in range(SMALL_FLEET):  # a fleet's contact test (past SMALL_FLEET vehicles)
        sim.add_multirotor(f"F{i}", (0.5 + 0.5 * i, 2.5, 0.5))
    nav = Navigator("A", a, a, "track", predictions=lambda _agent: [np.array([[2.0, 1.5, 0.5]])])
    nav.follow(np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 1.0]]), np.array([3.0, 3.0, 1.0]), 0.0)
    nav.step(0.0)
    sim.step()  # its contact test: the clearance to the walls
    sim.world.surface_points(np.array([1.0, 1.0, 0.5]), 1.0)
    from btmission.links.bus import SMALL_FLEET, InMemoryBus

    bus = InMemoryBus()  # a fleet's neighbour query (past SMALL_FLEET agents)
    for i in range(SMALL_FLEET + 1):
        bus.share_prediction(f"V{i}", 0.0, np.array([[float(i), 0.0, 1.0]]))
    bus.neighbour_positions("V0", 0.0, 0.1, np.array([0.0, 0.0, 1.0]), 6.0)
    PotentialField().step(np.ones((2, 3)), (1.0, 0.0, 0.0))
    _fleet_step(sim, nav, bus)


def _fleet_step(sim: Simulator, nav: Navigator, bus: InMemoryBus) -> None:
    """The fleet's control step (:func:`~btmission.runtime._fleet_kernels.fleet_follow`) for
    two drones of the warm-up's simulator, with the argument types of a run's."""
    import numpy as np

    from btmission.backends.mapsensors import sphere_points
    from btmission.runtime._fleet_kernels import fleet_follow
    from btmission.runtime.navcontrol import CARROT_WINDOW
    from btmission.runtime.navigation import POSITION_GAIN, SETTLED_M_S

    cells = sim.world.cells
    table = sim.bodies()
    route = np.zeros((2, 9))
    route[:, 0:3] = [[1.0, 1.0, 1.0], [3.0, 3.0, 1.0]]
    n = len(bus._row_names)
    prev = bus._starts[:n]
    assert nav._apf is not None
    fleet_follow(
        np.concatenate([route, route]), np.array([0, 2, 4], dtype=np.int64),
        np.zeros(2, dtype=np.int64), np.ones((2, 7)), np.ones((2, 4)),
        np.array([0, 1], dtype=np.int64), np.full((2, 3), 3.0), np.zeros(2, dtype=np.bool_),
        np.zeros((2, 3)), cells.points, cells.starts, cells.lo, float(cells.cell), cells.dims,
        3.0, table.centres, table.radii, sphere_points(), prev, prev.copy(),
        np.arange(n, dtype=np.int64), np.array([0, 1], dtype=np.int64),
        np.array([0, 1], dtype=np.int64), 6.0, CARROT_WINDOW, 1.0, 0.3, SETTLED_M_S, 1.0,
        POSITION_GAIN, nav._apf.config.packed, nav._apf.config.packed,
    )  # fmt: skip


def _planner() -> None:
    """A run's path costs and route on a tiny map (:class:`btmission.runtime.paths.PathCosts`:
    backward one-to-all D*+ searches with a risk layer, the gather of bids and their range
    check, a path), and an A* query."""
    import numpy as np

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


_prepared = False


def prepare_run() -> None:
    """Load what a mission run's loop would otherwise load on its first steps — the planner's
    and the vehicle control's numba kernels (from the cache; compiled if missing) and the
    assignment solver's scipy module — so that the loop does not stall for a second at its
    first auction round (a real-time run would miss its deadlines). Once per process;
    :class:`~btmission.runtime.runner.MissionRun` calls it while it builds."""
    global _prepared
    if _prepared:
        return
    import scipy.optimize  # noqa: F401  (the assignment's linear_sum_assignment)

    _planner()
    _vehicle_control()
    _prepared = True


def _calls() -> list[tuple[str, Callable[[], None]]]:
    """Kernels no command runs on its own: the functions that run them."""
    return [
        ("viewer surface mesh", _viewer_mesh),
        ("assignment pruning", _pruned_assignment),
        ("vehicle control (LiDAR, APF, route)", _vehicle_control),
    ]


def warm_up(echo: Callable[[str], None] = print) -> float:
    """Run every kernel once (module docstring); returns the seconds it took."""
    from click.testing import CliRunner

    from btmission.cli.main import cli

    t0 = time.perf_counter()
    runner = CliRunner()
    with tempfile.TemporaryDirectory(prefix="btmission-warmup-") as tmp:
        for name, args in _commands(Path(tmp)):
            t = time.perf_counter()
            result = runner.invoke(cli, args, catch_exceptions=True)
            took = time.perf_counter() - t
            if result.exit_code not in (0, 1):  # 1: a run with open tasks (cut at 2 s)
                echo(
                    f"warm-up: {name}: exit {result.exit_code} (skipped; it compiles on first use)"
                )
            else:
                echo(f"warm-up: {name} compiled in {took:.1f} s")
    for name, call in _calls():
        t = time.perf_counter()
        try:
            call()
        except Exception as exc:  # as for a command: a failed step only loses its head start
            echo(f"warm-up: {name}: {exc!r} (skipped; it compiles on first use)")
        else:
            echo(f"warm-up: {name} compiled in {time.perf_counter() - t:.1f} s")
    return time.perf_counter() - t0


def main() -> int:
    total = warm_up(lambda text: print(text, file=sys.stderr))
    print(f"warm-up: numba kernels ready ({total:.1f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
