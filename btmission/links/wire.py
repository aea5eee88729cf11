"""The wire form of the coordinator/agent messages: versioned plain dicts, as JSON bytes.

Every message of :mod:`btmission.links.bus` — :class:`~btmission.allocation.auction.Announcement`,
:class:`~btmission.allocation.auction.Bid`, :class:`~btmission.links.bus.Assignment`,
:class:`~btmission.links.bus.AgentStatus`, :class:`~btmission.allocation.loop.Progress`,
:class:`~btmission.links.bus.ProgressAck` and :class:`~btmission.links.bus.Prediction` —
becomes a JSON object with the format version ``v`` and the message ``kind``, then its fields::

    {"v": 2, "kind": "bid", "agent": "R1", "time_s": 2.5, "committed_to": null, "serial": 3,
     "costs": "AAAAAAAAKUAAAAAAAAD4fw==", "tasks": ["T1", "T2"]}

Arrays are lists. JSON has no NaN or infinity, so a non-finite number in a float field is the
string ``"nan"``, ``"inf"`` or ``"-inf"``. Decoding checks everything — the version, the kind,
every field's presence and type, and the size of the bytes against
``BTMISSION_MAX_MESSAGE_BYTES`` before parsing — and raises :class:`WireError`, with the message
kind and the field, for anything else; a transport can drop (and count) such a message without
knowing the format.

Format version 2 (what :func:`encode` writes; :func:`decode` reads versions 1 and 2):

* a bid's ``costs`` are one string, the base64 of the costs as little-endian float64 (NaN — "no
  bid" — and infinity — "unreachable" — as themselves), in the order of its ``tasks``, which are
  still listed: a bid decodes on its own, whoever receives it. Version 1 wrote a list of
  numbers (non-finite ones as ``"nan"``, ``"inf"``, ``"-inf"``): at 400 tasks 10.5 kB, ~0.2 ms to
  write and as long to read, against 8 kB and ~0.03 ms each way;
* announcements and assignments carry the coordinator's ``epoch`` (its incarnation:
  :attr:`~btmission.allocation.auction.Announcement.epoch`; 0 in version 1) and an assignment the
  ``serial`` of its announcement. The announcement itself is embedded (``"announcement"``, last)
  or left out (:func:`encode` with ``embed=False``): then the receiver must have it — ``known``
  in :func:`decode`, with the same epoch and serial — or decoding raises
  :class:`UnknownAnnouncement` (the agent waits for the next announcement; see
  docs/distributed.md for when the coordinator embeds it).
"""

from __future__ import annotations

import base64
import binascii
import json
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeAlias

import numpy as np

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Progress
from btmission.allocation.tasks import TaskInfo
from btmission.errors import BtmissionError
from btmission.limits import MAX_MESSAGE_BYTES
from btmission.links.bus import (
    AgentStatus,
    Assignment,
    MissionEnd,
    Prediction,
    ProgressAck,
)

WIRE_VERSION = 2
"""The version :func:`encode` writes."""
VERSIONS = (1, 2)
"""The versions :func:`decode` reads."""
MAX_EPOCH = 2**64 - 1

Message: TypeAlias = (
    Announcement | Bid | Assignment | AgentStatus | Progress | ProgressAck | Prediction | MissionEnd
)

PROGRESS_EVENTS = ("committed", "done", "failed", "gave_up")
_MAX_ATTEMPTS = TaskInfo.max_attempts
"""A task's ``max_attempts`` when its announcement leaves it out (the default)."""


class WireError(BtmissionError, ValueError):
    """A message that cannot be decoded (or encoded): the text says which kind and field."""


class UnknownAnnouncement(WireError):
    """An assignment that names its announcement by epoch and serial, which the receiver does
    not have (``known``): not a bad message; the next announcement (or a later assignment that
    embeds it) brings it."""


# ------------------------------------------------------------------------------------ encoding
def _num(x: float) -> float | str:
    x = float(x)
    if math.isfinite(x):
        return x
    return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")


def _nums(xs: Any) -> list[float | str]:
    arr = np.asarray(xs, dtype=np.float64).ravel()
    out: list[float | str] = list(arr.tolist())  # Python floats, as float(x) gives
    bad = ~np.isfinite(arr)
    if bad.any():
        for i in np.flatnonzero(bad):
            out[i] = _num(arr[i])
    return out


def _plain(v: Any, where: str) -> Any:
    """A task field as JSON: tuples and arrays as lists, finite numbers only."""
    if v is None or isinstance(v, (str, bool)):
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(v):
            raise WireError(f"{where}: {v} is not a finite number")
        return float(v)
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, (list, tuple)):
        return [_plain(x, where) for x in v]
    if isinstance(v, Mapping):
        return {str(k): _plain(x, f"{where}.{k}") for k, x in v.items()}
    raise WireError(f"{where}: {type(v).__name__} cannot be sent")


def _task(t: TaskInfo) -> dict[str, Any]:
    out = {
        "id": t.id,
        "type": t.type,
        "fields": _plain(dict(t.fields), f"task '{t.id}' fields"),
        "priority": t.priority,
        "arrival_s": t.arrival_s,
        "multi_stage": t.multi_stage,
    }
    if t.max_attempts != _MAX_ATTEMPTS:  # (only when not the default: announcements stay small)
        out["max_attempts"] = t.max_attempts
    return out


def _announcement(a: Announcement) -> dict[str, Any]:
    return {
        "epoch": a.epoch,
        "serial": a.serial,
        "time_s": a.time_s,
        "tasks": [_task(t) for t in a.tasks],
    }


_SEP = (",", ":")


def _dumps(obj: Any) -> str:
    return json.dumps(obj, allow_nan=False, separators=_SEP)


def _announcement_json(a: Announcement) -> str:
    """``{"serial":…,"time_s":…,"tasks":[…]}`` of ``a``, made once per announcement object
    (the coordinator sends one unchanged announcement every round, and in every assignment)."""
    cached = a.__dict__.get("_wire_json")
    if cached is None:
        cached = _dumps(_announcement(a))
        object.__setattr__(a, "_wire_json", cached)
    return cached  # type: ignore[no-any-return]


_ANN_HEAD = f'{{"v":{WIRE_VERSION},"kind":"announcement",'
_EMBEDDED = b',"announcement":{'


def _costs(costs: Any) -> str:
    """Costs as the base64 of little-endian float64 (NaN and infinity as themselves)."""
    arr = np.ascontiguousarray(np.asarray(costs, dtype="<f8").ravel())
    return base64.b64encode(arr.tobytes()).decode("ascii")


class _LastIds:
    """The JSON of the last bid's task ids: an agent's bids list the ids of one announcement
    (the same tuple object, :meth:`Bid.aligned`) round after round."""

    last: tuple[tuple[str, ...], str] | None = None

    @classmethod
    def json(cls, ids: tuple[str, ...]) -> str:
        cached = cls.last
        if cached is not None and cached[0] is ids:
            return cached[1]
        text = _dumps(list(ids))
        cls.last = (ids, text)
        return text


def _bid_head(msg: Bid) -> dict[str, Any]:
    """A bid's dict without its costs and tasks (which come last)."""
    return {
        "v": WIRE_VERSION,
        "kind": "bid",
        "agent": msg.agent,
        "time_s": _num(msg.time_s),
        "committed_to": msg.committed_to,
        "serial": msg.serial,
    }


def to_dict(msg: Message, *, embed: bool = True) -> dict[str, Any]:
    """The message as a plain, JSON-ready dict (``v``, ``kind``, then its fields); ``embed``:
    an assignment carries its announcement (else only its epoch and serial)."""
    body: dict[str, Any]
    if isinstance(msg, Announcement):
        kind, body = "announcement", _announcement(msg)
    elif isinstance(msg, Bid):
        return {**_bid_head(msg), "costs": _costs(msg.costs), "tasks": list(msg.tasks)}
    elif isinstance(msg, Assignment):
        head = _assignment_head(msg)
        return {**head, "announcement": _announcement(msg.announcement)} if embed else head
    elif isinstance(msg, AgentStatus):
        kind = "status"
        body = {
            "agent": msg.agent,
            "time_s": msg.time_s,
            "position": _nums(msg.position),
            "mode": msg.mode,
            "armed": msg.armed,
            "battery": _num(msg.battery),
            "task": msg.task,
            "action": msg.action,
            "vehicle_link": msg.vehicle_link,
            "at_rest": msg.at_rest,
        }
    elif isinstance(msg, Progress):
        kind = "progress"
        body = {
            "agent": msg.agent,
            "task": msg.task,
            "event": msg.event,
            "time_s": msg.time_s,
            "reason": msg.reason,
        }
    elif isinstance(msg, ProgressAck):
        kind = "ack"
        body = {"agent": msg.agent, "keys": [[t, e, s] for t, e, s in msg.keys]}
    elif isinstance(msg, Prediction):
        kind = "prediction"
        pos = np.asarray(msg.positions, dtype=np.float64)
        body = {
            "agent": msg.agent,
            "time_s": msg.time_s,
            "positions": [_nums(row) for row in pos],
        }
    elif isinstance(msg, MissionEnd):
        kind = "end"
        body = {
            "time_s": msg.time_s,
            "reason": msg.reason,
            "done": list(msg.done),
            "open": dict(msg.open),
        }
    else:
        raise WireError(f"{type(msg).__name__} is not a message")
    return {"v": WIRE_VERSION, "kind": kind, **body}


def _assignment_head(msg: Assignment) -> dict[str, Any]:
    """An assignment's dict without its announcement (which comes last)."""
    return {
        "v": WIRE_VERSION,
        "kind": "assignment",
        "epoch": msg.announcement.epoch,
        "serial": msg.announcement.serial,
        "time_s": msg.time_s,
        "round": msg.round,
        "tasks": dict(msg.tasks),
        **({} if msg.sent_s is None else {"sent_s": msg.sent_s}),
    }


def encode(msg: Message, *, embed: bool = True) -> bytes:
    """The message as JSON bytes (UTF-8), format :data:`WIRE_VERSION`. ``embed=False``: an
    assignment names its announcement (epoch and serial) instead of carrying it. Raises
    :class:`WireError` past the size budget."""
    # the same bytes as ``json.dumps(to_dict(msg))``, the repeated parts made once
    if isinstance(msg, Announcement):
        data = (_ANN_HEAD + _announcement_json(msg)[1:]).encode()
    elif isinstance(msg, Assignment):
        head = _dumps(_assignment_head(msg))
        if embed:
            head = head[:-1] + ',"announcement":' + _announcement_json(msg.announcement) + "}"
        data = head.encode()
    elif isinstance(msg, Bid):
        head = _dumps(_bid_head(msg))[:-1]
        ids = _LastIds.json(msg.tasks)
        data = f'{head},"costs":"{_costs(msg.costs)}","tasks":{ids}}}'.encode()
    else:
        data = _dumps(to_dict(msg)).encode()
    if len(data) > MAX_MESSAGE_BYTES.limit:
        raise WireError(
            MAX_MESSAGE_BYTES.exceeded(f"the {to_dict(msg)['kind']} message", len(data))
        )
    return data


# ------------------------------------------------------------------------------------ decoding
class _Fields:
    """Typed access to a message's fields; every problem names the kind and the field."""

    def __init__(
        self,
        kind: str,
        data: Mapping[str, Any],
        version: int = WIRE_VERSION,
        known: Sequence[Announcement] = (),
    ) -> None:
        self.kind = kind
        self.data = data
        self.version = version
        self.known = known

    def fail(self, name: str, expected: str, got: Any = None) -> WireError:
        shown = "" if got is None else f" (got {_show(got)})"
        return WireError(f"{self.kind} message: field '{name}' must be {expected}{shown}")

    def raw(self, name: str) -> Any:
        if name not in self.data:
            raise WireError(f"{self.kind} message: missing field '{name}'")
        return self.data[name]

    def text(self, name: str, optional: bool = False) -> Any:
        v = self.raw(name)
        if (v is None and optional) or isinstance(v, str):
            return v
        raise self.fail(name, "a string" + (" or null" if optional else ""), v)

    def integer(self, name: str, optional: bool = False) -> Any:
        v = self.raw(name)
        if (v is None and optional) or (isinstance(v, int) and not isinstance(v, bool)):
            return v
        raise self.fail(name, "an integer" + (" or null" if optional else ""), v)

    def epoch(self) -> int:
        """The coordinator's epoch (version 2; 0 in version 1, which has none)."""
        if self.version < 2:
            return 0
        v = self.integer("epoch")
        if not 0 <= v <= MAX_EPOCH:
            raise self.fail("epoch", f"an integer from 0 to {MAX_EPOCH}", v)
        return int(v)

    def flag(self, name: str) -> bool:
        v = self.raw(name)
        if isinstance(v, bool):
            return v
        raise self.fail(name, "true or false", v)

    def number(self, name: str, finite: bool = True) -> float:
        v = self.raw(name)
        return _number(v, finite, lambda: self.fail(name, _NUM[finite], v))

    def numbers(self, name: str, v: Any = None, finite: bool = True) -> list[float]:
        v = self.raw(name) if v is None else v
        expected = "a list of " + _NUMS[finite]
        if not isinstance(v, list):
            raise self.fail(name, expected, v)
        out = _plain_numbers(v, finite)  # the usual case, fast
        if out is not None:
            return out
        return [_number(x, finite, lambda: self.fail(name, expected, v)) for x in v]

    def texts(self, name: str) -> list[str]:
        v = self.raw(name)
        # the types in C first (a bid lists 400 ids), subclasses of str the slow way
        if isinstance(v, list) and (
            set(map(type, v)) <= {str} or all(isinstance(x, str) for x in v)
        ):
            return v
        raise self.fail(name, "a list of strings", v)

    def mapping(self, name: str) -> Mapping[str, Any]:
        v = self.raw(name)
        if isinstance(v, dict):
            return v
        raise self.fail(name, "an object", v)


_NUM = {True: "a finite number", False: 'a number ("nan", "inf" and "-inf" included)'}
_NUMS = {True: "finite numbers", False: 'numbers ("nan", "inf" and "-inf" included)'}
_NONFINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


def _plain_numbers(v: list[Any], finite: bool) -> list[float] | None:
    """``v`` as floats when every item is a number (or, unless ``finite``, one of the
    non-finite strings); None for anything else (:func:`_number` then says what is wrong)."""
    out: list[float] = []
    append = out.append
    for x in v:
        t = type(x)
        if t is float:
            append(x)
        elif t is int:
            append(float(x))
        elif t is str and not finite and x in _NONFINITE:
            append(_NONFINITE[x])
        else:
            return None
    if finite and not all(map(math.isfinite, out)):
        return None
    return out


def _number(v: Any, finite: bool, error: Callable[[], WireError]) -> float:
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        x = float(v)
    elif isinstance(v, str) and v in _NONFINITE and not finite:
        x = _NONFINITE[v]
    else:
        raise error()
    if finite and not math.isfinite(x):
        raise error()
    return x


def _no_constant(name: str) -> Any:
    raise ValueError(f'{name} is not JSON (a message writes "nan", "inf" or "-inf")')


def _show(v: Any) -> str:
    text = json.dumps(v) if isinstance(v, (str, int, float, bool, type(None))) else type(v).__name__
    text = "list" if isinstance(v, list) else ("object" if isinstance(v, dict) else text)
    return text if len(text) <= 40 else text[:37] + "..."


def _task_from(kind: str, data: Any, i: int) -> TaskInfo:
    if not isinstance(data, dict):
        raise WireError(f"{kind} message: task {i} must be an object (got {_show(data)})")
    f = _Fields(f"{kind}", data)
    try:
        return TaskInfo(
            f.text("id"),
            f.text("type"),
            dict(f.mapping("fields")),
            f.number("priority"),
            f.number("arrival_s"),
            f.flag("multi_stage"),
            f.integer("max_attempts") if "max_attempts" in data else _MAX_ATTEMPTS,
        )
    except WireError as exc:
        raise WireError(str(exc).replace(" message:", f" message, task {i}:", 1)) from None
    except ValueError as exc:  # TaskInfo's own checks (priority > 0 ...)
        raise WireError(f"{kind} message, task {i}: {exc}") from None


def _announcement_from(kind: str, data: Any, version: int) -> Announcement:
    if not isinstance(data, dict):
        raise WireError(f"{kind} message: field 'announcement' must be an object")
    f = _Fields(kind, data, version)
    tasks = f.raw("tasks")
    if not isinstance(tasks, list):
        raise f.fail("tasks", "a list of tasks", tasks)
    serial = f.integer("serial")
    return Announcement(
        serial,
        f.number("time_s"),
        tuple(_task_from(kind, t, i) for i, t in enumerate(tasks)),
        f.epoch(),
    )


_COSTS_B64 = "base64 of little-endian float64 (8 bytes a cost)"


def _costs_from(f: _Fields, n_tasks: int) -> np.ndarray:
    """A bid's costs: version 2's base64 string, version 1's list of numbers."""
    if f.version < 2:
        costs = np.array(f.numbers("costs", finite=False), dtype=np.float64)
    else:
        v = f.raw("costs")
        if not isinstance(v, str):
            raise f.fail("costs", _COSTS_B64, v)
        try:
            raw = base64.b64decode(v, validate=True)
        except (binascii.Error, ValueError):
            raise f.fail("costs", _COSTS_B64 + ", not valid base64", v) from None
        if len(raw) % 8:
            raise f.fail("costs", _COSTS_B64 + f", not {len(raw)} bytes", v)
        costs = np.frombuffer(raw, dtype="<f8").astype(np.float64)  # a writable copy
    if len(costs) != n_tasks:
        raise WireError(f"bid message: {len(costs)} costs for {n_tasks} task(s)")
    return costs


def _bid(f: _Fields) -> Bid:
    tasks = f.texts("tasks")
    return Bid(
        f.text("agent"),
        f.number("time_s"),
        tuple(tasks),
        _costs_from(f, len(tasks)),
        f.text("committed_to", optional=True),
        f.integer("serial", optional=True),
    )


def _assignment(f: _Fields) -> Assignment:
    tasks = f.mapping("tasks")
    for agent, task in tasks.items():
        if task is not None and not isinstance(task, str):
            raise f.fail(f"tasks.{agent}", "a task id or null", task)
    return Assignment(
        f.number("time_s"),
        f.integer("round"),
        dict(tasks),
        _assigned_from(f),
        f.number("sent_s") if "sent_s" in f.data else None,
    )


def _assigned_from(f: _Fields) -> Announcement:
    """An assignment's announcement: embedded (always in version 1), else ``f.known`` when it
    is one of them and is the one named (epoch and serial), else :class:`UnknownAnnouncement`."""
    if f.version < 2:
        return _announcement_from(f.kind, f.raw("announcement"), f.version)
    epoch, serial = f.epoch(), f.integer("serial")
    if "announcement" in f.data:
        ann = _announcement_from(f.kind, f.data["announcement"], f.version)
        if (ann.epoch, ann.serial) != (epoch, serial):
            raise WireError(
                f"assignment message: it names announcement {serial} of epoch {epoch} but "
                f"carries announcement {ann.serial} of epoch {ann.epoch}"
            )
        return ann
    for known in f.known:
        if known.serial == serial and known.epoch == epoch:
            return known
    raise UnknownAnnouncement(
        f"assignment message: announcement {serial} of epoch {epoch} is not known here and "
        "not embedded (the next announcement brings it)"
    )


def _status(f: _Fields) -> AgentStatus:
    pos = f.numbers("position")
    if len(pos) != 3:
        raise f.fail("position", "[x, y, z]", f.raw("position"))
    return AgentStatus(
        f.text("agent"),
        f.number("time_s"),
        (pos[0], pos[1], pos[2]),
        f.text("mode"),
        f.flag("armed"),
        f.number("battery", finite=False),
        f.text("task", optional=True),
        f.text("action"),
        f.flag("vehicle_link") if "vehicle_link" in f.data else True,
        f.flag("at_rest") if "at_rest" in f.data else False,
    )


def _progress(f: _Fields) -> Progress:
    event = f.text("event")
    if event not in PROGRESS_EVENTS:
        raise f.fail("event", " or ".join(PROGRESS_EVENTS), event)
    return Progress(f.text("agent"), f.text("task"), event, f.number("time_s"), f.text("reason"))


def _ack(f: _Fields) -> ProgressAck:
    keys = f.raw("keys")
    expected = "a list of [task, event, time_s]"
    if not isinstance(keys, list):
        raise f.fail("keys", expected, keys)
    out: list[tuple[str, str, float]] = []
    for k in keys:
        if not (isinstance(k, list) and len(k) == 3 and isinstance(k[0], str) and isinstance(k[1], str)):  # fmt: skip
            raise f.fail("keys", expected, keys)
        out.append((k[0], k[1], _number(k[2], True, lambda: f.fail("keys", expected, keys))))
    return ProgressAck(f.text("agent"), tuple(out))


def _prediction(f: _Fields) -> Prediction:
    rows = f.raw("positions")
    expected = "a list of [x, y] or [x, y, z] rows, all the same length"
    if not isinstance(rows, list) or not rows:
        raise f.fail("positions", expected, rows)
    pts = [f.numbers("positions", row) for row in rows]
    if len({len(p) for p in pts}) != 1 or len(pts[0]) not in (2, 3):
        raise f.fail("positions", expected)
    return Prediction(f.text("agent"), f.number("time_s"), np.array(pts, dtype=np.float64))


def _end(f: _Fields) -> MissionEnd:
    t, reason, done, still = (
        f.number("time_s"),
        f.text("reason"),
        f.texts("done"),
        f.mapping("open"),
    )
    if not all(isinstance(v, str) for v in still.values()):
        raise f.fail("open", "an object of task id → text", dict(still))
    return MissionEnd(t, reason, tuple(done), dict(still))


_DECODERS: dict[str, Callable[[_Fields], Message]] = {
    "announcement": lambda f: _announcement_from(f.kind, f.data, f.version),
    "bid": _bid,
    "assignment": _assignment,
    "status": _status,
    "progress": _progress,
    "ack": _ack,
    "prediction": _prediction,
    "end": _end,
}
KINDS: tuple[str, ...] = tuple(_DECODERS)


def _reuse(raw: bytes, known: Announcement) -> Message | None:
    """``known``, or an assignment around it, when ``raw`` is exactly that encoding; else None."""
    body = known.__dict__.get("_wire_bytes")
    if body is None:
        body = _announcement_json(known).encode()
        object.__setattr__(known, "_wire_bytes", body)
    if len(raw) == len(_ANN_HEAD) + len(body) - 1 and raw == _ANN_HEAD.encode() + body[1:]:
        return known
    # an assignment: the compact encoding ends with ',"announcement":' + body + '}'; a JSON
    # string cannot hold an unescaped quote, so the first such bytes are the top-level key
    pos = raw.find(_EMBEDDED)
    if pos < 0 or raw[pos + len(_EMBEDDED) - 1 : -1] != body or not raw.endswith(b"}"):
        return None
    try:
        head = json.loads(raw[:pos] + b"}", parse_constant=_no_constant)
    except (ValueError, RecursionError):
        return None
    if not isinstance(head, dict) or head.get("kind") != "assignment":
        return None
    v = head.get("v")
    if v != WIRE_VERSION or isinstance(v, bool):
        return None  # version 1 embeds a version 1 announcement: not these bytes
    # the head names ``known`` by epoch and serial (else UnknownAnnouncement: it does not
    # match what it carries, which is ``known``)
    try:
        return _assignment(_Fields("assignment", head, WIRE_VERSION, (known,)))
    except UnknownAnnouncement:
        return None  # decoded as usual: a clear error


def from_dict(data: Any, known: Announcement | Sequence[Announcement] | None = None) -> Message:
    """The message of a plain dict (:func:`to_dict`), of format version 1 or 2. ``known``: the
    announcement(s) an assignment that does not embed its own may name. Raises
    :class:`WireError` (:class:`UnknownAnnouncement` for such an assignment naming another)."""
    if not isinstance(data, dict):
        raise WireError(f"a message must be a JSON object (got {_show(data)})")
    if "v" not in data:
        raise WireError("message without a version 'v'")
    v = data["v"]
    if v not in VERSIONS or isinstance(v, bool):
        raise WireError(
            f"message version {_show(v)} is not supported (expected "
            f"{' or '.join(map(str, VERSIONS))})"
        )
    kind = data.get("kind")
    if kind not in _DECODERS:
        raise WireError(f"unknown message kind {_show(kind)} (expected one of: {', '.join(KINDS)})")
    return _DECODERS[kind](_Fields(kind, data, v, _sequence(known)))


def _sequence(known: Announcement | Sequence[Announcement] | None) -> Sequence[Announcement]:
    return () if known is None else (known,) if isinstance(known, Announcement) else known


def decode(
    data: bytes | bytearray | memoryview | str,
    known: Announcement | Sequence[Announcement] | None = None,
) -> Message:
    """The message in JSON ``data`` (:func:`encode`). Raises :class:`WireError` for bytes over
    the size budget, bad JSON, or a bad message.

    ``known``: an announcement decoded (or sent) before, or several, the latest first. An
    announcement message that is exactly the encoding of the (first) one gives back that
    object, and so does the announcement inside an assignment (the coordinator repeats one
    announcement every round and in every assignment; decoding 400 tasks again takes ~2 ms).
    Anything else is decoded as usual. An assignment that does not embed its announcement gets
    the known one it names (epoch and serial), else :class:`UnknownAnnouncement`."""
    size = len(data.encode() if isinstance(data, str) else data)
    if size > MAX_MESSAGE_BYTES.limit:
        raise WireError(MAX_MESSAGE_BYTES.exceeded("the message", size))
    latest = known if isinstance(known, Announcement) else (known[0] if known else None)
    if latest is not None and not isinstance(data, str):
        same = _reuse(bytes(data), latest)
        if same is not None:
            return same
    try:
        parsed = json.loads(
            bytes(data) if not isinstance(data, str) else data, parse_constant=_no_constant
        )
    except (ValueError, RecursionError) as exc:
        raise WireError(f"the message is not JSON: {exc}") from None
    return from_dict(parsed, known)
