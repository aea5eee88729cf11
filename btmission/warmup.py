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


WARM_RUN = """
mission: warm_up
version: 1
world:
  map: {generate: empty, size: [12, 12, 4]}
  resolution: 0.5
agents:
  - {id: A, library: aerial, start: [2, 2, 0]}
  - {id: B, library: aerial, start: [4, 2, 0]}
tasks:
  - {id: T1, type: inspect, location: [9, 9, 2]}
task_types:
  inspect: {goal: at_goal(location), cost: path_cost(location)}
runtime: {controller: track}
"""
"""Two drones in a small empty world: building their run loads what a run's loop calls."""


def _vehicle_control() -> None:
    """A run's loop kernels, loaded as a run loads them while it builds
    (:mod:`btmission.runtime.prewarm`: the planner, the navigator and the bus; the simulator's
    model and LiDAR, warmed by its provider; the fleet's batched control step), for a
    two-drone mission (:data:`WARM_RUN`); a MAVLink vehicle's map sensors
    (:class:`~btmission.backends.mavlink.MapSensorsAtReports`); then the APF of
    :class:`~btmission.control.apf.PotentialField` (the control examples and benchmark) and the
    rock-face ball query of :mod:`btmission.world._surface_kernels`."""
    import numpy as np

    from btmission.backends.mavlink import MapSensorsAtReports
    from btmission.backends.sim import SimConfig
    from btmission.backends.simworld import SimWorld
    from btmission.control.apf import PotentialField
    from btmission.missions import load_mission_text
    from btmission.runtime.runner import MissionRun

    run = MissionRun(load_mission_text(WARM_RUN, "warm_up.yaml"))
    run.close()
    world = SimWorld(run.map)
    MapSensorsAtReports(world, SimConfig(), np.random.default_rng(0)).warm_up()
    PotentialField().step(np.ones((2, 3)), (1.0, 0.0, 0.0))
    world.surface_points(np.array([1.0, 1.0, 0.5]), 1.0)


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
