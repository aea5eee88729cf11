"""The wire codec of the coordinator/agent messages: round trips and bad input."""

from __future__ import annotations

import base64
import json
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Progress
from btmission.allocation.tasks import TaskInfo
from btmission.links.bus import AgentStatus, Assignment, MissionEnd, Prediction, ProgressAck
from btmission.links.wire import (
    KINDS,
    WIRE_VERSION,
    UnknownAnnouncement,
    WireError,
    decode,
    encode,
    to_dict,
)

ANN = Announcement(
    3,
    1.5,
    (
        TaskInfo("T1", "inspect", {"location": [1.0, 2.5, 0.0]}, 2.0, 0.0),
        TaskInfo(
            "P1", "pick_and_deliver", {"pickup": "dock", "dropoff": [4, 5, 0]}, 1.0, 1.5, True
        ),
    ),
)


def roundtrip(msg: Any) -> Any:
    data = encode(msg)
    json.loads(data)  # strict JSON: no NaN / Infinity tokens
    assert b"NaN" not in data and b"Infinity" not in data
    return decode(data)


def test_announcement_and_assignment_round_trip() -> None:
    assert roundtrip(ANN) == ANN
    msg = Assignment(1.6, 17, {"R1": "T1", "R2": None}, ANN)
    back = roundtrip(msg)
    assert back == msg and back.announcement.tasks[1].multi_stage
    assert to_dict(msg)["v"] == WIRE_VERSION and to_dict(msg)["kind"] == "assignment"


def test_bid_round_trips_nan_and_inf_costs() -> None:
    bid = Bid.aligned("R1", 1.5, ANN, [12.25, math.nan], committed_to="T1")
    assert bid.serial == 3
    back = roundtrip(bid)
    assert (back.agent, back.time_s, back.tasks, back.committed_to, back.serial) == (
        "R1", 1.5, ("T1", "P1"), "T1", 3,
    )  # fmt: skip
    np.testing.assert_array_equal(back.costs, bid.costs)  # NaN == NaN here
    inf = roundtrip(Bid.of("R2", 2.0, {"T1": math.inf, "P1": 0.0}))
    assert inf.costs[0] == math.inf and inf.serial is None
    costs = to_dict(bid)["costs"]  # version 2: base64 of little-endian float64
    assert costs == base64.b64encode(np.array([12.25, math.nan], "<f8").tobytes()).decode()
    assert back.costs.flags.writeable and back.costs.dtype == np.float64


def b64(costs: list[float]) -> str:
    return base64.b64encode(np.array(costs, dtype="<f8").tobytes()).decode()


@given(
    st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), max_size=60),
    st.one_of(st.none(), st.integers(0, 2**40)),
)
def test_a_bid_round_trips_every_float64_exactly(costs: list[float], serial: int | None) -> None:
    tasks = tuple(f"T{j}" for j in range(len(costs)))
    bid = Bid("R1", 0.5, tasks, np.array(costs, dtype=np.float64), None, serial)
    back = decode(encode(bid))
    assert isinstance(back, Bid) and back.tasks == tasks and back.serial == serial
    # bit for bit: -0.0, NaN and infinities included
    assert back.costs.tobytes() == bid.costs.tobytes()


def test_an_empty_bid_round_trips() -> None:
    empty = Bid.of("R1", 1.0, {}, serial=2)
    back = roundtrip(empty)
    assert back.tasks == () and back.costs.shape == (0,) and back.serial == 2
    assert to_dict(empty)["costs"] == "" and to_dict(empty)["tasks"] == []


def test_status_progress_ack_and_prediction_round_trip() -> None:
    st = AgentStatus("R1", 3.0, (1.0, 2.0, 0.5), "OFFBOARD", True, 0.87, "T1", "fly_to")
    assert roundtrip(st) == st
    idle = AgentStatus("R2", 3.0, (0.0, 0.0, 0.0), "HOLD", False, math.nan, None, "")
    back = roundtrip(idle)
    assert back.task is None and math.isnan(back.battery)
    for p in (
        Progress("R1", "T1", "done", 84.3),
        Progress("R1", "P1", "failed", 9.0, "blocked"),
        Progress("R1", "T2", "gave_up", 34.4, "arm: PreArm: Compass not calibrated"),
    ):
        assert roundtrip(p) == p
    ack = ProgressAck("R1", (("T1", "done", 84.3), ("P1", "committed", 20.1)))
    assert roundtrip(ack) == ack
    for shape in ((11, 2), (1, 3)):
        pred = Prediction("R3", 4.2, np.arange(math.prod(shape), dtype=float).reshape(shape) / 3)
        out = roundtrip(pred)
        assert out.agent == "R3" and out.time_s == 4.2
        np.testing.assert_array_equal(out.positions, pred.positions)


def test_a_tasks_max_attempts_goes_only_when_it_is_not_the_default() -> None:
    five = Announcement(4, 2.0, (TaskInfo("T1", "inspect", {}, max_attempts=5), *ANN.tasks))
    back = roundtrip(five)
    assert back == five and back.tasks[0].max_attempts == 5
    tasks = to_dict(five)["tasks"]
    assert tasks[0]["max_attempts"] == 5 and "max_attempts" not in tasks[1]
    assert roundtrip(ANN).tasks[0].max_attempts == 3


def test_every_kind_has_a_round_trip_test() -> None:
    assert set(KINDS) == {
        "announcement", "bid", "assignment", "status", "progress", "ack", "prediction", "end",
    }  # fmt: skip


def test_at_rest_and_the_end_of_a_mission_round_trip() -> None:
    st = AgentStatus("R1", 9.0, (1.0, 2.0, 0.0), "LAND", False, 0.5, None, "", True, True)
    assert roundtrip(st) == st and roundtrip(st).at_rest
    older = to_dict(st)
    del older["at_rest"]  # a v1 status from before the field: not at rest
    assert not decode(json.dumps(older)).at_rest  # type: ignore[union-attr]
    end = MissionEnd(311.5, "completed", ("T1", "T2"), {"T3": "failed: blocked"})
    assert roundtrip(end) == end
    bad = {**to_dict(end), "open": {"T3": 4}}
    with pytest.raises(WireError, match="end message: field 'open'"):
        decode(json.dumps(bad))
    with pytest.raises(WireError, match="end message: missing field 'reason'"):
        decode(json.dumps({"v": WIRE_VERSION, "kind": "end", "time_s": 1.0}))


def good_bid() -> dict[str, Any]:
    return to_dict(Bid.aligned("R1", 1.5, ANN, [1.0, math.inf]))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"v": 3}, "message version 3 is not supported (expected 1 or 2)"),
        ({"v": None}, "message version null is not supported"),
        ({"kind": "hello"}, 'unknown message kind "hello" (expected one of: announcement, bid,'),
        ({"agent": 7}, "bid message: field 'agent' must be a string (got 7)"),
        ({"costs": b64([1.0])}, "bid message: 1 costs for 2 task(s)"),
        ({"costs": b64([1.0, 2.0, 3.0])}, "bid message: 3 costs for 2 task(s)"),
        (
            {"costs": [1.0, 2.0]},  # version 1's list in a version 2 bid
            "bid message: field 'costs' must be base64 of little-endian float64 (8 bytes a "
            "cost) (got list)",
        ),
        ({"costs": "AAAA*AAA"}, 'a cost), not valid base64 (got "AAAA*AAA")'),
        ({"costs": "AAAAAAAAAA"}, "not valid base64"),  # bad padding
        ({"costs": "AAA=AAAAAAAA"}, "not valid base64"),  # data after the padding
        ({"costs": "AAAAAAAAAAA\n"}, "not valid base64"),
        ({"costs": base64.b64encode(b"x" * 12).decode()}, "8 bytes a cost), not 12 bytes"),
        ({"costs": None}, "field 'costs' must be base64 of little-endian float64"),
        ({"time_s": "nan"}, "bid message: field 'time_s' must be a finite number (got \"nan\")"),
        ({"serial": 1.5}, "bid message: field 'serial' must be an integer or null (got 1.5)"),
        ({"tasks": "T1"}, "bid message: field 'tasks' must be a list of strings"),
    ],
)
def test_a_bad_field_is_one_clear_error(change: dict[str, Any], message: str) -> None:
    data = {**good_bid(), **change}
    with pytest.raises(WireError) as err:
        decode(json.dumps(data).encode())
    assert message in str(err.value)


V1_BID = {"v": 1, "kind": "bid", "agent": "R1", "time_s": 1.5, "tasks": ["T1", "P1"],
          "costs": [1.0, "inf"], "committed_to": None, "serial": 3}  # fmt: skip


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"costs": [1.0]}, "bid message: 1 costs for 2 task(s)"),
        (
            {"costs": [1.0, "lots"]},
            'bid message: field \'costs\' must be a list of numbers ("nan", "inf" and',
        ),
        (
            {"costs": [1.0, True]},
            'bid message: field \'costs\' must be a list of numbers ("nan", "inf" and',
        ),
        ({"costs": b64([1.0, 2.0])}, "bid message: field 'costs' must be a list of numbers"),
    ],
)
def test_a_bad_version_1_bid_is_one_clear_error(change: dict[str, Any], message: str) -> None:
    with pytest.raises(WireError) as err:
        decode(json.dumps({**V1_BID, **change}).encode())
    assert message in str(err.value)


def test_version_1_messages_are_still_decoded() -> None:
    """What a sender of format version 1 writes: costs as a list, no epoch, the announcement
    always inside the assignment."""
    bid = decode(json.dumps(V1_BID))
    assert isinstance(bid, Bid) and bid.tasks == ("T1", "P1") and bid.serial == 3
    assert bid.costs.tolist() == [1.0, math.inf]
    v1_ann = {"serial": 3, "time_s": 1.5, "tasks": to_dict(ANN)["tasks"]}
    ann = decode(json.dumps({"v": 1, "kind": "announcement", **v1_ann}))
    assert ann == ANN and ann.epoch == 0  # type: ignore[union-attr]
    asg = {"v": 1, "kind": "assignment", "time_s": 1.6, "round": 17, "tasks": {"R1": "T1"},
           "announcement": v1_ann}  # fmt: skip
    got = decode(json.dumps(asg).encode(), known=ANN)
    assert got == Assignment(1.6, 17, {"R1": "T1"}, ANN)
    del asg["announcement"]  # version 1 has no assignment without its announcement
    with pytest.raises(WireError, match=r"^assignment message: missing field 'announcement'$"):
        decode(json.dumps(asg).encode(), known=ANN)
    with pytest.raises(WireError, match="announcement message: field 'epoch' must be an integer"):
        decode(json.dumps({"v": 2, "kind": "announcement", **v1_ann, "epoch": "1"}))


def test_an_assignment_may_name_its_announcement_instead_of_carrying_it() -> None:
    ann = Announcement(3, 1.5, ANN.tasks, epoch=2**64 - 1)
    msg = Assignment(1.6, 17, {"R1": "T1", "R2": None}, ann)
    short = encode(msg, embed=False)
    assert b'"announcement"' not in short and len(short) < len(encode(msg)) // 3
    assert to_dict(msg, embed=False)["serial"] == 3
    assert json.loads(short) == to_dict(msg, embed=False)
    back = decode(short, known=ann)
    assert back == msg and back.announcement is ann  # type: ignore[union-attr]
    known = decode(encode(ann))  # the receiver's own copy, decoded earlier
    assert decode(short, known=known).announcement is known  # type: ignore[union-attr]
    for other in (None, Announcement(4, 1.5, ANN.tasks, ann.epoch), ANN):  # serial, epoch
        with pytest.raises(UnknownAnnouncement, match=r"^assignment message: announcement 3 "
                           r"of epoch 18446744073709551615 is not known here and not embedded"):  # fmt: skip
            decode(short, known=other)
    assert issubclass(UnknownAnnouncement, WireError)
    wrong = json.loads(encode(msg))
    wrong["serial"] = 4  # names another announcement than it carries
    with pytest.raises(WireError, match=r"names announcement 4 of epoch \d+ but carries "
                       r"announcement 3 of epoch"):  # fmt: skip
        decode(json.dumps(wrong), known=ann)
    for epoch in (-1, 2**64, True, 1.0):
        bad = {**json.loads(short), "epoch": epoch}
        with pytest.raises(WireError, match="assignment message: field 'epoch' must be"):
            decode(json.dumps(bad), known=ann)


def test_missing_fields_and_bad_nested_tasks() -> None:
    data = good_bid()
    del data["committed_to"]
    with pytest.raises(WireError, match=r"^bid message: missing field 'committed_to'$"):
        decode(json.dumps(data))
    ann = to_dict(ANN)
    ann["tasks"][1]["priority"] = -1
    with pytest.raises(WireError, match="announcement message, task 1: task 'P1': priority"):
        decode(json.dumps(ann))
    ann["tasks"][1] = {"id": "P1"}
    with pytest.raises(WireError, match="announcement message, task 1: missing field 'type'"):
        decode(json.dumps(ann))
    prog = to_dict(Progress("R1", "T1", "done", 1.0))
    with pytest.raises(WireError, match="field 'event' must be committed or done or failed"):
        decode(json.dumps({**prog, "event": "finished"}))
    pred = to_dict(Prediction("R1", 0.0, np.zeros((3, 2))))
    pred["positions"][1] = [0.0, 0.0, 0.0]
    with pytest.raises(WireError, match="field 'positions' must be a list of"):
        decode(json.dumps(pred))


def test_bytes_that_are_not_a_message() -> None:
    for data, message in [
        (b"{not json", "the message is not JSON"),
        (b'{"v": 1, "kind": "bid", "costs": [NaN]}', "NaN is not JSON"),
        (b"[1, 2]", "a message must be a JSON object (got list)"),
        (b'{"kind": "bid"}', "message without a version 'v'"),
        (b"[" * 100_000 + b"]" * 100_000, "the message is not JSON"),
        (b"\xff\xfe", "the message is not JSON"),
    ]:
        with pytest.raises(WireError, match=message.replace("(", r"\(").replace(")", r"\)")):
            decode(data)


def test_oversized_messages_are_refused_before_parsing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BTMISSION_MAX_MESSAGE_BYTES", "100")
    with pytest.raises(WireError) as err:
        decode(b" " * 101)
    assert str(err.value) == (
        "the message is 101, the limit is 100 (set BTMISSION_MAX_MESSAGE_BYTES to change it)"
    )
    with pytest.raises(WireError, match=r"the announcement message is \d+, the limit is 100"):
        encode(ANN)
    monkeypatch.delenv("BTMISSION_MAX_MESSAGE_BYTES")
    assert decode(encode(ANN)) == ANN


def test_a_task_field_that_cannot_be_sent() -> None:
    bad = Announcement(1, 0.0, (TaskInfo("T1", "inspect", {"location": [math.nan, 0, 0]}),))
    with pytest.raises(WireError, match=r"task 'T1' fields.location: nan is not a finite number"):
        encode(bad)
    with pytest.raises(WireError, match="object is not a message"):
        to_dict(object())  # type: ignore[arg-type]


def _generic(msg: Any) -> bytes:
    return json.dumps(to_dict(msg), allow_nan=False, separators=(",", ":")).encode()


def test_the_fast_encodings_are_the_plain_json_of_to_dict() -> None:
    """Announcements keep their tasks' JSON, assignments splice it in, number lists skip a
    Python call per number: the bytes are those of ``json.dumps(to_dict(msg))``."""
    big = Announcement(9, 2.0, tuple(TaskInfo(f"T{j}", "inspect", {"location": [j / 3, -j, 0.5]},
                                              1.0 + j % 3, j * 0.1) for j in range(50)))  # fmt: skip
    costs = np.linspace(0, 7, 50)
    costs[[3, 9, 10]] = [math.nan, math.inf, -math.inf]
    for msg in (
        ANN,
        big,
        Announcement(),
        Assignment(1.6, 17, {"R1": "T1", "R2": None}, ANN),
        Assignment(0.0, 1, {}, big),
        Bid.aligned("R1", 1.5, big, costs),
        Prediction("R1", 2.0, np.array([[0.1, 1e-300], [np.float32(0.3), 2**60]])),
    ):
        assert encode(msg) == _generic(msg)
        assert encode(msg) == encode(msg)  # the cached part too


def test_decoding_reuses_a_known_announcement_exactly() -> None:
    other = Announcement(4, 1.5, ANN.tasks[:1])
    known = decode(encode(ANN))
    assert isinstance(known, Announcement)
    assert decode(encode(ANN), known) is known
    msg = Assignment(1.6, 17, {"R1": "T1", "announcement": None}, ANN)
    back = decode(encode(msg), known)
    assert back == msg and back.announcement is known
    for data in (encode(other), encode(Assignment(1.6, 17, {"R1": None}, other))):
        got = decode(data, known)  # another announcement: decoded, not reused
        assert got == decode(data) and got is not known
        assert getattr(got, "announcement", got) is not known
    spaced = json.dumps(to_dict(msg)).encode()  # not the compact encoding: decoded as usual
    assert decode(spaced, known) == msg and decode(spaced, known).announcement is not known
    bad = encode(msg).replace(b'"round":17', b'"round":"17"')
    with pytest.raises(WireError, match="field 'round' must be an integer"):
        decode(bad, known)
    v3 = encode(msg).replace(b'"v":2', b'"v":3')
    with pytest.raises(WireError, match="message version 3 is not supported"):
        decode(v3, known)
    renamed = encode(msg).replace(b'"serial":3', b'"serial":5', 1)  # the head's, not the body's
    with pytest.raises(WireError, match="names announcement 5 of epoch 0 but carries"):
        decode(renamed, known)
    body = b"{" + encode(ANN)[len(b'{"v":2,"kind":"announcement",') :]
    nested = encode(msg)[:-1] + b',"announcement":' + body + b"}"
    assert decode(nested, known) == decode(nested)  # a second top-level key: the usual path


def test_number_lists_still_refuse_what_they_refused() -> None:
    good = {**to_dict(Bid.of("R1", 1.0, {"A": 1.0, "B": 2.0})), "v": 1}  # costs: a list
    for costs, ok in (([1, 2.5], True), ([True, 1.0], False), (["inf", 1], True),
                      (["x", 1], False), (["BIG", 1], True)):  # fmt: skip
        data = json.dumps({**good, "costs": costs}).replace('"BIG"', "1e999").encode()
        if ok:
            assert len(decode(data).costs) == 2  # type: ignore[union-attr]
        else:
            with pytest.raises(WireError, match="field 'costs' must be a list of numbers"):
                decode(data)
    st = to_dict(AgentStatus("R1", 3.0, (1.0, 2.0, 0.5), "HOLD", True, 0.8, None, ""))
    for pos in (["BIG", 0, 0], [True, 0, 0], ["nan", 0, 0]):
        data = json.dumps({**st, "position": pos}).replace('"BIG"', "1e999").encode()
        with pytest.raises(WireError, match="field 'position' must be a list of finite numbers"):
            decode(data)
