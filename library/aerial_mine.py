"""Implementations of the ``aerial_mine`` capability library (spec: ``aerial_mine.yaml``).

``aerial_mine`` is seed 000's Table I plus ``relocalize``; only the new leaf has an
implementation here (the Table I actions are bound by the runtime, as for ``aerial``).

``relocalize`` is a py_trees behaviour around the pure
:class:`~btmission.localization.relocalize.Relocalizer`: it reads the latest LiDAR scan from the
agent's blackboard and writes whether the agent is localised and the transform of its frame into
the map frame W. Blackboard keys (relative to the agent's namespace, e.g. ``/agents/R1``):

=====================  =====  ===========================================================
key                    access  content
=====================  =====  ===========================================================
``scan``               read   latest scan, ``(N, 3)`` points in the robot frame,
                              gravity-aligned (the simulator writes
                              :func:`~btmission.localization.scan.simulate_scan` at the
                              agent's true pose)
``is_localized``       write  True once a scan was localised
``world_from_robot``   write  4×4 ``T_world_robot`` when the scan was taken (seed 000's
                              ``T : R → W``)
``reloc_confidence``   write  0-1 (docs/relocalization.md says what it means)
``reloc_result``       write  the whole :class:`~btmission.localization.relocalize.Relocalization`
=====================  =====  ===========================================================

The relocalizer (place database and prepared map) is given to the constructor or to
``setup(relocalizer=...)`` / ``setup(reloc_database="map_db.npz")``. The work (~0.1 s) runs on a
worker thread so that the tree keeps ticking (RUNNING meanwhile), or in the tick itself with
``blocking=True``. A scan that is not localised gives FAILURE (``is_localized`` False); ticking the
leaf again tries the newest scan.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
from importlib.resources import files
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import py_trees

from btmission.plugins import Implementations

SPEC = files(__package__).joinpath("aerial_mine.yaml")
"""The library file; the ``btmission.libraries`` entry point ``aerial_mine`` points here."""

IMPLEMENTATIONS = Implementations("aerial_mine")

log = logging.getLogger(__name__)

SCAN = "scan"
IS_LOCALIZED = "is_localized"
WORLD_FROM_ROBOT = "world_from_robot"
CONFIDENCE = "reloc_confidence"
RESULT = "reloc_result"


@IMPLEMENTATIONS.action("relocalize")
class Relocalize(py_trees.behaviour.Behaviour):
    """Global relocalization leaf: scan on the blackboard in, ``is_localized`` and the pose out.

    Args:
        name: the behaviour's name.
        relocalizer: a :class:`~btmission.localization.relocalize.Relocalizer` (or give one to
            :meth:`setup`).
        namespace: the agent's blackboard namespace.
        robot_from_sensor: 4×4 mounting of the LiDAR on the robot (identity: the scan is in the
            robot frame).
        blocking: localise inside the tick instead of on a worker thread.
    """

    def __init__(
        self,
        name: str = "relocalize",
        *,
        relocalizer: Any = None,
        namespace: str = "/",
        robot_from_sensor: npt.ArrayLike | None = None,
        blocking: bool = False,
    ) -> None:
        super().__init__(name)
        self.relocalizer = relocalizer
        self.blocking = blocking
        self.sensor_from_robot = (
            np.eye(4)
            if robot_from_sensor is None
            else np.linalg.inv(np.asarray(robot_from_sensor, dtype=np.float64))
        )
        self.blackboard = self.attach_blackboard_client(name=name, namespace=namespace)
        self.blackboard.register_key(SCAN, access=py_trees.common.Access.READ)
        for key in (IS_LOCALIZED, WORLD_FROM_ROBOT, CONFIDENCE, RESULT):
            self.blackboard.register_key(key, access=py_trees.common.Access.WRITE)
        self._executor: ThreadPoolExecutor | None = None
        self._job: Future[Any] | None = None
        self._done: Any = None

    # ------------------------------------------------------------------ py_trees hooks
    def setup(self, **kwargs: Any) -> None:
        """Take ``relocalizer`` (a Relocalizer) or ``reloc_database`` (a path) from the tree's
        setup arguments when none was given to the constructor."""
        if self.relocalizer is None and kwargs.get("relocalizer") is not None:
            self.relocalizer = kwargs["relocalizer"]
        if self.relocalizer is None and kwargs.get("reloc_database") is not None:
            from btmission.localization.database import load_database
            from btmission.localization.relocalize import Relocalizer

            self.relocalizer = Relocalizer(load_database(Path(kwargs["reloc_database"])))
        if self.relocalizer is None:
            raise RuntimeError(
                f"{self.name}: no relocalizer (pass relocalizer= or reloc_database= to setup)"
            )
        if not self.blocking and self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="relocalize")

    def initialise(self) -> None:
        self._job = None
        self._done = None
        self.feedback_message = "waiting for a scan"

    def update(self) -> py_trees.common.Status:
        if self.relocalizer is None:
            self.feedback_message = "not set up: no relocalizer"
            return py_trees.common.Status.FAILURE
        if self._job is None and self._done is None:
            scan = self.blackboard.get(SCAN) if self.blackboard.exists(SCAN) else None
            if scan is None:
                self.feedback_message = "waiting for a scan"
                return py_trees.common.Status.RUNNING
            points = np.asarray(scan, dtype=np.float64)
            if self.blocking or self._executor is None:
                self._done = self.relocalizer.localize(points)
            else:
                self._job = self._executor.submit(self.relocalizer.localize, points)
        if self._done is None:
            assert self._job is not None
            if not self._job.done():
                self.feedback_message = "localising"
                return py_trees.common.Status.RUNNING
            self._done = self._job.result()
        return self._publish(self._done)

    def terminate(self, new_status: py_trees.common.Status) -> None:
        if new_status == py_trees.common.Status.INVALID and self._job is not None:
            self._job.cancel()  # a running localisation finishes; its result is dropped
        self._job = None

    def shutdown(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    # ------------------------------------------------------------------ results
    def _publish(self, result: Any) -> py_trees.common.Status:
        self.blackboard.set(RESULT, result)
        self.blackboard.set(CONFIDENCE, float(result.confidence))
        self.blackboard.set(IS_LOCALIZED, bool(result.localized))
        self.feedback_message = result.reason
        if not result.localized:
            log.info("%s: %s", self.name, result.reason)
            return py_trees.common.Status.FAILURE
        world_from_robot = np.asarray(result.pose, dtype=np.float64) @ self.sensor_from_robot
        self.blackboard.set(WORLD_FROM_ROBOT, world_from_robot)
        return py_trees.common.Status.SUCCESS


@IMPLEMENTATIONS.condition("is_localized")
def is_localized(ctx: Any) -> bool:
    """Whether the agent is localised in the map: its blackboard's ``is_localized`` (False while
    unset). ``ctx`` is the agent's blackboard client (or any mapping holding the key)."""
    if isinstance(ctx, dict):
        return bool(ctx.get(IS_LOCALIZED, False))
    try:
        return bool(ctx.get(IS_LOCALIZED)) if ctx.exists(IS_LOCALIZED) else False
    except (AttributeError, KeyError):
        return False
