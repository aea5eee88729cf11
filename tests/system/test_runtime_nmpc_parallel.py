"""The runner's deferred NMPC solves (issue 19): the drones' solves of one step overlap on the
NMPC thread pool and are collected in a fixed order, and the run stays the run it was."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from btmission.missions import load_mission
from btmission.runtime.runner import MissionRun

MINE = Path(__file__).resolve().parents[2] / "missions" / "mine_inspection.yaml"


@pytest.mark.slow
def test_deferred_nmpc_solves_give_the_serial_run() -> None:
    mission = load_mission(MINE)
    poses = {}
    for defer in (False, True):
        run = MissionRun(mission, controller="nmpc")
        navigators = [side.agent.navigator for side in run.agent_sides]
        assert all(nav.defer_nmpc for nav in navigators)  # the runner's default
        for nav in navigators:
            nav.defer_nmpc = defer
        for _ in range(400):  # 20 s: take-off and the first metres of every drone's route
            run.step()
        assert all(len(nav.solve_times) > 300 for nav in navigators)
        for nav in navigators:  # the solves' CPU time, whichever thread solved: > 0, ≤ wall
            assert 0 < nav.solve_cpu_s <= sum(nav.solve_times) + 0.01 * len(nav.solve_times)
        poses[defer] = np.array(
            [
                [*v.backend.telemetry().position, *v.backend.telemetry().velocity]
                for v in run.vehicles.values()
            ]
        )
        run.close()
    np.testing.assert_array_equal(poses[True], poses[False])
