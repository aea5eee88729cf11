"""Which compiled kernels a run loads while it builds and which its loop loads after, measured in
a fresh interpreter (``python -m tests.warm_loop MISSION UNTIL [fleet|each]``), where no earlier
test has loaded any: prints one JSON object (:func:`measure`) for ``tests/unit/tools/test_warmup.py``."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path
from typing import Any

KERNEL_MODULES = (
    "btmission.allocation._bid_kernels",
    "btmission.backends._multirotor_kernels",
    "btmission.control._apf_kernels",
    "btmission.links._neighbour_kernels",
    "btmission.planning._kernels",
    "btmission.runtime._fleet_kernels",
    "btmission.runtime._route_kernels",
    "btmission.world._surface_kernels",
)
"""The modules of the kernels a run's loop calls (the planner, the bids' check, the navigator,
the bus, the fleet step, the simulator's model and LiDAR, the map sensors)."""


def signatures() -> dict[str, list[str]]:
    """Every kernel of :data:`KERNEL_MODULES` (``module.function``) → its loaded signatures."""
    from numba.core.registry import CPUDispatcher

    out: dict[str, list[str]] = {}
    for name in KERNEL_MODULES:
        mod = importlib.import_module(name)
        for f in vars(mod).values():
            if isinstance(f, CPUDispatcher) and f.py_func.__module__ == name:
                out[f"{name.rsplit('.', 1)[1]}.{f.__name__}"] = [str(s) for s in f.signatures]
    return out


def measure(mission_path: Path, until: float, fleet_step: bool) -> dict[str, Any]:
    """Build the run of ``mission_path`` (tracking controller), note the kernels loaded, run it
    to ``until`` and note what the loop loaded besides."""
    from btmission.missions import load_mission
    from btmission.runtime.runner import MissionRun

    run = MissionRun(load_mission(mission_path), controller="track", fleet_step=fleet_step)
    highest = dict.fromkeys(run.vehicles, 0.0)

    def heights(run: MissionRun) -> None:
        for name, v in run.vehicles.items():
            highest[name] = max(highest[name], v.backend.telemetry().height_above_ground)

    try:
        built = signatures()
        scipy_loaded = "scipy.optimize" in sys.modules
        run.run(until=until, progress=heights)
        after = signatures()
        return {
            "built": {k: len(v) for k, v in built.items()},
            "scipy_at_build": scipy_loaded,
            "loop_loaded": {
                k: [s for s in v if s not in built.get(k, [])]
                for k, v in after.items()
                if len(v) != len(built.get(k, []))
            },
            "heights": [v.backend.telemetry().height_above_ground for v in run.vehicles.values()],
            "highest": list(highest.values()),
            "searches": run.paths.searches,
            "batched": run._fleet.batched if run._fleet is not None else 0,
        }
    finally:
        run.close()


if __name__ == "__main__":
    path, until, mode = Path(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
    print(json.dumps(measure(path, until, fleet_step=mode == "fleet")))
