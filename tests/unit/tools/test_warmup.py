"""The install-time warm-up compiles every numba kernel through the commands a run uses."""

from __future__ import annotations

from pathlib import Path

import pytest

from btmission import warmup


def test_the_warm_up_steps_name_real_files_and_commands(tmp_path: Path) -> None:
    from btmission.cli.main import cli

    steps = warmup._commands(tmp_path)
    names = [name for name, _ in steps]
    assert names == [
        "D*+ planner",
        "GA dispatch",
        "simulator LiDAR",
        "simulator depth camera",
        "relocalization ray casting",
    ]
    for _, args in steps:
        group: object = cli
        for word in args:  # each step's command path exists (bench planner, dispatch static ...)
            commands = getattr(group, "commands", None)
            if commands is None or word not in commands:
                break
            group = commands[word]
        assert not hasattr(group, "commands"), args
        for arg in args:
            if arg.endswith(".yaml"):
                assert Path(arg).is_file(), arg


def test_the_warm_up_calls_the_kernels_no_command_runs() -> None:
    assert [name for name, _ in warmup._calls()] == [
        "viewer surface mesh",
        "assignment pruning",
        "vehicle control (LiDAR, APF, route)",
    ]
    for _, call in warmup._calls():
        call()


def test_a_run_loads_its_loop_kernels_while_it_builds() -> None:
    """What prepare_run (called by MissionRun's build) loads covers the loop: a drone mission in
    the mine (D*+ fields and routes, bids, LiDAR on rock and bodies, APF with the others' push,
    carrot chasing, the clearance to the walls, the multirotors' step) then compiles or loads no kernel of the planner
    or the vehicle control, and the assignment's scipy module is already there."""
    import sys

    from numba.core.registry import CPUDispatcher

    from btmission.allocation import _bid_kernels as bids
    from btmission.backends import _multirotor_kernels as multirotor
    from btmission.bench.fleet import fleet_mission_text
    from btmission.control import _apf_kernels as apf
    from btmission.links import _neighbour_kernels as near
    from btmission.missions import load_mission_text
    from btmission.planning import _kernels as plan
    from btmission.runtime import _fleet_kernels as fleet
    from btmission.runtime import _route_kernels as route
    from btmission.runtime.runner import MissionRun
    from btmission.world import _surface_kernels as surf

    warmup.prepare_run()
    assert "scipy.optimize" in sys.modules
    kernels = [
        f for mod in (apf, route, surf, plan, near, multirotor, bids, fleet)
        for f in vars(mod).values()
        if isinstance(f, CPUDispatcher)
    ]  # fmt: skip
    before = {f.__name__: len(f.signatures) for f in kernels}
    used = {"navigator_force", "carrots", "scan_points", "nearest_distances"}
    used |= {"near_points"}  # a fleet's neighbour query (past SMALL_FLEET)
    used |= {"step_all", "first_bad_cost"}  # the multirotors' step; bids' range check
    used |= {"rock_rows", "near_pairs"}  # the simulator's contact test (past SMALL_FLEET)
    used |= {"fleet_follow"}  # the fleet's control step
    assert used <= set(before) and all(before[k] for k in used)
    run = MissionRun(load_mission_text(fleet_mission_text(10), "fleet.yaml"), controller="track")
    run.run(until=25)
    heights = [v.backend.telemetry().height_above_ground for v in run.vehicles.values()]
    assert min(heights) > 1.0, heights  # all ten flying their routes by then
    assert run.paths.searches > 0
    assert {f.__name__: len(f.signatures) for f in kernels} == before


def test_the_pruning_warm_up_compiles_the_signatures_a_large_solve_uses() -> None:
    """After the warm-up's tiny problem, a benchmark-shaped one (two scan threads, priorities,
    incumbents, rescans) compiles nothing new: the warm-up's signatures are those of real use."""
    import numpy as np

    from btmission.allocation import _prune_kernel as kern
    from btmission.allocation.pruned import solve_pruned
    from btmission.allocation.solvers import AssignmentProblem
    from btmission.bench.auction import instance_costs

    warmup._pruned_assignment()
    kernels = (kern.scan_rows, kern.shortest_augmenting_paths)
    before = [len(f.signatures) for f in kernels]
    assert all(before)
    costs = instance_costs(200, 5000, 0.3, 0)
    inc = np.arange(200) * 3
    for bonus in (None, np.zeros(5000)):
        solve_pruned(AssignmentProblem.dense(costs, bonus=bonus, incumbent=inc), k=1)
    assert [len(f.signatures) for f in kernels] == before


@pytest.mark.slow
def test_the_warm_up_runs_every_step() -> None:
    lines: list[str] = []
    total = warmup.warm_up(lines.append)
    steps = len(warmup._commands(Path("/tmp"))) + len(warmup._calls())
    assert steps == 8 and len(lines) == steps, lines
    assert all(" compiled in " in line for line in lines), lines
    assert total > 0
