"""The mission report, computed from the event log alone (DESIGN.md §6).

:class:`ReportBuilder` is an :class:`~btmission.runtime.events.Observer`: feed it a run's events
live, or the events read back from its JSON Lines log (:func:`report_from_log`) — the same code
either way, so what a run prints and what ``btmission report LOG`` prints agree, and a log cut
short by a crash still gives the report of what happened until then.

* **Table III** (seed 000): per task, when it was added, when it finished, its execution time
  (from its allocation to the agent that completed it until completion) and that agent; tasks not
  done show their state and reason. Below it, when any attempt failed, every **attempt** that
  ended without success (an agent gave the task up, or reported it failed): when, by whom, its
  retries, its reason and what became of the task.
* **Table II** (seed 000): mission duration, total distance flown or driven, agents, tasks done,
  smallest clearance to rock, collisions.
* a **timeline** (Gantt chart: which agent executed which task when) and a **top view** (the map,
  the trajectories, starts and task locations), as PNG (matplotlib, imported only here, lazily).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from btmission.runtime.eventkinds import (
    AgentExcludedEvent,
    AgentTaskEvent,
    AttemptEvent,
    CollisionEvent,
    CommandEvent,
    DispatchEvent,
    EndEvent,
    HeaderEvent,
    LeafErrorEvent,
    ObjectsEvent,
    PoseEvent,
    RetryEvent,
    TaskAddedEvent,
    TaskStateEvent,
    WarningEvent,
)
from btmission.runtime.events import (
    Event,
    LogContents,
    LogError,
    TypedEvent,
    read_events,
)


@dataclass(frozen=True)
class AttemptRow:
    """An attempt at a task that ended without success (an ``attempt`` event)."""

    attempt: int
    max_attempts: int
    time_s: float
    agent: str
    retries: int
    """The ``retry`` events of that agent on that task before it (its vehicle's refusals)."""
    reason: str
    outcome: str
    """``offered to the others`` (a give-up, the task open again) or ``failed``."""


@dataclass(frozen=True)
class TaskRow:
    """One row of Table III."""

    task: str
    type: str
    added_s: float | None
    finished_s: float | None
    execution_s: float | None
    agent: str | None
    state: str
    reason: str = ""
    added_by: str = "mission"
    """Who added it: ``mission`` (its file), or the operator (``cli@127.0.0.1``, ``page@…``)."""
    attempts: tuple[AttemptRow, ...] = ()
    """Its attempts that ended without success, in order."""


@dataclass(frozen=True)
class Summary:
    """Table II."""

    duration_s: float
    distance_m: float
    agents: int
    tasks: int
    tasks_done: int
    min_clearance_m: float | None
    collisions: int
    end: str
    """How the run ended (completed, time limit, interrupted...; "log ends" for a cut log)."""


@dataclass
class MissionReport:
    """Everything the report shows, from a run's events."""

    header: dict[str, Any]
    rows: list[TaskRow]
    summary: Summary
    distance_by_agent: dict[str, float]
    trajectories: dict[str, np.ndarray]
    """Agent → (N, 3) positions from the pose events."""
    intervals: dict[str, list[tuple[str, float, float, str]]]
    """Agent → (task, start, end, outcome) for the Gantt chart; outcome: done / failed / left."""
    objects: list[dict[str, Any]] = field(default_factory=list)
    task_fields: dict[str, dict[str, Any]] = field(default_factory=dict)
    truncated: bool = False
    warnings: list[str] = field(default_factory=list)
    dispatched: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    """Truck → its missions adopted by the fleet dispatcher, in order (``dispatch`` events)."""
    incidents: list[str] = field(default_factory=list)
    """What went wrong while it ran: ``leaf_error`` and ``warning`` events, each once."""
    commands: list[CommandRow] = field(default_factory=list)
    """What operators did while it ran (``command`` events), in order."""
    excluded: list[str] = field(default_factory=list)
    """Agents the coordinator took out of the auction for their give-ups, with why."""


@dataclass(frozen=True)
class CommandRow:
    """One operator command (a ``command`` event)."""

    time_s: float
    by: str
    command: str
    args: str
    """Its arguments, as ``name=value`` pairs."""
    result: str
    """``ok``, or ``refused: <why>``."""


class ReportBuilder:
    """Accumulates events (an observer) and computes the :class:`MissionReport`."""

    def __init__(self) -> None:
        self.header: dict[str, Any] = {}
        self.added: dict[str, tuple[float, str]] = {}
        self.added_by: dict[str, str] = {}
        self.fields: dict[str, dict[str, Any]] = {}
        self.task_events: dict[str, list[TaskStateEvent]] = {}
        self.poses: dict[str, list[tuple[float, list[float]]]] = {}
        self.odometer: dict[str, float] = {}
        self.min_clearance: float | None = None
        self.rock_collisions = 0
        self.agent_collisions: set[tuple[str, str, float]] = set()
        self.agent_task: dict[str, list[tuple[float, str | None]]] = {}
        self.objects: list[dict[str, Any]] = []
        self.end: EndEvent | None = None
        self.last_t = 0.0
        self.warnings: list[str] = []
        self.dispatched: dict[str, list[dict[str, Any]]] = {}
        self.incidents: dict[str, None] = {}  # ordered set
        self.commands: list[CommandRow] = []
        self.attempts: dict[str, list[AttemptRow]] = {}
        self.retries: dict[tuple[str | None, str], int] = {}
        """(task, agent) → its retries since its last attempt ended."""
        self.excluded: list[str] = []

    def on_event(self, event: Event) -> None:
        self.last_t = max(self.last_t, event.t)
        ev = event.typed_or_none()  # (a log's reader skips a line of the wrong types)
        match ev:
            case HeaderEvent():
                self.header = ev.to_data()
            case TaskAddedEvent(task=task):
                self.added[task] = (_when(ev), "" if ev.type is None else ev.type)
                self.added_by[task] = ev.by or "mission"
                self.fields[task] = dict(ev.fields or {})
                for problem in ev.problems or []:
                    self.warnings.append(f"task {task}: {problem}")
            case TaskStateEvent():
                self.task_events.setdefault(ev.task, []).append(ev)
            case PoseEvent(agent=agent):
                self.poses.setdefault(agent, []).append((ev.t, ev.p))
                if ev.odometer_m is not None:
                    self.odometer[agent] = float(ev.odometer_m)
                c = ev.clearance_m
                if c is not None:
                    self.min_clearance = (
                        c if self.min_clearance is None else min(self.min_clearance, c)
                    )
            case CollisionEvent():
                other = str(ev.other)
                if other == "rock":
                    self.rock_collisions += 1
                else:
                    a, b = sorted((str(ev.agent), other))
                    self.agent_collisions.add((a, b, round(ev.t, 3)))
            case AgentTaskEvent():
                self.agent_task.setdefault(ev.agent, []).append((ev.t, ev.task))
            case ObjectsEvent():
                self.objects.extend(ev.objects or [])
            case DispatchEvent():
                if ev.event == "adopted" and ev.mission:
                    self.dispatched.setdefault(str(ev.truck), []).append(ev.mission)
            case LeafErrorEvent():
                what = f"{ev.leaf} raised {ev.error}: {ev.message}"
                self.incidents[f"agent {ev.agent}: {what} (traceback in the log)"] = None
            case WarningEvent():
                self.incidents[str(ev.message)] = None
            case RetryEvent():
                key = (ev.task, ev.agent)
                self.retries[key] = self.retries.get(key, 0) + 1
            case AttemptEvent():
                outcome = "offered to the others" if ev.state == "open" else str(ev.state)
                row = AttemptRow(int(ev.attempt), int(ev.max_attempts), _when(ev), ev.agent,
                                 self.retries.pop((ev.task, ev.agent), 0), ev.reason, outcome)  # fmt: skip
                self.attempts.setdefault(ev.task, []).append(row)
            case AgentExcludedEvent():
                self.excluded.append(f"{ev.agent} at t={ev.t:.1f}s: {ev.reason}")
            case CommandEvent():
                args = ", ".join(f"{k}={_plain_text(v)}" for k, v in ev.args.items())
                ok = ev.ok is None or bool(ev.ok)
                result = "ok" if ok else f"refused: {ev.error or ''}".rstrip(": ")
                self.commands.append(CommandRow(ev.t, ev.by or "", str(ev.command), args, result))
            case EndEvent():
                self.end = ev

    # ------------------------------------------------------------------ computing
    def _row(self, task: str) -> TaskRow:
        added, ttype = self.added.get(task, (None, ""))
        evs = self.task_events.get(task, [])
        state = evs[-1].state if evs else "open"
        reason = (evs[-1].reason or "") if evs else "not allocated yet"
        if state == "done":
            done = evs[-1]
            agent = done.agent
            start = None
            for ev in evs[:-1]:  # the allocation of the agent that finished it
                if ev.agent == agent and ev.state == "assigned":
                    start = _when(ev)
                elif ev.agent != agent:
                    start = None
            execution = None if start is None else _when(done) - start
            by = self.added_by.get(task, "mission")
            tried = tuple(self.attempts.get(task, ()))
            return TaskRow(task, ttype, added, _when(done), execution, agent, "done", "", by, tried)
        agent = evs[-1].agent if evs else None
        by = self.added_by.get(task, "mission")
        tried = tuple(self.attempts.get(task, ()))
        return TaskRow(task, ttype, added, None, None, agent, str(state), str(reason), by, tried)

    def report(self) -> MissionReport:
        tasks = list(self.added)
        for t in self.task_events:
            if t not in self.added:
                tasks.append(t)
        rows = [self._row(t) for t in tasks]
        agents = [a["id"] for a in self.header.get("agents", [])] or sorted(self.poses)
        trajectories = {
            a: np.array([p for _, p in self.poses.get(a, [])], dtype=float).reshape(-1, 3)
            for a in agents
        }
        distance = {a: self.odometer.get(a, _path_length(trajectories[a])) for a in agents}
        end_reason = str(self.end.reason) if self.end is not None else "log ends"
        duration = self.end.t if self.end is not None else self.last_t
        summary = Summary(
            duration_s=duration,
            distance_m=float(sum(distance.values())),
            agents=len(agents),
            tasks=len(rows),
            tasks_done=sum(1 for r in rows if r.state == "done"),
            min_clearance_m=self.min_clearance,
            collisions=self.rock_collisions + len(self.agent_collisions),
            end=end_reason,
        )
        return MissionReport(
            self.header,
            rows,
            summary,
            distance,
            trajectories,
            self._intervals(duration),
            list(self.objects),
            dict(self.fields),
            warnings=list(self.warnings),
            dispatched={k: list(v) for k, v in self.dispatched.items()},
            incidents=list(self.incidents),
            commands=list(self.commands),
            excluded=list(self.excluded),
        )

    def _intervals(self, end: float) -> dict[str, list[tuple[str, float, float, str]]]:
        done_by = {
            t: (evs[-1].agent, evs[-1].state)
            for t, evs in self.task_events.items()
            if evs and evs[-1].state in ("done", "failed")
        }
        out: dict[str, list[tuple[str, float, float, str]]] = {}
        for agent, changes in self.agent_task.items():
            spans = []
            for (t0, task), nxt in zip(changes, [*changes[1:], (end, None)]):
                if task is None:
                    continue
                who, state = done_by.get(task, (None, None))
                outcome = str(state) if who == agent and nxt[1] is None else "left"
                spans.append((str(task), t0, nxt[0], outcome))
            out[agent] = spans
        return out


def _when(ev: TypedEvent) -> float:
    """When it happened: ``reported_s`` for an event published late (see
    :meth:`~btmission.runtime.runner.MissionRun.emit_event`), else its time."""
    return float(ev.reported_s) if ev.reported_s is not None else ev.t


def _path_length(points: np.ndarray) -> float:
    if len(points) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def build_report(events: Iterable[Event]) -> MissionReport:
    b = ReportBuilder()
    for ev in events:
        b.on_event(ev)
    return b.report()


def report_from_log(path: str | Path) -> MissionReport:
    """The report of a JSON Lines log (raises :class:`~btmission.runtime.events.LogError`)."""
    contents: LogContents = read_events(path)
    rep = build_report(contents.events)
    rep.truncated = contents.truncated
    if contents.truncated:
        rep.warnings.append("the last line of the log was cut off (the run was killed)")
    if contents.skipped:
        rep.warnings.append(f"unreadable lines skipped: {contents.skipped[:5]}")
    return rep


def merge_log_files(
    coordinator: str | Path, agents: Sequence[str | Path], out: str | Path | None = None
) -> MissionReport:
    """The report of a run spread over processes: the coordinator's log and its agent
    processes' logs merged (:func:`~btmission.runtime.distribution.merge_logs`), written to
    ``out`` if given (one log, as a one-process run's). Raises
    :class:`~btmission.runtime.events.LogError` for a log that cannot be read or merged."""
    from btmission.runtime.distribution import MergeError, merge_logs

    first = read_events(coordinator)
    others = [read_events(p) for p in agents]
    try:
        events = merge_logs(first.events, [o.events for o in others])
    except MergeError as exc:
        raise LogError(f"{coordinator}: {exc}") from None
    if out is not None:
        with open(out, "x", encoding="utf-8") as f:
            for ev in events:
                f.write(ev.to_json() + "\n")
    rep = build_report(events)
    cut = [str(p) for p, c in zip([coordinator, *agents], [first, *others]) if c.truncated]
    if cut:
        rep.truncated = True
        rep.warnings.append(f"the last line was cut off (a process was killed): {', '.join(cut)}")
    return rep


# ---------------------------------------------------------------------------- text
def _f(v: float | None, digits: int = 0) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    return f"{v:.{digits}f}"


def format_report(rep: MissionReport) -> str:
    """Table III and Table II of seed 000 as text (the warnings: :func:`format_warnings`)."""
    h = rep.header
    s = rep.summary
    lines = [
        f"Mission {h.get('mission', '?')} — {h.get('description', '')}".rstrip(" —"),
        f"seed {h.get('seed', '?')}, controller {h.get('controller', '?')}, ended: {s.end}",
        "",
        "Tasks (seed 000 Table III)",
    ]
    head: tuple[str, ...] = ("Task", "Added [s]", "Finished [s]", "Execution [s]", "Agent", "Note")
    body: list[tuple[str, ...]] = [
        (
            r.task,
            _f(r.added_s, 1),
            _f(r.finished_s, 1),
            _f(r.execution_s, 1),
            r.agent or "—",
            "" if r.state == "done" else f"{r.state}: {r.reason}".rstrip(": "),
        )
        for r in rep.rows
    ]
    if any(r.added_by not in ("mission", "api") for r in rep.rows):  # an operator added some
        head = (*head[:2], "Added by", *head[2:])
        body = [(*b[:2], r.added_by, *b[2:]) for b, r in zip(body, rep.rows)]
    lines += table_lines(head, body)
    tried = [(r.task, a) for r in rep.rows for a in r.attempts]
    if tried:  # (a run where every attempt succeeded shows nothing here)
        lines += ["", f"Attempts that did not succeed ({len(tried)})"]
        lines += table_lines(
            ("Task", "Attempt", "Time [s]", "Agent", "Retries", "Then", "Reason"),
            [
                (
                    task,
                    f"{a.attempt} of {a.max_attempts}",
                    _f(a.time_s, 1),
                    a.agent,
                    str(a.retries),
                    a.outcome,
                    a.reason,
                )
                for task, a in tried
            ],
        )
    for line in rep.excluded:
        lines.append(f"Taken out of the auction: {line}")
    lines += ["", "Mission (seed 000 Table II)"]
    clearance = "—" if s.min_clearance_m is None else f"{s.min_clearance_m:.2f} m"
    per_agent = ", ".join(f"{a} {d:.1f}" for a, d in rep.distance_by_agent.items())
    summary = [
        ("Mission duration", f"{s.duration_s:.1f} s"),
        ("Total distance covered", f"{s.distance_m:.1f} m ({per_agent})" if per_agent else "0 m"),
        ("Number of agents", str(s.agents)),
        ("Tasks done", f"{s.tasks_done} of {s.tasks}"),
        ("Min clearance to rock", clearance),
        ("Collisions", str(s.collisions)),
    ]
    lines += table_lines(("Parameter", "Value"), summary)
    if rep.objects or rep.header.get("artifacts"):
        truth = rep.header.get("artifacts") or []
        lines += ["", f"Objects localised ({len(rep.objects)}; {len(truth)} placed in the world)"]
        lines += table_lines(
            ("Label", "Position [m]", "Observations", "Error [m]"),
            [
                (
                    str(o.get("label")),
                    "[" + ", ".join(f"{v:.2f}" for v in o.get("p", [])) + "]",
                    str(o.get("observations", "")),
                    _f(_nearest(o, truth), 2),
                )
                for o in rep.objects
            ],
        )
    if rep.commands:  # what operators did (a run without commands shows nothing here)
        lines += ["", f"Operator commands ({len(rep.commands)})"]
        lines += table_lines(
            ("Time [s]", "By", "Command", "Arguments", "Result"),
            [(_f(c.time_s, 1), c.by, c.command, c.args, c.result) for c in rep.commands],
        )
    return "\n".join(lines)


def format_warnings(rep: MissionReport, *, incidents: bool = True) -> list[str]:
    """The report's warnings (a log cut off, unreadable lines, task problems) and, with
    ``incidents``, what went wrong during the run (leaf errors, runtime warnings), one line
    each: the CLI prints them on stderr, apart from the tables."""
    return [f"warning: {w}" for w in rep.warnings + (rep.incidents if incidents else [])]


def _row_json(row: TaskRow) -> dict[str, Any]:
    """A task's row as plain data; its ``attempts`` only when it has some."""
    out = {k: v for k, v in row.__dict__.items() if k != "attempts"}
    if row.attempts:
        out["attempts"] = [a.__dict__ for a in row.attempts]
    return out


def _plain_text(value: Any) -> str:
    """A command argument as the report shows it (mappings and lists as compact JSON)."""
    if isinstance(value, (dict, list)):
        return json.dumps(value, separators=(",", ":"))
    return str(value)


def _nearest(obj: Mapping[str, Any], truth: Sequence[Mapping[str, Any]]) -> float | None:
    """Distance from a localised object to the nearest placed artifact of its class."""
    same = [t["p"] for t in truth if t.get("label") == obj.get("label")]
    if not same or not obj.get("p"):
        return None
    return min(math.dist(obj["p"], p) for p in same)


def table_lines(head: tuple[str, ...], rows: Sequence[tuple[str, ...]]) -> list[str]:
    widths = [
        max(len(head[i]), *(len(r[i]) for r in rows)) if rows else len(head[i])
        for i in range(len(head))
    ]
    fmt = "  ".join("{:<" + str(w) + "}" for w in widths)
    out = [fmt.format(*head).rstrip(), fmt.format(*("-" * w for w in widths)).rstrip()]
    out += [fmt.format(*r).rstrip() for r in rows]
    return out


def report_json(rep: MissionReport) -> dict[str, Any]:
    """Plain data of Tables II and III."""
    s = rep.summary
    return {
        "mission": rep.header.get("mission"),
        "summary": {
            "duration_s": s.duration_s,
            "distance_m": s.distance_m,
            "distance_by_agent_m": rep.distance_by_agent,
            "agents": s.agents,
            "tasks": s.tasks,
            "tasks_done": s.tasks_done,
            "min_clearance_m": s.min_clearance_m,
            "collisions": s.collisions,
            "end": s.end,
        },
        "tasks": [_row_json(r) for r in rep.rows],
        "objects": rep.objects,
        "commands": [c.__dict__ for c in rep.commands],
        **({"excluded": list(rep.excluded)} if rep.excluded else {}),
        "truncated": rep.truncated,
    }


# ---------------------------------------------------------------------------- figures
def _figure(size: tuple[float, float]) -> Any:
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, no global state

    return Figure(figsize=size, layout="constrained")


def timeline_png(rep: MissionReport, path: str | Path) -> Path:
    """Gantt chart: one row per agent, a bar per task it executed (seed 000 Table III)."""
    agents = list(rep.distance_by_agent) or sorted(rep.intervals)
    fig = _figure((10, 1.2 + 0.6 * max(1, len(agents))))
    ax = fig.subplots()
    tasks = [r.task for r in rep.rows]
    colour = {t: f"C{i % 10}" for i, t in enumerate(tasks)}
    for i, agent in enumerate(agents):
        for task, t0, t1, outcome in rep.intervals.get(agent, []):
            ax.barh(
                i,
                max(t1 - t0, 0.05),
                left=t0,
                color=colour.get(task, "grey"),
                alpha=1.0 if outcome == "done" else 0.35,
                edgecolor="black",
                hatch="" if outcome == "done" else "//",
            )
            if t1 - t0 > 0.04 * max(rep.summary.duration_s, 1e-9):
                ax.text((t0 + t1) / 2, i, task, ha="center", va="center", fontsize=8)
    for r in rep.rows:
        if r.added_s is not None and r.added_s > 0:
            ax.axvline(r.added_s, color=colour.get(r.task, "grey"), ls=":", lw=1)
            ax.text(
                r.added_s, len(agents) - 0.4, f"{r.task} added", fontsize=7, rotation=90, va="top"
            )
    ax.set_yticks(range(len(agents)), agents)
    ax.set_ylim(-0.6, len(agents) - 0.4)
    ax.set_xlim(0, max(rep.summary.duration_s, 1.0))
    ax.set_xlabel("mission time [s]")
    ax.set_title(
        f"{rep.header.get('mission', '')}: task execution per agent "
        "(solid: completed, hatched: left for another task or lost)"
    )
    out = Path(path)
    fig.savefig(out, dpi=100)
    return out


def dispatch_png(rep: MissionReport, path: str | Path) -> Path:
    """Fig. 3-style chart of what the fleet dispatcher planned (seed 004): one row per truck, its
    dispatched missions joined — stops, drives, prioritised (loaded) drives, pause visits."""
    from btmission.dispatch.plot import gantt_png
    from btmission.dispatch.service import missions_from_records
    from btmission.spec.topomap import topomap_ref

    ref = (rep.header.get("world") or {}).get("topomap")
    if not ref or not rep.dispatched:
        raise ValueError("the log has no dispatched missions")
    tmap = topomap_ref(str(ref), _mission_dir(rep.header))
    trucks = sorted(rep.dispatched)
    fleet = [missions_from_records(tmap, rep.dispatched[t]) for t in trucks]
    title = f"{rep.header.get('mission', '')}: dispatched schedule on map {tmap.name}"
    out = Path(path)
    out.write_bytes(gantt_png(tmap, fleet, title, labels=trucks))
    return out


def _mission_dir(header: Mapping[str, Any]) -> Path:
    """The directory the mission's map files are relative to: ``world_ref.base_dir`` (version 2
    logs; absolute), else the mission file's directory (relative to where ``report`` runs)."""
    ref = header.get("world_ref")
    if isinstance(ref, Mapping) and isinstance(ref.get("base_dir"), str):
        return Path(ref["base_dir"])
    return Path(str(header.get("file", "."))).parent


def world_from_header(header: Mapping[str, Any]) -> Any:
    """The mission's voxel map rebuilt from the log's header (None if it cannot be)."""
    try:
        from btmission.spec.sections import WorldSpec
        from btmission.world.build import world_from_spec

        world = WorldSpec.model_validate(header["world"])
        return world_from_spec(world, _mission_dir(header))
    except Exception:
        return None


def topview_png(rep: MissionReport, path: str | Path, voxel_map: Any = None) -> Path:
    """Top view: open space of the map (grey), trajectories, starts (squares), tasks (×),
    artifacts placed in the simulator (stars) and the objects localised (+)."""
    vm = voxel_map if voxel_map is not None else world_from_header(rep.header)
    aspect = 0.6
    if vm is not None:
        ex = vm.extent
        aspect = ex[1] / max(ex[0], 1e-9)
    fig = _figure((10, max(3.5, 10 * aspect) + 0.8))
    ax = fig.subplots()
    ax.set_facecolor("#202020")
    if vm is not None:
        from btmission.world.voxel import OCCUPIED

        open_cols = (vm.state != OCCUPIED).any(axis=2)
        lo = vm.origin
        ex = vm.extent
        ax.imshow(
            np.where(open_cols, 0.85, 0.25).T,
            origin="lower",
            extent=(lo[0], lo[0] + ex[0], lo[1], lo[1] + ex[1]),
            cmap="gray",
            vmin=0,
            vmax=1,
            interpolation="nearest",
        )
    for i, (agent, traj) in enumerate(rep.trajectories.items()):
        if len(traj):
            ax.plot(traj[:, 0], traj[:, 1], color=f"C{i % 10}", lw=1.5, label=agent)
    for i, a in enumerate(rep.header.get("agents", [])):
        st = a.get("start", [0, 0, 0])
        ax.plot(st[0], st[1], "s", color=f"C{i % 10}", mec="white", ms=7)
    for task, pos in _task_positions(rep):
        ax.plot(pos[0], pos[1], "x", color="#d62728", ms=8, mew=2)
        ax.annotate(
            task,
            (pos[0], pos[1]),
            xytext=(4, 4),
            textcoords="offset points",
            fontsize=8,
            color="#d62728",
        )
    for a in rep.header.get("artifacts") or []:
        ax.plot(a["p"][0], a["p"][1], "*", color="#ff9f1c", ms=12, mec="black")
    for o in rep.objects:
        ax.plot(o["p"][0], o["p"][1], "+", color="#17becf", ms=12, mew=2)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{rep.header.get('mission', '')}: trajectories (top view)")
    if rep.trajectories:
        ax.legend(loc="upper right", fontsize=8)
    out = Path(path)
    fig.savefig(out, dpi=100)
    return out


def _task_positions(rep: MissionReport) -> list[tuple[str, list[float]]]:
    out = []
    for r in rep.rows:
        points = [
            (name, v)
            for name, v in rep.task_fields.get(r.task, {}).items()
            if isinstance(v, list) and len(v) == 3
        ]
        for name, value in points:
            out.append((r.task if len(points) == 1 else f"{r.task} {name}", value))
    return out
