"""Mission events: one observer interface for the event log, the report, the tests and the viewer.

Everything that happens in a run is an :class:`Event` — a time, a kind and plain-data fields —
published to every :class:`Observer` subscribed to an :class:`EventStream` (DESIGN.md §6, STYLE.md
item 8: logging, viewing and test checks are all observers; nodes never import them).

The kinds a run emits (fields in brackets; positions are ``[x, y, z]`` lists in metres):

=================  =======================================================================
``header``         first event of a log, written before anything is built: ``format``,
                   ``version``, ``mission``, ``file``, ``seed``, ``controller``, ``world`` (the
                   mission's world spec), ``agents`` (``[{id, library, vehicle, start}]``),
                   ``tasks`` (``[{id, type, at, fields}]``)
``built``          the run is built: ``map`` (shape, resolution, origin), ``build_s``
``task_added``     a task entered the pool: ``task``, ``type``, ``fields``, ``by`` (mission/api)
``task``           a task changed state or agent (the auction pool's history): ``task``,
                   ``state`` (open/assigned/committed/done/failed/unreachable), ``agent``,
                   ``reason``
``round``          one auction round: ``round``, ``announced``, ``agents``, ``method``,
                   ``bids``, ``step_ms``; ``assignments`` (agent → task) when they changed,
                   ``dropped`` (agents that stopped bidding) when there are any
``agent_task``     an agent started or stopped executing a task: ``agent``, ``task`` (or null)
``stage``          an agent's tree started an action: ``agent``, ``task``, ``action``
``committed``      an agent passed its task's commit point (k_bt = 0): ``agent``, ``task``
``progress``       an agent reported ``done`` / ``failed`` for ``task`` (``reason``)
``pose``           ground truth from the simulator: ``agent``, ``p``, ``v``, ``yaw``, ``mode``,
                   ``armed``, ``flying``, ``odometer_m``, ``clearance_m`` (the smallest
                   distance to rock since the previous pose event, null when not measured)
``collision``      the simulator detected a collision: ``agent``, ``with`` (rock/agent id),
                   ``p``
``agent_lost``     an agent stopped (killed, link lost): ``agent``, ``reason``
``objects``        an agent reported localised objects: ``agent``, ``objects``
                   (``[{label, p, observations}]``), ``truth`` (``[{label, p}]``)
``relocalized``    an agent localised itself in the map from one LiDAR scan (library
                   ``aerial_mine``): ``agent``, ``task``, ``localized``, ``confidence``,
                   ``fitness``, ``reason``, ``points``, ``sensor``, ``time_ms``, ``truth`` (the
                   telemetry pose ``{x, y, z, yaw_deg}``: the true pose in the simulator) and,
                   when localised, ``estimate`` and its ``error_m``, ``error_deg``
``leaf_error``     a library's leaf (or service) raised; it failed and the run went on:
                   ``agent``, ``task``, ``leaf``, ``phase``, ``error``, ``message``, ``where``,
                   ``traceback``
``warning``        the coordinator refused something, or an action's argument is on nobody's
                   blackboard (``agent``, ``variable``, ``leaf``): ``message``
``end``            last event: ``reason`` (completed/time limit/interrupted/terminated/...),
                   ``wall_s``, ``done``, ``open`` (arrived tasks only), ``pending`` (still
                   to arrive)

A run publishes events in time order; one that happened earlier than it is published (an
agent's report, taken by the next auction round) carries its own time as ``reported_s``.
=================  =======================================================================

:class:`JsonlEventLog` writes them as JSON Lines, one event per line, flushed as written, so a
crash loses nothing already logged; :func:`read_events` reads such a log back (a truncated last
line — the process died while writing it — is skipped and reported).
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol, runtime_checkable

LOG_FORMAT = "btmission-log"
LOG_VERSION = 1


@dataclass(frozen=True)
class Event:
    """Something that happened at mission time ``t`` (seconds): its ``kind`` and fields."""

    t: float
    kind: str
    data: Mapping[str, Any] = field(default_factory=dict)

    def get(self, key: str, default: Any = None) -> Any:
        return self.data.get(key, default)

    def to_json(self) -> str:
        """One JSON object: ``{"t": ..., "ev": kind, **data}`` (inf/NaN as null)."""
        return json.dumps(
            {"t": round(self.t, 4), "ev": self.kind, **_plain(self.data)},
            separators=(",", ":"),
            allow_nan=False,
        )

    @classmethod
    def from_json(cls, line: str) -> Event:
        obj = json.loads(line)
        if not isinstance(obj, dict) or "ev" not in obj or "t" not in obj:
            raise ValueError("not a btmission event (expected an object with 't' and 'ev')")
        t = float(obj.pop("t"))
        kind = str(obj.pop("ev"))
        return cls(t, kind, obj)


def _plain(value: Any) -> Any:
    """JSON-safe copy: tuples/arrays → lists, non-finite floats → None, floats rounded."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist"):  # numpy arrays and scalars
        return _plain(value.tolist())
    if isinstance(value, float):
        return round(value, 4) if math.isfinite(value) else None
    return value


@runtime_checkable
class Observer(Protocol):
    """Anything that wants to see a run's events (log, report, tests, viewer)."""

    def on_event(self, event: Event) -> None: ...


class EventStream:
    """Fans each published event out to the subscribed observers, in subscription order."""

    def __init__(self, observers: Iterable[Observer] = ()) -> None:
        self._observers: list[Observer] = list(observers)

    def subscribe(self, observer: Observer) -> None:
        self._observers.append(observer)

    def unsubscribe(self, observer: Observer) -> None:
        self._observers.remove(observer)

    def emit(self, t: float, kind: str, **data: Any) -> Event:
        ev = Event(t, kind, data)
        for obs in self._observers:
            obs.on_event(ev)
        return ev


class Recorder:
    """Keeps every event in memory (tests and the live report)."""

    def __init__(self) -> None:
        self.events: list[Event] = []

    def on_event(self, event: Event) -> None:
        self.events.append(event)

    def of(self, kind: str) -> list[Event]:
        return [e for e in self.events if e.kind == kind]


class JsonlEventLog:
    """Append-only JSON Lines log: one event per line, flushed to the OS after every event."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: IO[str] | None = self.path.open("a", encoding="utf-8")
        self.count = 0

    def on_event(self, event: Event) -> None:
        if self._fh is None:
            return
        self._fh.write(event.to_json() + "\n")
        self._fh.flush()
        self.count += 1

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> JsonlEventLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _text(v: Any) -> bool:
    return isinstance(v, str)


def _point(v: Any) -> bool:
    return isinstance(v, list) and len(v) == 3 and all(_number(x) for x in v)


def _list_of(check: Any) -> Any:
    return lambda v: isinstance(v, list) and all(check(x) for x in v)


def _or_none(check: Any) -> Any:
    return lambda v: v is None or check(v)


def _agent_entry(v: Any) -> bool:
    return isinstance(v, dict) and _text(v.get("id")) and _point(v.get("start", [0, 0, 0]))


def _placed(v: Any) -> bool:  # an artifact or a detected object
    return isinstance(v, dict) and _point(v.get("p"))


_EVENT_FIELDS: dict[str, dict[str, Any]] = {
    "header": {"agents": _list_of(_agent_entry),
               "tasks": _or_none(_list_of(lambda v: isinstance(v, dict))),
               "world": _or_none(lambda v: isinstance(v, dict)), "artifacts": _or_none(_list_of(
                   _placed))},
    "task_added": {"task": _text, "fields": lambda v: isinstance(v, dict),
                   "problems": _list_of(_text)},
    "task": {"task": _text, "state": _text, "agent": _or_none(_text)},
    "pose": {"agent": _text, "p": _point, "odometer_m": _or_none(_number),
             "clearance_m": _or_none(_number)},
    "agent_task": {"agent": _text, "task": _or_none(_text)},
    "objects": {"objects": _list_of(_placed)},
}  # fmt: skip
"""What ``report`` reads of each kind of event (a field may be absent, unless noted)."""


def event_problem(ev: Event) -> str | None:
    """What is wrong with the shape of an event read from a log (None when it can be reported):
    a time that is not a finite number, or a field the report reads of the wrong type."""
    if not math.isfinite(ev.t):
        return f"time {ev.t} is not a finite number"
    if "reported_s" in ev.data and not _number(ev.data["reported_s"]):
        return "field 'reported_s' has the wrong type"
    for name, check in _EVENT_FIELDS.get(ev.kind, {}).items():
        if name in ev.data and not check(ev.data[name]):
            return f"field '{name}' has the wrong type (got {json.dumps(ev.data[name])[:60]})"
    return None


class LogError(ValueError):
    """A file that is not a btmission event log (or an unreadable one)."""


@dataclass
class LogContents:
    """Events read from a log, and what could not be read."""

    events: list[Event]
    truncated: bool = False
    """The last line was cut off (the run was killed while writing it)."""
    skipped: list[int] = field(default_factory=list)
    """Line numbers of other unreadable lines."""


def read_events(path: str | Path) -> LogContents:
    """Read a JSON Lines event log. Raises :class:`LogError` if it is not one (or is not a
    regular file, or is over :data:`~btmission.limits.MAX_LOG_BYTES`)."""
    from btmission import limits
    from btmission.spec.source import FileRefused, read_regular_file

    p = Path(path)
    try:
        data = read_regular_file(p, limits.MAX_LOG_BYTES)
    except FileNotFoundError:
        raise LogError(f"{p}: no such log file") from None
    except FileRefused as exc:
        raise LogError(f"{p}: {exc}") from None
    except OSError as exc:
        raise LogError(f"{p}: cannot read: {exc.strerror or exc}") from None
    text = data.decode("utf-8", errors="replace")
    lines = list(enumerate(io.StringIO(text, newline=None), start=1))  # as a text-mode file reads
    events: list[Event] = []
    skipped: list[int] = []
    truncated = False
    for i, (number, line) in enumerate(lines):
        if not line.strip():
            continue
        try:
            ev = Event.from_json(line)
            problem = event_problem(ev)
            if problem:
                if ev.kind == "header":
                    raise LogError(f"{p}:{number}: header: {problem}")
                raise ValueError(problem)
            events.append(ev)
        except LogError:
            raise
        except (ValueError, TypeError, RecursionError):  # RecursionError: [[[[... nested
            if i == len(lines) - 1 and not line.endswith("\n"):
                truncated = True
            else:
                skipped.append(number)
    if not events or events[0].kind != "header" or events[0].get("format") != LOG_FORMAT:
        raise LogError(
            f"{p}: not a btmission event log (the first line must be a '{LOG_FORMAT}' header)"
        )
    version = events[0].get("version")
    if version != LOG_VERSION:
        raise LogError(f"{p}: log format version {version!r}; this btmission reads {LOG_VERSION}")
    return LogContents(events, truncated, skipped)
