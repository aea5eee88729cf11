"""The install-time warm-up compiles every numba kernel through the commands a run uses, and a
run loads its loop's kernels while it builds (btmission.runtime.prewarm, the providers'
warm_up): its loop then loads none, checked in a fresh interpreter (tests/warm_loop.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from btmission import warmup
from btmission.backends.mavlink_modes import Autopilot
from tests.load import margin

ROOT = Path(__file__).resolve().parents[3]


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


def loop_kernels(mission: Path, until: float, mode: str = "fleet") -> dict[str, Any]:
    """What :mod:`tests.warm_loop` measures of a run of ``mission`` to ``until`` in a fresh
    interpreter: in this one, earlier tests may have loaded the kernels a run's build should."""
    done = subprocess.run(
        [sys.executable, "-m", "tests.warm_loop", str(mission), str(until), mode],
        capture_output=True, text=True, cwd=ROOT, timeout=300 * margin(), check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    out: dict[str, Any] = json.loads(done.stdout.splitlines()[-1])
    return out


@pytest.mark.parametrize("mode", ["fleet", "each"])
def test_a_run_loads_its_loop_kernels_while_it_builds(tmp_path: Path, mode: str) -> None:
    """What MissionRun's build loads (the runtime's prewarm_run, the simulator provider's
    warm_up, the fleet step's) covers the loop: a ten-drone mission in the mine (D*+ fields and
    routes, bids, LiDAR on rock and bodies, APF with the others' push, carrot chasing, the
    clearance to the walls, the multirotors' step, the fleet's batched step or each drone's
    own) then loads no kernel, and the assignment's scipy module is already there."""
    from btmission.bench.fleet import fleet_mission_text

    mission = tmp_path / "fleet.yaml"
    mission.write_text(fleet_mission_text(10))
    out = loop_kernels(mission, 25.0, mode)
    assert out["scipy_at_build"]
    used = {"_apf_kernels.navigator_force", "_route_kernels.carrots"}
    used |= {"_surface_kernels.scan_points", "_surface_kernels.nearest_distances"}
    used |= {"_neighbour_kernels.near_states"}  # a fleet's neighbour query (past SMALL_FLEET)
    used |= {"_multirotor_kernels.step_all", "_bid_kernels.first_bad_cost"}  # bids' check
    used |= {"_multirotor_kernels.rock_rows", "_multirotor_kernels.near_pairs"}  # contacts
    used |= {"_kernels.search"} | ({"_fleet_kernels.fleet_follow"} if mode == "fleet" else set())
    assert {k for k, n in out["built"].items() if n} >= used
    assert min(out["heights"]) > 1.0, out["heights"]  # all ten flying their routes by then
    assert out["searches"] > 0 and (out["batched"] > 0) == (mode == "fleet")
    assert out["loop_loaded"] == {}


@pytest.mark.serial
def test_a_mavlink_run_loads_its_loop_kernels_while_it_builds(tmp_path: Path) -> None:
    """A MAVLink drone with map sensors (no fleet step: the provider ray-casts no fleet; its
    LiDAR's arrays are not the simulator's): its provider's warm_up and the runtime's cover
    what its loop calls — the navigator on that LiDAR, the planner, the bids."""
    from tests.mavlink_helpers import SPEED, mavsim
    from tests.system.test_mavlink_run import MISSION  # one drone, one inspection

    with mavsim(Autopilot.PX4) as sim:
        text = MISSION.format(url=sim.endpoints[0].url, speed=SPEED)
        text = text.replace("telemetry_hz: 20}", "telemetry_hz: 20, map_sensors: true}")
        assert "map_sensors: true" in text
        mission = tmp_path / "small.yaml"
        mission.write_text(text.lstrip())
        out = loop_kernels(mission, 25.0, "each")
    assert min(out["highest"]) > 1.0, out["highest"]  # it took off and flew to its task
    assert out["searches"] > 0 and out["batched"] == 0
    used = {"_apf_kernels.navigator_force", "_route_kernels.carrots"}
    used |= {"_surface_kernels.scan_points", "_bid_kernels.first_bad_cost", "_kernels.search"}
    assert {k for k, n in out["built"].items() if n} >= used
    assert out["loop_loaded"] == {}


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
