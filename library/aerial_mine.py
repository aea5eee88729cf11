"""Implementations of the ``aerial_mine`` capability library (spec: ``aerial_mine.yaml``).

``aerial_mine`` is seed 000's Table I plus one action, ``relocalize``, achieving the condition
``is_localized`` that ``takeoff`` needs first (§IV-C1: before a mission each agent finds the
transform ``T : R → W`` from its frame to the shared map frame W, from one LiDAR scan). Every
Table I action and condition, the vehicle kind, the settings and the setup hooks are ``aerial``'s
own (:meth:`~btmission.plugins.Implementations.extend`), so ``aerial``'s tree stays exactly seed
000's Fig. 8 and this library's is Fig. 8 with one more fallback under take-off.

``relocalize`` is a :class:`~btmission.runtime.leaves.StatefulAction`: on every tick until it ends
it asks the agent's sensors for the latest full-range 3D LiDAR scan
(:meth:`~btmission.vehicles.base.Sensors.lidar_scan`: in the simulator, every beam of an
OS1-32-like sensor ray-cast through the voxel map from the vehicle's true pose), RUNNING while
there is none (a real driver needs a full turn first; FAILURE after ``SCAN_TIMEOUT_S``), then
localises it inside the tick — so a run stays deterministic for a seed — with the
:class:`~btmission.localization.relocalize.Relocalizer` (descriptors → candidate poses →
coarse-then-fine GICP → best fit; ~0.1 s). It writes on the agent's blackboard

=====================  ==============================================================
key                    content
=====================  ==============================================================
``is_localized``       True once a scan was localised (the condition reads it)
``world_from_robot``   4×4 ``T_world_robot`` when the scan was taken (the LiDAR mounting
                       taken out): seed 000's ``T : R → W``
``reloc_confidence``   0-1 (docs/relocalization.md says what it means)
``reloc_result``       the whole :class:`~btmission.localization.relocalize.Relocalization`
=====================  ==============================================================

publishes a ``relocalized`` event (estimate, confidence, the vehicle's telemetry pose — the truth
in the simulator — and the error against it), and ends SUCCESS, or FAILURE with the reason ("not
localised: …") reported with the task.

**The relocalizer** is made once per map by a setup hook, before the first tick: from the place
database file of the setting ``reloc_database`` (relative to the mission file, as its map file is;
``btmission reloc build`` writes one), or, when that is empty, built from the run's own voxel map
with places every ``reloc_spacing_m`` metres. Relocalizers are memoised by map content and
settings (:func:`shared_relocalizer`), so N agents on one map — and several runs of one mission in
a process — build one database.

**What the estimate is used for.** It gates take-off (an agent that cannot localise does not fly,
and its task fails with the reason) and it is logged with its error. Navigation still uses the
vehicle's telemetry: in the simulator that is already the true pose in W, so there is nothing to
correct; a real vehicle whose odometry starts in its own frame would need ``world_from_robot``
applied to its telemetry, which the runtime does not do yet.

Settings (``runtime.settings`` of a mission, :class:`MineSettings`): ``reloc_database`` (path,
default ``""``: build one from the map), ``reloc_spacing_m`` (1.0: the spacing the benchmark
measured) and the navigator's.
"""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from py_trees.common import Status

from btmission.diagnostics import Diagnostic, Location, Severity, SpecError
from btmission.runtime.eventkinds import RelocalizedEvent
from btmission.runtime.leaves import AgentContext, StatefulAction
from btmission.settings import SettingError, settings_from
from btmission_library import aerial

if TYPE_CHECKING:
    from btmission.localization.relocalize import Relocalization, Relocalizer
    from btmission.spec.mission import Mission as MissionFile
    from btmission.vehicles.base import LidarScan
    from btmission.world.voxel import VoxelMap

SPEC = files(__package__).joinpath("aerial_mine.yaml")
"""The library file; the ``btmission.libraries`` entry point ``aerial_mine`` points here."""


@dataclass(frozen=True)
class MineSettings:
    """The ``aerial_mine`` library's own settings (``runtime.settings`` of a mission), besides
    the navigator's."""

    reloc_database: str = ""
    """The relocalizer's place database, relative to the mission file; empty: built from the map.

    ``btmission reloc build`` writes one."""
    reloc_spacing_m: float = 1.0
    """Spacing of the places of a database built from the map (m; 1.0: what the benchmark
    measured)."""


IMPLEMENTATIONS = aerial.IMPLEMENTATIONS.extend("aerial_mine", settings=MineSettings)

IS_LOCALIZED = "is_localized"
WORLD_FROM_ROBOT = "world_from_robot"
CONFIDENCE = "reloc_confidence"
RESULT = "reloc_result"
RELOCALIZER = "relocalizer"
"""``ctx.state`` key of the agent's :class:`Relocalizer` (set by the setup hook)."""
SCAN_TIMEOUT_S = 5.0
"""``relocalize`` fails when the sensors give no scan for this long."""
CACHE_SIZE = 2
"""Relocalizers kept (each holds its map and database: tens of MB for a 200 m mine)."""


# ------------------------------------------------------------------------------- relocalizers
_cache: OrderedDict[tuple[Any, ...], Relocalizer] = OrderedDict()


def _map_key(vm: VoxelMap) -> str:
    h = hashlib.blake2b(vm.state.tobytes(), digest_size=16)
    h.update(repr((vm.state.shape, vm.resolution, vm.origin)).encode())
    return h.hexdigest()


def shared_relocalizer(
    vm: VoxelMap, database: Path | None = None, *, spacing_m: float = 1.0
) -> Relocalizer:
    """The relocalizer of a place database file, or of ``vm`` (a database built with places
    every ``spacing_m`` metres), made once and memoised (the last ``CACHE_SIZE``, keyed by the
    file's path, size and modification time, or by the map's content and the spacing).

    Raises :class:`~btmission.localization.database.DatabaseError` when the file cannot be read
    or the map has no place for a sensor."""
    from btmission.localization.database import build_database, load_database
    from btmission.localization.relocalize import Relocalizer

    if database is not None:
        st = database.stat() if database.is_file() else None
        key: tuple[Any, ...] = (
            "file",
            str(database.resolve()),
            st.st_size if st else -1,
            st.st_mtime_ns if st else -1,
        )
    else:
        key = ("map", _map_key(vm), float(spacing_m))
    found = _cache.get(key)
    if found is not None:
        _cache.move_to_end(key)
        return found
    db = (
        load_database(database) if database is not None else build_database(vm, spacing_m=spacing_m)
    )
    reloc = Relocalizer(db)
    _cache[key] = reloc
    while len(_cache) > CACHE_SIZE:
        _cache.popitem(last=False)
    return reloc


def database_path(setting: Any, mission: MissionFile | None) -> Path | None:
    """The ``reloc_database`` setting as a path (relative to the mission file); None: unset."""
    name = str(setting or "")
    if not name:
        return None
    database = Path(name)
    if not database.is_absolute() and mission is not None:
        database = mission.base_dir / database
    return database


def check_mission(mission: MissionFile) -> list[Diagnostic]:
    """A ``reloc_database`` that is not a file, found before any run (``validate`` and ``run``
    call it through :func:`btmission.runtime.runcheck.run_problems`); its content is read when the
    run sets the agents up."""
    try:
        settings = settings_from(MineSettings, mission.spec.runtime.settings)
    except SettingError:  # a value of the wrong type: run_problems' settings check says so
        return []
    database = database_path(settings.reloc_database, mission)
    if database is None or database.is_file():
        return []
    where = mission.locate(("runtime", "settings", "reloc_database"))
    return [Diagnostic(Severity.ERROR, "bad-setting",
                       f"cannot make the relocalizer: {database}: no such file",
                       "runtime.settings.reloc_database", where)]  # fmt: skip


@IMPLEMENTATIONS.on_setup
def _setup_relocalizer(ctx: AgentContext) -> None:
    """Give the agent its map's relocalizer (module docstring); a bad setting is a mission
    error (exit status 2), reported before anything runs."""
    from btmission.localization.database import DatabaseError

    mission = ctx.agent.mission if ctx.agent is not None else None
    where = Location(mission.file if mission is not None else "<settings>")

    def bad(setting: str, message: str) -> SpecError:
        return SpecError(
            [
                Diagnostic(
                    Severity.ERROR,
                    "bad-setting",
                    message,
                    f"runtime.settings.{setting}",
                    where,
                )
            ]
        )

    spacing_wrong = "expected a positive number of metres, got {!r}"
    try:
        settings = ctx.settings_of(MineSettings)
    except SettingError as exc:
        wrong = exc.setting
        if wrong is None:  # (every SettingError the settings raise names its setting)
            raise
        raise bad(wrong.name, spacing_wrong.format(exc.value) if wrong.name == "reloc_spacing_m"
                  else f"expected {wrong.expected}, got {exc.value!r}") from None  # fmt: skip
    spacing = settings.reloc_spacing_m
    if not spacing > 0:
        raise bad("reloc_spacing_m", spacing_wrong.format(spacing))
    database = database_path(settings.reloc_database, mission)
    try:
        ctx.state[RELOCALIZER] = shared_relocalizer(ctx.paths.map, database, spacing_m=spacing)
    except DatabaseError as exc:
        setting = "reloc_database" if database is not None else "reloc_spacing_m"
        raise bad(setting, f"cannot make the relocalizer: {exc}") from None


# ------------------------------------------------------------------------------- leaves
@IMPLEMENTATIONS.condition("is_localized")
def is_localized(ctx: AgentContext) -> bool:
    """The agent knows its pose in the map frame W (its blackboard's ``is_localized``)."""
    return bool(ctx.blackboard.get(IS_LOCALIZED, False))


def _pose_record(pose: np.ndarray) -> dict[str, float]:
    from btmission.localization.scan import yaw_of

    return {
        "x": round(float(pose[0, 3]), 4),
        "y": round(float(pose[1, 3]), 4),
        "z": round(float(pose[2, 3]), 4),
        "yaw_deg": round(float(np.degrees(yaw_of(pose))), 3),
    }


@IMPLEMENTATIONS.action("relocalize")
class Relocalize(StatefulAction):
    """Localise the agent in the shared map from one LiDAR scan (module docstring)."""

    def on_start(self) -> Status:
        self._since = self.ctx.now()
        return self.on_running()

    def on_running(self) -> Status:
        reloc: Relocalizer | None = self.ctx.state.get(RELOCALIZER)
        if reloc is None:
            self.reason = "no relocalizer (the library's setup hook did not run)"
            return Status.FAILURE
        sensors = self.ctx.sensors
        if sensors is None:
            self.reason = "the vehicle has no sensors"
            return Status.FAILURE
        scan = sensors.lidar_scan()
        if scan is None:
            if self.ctx.now() - self._since >= SCAN_TIMEOUT_S:
                self.reason = f"no LiDAR scan within {SCAN_TIMEOUT_S:g} s"
                return Status.FAILURE
            return Status.RUNNING
        t0 = time.perf_counter()
        result = reloc.localize(scan.points)
        return self._publish(result, scan, (time.perf_counter() - t0) * 1000)

    def _publish(self, result: Relocalization, scan: LidarScan, ms: float) -> Status:
        from btmission.localization.relocalize import pose_error
        from btmission.localization.scan import pose_matrix

        board = self.ctx.blackboard
        board.set(RESULT, result)
        board.set(CONFIDENCE, float(result.confidence))
        board.set(IS_LOCALIZED, bool(result.localized))
        tel = self.ctx.telemetry()
        p = tel.position
        truth = pose_matrix(float(p[0]), float(p[1]), float(p[2]), tel.yaw)
        found: dict[str, Any] = {}  # the estimate and its error, when localised
        if result.localized and result.pose is not None:
            estimate = np.asarray(result.pose) @ np.linalg.inv(scan.robot_from_sensor)
            board.set(WORLD_FROM_ROBOT, estimate)
            err_m, err_deg = pose_error(estimate, truth)
            found = {
                "estimate": _pose_record(estimate),
                "error_m": round(err_m, 4),
                "error_deg": round(err_deg, 3),
            }
        else:
            board.unset(WORLD_FROM_ROBOT)
            self.reason = result.reason
        self.ctx.events(
            RelocalizedEvent(
                agent=self.ctx.agent_id,
                task=board.get("task"),
                localized=bool(result.localized),
                confidence=round(float(result.confidence), 4),
                fitness=round(float(result.fitness), 4),
                reason=result.reason,
                points=len(scan.points),
                sensor=scan.sensor,
                time_ms=round(ms, 1),
                truth=_pose_record(truth),
                **found,
            )
        )
        return Status.SUCCESS if result.localized else Status.FAILURE
