"""The one check of a task added to a running mission, whoever adds it.

A task reaches a running mission from the operator console's page and its HTTP API, from the CLI
(``btmission task add``, through that API) and from a script (:meth:`MissionRun.add_task
<btmission.runtime.runner.MissionRun.add_task>`, an :class:`~btmission.runtime.commands.AddTask`
given to ``submit`` or ``at``). Each goes through the run's
:class:`~btmission.runtime.command_port.CommandPort`, whose :class:`TaskCheck` is the only check
of it, with the rules and messages of the mission file (whose own tasks the loader checks,
:func:`btmission.spec.mission.compile_mission`). :meth:`TaskCheck.reserve`, under one lock:

1. a priority given by name (``low``, ``normal``, ``high``, ``urgent``: multiples of the type's
   own, :data:`~btmission.runtime.commands.PRIORITY_LEVELS`) becomes a number;
2. a task without an id gets the next free one in the mission's pattern (:func:`next_task_id`);
3. the task is read as the mission file's model reads it
   (:func:`btmission.spec.mission.check_added_task`): its type, the fields the type needs and
   no others, their values, its time, its priority and the bound on it, place names against the
   topological map — with the messages ``btmission validate`` gives;
4. its positions are checked against the map as ``btmission validate`` checks them
   (:func:`btmission.world.checks.point_problem`: outside the map, inside rock);
5. its id must be free (not in the pool, not taken by a task queued to enter it), and the pool
   must hold fewer than ``BTMISSION_MAX_TASKS`` tasks;
6. its id is reserved: of two threads adding one id, one is refused.

The answer is the :class:`~btmission.allocation.tasks.TaskInfo` the queued ``AddTask`` carries and
the coordinator puts in the pool as it is. A refusal is a :class:`TaskError` whose message names
the field (``location: (1, 2, 0) is inside rock ...``). A changed priority (``SetPriority``, the
console's PATCH) is checked by :meth:`TaskCheck.priority`, with the same bounds and messages.
"""

from __future__ import annotations

import json
import re
import threading
from collections import Counter
from collections.abc import Callable, Collection, Iterable, Mapping
from typing import TYPE_CHECKING, Any

from btmission.allocation.tasks import TaskInfo
from btmission.errors import BtmissionError

if TYPE_CHECKING:
    from btmission.allocation.tasks import TaskPool
    from btmission.diagnostics import Diagnostic
    from btmission.spec.mission import Mission
    from btmission.world.voxelmap import VoxelMap

TOO_MANY = "too-many-tasks"
"""The :attr:`TaskError.code` of a task refused because the pool is full (a conflict with the
run, not a bad task)."""


class TaskError(BtmissionError, ValueError):
    """A task (or a task's new priority) that cannot be used: ``message`` says why, naming the
    field; ``field`` is that field (None: the task as a whole); ``code`` the mission file's
    diagnostic code for the same problem (``unknown-task-type``, ``missing-field``,
    ``duplicate-id``, ``schema`` ...) or :data:`TOO_MANY`."""

    def __init__(self, message: str, field: str | None = None, code: str = "schema") -> None:
        super().__init__(message)
        self.message = message
        self.field = field
        self.code = code


_MISSING = re.compile(r"lacks field '([^']+)'")
_ID = re.compile(r"^(.*?)(\d+)$")


def refusal(d: Diagnostic) -> TaskError:
    """The :class:`TaskError` of the mission file's diagnostic ``d`` about a task: its message,
    led by the field it names unless it names it already (``type: unknown task type ...``)."""
    missing = _MISSING.search(d.message) if d.code == "missing-field" else None
    field = d.item or (missing.group(1) if missing else None)
    named = field and d.message.startswith((field, f"task field '{field}'"))
    return TaskError(f"{field}: {d.message}" if field and not named else d.message, field, d.code)


def next_task_id(
    tasks: Iterable[tuple[str, str]], task_type: str | None, taken: Callable[[str], bool]
) -> str:
    """The next free id in the pattern of ``tasks`` (``(id, type)`` pairs): T1..T7 → T8; that of
    the tasks of ``task_type`` if there are some (P1 → P2 beside I1, I2), else ``T<n>``. An id
    ``taken`` is skipped."""
    pairs = list(tasks)
    ids = [tid for tid, ttype in pairs if ttype == task_type] if task_type else []
    ids = ids or [tid for tid, _ in pairs]
    prefixes: Counter[str] = Counter()
    top: dict[str, int] = {}
    for tid in ids:
        m = _ID.match(tid)
        if m:
            prefixes[m.group(1)] += 1
            top[m.group(1)] = max(top.get(m.group(1), 0), int(m.group(2)))
    prefix = prefixes.most_common(1)[0][0] if prefixes else "T"
    n = top.get(prefix, 0) + 1
    while taken(f"{prefix}{n}"):
        n += 1
    return f"{prefix}{n}"


class TaskCheck:
    """The run's one check of a task to add (module docstring). ``pool`` gives the
    coordinator's pool as it stands (any thread may read it: each change replaces it); ``places``
    are the topological map's nodes (empty: the mission has none); ``world`` the map positions
    are checked against (None: no map)."""

    def __init__(
        self,
        mission: Mission,
        pool: Callable[[], TaskPool],
        *,
        places: Collection[str] = (),
        world: VoxelMap | None = None,
    ) -> None:
        self.mission = mission
        self._pool = pool
        self.places = frozenset(places)
        self.world = world
        self._lock = threading.RLock()  # (reserve asks next_id under it)
        self._waiting: dict[str, str] = {}
        """Ids reserved by tasks queued to enter the pool, and their types."""

    # ------------------------------------------------------------------ what is taken
    def knows(self, task_id: str) -> bool:
        """Whether ``task_id`` is taken: in the pool, or reserved by a task queued to enter it."""
        # (the reservation first: it is released only once the task is in the pool)
        return task_id in self._waiting or task_id in self._pool()

    @property
    def waiting(self) -> bool:
        """Whether some checked task is still queued to enter the pool (the run is not over)."""
        return bool(self._waiting)

    def type_of(self, task_id: str) -> str | None:
        """The type of the task ``task_id`` (in the pool or queued to enter it), or None."""
        t = self._pool().get(task_id)
        return t.info.type if t is not None else self._waiting.get(task_id)

    def next_id(self, task_type: str | None = None) -> str:
        """The next free id in the mission's pattern (:func:`next_task_id`)."""
        with self._lock:
            tasks = [(t.id, t.info.type) for t in self._pool()]
            return next_task_id([*tasks, *self._waiting.items()], task_type, self.knows)

    # ------------------------------------------------------------------ the check
    def reserve(self, task: Mapping[str, Any] | TaskInfo, now: float) -> TaskInfo:
        """Check ``task`` (``{id?, type, <fields>, priority?, at?}``, or a TaskInfo) at mission
        time ``now`` and reserve its id, atomically (module docstring); the task as the pool
        will have it. Raises :class:`TaskError`."""
        with self._lock:
            info = self._check(task, now)
            self._waiting[info.id] = info.type
        return info

    def release(self, task_id: str) -> None:
        """The task ``task_id`` reserved is in the pool now (or never will be: refused when
        applied, or the run ended first)."""
        with self._lock:
            self._waiting.pop(task_id, None)

    def _check(self, task: Mapping[str, Any] | TaskInfo, now: float) -> TaskInfo:
        from btmission.diagnostics import SpecError
        from btmission.limits import MAX_TASKS
        from btmission.spec.mission import check_added_task
        from btmission.spec.source import parse_yaml

        data: Any = _as_data(task)
        if isinstance(data, Mapping):
            data = dict(data)
            if data.get("id") in (None, ""):
                data["id"] = self.next_id(data.get("type"))
            if isinstance(data.get("priority"), str):  # a name (high: twice the type's)
                data["priority"] = self._priority_number(data["priority"], data.get("type"))
        try:  # the mission file's model and checks, on the task as JSON (JSON is YAML)
            text = json.dumps(data, default=_plain)
        except (TypeError, ValueError, RecursionError) as exc:
            raise TaskError(
                f"a task holds numbers, strings, lists and mappings only ({exc})"
            ) from None
        try:
            checked = check_added_task(
                self.mission, parse_yaml(text, "<task>"), self.places or None
            )
        except SpecError as exc:
            raise refusal(exc.diagnostics[0]) from None
        for name, value in checked.fields.items():
            problem = self._where_problem(value)
            if problem is not None:
                raise TaskError(f"{name}: {problem[1]}", name, problem[0])
        if self.knows(checked.id):
            raise TaskError(f"id: duplicate task id '{checked.id}'", "id", "duplicate-id")
        limit = int(MAX_TASKS.value)
        if len(self._pool()) + len(self._waiting) >= limit:
            raise TaskError(f"the mission has {limit} tasks already (BTMISSION_MAX_TASKS)",
                            code=TOO_MANY)  # fmt: skip
        tt = self.mission.task_types[checked.type]
        return TaskInfo(
            checked.id,
            checked.type,
            dict(checked.fields),
            checked.priority,
            max(checked.at, now),
            tt.commit_after is not None,
            tt.max_attempts,
        )

    def priority(self, task_id: str, value: Any) -> float:
        """A new priority for the task ``task_id`` (a number > 0, or a name: a multiple of its
        type's), within the bounds of a task's priority in the mission file, with its messages.
        Raises :class:`TaskError`."""
        from btmission.diagnostics import SpecError
        from btmission.spec.mission import check_priority

        if isinstance(value, str):
            value = self._priority_number(value, self.type_of(task_id))
        try:
            return check_priority(self.mission, task_id, value)
        except SpecError as exc:
            raise refusal(exc.diagnostics[0]) from None

    def _priority_number(self, value: str, task_type: Any) -> Any:
        """A priority given as text: a name of PRIORITY_LEVELS (a multiple of the priority of
        ``task_type``, 1 if it is none) or a number written as text."""
        from btmission.runtime.commands import CommandError, priority_value

        tt = self.mission.task_types.get(task_type) if isinstance(task_type, str) else None
        try:
            return priority_value(value, tt.priority if tt is not None else 1.0)
        except CommandError as exc:
            raise TaskError(str(exc), "priority") from None

    def _where_problem(self, value: Any) -> tuple[str, str] | None:
        """(code, message) when ``value`` is a position ``[x, y, z]`` outside the map or inside
        rock (as ``btmission validate`` says it)."""
        from btmission.world.checks import point_problem

        if self.world is None or not (isinstance(value, (list, tuple)) and len(value) == 3):
            return None
        return point_problem(self.world, (float(value[0]), float(value[1]), float(value[2])))


def _as_data(task: Any) -> Any:
    """A task as the plain data an operator gives (a TaskInfo as its mapping)."""
    if isinstance(task, TaskInfo):
        return {"id": task.id, "type": task.type, **task.fields, "priority": task.priority,
                "at": task.arrival_s}  # fmt: skip
    return task


def _plain(value: Any) -> Any:
    """A numpy number or array as plain data (json.dumps' fallback)."""
    tolist = getattr(value, "tolist", None)
    if callable(tolist):
        return tolist()
    raise TypeError(f"{type(value).__name__} {value!r} is not one")
