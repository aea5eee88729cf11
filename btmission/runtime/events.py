"""Mission events: one observer interface for the event log, the report, the tests and the viewer.

Everything that happens in a run is an :class:`Event` — a time, a kind and plain-data fields —
published to every :class:`Observer` subscribed to an :class:`EventStream` (DESIGN.md §6, STYLE.md
item 8: logging, viewing and test checks are all observers; nodes never import them). Observers
are called on the run's thread: a slow one (a live viewer) goes behind a
:class:`~btmission.runtime.observers.QueuedObserver`, which never holds the run up.

The kinds a run emits (fields in brackets; positions are ``[x, y, z]`` lists in metres). Each
has a typed class below (:class:`TypedEvent` subclasses, frozen dataclasses), which producers
make and publish (``run.emit_event(PoseEvent(...))``, a leaf's ``ctx.events(StageEvent(...))``)
and consumers read (``Event.typed()``: the report, the viewer's feed, a restarted coordinator):

===================  =====================================================================
``header``           first event of a log, written before anything is built: ``format``,
                     ``version``, ``mission``, ``description``, ``file``, ``seed``,
                     ``controller``, ``world`` (the mission's world spec), ``world_ref``
                     (where the map is: :func:`world_reference`; version 2), ``step_s``,
                     ``part`` (a distributed run's process), ``auction_rate_hz``, ``agents``
                     (``[{id, library, vehicle, start}]``), ``tasks``
                     (``[{id, type, at, fields}]``), ``artifacts``; early version 1 logs:
                     ``map``
``built``            the run is built: ``map`` (shape, resolution, origin), ``build_s``,
                     ``started_unix`` (a distributed run's coordinator: its clock's zero)
``resumed``          first event a restarted coordinator adds to its predecessor's log:
                     ``log``, ``last_s``
``task_added``       a task entered the pool: ``task``, ``type``, ``fields``, ``priority``,
                     ``by`` (mission/api), ``problems``, ``at`` (when it arrives, if later)
``task``             a task changed state or agent (the auction pool's history): ``task``,
                     ``state`` (open/assigned/committed/done/failed/unreachable), ``agent``,
                     ``reason``
``round``            one auction round: ``round``, ``announced``, ``agents``, ``method``,
                     ``bids``, ``step_ms``; ``assignments`` (agent → task) when they
                     changed, ``dropped`` (agents that stopped bidding), ``late_bids`` and
                     ``stale_bids`` when there are any
``withdrawn``        an agent's assignment went to another's late report: ``agent``,
                     ``task``, ``by``, ``reason``
``agent_task``       an agent started or stopped executing a task: ``agent``, ``task`` (or
                     null)
``stage``            an agent's tree started an action: ``agent``, ``task``, ``action``
``committed``        an agent passed its task's commit point (k_bt = 0): ``agent``, ``task``
``progress``         ``agent`` reported ``event`` done / failed / committed / gave_up for
                     ``task`` (``reason``)
``retry``            an action asks its vehicle again for a command it refused transiently:
                     ``agent``, ``task``, ``action``, ``retry``, ``retries``, ``reason``,
                     ``wait_s``
``attempt``          an agent's attempt at a task ended without success (taken by the
                     coordinator): ``task``, ``agent``, ``attempt``, ``max_attempts``,
                     ``reason``, ``gave_up``, ``state`` (open/failed), ``cooldown_until``
``agent_excluded``   the coordinator took an agent out of the auction for its give-ups:
                     ``agent``, ``tasks``, ``reason``
``route``            an agent adopted a new planned path (D*+): ``agent``, ``task``,
                     ``points`` (at most a few hundred), ``length_m``; version 2
``tree``             an agent's behaviour-tree nodes whose status changed: ``agent``,
                     ``changes`` (``[[uid, old, new], ...]``) and, in its first one,
                     ``nodes``; its blackboard keys that changed (``blackboard``) or were
                     removed (``unset``); at most one per agent per ``tree_event_s``
                     setting; version 2
``pose``             ground truth from the simulator: ``agent``, ``p``, ``v``, ``yaw``,
                     ``mode``, ``armed``, ``flying``, ``odometer_m``, ``clearance_m`` (the
                     smallest distance to rock since the previous pose event, null when not
                     measured)
``collision``        the simulator detected a collision: ``agent``, ``other`` (rock/agent
                     id), ``p``
``agent_lost``       an agent stopped (killed, link lost): ``agent``, ``reason``
``link``             an agent's link to the coordinator was cut or restored: ``agent``,
                     ``up``
``vehicle_link``     an agent lost or heard again its vehicle's autopilot: ``agent``, ``up``,
                     ``mode`` (when it came back)
``coordinator_link`` an agent lost (nothing heard for ``agent_timeout_s``) or heard again its
                     coordinator: ``agent``, ``up``, ``silent_s``
``taken_over``       an agent's vehicle was taken over by its autopilot's failsafe or its
                     pilot: ``agent``, ``mode``, ``failsafe``, ``final`` (the agent stands
                     down), ``task`` (handed back)
``clock``            an agent process set its clock to its coordinator's: ``agent``,
                     ``was_s``, ``now_s``
``signal``           a supervisor signal was set on an agent: ``agent``, ``name``, ``value``
``command``          an operator's command: ``command``, ``by``, its arguments (``task``,
                     ``agent``, ``reason``, ...), ``ok``, ``error`` (when refused)
``objects``          an agent reported localised objects: ``agent``, ``objects``
                     (``[{label, p, observations}]``), ``rejected``
``junction``         DPHR saw a junction and chose a branch (library ``compra``): ``agent``,
                     ``offsets``, ``chosen``
``junction_switch``  DPHR left the branch it followed for another: ``agent``, ``offsets``,
                     ``chosen``, ``was``
``relocalized``      an agent localised itself in the map from one LiDAR scan (library
                     ``aerial_mine``): ``agent``, ``task``, ``localized``, ``confidence``,
                     ``fitness``, ``reason``, ``points``, ``sensor``, ``time_ms``, ``truth``
                     (the telemetry pose ``{x, y, z, yaw_deg}``: the true pose in the
                     simulator) and, when localised, ``estimate`` and its ``error_m``,
                     ``error_deg``
``dispatch``         the fleet dispatcher (seed 004) handled a truck: ``truck``, ``event``,
                     ``goal``, ``reason`` (deferred) and, when adopted, ``to``, ``items``,
                     ``depart``, ``arrive``, ``mission``
``leaf_error``       a library's leaf (or service) raised; it failed and the run went on:
                     ``agent``, ``task``, ``leaf``, ``phase``, ``error``, ``message``,
                     ``where``, ``traceback``
``warning``          the coordinator refused something, or an action's argument is on
                     nobody's blackboard (``agent``, ``variable``, ``leaf``): ``message``
``internal_error``   a bug outside any leaf ended the run: ``type``, ``message``,
                     ``traceback``
``end``              last event: ``reason`` (completed/time limit/interrupted/terminated/...),
                     ``wall_s``, ``steps``, ``done``, ``open`` (arrived tasks only),
                     ``pending`` (still to arrive), ``cancelled`` (when any)
===================  =====================================================================

A run publishes events in time order; one that happened earlier than it is published (an
agent's report, taken by the next auction round) carries its own time as ``reported_s``.

Libraries may publish kinds of their own: typed, with a class they register with
:func:`register_event` (``haulage``'s ``load`` and ``offload``: ``ctx.events(LoadEvent(...))``),
or by name (``ctx.events(kind, **fields)``), which a kind nobody registered reads as a
:class:`GenericEvent` (its fields in ``extra``). They are logged and reported like any other.

:class:`JsonlEventLog` writes events as JSON Lines, one event per line, flushed as written, so a
crash loses nothing already logged; :func:`read_events` reads such a log back (a truncated last
line — the process died while writing it — is skipped and reported; a line whose fields do not
have its kind's types is skipped too). Version 1 logs (before ``world_ref``, ``route`` and
``tree``) read the same; a log of an unknown version is refused.
"""

from __future__ import annotations

import io
import json
import math
import types
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import (
    IO,
    Annotated,
    Any,
    ClassVar,
    Protocol,
    Self,
    TypeVar,
    Union,
    get_args,
    get_origin,
    get_type_hints,
    runtime_checkable,
)

from btmission.errors import BtmissionError

LOG_FORMAT = "btmission-log"
LOG_VERSION = 2
"""The version this btmission writes. 2: the header's ``world_ref``, ``tree`` and ``route``
events (version 1 logs have neither and read the same)."""
READS_VERSIONS = (1, 2)
"""Log versions ``btmission report`` reads."""


@dataclass(frozen=True)
class Event:
    """Something that happened at mission time ``t`` (seconds): its ``kind`` and fields."""

    t: float
    kind: str
    data: Mapping[str, Any] = field(default_factory=dict)
    _typed: TypedEvent | None = field(default=None, init=False, repr=False, compare=False)
    _json: bool = field(default=False, init=False, repr=False, compare=False)
    """Its data was read from JSON (:meth:`from_json`): plain already."""

    def get(self, key: str, default: Any = None) -> Any:
        return self.data.get(key, default)

    def to_json(self) -> str:
        """One JSON object: ``{"t": ..., "ev": kind, **data}`` (inf/NaN as null)."""
        return json.dumps(
            {"t": round(self.t, 4), "ev": self.kind, **_plain(self.data)},
            separators=(",", ":"),
            allow_nan=False,
        )

    def typed(self) -> TypedEvent:
        """This event as its kind's typed class (:func:`event_class`; :class:`GenericEvent` for
        a kind nobody registered), with the values its JSON form has (an event read from a
        log: the values read) — what a consumer reads (the report, the viewer's feed, a
        restarted coordinator), live or from a log alike. Made once (events are not changed
        after they are published; :func:`read_events` makes it as it checks the line). Raises
        :class:`EventError` if a field has the wrong type."""
        typed = self._typed
        if typed is None:
            data = self.data if self._json else _plain(self.data)
            typed = typed_event(self.t, self.kind, data)
            object.__setattr__(self, "_typed", typed)
        return typed

    def typed_or_none(self) -> TypedEvent | None:
        """:meth:`typed`, or None for an event whose fields do not have its kind's types (a
        library's bad event, published live: :func:`read_events` skips such a line of a log, so
        a consumer skips it live too)."""
        try:
            return self.typed()
        except EventError:
            return None

    @classmethod
    def from_json(cls, line: str) -> Event:
        obj = json.loads(line)
        if not isinstance(obj, dict) or "ev" not in obj or "t" not in obj:
            raise ValueError("not a btmission event (expected an object with 't' and 'ev')")
        t = float(obj.pop("t"))
        kind = str(obj.pop("ev"))
        ev = cls(t, kind, obj)
        object.__setattr__(ev, "_json", True)
        return ev


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


# ---------------------------------------------------------------------------- typed events
def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _text(v: Any) -> bool:
    return isinstance(v, str)


def _point(v: Any) -> bool:
    return isinstance(v, list) and len(v) == 3 and all(_number(x) for x in v)


def _agent_entry(v: Any) -> bool:
    return isinstance(v, dict) and _text(v.get("id")) and _point(v.get("start", [0, 0, 0]))


def _placed(v: Any) -> bool:  # an artifact or a detected object
    return isinstance(v, dict) and _point(v.get("p"))


def _change(v: Any) -> bool:  # [node, old status, new status]
    return (
        isinstance(v, list)
        and len(v) == 3
        and isinstance(v[0], (int, str))
        and not isinstance(v[0], bool)
        and _text(v[1])
        and _text(v[2])
    )


def _tree_node(v: Any) -> bool:  # [name, parent uid (-1: the root), kind]
    return isinstance(v, list) and len(v) == 3 and _text(v[0]) and isinstance(v[1], int)


Point = Annotated[list[float], _point]
"""A position ``[x, y, z]`` in metres."""
AgentEntry = Annotated[dict[str, Any], _agent_entry]
"""An agent of the header: ``{id, library, vehicle, start}``."""
Placed = Annotated[dict[str, Any], _placed]
"""Something at a place: ``{label, p, ...}`` (an artifact, a localised object)."""
StatusChange = Annotated[list[Any], _change]
"""``[node uid, old status, new status]`` (a ``tree`` event)."""
TreeNode = Annotated[list[Any], _tree_node]
"""``[name, parent uid, kind]`` (a ``tree`` event's ``nodes``)."""

Check = Callable[[Any], bool]


def _checker(tp: Any) -> Check:
    """The check of a JSON value against a field's type: ``str``, ``int``, ``float`` (finite),
    ``bool``, ``Any``, ``X | None``, ``list[X]``, ``dict[str, X]``, or ``Annotated[T, check]``
    (the check given)."""
    if tp is Any:
        return lambda v: True
    origin = get_origin(tp)
    args = get_args(tp)
    if origin is Annotated:
        check: Check = args[1]
        return check
    if origin in (Union, types.UnionType):
        checks = [_checker(a) for a in args]
        return lambda v: any(c(v) for c in checks)
    if tp is type(None):
        return lambda v: v is None
    if tp is bool:
        return lambda v: isinstance(v, bool)
    if tp is int:
        return lambda v: isinstance(v, int) and not isinstance(v, bool)
    if tp is float:
        return _number
    if tp is str:
        return _text
    if origin is list:
        item = _checker(args[0]) if args else _checker(Any)
        return lambda v: isinstance(v, list) and all(item(x) for x in v)
    if origin is dict or tp is dict:
        value = _checker(args[1]) if args else _checker(Any)
        return lambda v: isinstance(v, dict) and all(value(x) for x in v.values())
    raise TypeError(f"no JSON check for an event field of type {tp!r}")


def optional(*, written_with: str | None = None) -> Any:
    """An event field that is left out of the JSON when it is None (it is absent from most
    events of its kind), e.g. ``round.assignments`` — unless the field ``written_with`` is set:
    then it is written, null included (``leaf_error.task`` is null for an agent's leaf that
    raised while the agent had no task, and absent for a run-wide service's error)."""
    return field(default=None, metadata={"optional": True, "written_with": written_with})


class EventError(BtmissionError, ValueError):
    """An event whose fields do not have the types of its kind's class."""


_BASE_FIELDS = frozenset({"t", "reported_s", "extra", "_absent"})


@dataclass(frozen=True, kw_only=True)
class TypedEvent:
    """Base of the typed events: one frozen dataclass per kind (module docstring), registered
    with :func:`register_event`. Field values are plain JSON data (lists, dicts, numbers,
    strings), exactly what the log holds.

    Its JSON form is the :class:`Event`'s: ``{"t", "ev", <fields in class order>, <extra>,
    "reported_s"}`` (a class may put ``extra`` right after one of its fields:
    :attr:`EXTRA_AFTER`). An event read from a log keeps which fields it lacked (they stay out),
    so JSON → typed → JSON gives the same bytes; a field declared with :func:`optional` is also
    left out when it is None.

    Producers make the event and publish it (:meth:`MissionRun.emit_event
    <btmission.runtime.runner.MissionRun.emit_event>`, an agent's or a library's
    ``ctx.events(event)``) without a time: the run stamps it when it publishes it.
    """

    KIND: ClassVar[str] = ""
    _FIELDS: ClassVar[tuple[tuple[str, Check, bool], ...]] = ()
    """(name, check, optional) of the kind's own fields, in order (set by register_event)."""
    _WRITTEN_WITH: ClassVar[Mapping[str, str]] = {}
    """Optional field → the field whose being set writes it even when None (:func:`optional`)."""
    EXTRA_AFTER: ClassVar[str | None] = None
    """The field after which :attr:`extra` goes in the JSON (None: after them all)."""

    t: float = math.nan
    """Mission time (s) at which the event was published; NaN in an event made to be
    published (the run stamps it with the time then), or the time it happened, if that was
    earlier (it is published then with ``reported_s``)."""
    reported_s: float | None = None
    """When it happened, if earlier than published (an agent's report, taken by the next
    round)."""
    extra: Mapping[str, Any] = field(default_factory=dict)
    """Fields the class does not declare (a newer log, a library's additions), in log order."""
    _absent: frozenset[str] | None = field(default=None, repr=False, compare=False)

    @property
    def kind(self) -> str:
        return self.KIND

    @classmethod
    def problem(cls, data: Mapping[str, Any]) -> str | None:
        """What is wrong with ``data`` as this kind's fields (None: nothing): the first field
        present with a value of the wrong type. Fields may be absent."""
        if "reported_s" in data and not _number(data["reported_s"]):
            return "field 'reported_s' has the wrong type"
        for name, check, _ in cls._FIELDS:
            if name in data and not check(data[name]):
                return f"field '{name}' has the wrong type (got {json.dumps(data[name])[:60]})"
        return None

    @classmethod
    def from_data(cls, t: float, data: Mapping[str, Any]) -> Self:
        """The typed event of plain fields (JSON data). Raises :class:`EventError`."""
        problem = cls.problem(data)
        if problem:
            raise EventError(f"{cls.KIND or 'event'}: {problem}")
        own = {name for name, _, _ in cls._FIELDS}
        kw = {name: data.get(name) for name in own}
        extra = {k: v for k, v in data.items() if k not in own and k != "reported_s"}
        return cls(
            t=t,
            reported_s=data.get("reported_s"),
            extra=extra,
            _absent=frozenset(name for name in own if name not in data),
            **kw,
        )

    def to_data(self) -> dict[str, Any]:
        """The fields, in their JSON order."""
        out: dict[str, Any] = {}
        after = self.EXTRA_AFTER
        for name, _, is_optional in self._FIELDS:
            value = getattr(self, name)
            if self._absent is not None:
                if name in self._absent:
                    continue
            elif is_optional and value is None:
                with_ = self._WRITTEN_WITH.get(name)
                if with_ is None or getattr(self, with_) is None:
                    continue
            out[name] = value
            if name == after:
                out.update(self.extra)
        if after is None or after not in out:
            out.update(self.extra)
        if self.reported_s is not None:
            out["reported_s"] = self.reported_s
        return out

    def to_event(self) -> Event:
        return Event(self.t, self.kind, self.to_data())

    def to_json(self) -> str:
        return self.to_event().to_json()


@dataclass(frozen=True, kw_only=True)
class GenericEvent(TypedEvent):
    """An event of a kind no class is registered for — a library's own kind, such as
    ``haulage``'s ``load`` before its module is imported: all its fields are in ``extra``."""

    name: str
    """The event's kind."""

    @property
    def kind(self) -> str:
        return self.name


EVENT_CLASSES: dict[str, type[TypedEvent]] = {}
"""Kind → its typed class (:func:`register_event`)."""

E = TypeVar("E", bound=type[TypedEvent])


def register_event(cls: E) -> E:
    """Class decorator (above ``@dataclass(frozen=True, kw_only=True)``): ``cls`` is the typed
    class of the kind ``cls.KIND``. Libraries register their own kinds the same way::

        @register_event
        @dataclass(frozen=True, kw_only=True)
        class Loaded(TypedEvent):
            KIND = "load"
            agent: str
            until: float

    A kind is registered once; registering it again with a class of another name is an error
    (two libraries cannot give one kind different fields)."""
    kind = cls.KIND
    if not kind:
        raise ValueError(f"{cls.__qualname__}: set KIND to the event's kind")
    old = EVENT_CLASSES.get(kind)
    if old is not None and (old.__module__, old.__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(
            f"event kind '{kind}' is already {old.__module__}.{old.__qualname__}; "
            f"{cls.__module__}.{cls.__qualname__} cannot register it again"
        )
    hints = get_type_hints(cls, include_extras=True)
    own = [f for f in fields(cls) if f.name not in _BASE_FIELDS]
    cls._FIELDS = tuple(
        (f.name, _checker(hints[f.name]), bool(f.metadata.get("optional"))) for f in own
    )
    cls._WRITTEN_WITH = {
        f.name: f.metadata["written_with"] for f in own if f.metadata.get("written_with")
    }
    if cls.EXTRA_AFTER is not None and cls.EXTRA_AFTER not in {f.name for f in own}:
        raise ValueError(f"{cls.__qualname__}: EXTRA_AFTER names no field of it")
    EVENT_CLASSES[kind] = cls
    return cls


def event_class(kind: str) -> type[TypedEvent]:
    """The typed class of ``kind`` (:class:`GenericEvent` for a kind nobody registered)."""
    return EVENT_CLASSES.get(kind, GenericEvent)


def typed_event(t: float, kind: str, data: Mapping[str, Any]) -> TypedEvent:
    """The typed event of ``kind`` with plain ``data`` (JSON data). Raises :class:`EventError`."""
    cls = EVENT_CLASSES.get(kind)
    if cls is not None:
        return cls.from_data(t, data)
    problem = TypedEvent.problem(data)
    if problem:
        raise EventError(f"{kind}: {problem}")
    return GenericEvent(
        t=t,
        name=kind,
        reported_s=data.get("reported_s"),
        extra={k: v for k, v in data.items() if k != "reported_s"},
        _absent=frozenset(),
    )


EmitEvent = Callable[[TypedEvent], None]
"""Where a producer publishes its events: the run's
:meth:`~btmission.runtime.runner.MissionRun.emit_event`, an agent's (which notes the action a
``stage`` event starts, then passes it on), a test's ``list.append``."""


def event_of(event: TypedEvent | str, fields: Mapping[str, Any]) -> TypedEvent:
    """What a library's ``ctx.events(...)`` was given, as a typed event: the event itself, or —
    a kind of the library's own that has no class, given by name with its fields — a
    :class:`GenericEvent` of them (they are written as given)."""
    if isinstance(event, TypedEvent):
        if fields:
            raise TypeError(
                f"{event.kind}: a typed event takes no other fields ({', '.join(fields)})"
            )
        return event
    return GenericEvent(name=event, extra=dict(fields))


def world_reference(world: Mapping[str, Any] | None, base_dir: str | Path) -> dict[str, Any]:
    """What a viewer needs, besides the header's ``world``, to load the map from the log alone:
    ``base_dir`` (the mission's directory, absolute: ``world_from_spec(world, base_dir)``
    rebuilds the map), ``map`` (the map file's absolute path; None for a generated map: the
    generator's parameters are in ``world.map``) and ``topomap`` (a built-in map's name or the
    file's absolute path; None without one)."""
    base = Path(base_dir).resolve()
    w = world or {}
    spec = w.get("map") or {}
    map_file = spec.get("file") if isinstance(spec, Mapping) else None
    topo = w.get("topomap")
    if topo is not None:
        from btmission.dispatch.maps import BUILTIN_MAPS

        if topo not in BUILTIN_MAPS:
            topo = str(base / str(topo))
    return {
        "base_dir": str(base),
        "map": str(base / str(map_file)) if map_file is not None else None,
        "topomap": topo,
    }


def event_problem(ev: Event) -> str | None:
    """What is wrong with the shape of an event read from a log (None when it can be reported):
    a time that is not a finite number, or a field of the wrong type for its kind's class."""
    if not math.isfinite(ev.t):
        return f"time {ev.t} is not a finite number"
    return event_class(ev.kind).problem(ev.data)


class LogError(BtmissionError, ValueError):
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
            if ev.kind == "header" and not events:
                _check_format(p, ev)  # before the fields: a newer version may have other ones
            problem = _read_problem(ev)
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
    if not events or events[0].kind != "header":
        raise _not_a_log(p)
    return LogContents(events, truncated, skipped)


def _read_problem(ev: Event) -> str | None:
    """:func:`event_problem`, making the event's typed form on the way (its consumers read it
    next: checked once)."""
    if not math.isfinite(ev.t):
        return f"time {ev.t} is not a finite number"
    try:
        ev.typed()
    except EventError:
        return event_problem(ev)
    return None


def _not_a_log(p: Path) -> LogError:
    return LogError(
        f"{p}: not a btmission event log (the first line must be a '{LOG_FORMAT}' header)"
    )


def _check_format(p: Path, header: Event) -> None:
    """Raise :class:`LogError` unless ``header`` heads a log of a version this btmission reads."""
    if header.get("format") != LOG_FORMAT:
        raise _not_a_log(p)
    version = header.get("version")
    if isinstance(version, bool) or version not in READS_VERSIONS:
        known = " and ".join(str(v) for v in READS_VERSIONS)
        raise LogError(f"{p}: log format version {version!r}; this btmission reads {known}")


# The kinds themselves (every class registers itself): after everything they build on.
from btmission.runtime import eventkinds as _kinds  # noqa: E402, F401
