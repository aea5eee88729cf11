"""Mission files (DESIGN.md §4.3): the schema users write and the checked :class:`Mission`.

Loading validates the whole file and reports every problem at once, each with file:line:col and
the item: YAML syntax, unknown keys, wrong types, duplicate ids, unknown libraries, conditions and
task types, task fields a task type needs but a task lacks (or has but no type uses), cost
expressions, commit conditions, and whether every agent's trees synthesise. Checks against the map
(locations inside rock) belong to the world-map component.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Generic, Literal, Protocol, TypeVar

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
)

from btmission.diagnostics import Diagnostic, Location, Severity, SpecError, errors
from btmission.spec.budgets import check_mission_scale
from btmission.spec.common import (
    FiniteFloat,
    FormatVersion,
    Identifier,
    number_problem,
    shown,
    validate_model,
)
from btmission.spec.costexpr import CostExpr, CostExprError, parse_cost
from btmission.spec.library import Atom, Library, resolve_ref
from btmission.spec.sections import (
    FileMap,
    RuntimeSpec,
    Vec3,
    WorldSpec,
    _Strict,
)
from btmission.spec.source import Source, format_path
from btmission.spec.vehicleref import BACKEND_RE, VehicleRef

MISSION_FORMAT_VERSION = 1


class ResolvedLibrary(Protocol):
    """What the file model needs of an agent's library: its checked model and its findings.
    (Loading gives :class:`btmission.plugins.LoadedLibrary`, which also carries the
    implementations; the file model never looks at them.)"""

    @property
    def library(self) -> Library: ...

    @property
    def diagnostics(self) -> list[Diagnostic]: ...


L = TypeVar("L", bound=ResolvedLibrary)

LibraryResolver = Callable[[str, Path, Location], L]
"""Finds an agent's library: ``resolve(ref, base_dir, where)`` — the reference as the mission
writes it, the mission file's directory, and where the reference is written (for the message).
Raises :class:`SpecError` when it cannot be found. The file model does not load libraries
itself (it would import their implementation code): :func:`btmission.missions.load_mission`
passes :func:`btmission.plugins.load_library`."""


NORTH_YAW_DEG = 90.0
"""Default world yaw of a vehicle's local north: world +y is north (a map laid out north-up)."""


class OriginSpec(_Strict):
    """Where a MAVLink vehicle's local NED frame (its EKF origin) is in the world."""

    position: Vec3 = Field(description="World position [x, y, z] (m) of the vehicle's EKF origin.")
    north_yaw_deg: FiniteFloat = Field(
        NORTH_YAW_DEG,
        description="World yaw (degrees, counter-clockwise from +x) of the vehicle's local north "
        "(its NED +x axis); 90: world +y is north.",
    )


ORIGIN_FORMS = "[x, y, z] or {position: [x, y, z], north_yaw_deg: 90}"


def _origin_shorthand(v: Any) -> Any:
    """``origin: [x, y, z]`` is ``origin: {position: [x, y, z]}``; anything but a list or a
    mapping is refused with what is expected (not pydantic's union of both shapes)."""
    if v is None or isinstance(v, dict):
        return v
    if isinstance(v, list):
        if len(v) != 3 or any(number_problem(x) is not None for x in v):
            raise ValueError(f"expected {ORIGIN_FORMS}, with finite numbers (got {shown(v)})")
        return {"position": v}
    raise ValueError(f"expected {ORIGIN_FORMS} (got {shown(v)})")


class AgentSpec(_Strict):
    id: Identifier
    library: str = Field(description="Capability library: an installed name or a path to its YAML.")
    start: Vec3
    backend: str = Field(
        "sim",
        description="The vehicle provider: 'sim' (embedded simulator) or <scheme>://<address> "
        "of an installed provider, such as mavlink+udp://127.0.0.1:14540",
        json_schema_extra={"pattern": BACKEND_RE},
    )
    origin: Annotated[
        OriginSpec | None,
        BeforeValidator(_origin_shorthand, json_schema_input_type=Vec3 | OriginSpec | None),
    ] = Field(
        None,
        description="MAVLink vehicles: where the vehicle's local NED origin (its EKF origin) is "
        "in the world, " + ORIGIN_FORMS + "; default: its start, north along +y. Ignored by sim.",
    )

    @field_validator("backend")
    @classmethod
    def _backend(cls, v: str) -> str:
        VehicleRef.parse(v)  # its general form; the provider checks the rest (vehicleref.py)
        return v


class TaskSpec(BaseModel):
    """One task. Besides these keys, a task carries the fields its type's goal and cost use."""

    model_config = ConfigDict(extra="allow", frozen=True)
    id: Identifier
    type: Identifier
    at: FiniteFloat = Field(0.0, ge=0, description="Time (s) the task is added to the pool.")
    priority: FiniteFloat | None = Field(
        None, gt=0, description="Overrides the task type's priority."
    )


MAX_ATTEMPTS = 1000
"""Largest ``max_attempts`` of a task type (a task is not tried forever)."""

MAX_PRIORITY_WEIGHT = 1e12
"""Largest priority × priority_scale: the auction's bound on bids and bonuses
(btmission.allocation.solvers.MAX_COST); beyond it the profits overflow or swamp the costs."""


def _goal_value(v: Any) -> Any:
    """A goal: one condition, or a non-empty list of them (an empty list has nothing to do)."""
    if isinstance(v, str) or (isinstance(v, list) and v):
        return v
    raise ValueError(f"expected a goal condition or a non-empty list of them (got {v!r})")


GoalValue = Annotated[
    str | Annotated[list[str], Field(min_length=1)], BeforeValidator(_goal_value)
]  # min_length: the JSON Schema says it too


def _cost_value(v: Any) -> Any:
    """A task type's cost: an expression, or a finite number written without quotes (kept as
    the text of that number)."""
    if isinstance(v, (bool, int, float)):
        problem = number_problem(v)
        if problem:
            raise ValueError(
                f"{problem}; a cost is an expression such as path_cost(location) or a number ≥ 0"
            )
        return str(v)  # the expression of a constant, as written (-1, not -1.0)
    if not isinstance(v, str):
        raise ValueError(
            f"expected a cost expression such as path_cost(location) or a number ≥ 0 (got {v!r})"
        )
    return v


class TaskTypeSpec(_Strict):
    goal: GoalValue = Field(description="Goal condition(s), e.g. at_goal(location).")
    cost: Annotated[str | float, BeforeValidator(_cost_value)] = Field(
        description="Bid cost expression, e.g. path_cost(location), or a number ≥ 0."
    )
    commit_after: str | None = Field(
        None, description="Condition after which the agent commits to the task (k_bt = 0)."
    )
    priority: FiniteFloat = Field(
        1.0, gt=0, description="Priority; scaled by coordination.priority_scale."
    )
    max_attempts: int = Field(
        3,
        ge=1,
        le=MAX_ATTEMPTS,
        description="Agents' attempts at a task of this type before it fails for good: an "
        "agent whose vehicle keeps refusing (arming, OFFBOARD) gives the task up and it is "
        "offered to the others, until this many attempts have failed.",
    )


class CoordinationSpec(_Strict):
    auction_rate_hz: FiniteFloat = Field(10.0, gt=0, description="Auction rounds per second.")
    participation: FiniteFloat = Field(
        1.0, gt=0, le=1, description="Fraction of tasks each agent bids on."
    )
    priority_scale: FiniteFloat = Field(
        1000.0, ge=0, description="Weight of task priority in the profit."
    )
    solver: Literal["assignment", "ilp-scip"] = Field(
        "assignment", description="Assignment solver."
    )
    agent_timeout_s: FiniteFloat = Field(
        3.0, gt=0, description="Silence after which an agent is dropped."
    )
    lease_s: FiniteFloat = Field(
        30.0,
        gt=0,
        description="How long a silent agent keeps the task it holds (s, after its last word): "
        "the coordinator re-offers the task only then, and the agent, if it cannot reach the "
        "coordinator, stops the task agent_timeout_s before that. Long enough to ride out "
        "Wi-Fi drop-outs; a dead agent's task waits this long.",
    )
    bid_window_s: FiniteFloat = Field(
        0.0,
        ge=0,
        description="How long a round collects bids after its announcement (0: in the same "
        "step, as the in-process bus delivers them); later bids are ignored and counted.",
    )
    switch_cost: FiniteFloat = Field(
        0.0,
        ge=0,
        description="Added to an agent's bids on tasks other than the one it executes "
        "(hysteresis against swapping on near-equal bids; 0 = the paper's auction).",
    )
    cooldown_s: FiniteFloat = Field(
        30.0,
        ge=0,
        description="An agent that gave a task up (its vehicle kept refusing) gets no part in "
        "that task's allocation for this long (s): the other agents are offered it first.",
    )
    exclude_after: int = Field(
        3,
        ge=0,
        description="Different tasks an agent may give up in a row, none done between, before "
        "it is taken out of the auction, as the operator's exclude does (0: never); the last "
        "agent bidding is never taken out.",
    )

    @field_validator("lease_s")
    @classmethod
    def _lease_past_timeout(cls, v: float, info: ValidationInfo) -> float:
        timeout = info.data.get("agent_timeout_s")
        if isinstance(timeout, float) and v <= timeout:
            raise ValueError(
                f"must be longer than agent_timeout_s ({timeout:g} s): a silent agent keeps "
                "its task for the lease and stops it agent_timeout_s before the lease ends"
            )
        return v

    @field_validator("bid_window_s")
    @classmethod
    def _window_within_timeout(cls, v: float, info: ValidationInfo) -> float:
        timeout = info.data.get("agent_timeout_s")
        if isinstance(timeout, float) and v >= timeout:
            raise ValueError(
                f"must be shorter than agent_timeout_s ({timeout:g} s): every bid would be "
                "older than the timeout when the round allocates, so no agent would get a task"
            )
        return v


class DefaultBehaviorSpec(_Strict):
    goal: GoalValue = Field(description="Goal of the default behaviour, e.g. landed_at_home.")
    idle_timeout_s: FiniteFloat = Field(
        10.0, ge=0, description="Idle time before the default behaviour runs."
    )


class MissionSpec(_Strict):
    """A mission file (``version: 1``)."""

    mission: Identifier
    version: FormatVersion
    description: str = ""
    world: WorldSpec
    agents: list[AgentSpec] = Field(min_length=1)
    tasks: list[TaskSpec] = Field(default_factory=list)
    task_types: dict[Identifier, TaskTypeSpec]
    coordination: CoordinationSpec = CoordinationSpec()
    default_behavior: DefaultBehaviorSpec | None = None
    runtime: RuntimeSpec = RuntimeSpec()


# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TaskType:
    """A checked task type: goal atoms over task fields, cost expression, commit condition."""

    name: str
    goals: tuple[Atom, ...]
    cost: CostExpr
    commit_after: Atom | None
    priority: float
    fields: tuple[str, ...]
    """Every task field the type reads (goal, cost and commit symbols)."""
    max_attempts: int = 3
    """Agents' attempts before a task of this type fails for good."""


@dataclass(frozen=True)
class Task:
    id: str
    type: str
    at: float
    priority: float
    fields: Mapping[str, Any]
    where: Location = Location()


@dataclass(frozen=True)
class Agent:
    id: str
    library: str
    start: tuple[float, float, float]
    vehicle: VehicleRef
    """Its ``backend:``, read once (:mod:`btmission.spec.vehicleref`)."""
    where: Location = Location()

    @property
    def backend(self) -> str:
        """The ``backend:`` as written."""
        return self.vehicle.url


@dataclass(frozen=True)
class DefaultBehavior:
    goals: tuple[Atom, ...]
    idle_timeout_s: float


@dataclass
class Mission(Generic[L]):
    """A validated mission with its resolved libraries (of the type its resolver gives:
    :data:`btmission.missions.LoadedMission` for a mission loaded to run)."""

    name: str
    spec: MissionSpec
    file: str
    agents: list[Agent]
    tasks: list[Task]
    task_types: dict[str, TaskType]
    default_behavior: DefaultBehavior | None
    libraries: dict[str, L]
    """Library reference as written in the file → loaded library."""
    diagnostics: list[Diagnostic] = field(default_factory=list)
    """Warnings and infos found while loading (errors raise instead)."""
    source: Source | None = None
    """The parsed file, to locate what later checks (:mod:`btmission.runtime.runcheck`) find."""

    def agent(self, agent_id: str) -> Agent:
        for a in self.agents:
            if a.id == agent_id:
                return a
        raise KeyError(agent_id)

    def locate(self, path: Sequence[str | int], *, key: bool = False) -> Location:
        """Where ``path`` (e.g. ``("agents", 0, "start")``) is in the file (the file when the
        mission was not loaded from one)."""
        return self.source.locate(path, key=key) if self.source else Location(self.file)

    def library_of(self, agent_id: str) -> L:
        return self.libraries[self.agent(agent_id).library]

    @property
    def base_dir(self) -> Path:
        return Path(self.file).parent


def _goal_list(g: str | list[str]) -> list[str]:
    return [g] if isinstance(g, str) else list(g)


def _check_field_value(v: Any) -> str | None:
    expected = "expected a position [x, y, z], a number or a name"
    if isinstance(v, str):
        return None
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return None if number_problem(v) is None else f"{expected}; numbers must be finite"
    if isinstance(v, list) and len(v) == 3 and all(number_problem(x) is None for x in v):
        return None
    if (
        isinstance(v, list)
        and len(v) == 3
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
    ):
        return f"{expected}; coordinates must be finite numbers"
    return expected


AddProblem = Callable[..., None]
"""``add(path, message, code, severity=ERROR, key=False)``: how a check reports a problem."""


def _adder(src: Source, diags: list[Diagnostic], *, errors_only: bool = False) -> AddProblem:
    """The ``add`` of the checks: each problem a Diagnostic located in ``src``, into ``diags``
    (``errors_only``: warnings are dropped)."""

    def add(
        path: Sequence[str | int],
        message: str,
        code: str,
        sev: Severity = Severity.ERROR,
        key: bool = False,
    ) -> None:
        if sev is Severity.ERROR or not errors_only:
            diags.append(
                Diagnostic(sev, code, message, format_path(path), src.locate(path, key=key))
            )

    return add


def _check_task(
    t: TaskSpec,
    tpath: tuple[str | int, ...],
    spec: MissionSpec,
    task_types: Mapping[str, TaskType],
    src: Source,
    add: AddProblem,
    heavy: set[tuple[str | int, ...]],
) -> tuple[float, dict[str, Any]] | None:
    """One task's checks beyond the schema (its field values, its type, the fields the type
    needs and no others, when it arrives, its priority's weight); its priority and fields, or
    None when its type is unknown. Shared by mission files and tasks added while a mission runs
    (:func:`check_added_task`), so both get the same messages."""
    task_fields: dict[str, Any] = dict(t.model_extra or {})
    for k, v in task_fields.items():
        problem = _check_field_value(v)
        if problem:
            add((*tpath, k), f"task field '{k}': {problem} (got {v!r})", "schema")
    if t.type not in spec.task_types:
        close = difflib.get_close_matches(t.type, list(spec.task_types), n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        add(
            (*tpath, "type"),
            f"unknown task type '{t.type}'{hint}; declared: {', '.join(spec.task_types) or 'none'}",
            "unknown-task-type",
        )
        return None
    tt2 = task_types.get(t.type)
    if tt2 is None:
        return None
    for need in tt2.fields:
        if need not in task_fields:
            add(
                tpath,
                f"task '{t.id}' of type '{t.type}' lacks field '{need}' (the type uses: {', '.join(tt2.fields)})",
                "missing-field",
            )
    for k in task_fields:
        if k not in tt2.fields:
            add(
                (*tpath, k),
                f"unknown key '{k}' for a task of type '{t.type}' (expected: id, type, "
                f"at, priority, {', '.join(tt2.fields)})",
                "schema",
                key=True,
            )
    limit = spec.runtime.max_duration_s
    if t.at >= limit:
        add((*tpath, "at"), f"task '{t.id}' is added at {t.at:g} s, when a run has already "
            f"stopped (runtime.max_duration_s is {limit:g} s)", "never-added", Severity.WARNING)  # fmt: skip
    prio = t.priority if t.priority is not None else tt2.priority
    ppath: tuple[str | int, ...] = (*tpath, "priority")
    if t.priority is None:  # the type's priority, else the default 1: blame the scale
        ppath = ("task_types", t.type, "priority")
        if ppath not in src.key_positions:
            ppath = ("coordination", "priority_scale")
    heavy_problem = _priority_problem(t.id, prio, spec)
    if heavy_problem and ppath not in heavy:
        heavy.add(ppath)
        add(ppath, heavy_problem, "schema")
    return prio, task_fields


def _priority_problem(task_id: str, prio: float, spec: MissionSpec) -> str | None:
    """Why a task's priority (its own or its type's) is too large for the auction, or None:
    the one upper bound of a priority, wherever it comes from (the file, an added task, a
    changed priority: :func:`check_priority`)."""
    weight = prio * spec.coordination.priority_scale
    if weight <= MAX_PRIORITY_WEIGHT:
        return None
    return (f"task '{task_id}': priority {prio:g} × coordination.priority_scale "
            f"{spec.coordination.priority_scale:g} is {weight:g}; the auction takes at most "
            f"{MAX_PRIORITY_WEIGHT:g}")  # fmt: skip


def _place_problem(
    name: str, v: str, tt: TaskType, topomap: str | None, places: frozenset[str] | None
) -> tuple[str, str] | None:
    """(message, code) when the cost argument ``name`` is the place name ``v`` and that is not
    a place: no topological map, or no node of that name."""
    if places is None:
        return (f"task field '{name}' is used as a position by the cost '{tt.cost.text}': "
                f"expected [x, y, z] (a place name like {v!r} needs a world.topomap)", "schema")  # fmt: skip
    if v not in places:
        close = difflib.get_close_matches(v, sorted(places), n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        return (f"task field '{name}': '{v}' is not a node of the topological map "
                f"'{topomap}'{hint}", "unknown-place")  # fmt: skip
    return None


def check_added_task(mission: Mission, src: Source, places: frozenset[str] | None = None) -> Task:
    """A task added while ``mission`` runs (the run's one check of it,
    :class:`btmission.runtime.taskcheck.TaskCheck`, whoever adds it), given as the mapping
    ``src.data`` (``{id, type, [at], [priority], <the type's fields>}``), checked as a task of
    the mission file is: the same model, the same checks, the same messages; each problem's
    item names the field. ``places``: the topological map's nodes, if the mission has one.
    Raises :class:`SpecError` with every error."""
    if not isinstance(src.data, dict):
        raise SpecError([src.diag((), "a task must be a JSON object such as {\"type\": "
                                  "\"inspect\", \"location\": [x, y, z]}", "schema")])  # fmt: skip
    t: TaskSpec = validate_model(TaskSpec, src, "task")
    diags: list[Diagnostic] = []
    add = _adder(src, diags, errors_only=True)
    checked = _check_task(t, (), mission.spec, mission.task_types, src, add, set())
    if checked is not None and not diags:
        fields = checked[1]
        tt = mission.task_types[t.type]
        problem = tt.cost.probe(fields)
        if problem:
            add((), f"{problem} (the cost of task type '{t.type}': {tt.cost.text})",
                "cost-expression")  # fmt: skip
        for name, v in fields.items():
            if name in tt.cost.symbols and isinstance(v, str):
                found = _place_problem(name, v, tt, mission.spec.world.topomap, places)
                if found:
                    add((name,), *found)
    if diags:
        raise SpecError(diags)
    assert checked is not None
    return Task(t.id, t.type, t.at, checked[0], checked[1], src.locate(()))


def check_priority(mission: Mission, task_id: str, value: Any) -> float:
    """A new priority for the task ``task_id`` while ``mission`` runs (the
    operator's change of priority), checked as a task's ``priority:`` in the mission file is:
    the same model, bound and messages, the item ``priority``. Raises :class:`SpecError`."""
    # (the task's own id and type were checked when it was added: only the priority is read)
    src = Source("<priority>", {"id": "T", "type": "t", "priority": value})
    if value is None:
        raise SpecError([src.diag(("priority",), "expected a number > 0 (got null)", "schema")])
    t: TaskSpec = validate_model(TaskSpec, src, "task")
    assert t.priority is not None
    problem = _priority_problem(task_id, t.priority, mission.spec)
    if problem:
        raise SpecError([src.diag(("priority",), problem, "schema")])
    return t.priority


def compile_mission(spec: MissionSpec, src: Source, resolve: LibraryResolver[L]) -> Mission[L]:
    """Check everything that needs more than the schema, with each agent's library found by
    ``resolve``. Raises :class:`SpecError` with all errors."""
    from btmission.spec.agent_trees import check_agent_trees

    diags: list[Diagnostic] = []
    add = _adder(src, diags)
    base = Path(src.file).parent
    # agents: unique ids, libraries resolvable and sound
    agents: list[Agent] = []
    seen: dict[str, int] = {}
    libraries: dict[str, L] = {}
    lib_failed: set[str] = set()
    for i, a in enumerate(spec.agents):
        if a.id in seen:
            first = src.locate(("agents", seen[a.id], "id")).line
            add(
                ("agents", i, "id"),
                f"duplicate agent id '{a.id}' (first used on line {first})",
                "duplicate-id",
            )
        seen.setdefault(a.id, i)
        agents.append(
            Agent(a.id, a.library, a.start, VehicleRef.parse(a.backend), src.locate(("agents", i)))
        )
        if a.library in libraries or a.library in lib_failed:
            continue
        try:
            loaded = resolve(a.library, base, src.locate(("agents", i, "library")))
        except SpecError as exc:
            lib_failed.add(a.library)
            for d in exc.diagnostics:
                if d.code == "unknown-library":
                    add(("agents", i, "library"), d.message, d.code)
                else:
                    diags.append(d)
            continue
        lib_errors = errors(loaded.diagnostics)
        if lib_errors:
            lib_failed.add(a.library)
            add(
                ("agents", i, "library"),
                f"library '{a.library}' has {len(lib_errors)} error(s), listed below",
                "library-errors",
            )
            diags.extend(lib_errors)
            continue
        libraries[a.library] = loaded

    conditions_any: dict[str, Any] = {}
    for lib in libraries.values():
        conditions_any.update(lib.library.conditions)
    if lib_failed:
        conditions_any = {}  # a library is missing: checking goals against the rest would only add noise

    # task types: goals, cost, commit condition
    task_types: dict[str, TaskType] = {}
    for tname, tt in spec.task_types.items():
        path: tuple[str | int, ...] = ("task_types", tname)
        ok = True
        goals: list[Atom] = []
        for gi, gtext in enumerate(_goal_list(tt.goal)):
            gpath: tuple[str | int, ...] = (
                (*path, "goal") if isinstance(tt.goal, str) else (*path, "goal", gi)
            )
            atom, message, code = (
                resolve_ref(gtext, conditions_any, None) if conditions_any else (None, None, "")
            )
            if atom is None:
                if conditions_any:
                    add(gpath, f"{message} (in no agent's library)", code)
                ok = False
                continue
            goals.append(atom)
        try:
            cost = parse_cost(str(tt.cost))
        except CostExprError as exc:
            add((*path, "cost"), str(exc), "cost-expression")
            ok = False
        commit: Atom | None = None
        if tt.commit_after is not None and conditions_any:
            commit, message, code = resolve_ref(tt.commit_after, conditions_any, None)
            if commit is None:
                add((*path, "commit_after"), message or "bad condition", code)
                ok = False
        if not ok:
            continue
        goal_syms = {s for g in goals for s in g.args}
        if commit is not None:
            stray = [s for s in commit.args if s not in goal_syms]
            if stray:
                add(
                    (*path, "commit_after"),
                    f"'{commit}' uses {', '.join(stray)}, which the goal does not (goal symbols: "
                    f"{', '.join(sorted(goal_syms)) or 'none'})",
                    "undefined-parameter",
                )
        fields = tuple(sorted(goal_syms | set(cost.symbols)))
        task_types[tname] = TaskType(
            tname, tuple(goals), cost, commit, tt.priority, fields, tt.max_attempts
        )

    # default behaviour
    default: DefaultBehavior | None = None
    if spec.default_behavior is not None and conditions_any:
        dgoals: list[Atom] = []
        for gi, gtext in enumerate(_goal_list(spec.default_behavior.goal)):
            gpath = (
                ("default_behavior", "goal")
                if isinstance(spec.default_behavior.goal, str)
                else ("default_behavior", "goal", gi)
            )
            atom, message, code = resolve_ref(gtext, conditions_any, None)
            if atom is None:
                add(gpath, message or "bad goal", code)
            else:
                dgoals.append(atom)
        default = DefaultBehavior(tuple(dgoals), spec.default_behavior.idle_timeout_s)

    # tasks: unique ids, known types, the fields their type needs and nothing else
    tasks: list[Task] = []
    tseen: dict[str, int] = {}
    heavy: set[tuple[str | int, ...]] = set()  # priorities reported as too large
    for i, t in enumerate(spec.tasks):
        tpath: tuple[str | int, ...] = ("tasks", i)
        if t.id in tseen:
            first = src.locate(("tasks", tseen[t.id], "id")).line
            add(
                (*tpath, "id"),
                f"duplicate task id '{t.id}' (first used on line {first})",
                "duplicate-id",
            )
        tseen.setdefault(t.id, i)
        checked = _check_task(t, tpath, spec, task_types, src, add, heavy)
        if checked is None:
            continue
        prio, task_fields = checked
        tasks.append(Task(t.id, t.type, t.at, prio, task_fields, src.locate(tpath)))

    # cost expressions evaluate on the tasks' own values: no division by zero, no overflow,
    # no negative bid (reported at the task type's cost, naming the task)
    for tname, tt4 in task_types.items():
        samples: list[Task | None] = [t for t in tasks if t.type == tname] or [None]
        for sample in samples:
            values: Mapping[str, Any] = (
                sample.fields if sample is not None else dict.fromkeys(tt4.cost.symbols, 1.0)
            )
            problem = tt4.cost.probe(values)
            if problem:
                whose = f" (task '{sample.id}')" if sample is not None else ""
                add(("task_types", tname, "cost"), f"{problem}{whose}", "cost-expression")
                break

    # map file exists
    if isinstance(spec.world.map, FileMap):
        mp = base / spec.world.map.file
        if not mp.exists():
            add(
                ("world", "map", "file"),
                f"map file '{spec.world.map.file}' not found (looked in {base})",
                "no-file",
            )

    # topological map (GA dispatch): a built-in name or a file that loads
    places: frozenset[str] | None = None
    if spec.world.topomap is not None:
        found, places = _check_topomap(spec.world.topomap, base, src)
        diags.extend(found)
    # cost arguments: a position, or (with a topological map) the name of one of its nodes
    for i, ts in enumerate(spec.tasks):
        tt3 = task_types.get(ts.type)
        if tt3 is None:
            continue
        for name, v in (ts.model_extra or {}).items():  # in file order
            if (
                name not in tt3.cost.symbols
                or not isinstance(v, str)
                or (places is None and spec.world.topomap is not None)
            ):
                continue  # (a topological map with errors is reported above)
            wrong = _place_problem(name, v, tt3, spec.world.topomap, places)
            if wrong:
                add(("tasks", i, name), *wrong)

    mission = Mission(
        spec.mission, spec, src.file, agents, tasks, task_types, default, libraries, source=src
    )
    if not errors(diags):
        diags.extend(check_agent_trees(mission, src))
    if errors(diags):
        raise SpecError(errors(diags) + [d for d in diags if d.severity is not Severity.ERROR])
    mission.diagnostics = diags
    return mission


def _check_topomap(
    ref: str, base: Path, src: Source
) -> tuple[list[Diagnostic], frozenset[str] | None]:
    """Problems with ``world.topomap``, and its node names when it loads (dispatch is imported
    only when a mission names one)."""
    from btmission.dispatch.maps import BUILTIN_MAPS
    from btmission.spec.topomap import topomap_ref

    path = ("world", "topomap")
    if ref not in BUILTIN_MAPS and not (base / ref).exists():
        known = ", ".join(BUILTIN_MAPS)
        msg = f"topological map '{ref}' is neither a built-in map ({known}) nor a file in {base}"
        return [src.diag(path, msg, "no-file")], None
    try:
        tmap = topomap_ref(ref, base)
    except SpecError as exc:
        return [src.diag(path, f"topological map '{ref}' has errors, listed below", "topomap"),
                *exc.diagnostics], None  # fmt: skip
    return [], frozenset(tmap.index)


def mission_spec(src: Source) -> MissionSpec:
    """The file's schema model, after its size budgets (a 20,000-task file is refused before
    it is built). Raises :class:`SpecError`."""
    check_mission_scale(src)
    spec: MissionSpec = validate_model(MissionSpec, src, "mission")
    return spec
