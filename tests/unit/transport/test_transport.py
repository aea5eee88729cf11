"""The Zenoh transport (issue #17, part 1): key expressions, session settings, the coordinator and
agent links over Zenoh on loopback (one process and two), the auction over Zenoh against the
in-memory bus, injected duplicates, delays and reordering, bad payloads, link cuts, loopback-only
sockets, and bounded waits.

Every socket is on 127.0.0.1 (ports picked by the system), every wait is bounded
(tests/zenoh_helpers.py: ``WAIT_S``), nothing is timed. Tests that need eclipse-zenoh are skipped
without it, and fail under ``CI``.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Progress
from btmission.allocation.tasks import TaskInfo
from btmission.links import wire
from btmission.links.bus import (
    AgentLink,
    AgentStatus,
    Assignment,
    CoordinatorInbox,
    CoordinatorLink,
    InMemoryBus,
    ProgressAck,
)
from btmission.runtime.coordinator import Coordinator, new_epoch
from btmission.spec.mission import Mission
from btmission.transport import keys
from btmission.transport.acl import access_control
from btmission.transport.faulty import (
    Faults,
    FaultyAgentLink,
    FaultyCoordinatorLink,
    FaultyStream,
    fate,
    shuffle,
)
from btmission.transport.zenoh_link import ZenohAgentLink, ZenohCoordinatorLink, close_all
from btmission.transport.zenoh_plumbing import DecodeCache, Mailbox
from btmission.transport.zenoh_session import (
    NEEDS_NET,
    TransportError,
    ZenohMissing,
    ZenohSettings,
    import_zenoh,
    is_loopback,
    locators,
    loopback,
    open_session,
)
from tests import zenoh_child
from tests.system.test_runtime import mission_text
from tests.zenoh_helpers import (
    WAIT_S,
    coordinator,
    is_loopback_address,
    need_zenoh,
    own_sockets,
    pump,
    wait_until,
)

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture()
def zenoh_ready() -> None:
    need_zenoh()


# ------------------------------------------------------------------------------------ keys
def test_keys_of_every_channel() -> None:
    assert keys.key("mine", keys.ANNOUNCE) == "btmission/mine/announce"
    assert keys.key("mine", keys.ASSIGN) == "btmission/mine/assign"
    for channel in ("ack", "bids", "progress", "status", "predict"):
        k = keys.key("mine", channel, "R1")
        assert k == f"btmission/mine/{channel}/R1"
        assert keys.parse(k) == keys.Parsed("mine", channel, "R1")
        assert keys.parse(k).kind == keys.KINDS[channel]
    assert keys.parse("btmission/mine/assign") == keys.Parsed("mine", "assign", None)
    assert keys.every_agent("mine", "bids") == "btmission/mine/bids/*"
    assert keys.everything("mine") == "btmission/mine/**"
    assert keys.coordinator_token("m") == "btmission/m/alive/coordinator"
    assert keys.agent_token("m", "R1") == "btmission/m/alive/agents/R1"
    assert keys.agent_tokens("m") == "btmission/m/alive/agents/*"
    assert set(keys.KINDS.values()) == set(wire.KINDS)  # every message kind has its channel


@pytest.mark.parametrize(
    "name", ["", "a/b", "*", "**", "$x", "a b", "@x", ".x", "-x", "x?y", "x#y", "é", "a" * 129]
)
def test_names_that_could_break_a_key_are_refused(name: str) -> None:
    assert not keys.valid_name(name)
    with pytest.raises(keys.KeyExprError, match="cannot be used in a Zenoh key"):
        keys.key("mine", "bids", name)
    with pytest.raises(keys.KeyExprError, match="cannot be used in a Zenoh key"):
        keys.key(name, "announce")


def test_every_mission_and_agent_id_a_mission_file_accepts_is_a_valid_name() -> None:
    for name in ("mine_inspection", "R1", "_x", "G", "a" * 128, "truck-7", "v1.2"):
        assert keys.valid_name(name)


def test_bad_channels_and_keys_are_refused() -> None:
    with pytest.raises(keys.KeyExprError, match="unknown channel 'bid'"):
        keys.key("m", "bid", "R1")
    with pytest.raises(keys.KeyExprError, match="needs an agent id"):
        keys.key("m", "bids")
    with pytest.raises(keys.KeyExprError, match="has no agent chunk"):
        keys.key("m", "announce", "R1")
    with pytest.raises(keys.KeyExprError, match="not a per-agent channel"):
        keys.every_agent("m", "assign")
    for bad in ("other/m/bids/R1", "btmission/m", "btmission/m/bids", "btmission/m/bids/R1/x",
                "btmission/m/announce/R1", "btmission/m/nope/R1", "btmission/m/bids/*"):  # fmt: skip
        with pytest.raises(keys.KeyExprError):
            keys.parse(bad)


# ------------------------------------------------------------------------------------ settings
def test_settings_write_explicit_endpoints_and_turn_scouting_off() -> None:
    entries = dict(ZenohSettings().entries())
    assert entries["mode"] == '"peer"'
    assert json.loads(entries["listen/endpoints"]) == ["tcp/127.0.0.1:7447"]
    assert json.loads(entries["connect/endpoints"]) == []
    assert entries["scouting/multicast/enabled"] == "false"
    assert entries["scouting/gossip/enabled"] == "false"
    agent = dict(ZenohSettings.agent(["tcp/127.0.0.1:9000"], connect_timeout_s=1.5).entries())
    assert agent["mode"] == '"client"' and json.loads(agent["listen/endpoints"]) == []
    assert json.loads(agent["connect/endpoints"]) == ["tcp/127.0.0.1:9000"]
    assert agent["connect/timeout_ms"] == "1500"
    asked = dict(ZenohSettings(multicast_scouting=True, options=(("a/b", "1"),)).entries())
    assert asked["scouting/multicast/enabled"] == "true" and asked["a/b"] == "1"


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"mode": "router"}, "mode must be one of peer, client"),
        ({"listen": ("127.0.0.1:7447",)}, "is not a Zenoh endpoint"),
        ({"connect": ("tcp 1",)}, "is not a Zenoh endpoint"),
        ({"mode": "client", "listen": ()}, "a client needs at least one connect endpoint"),
        ({"connect_timeout_s": math.inf}, "connect_timeout_s must be a finite number"),
        ({"config_file": "/no/such.json5"}, "does not exist"),
    ],
)
def test_bad_settings_are_clear_errors(kw: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ZenohSettings(**kw)


def test_loopback_endpoints() -> None:
    assert loopback(0) == "tcp/127.0.0.1:0"
    for ep in ("tcp/127.0.0.1:7447", "tcp/localhost:1", "tcp/[::1]:7447", "tls/127.0.0.2:7447"):
        assert is_loopback(ep), ep
    for ep in ("tcp/0.0.0.0:7447", "tcp/[::]:0", "tcp/10.0.0.1:7447", "tls/base.local:7447"):
        assert not is_loopback(ep), ep
    with pytest.raises(ValueError):
        loopback(70000)


def test_btmission_never_imports_zenoh() -> None:
    code = (
        "import sys, btmission, btmission.transport, btmission.transport.keys, "
        "btmission.transport.faulty, btmission.transport.zenoh_link, "
        "btmission.transport.zenoh_session, btmission.transport.zenoh_plumbing, btmission.cli.main; "
        "assert 'zenoh' not in sys.modules, 'zenoh imported'"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, timeout=120, env=_env())  # fmt: skip
    assert proc.returncode == 0, proc.stderr


def test_without_zenoh_the_transport_says_how_to_install_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "zenoh", None)  # `import zenoh` raises ImportError
    with pytest.raises(ZenohMissing) as err:
        import_zenoh()
    assert str(err.value) == NEEDS_NET and "pip install 'btmission[net]'" in NEEDS_NET
    with pytest.raises(ZenohMissing):
        ZenohCoordinatorLink("m", settings=ZenohSettings.coordinator([loopback(0)]))
    with pytest.raises(ZenohMissing):
        ZenohSettings().config()


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    return env


# ------------------------------------------------------------------------------------ faults
def test_fate_and_order_are_pure_functions_of_the_seed() -> None:
    f = Faults(duplicate=0.3, delay=0.4, max_delay=3, reorder=True, seed=7)
    fates = [fate(f, "s", i) for i in range(200)]
    assert fates == [fate(f, "s", i) for i in range(200)]
    assert fates != [fate(Faults(0.3, 0.4, 3, True, seed=8), "s", i) for i in range(200)]
    assert fates != [fate(f, "t", i) for i in range(200)]
    copies = [x.copies for x in fates]
    assert set(copies) == {1, 2} and 30 < copies.count(2) < 90
    assert {d for x in fates for d in x.delays} == {0, 1, 2, 3}
    assert all(fate(Faults(duplicate=1.0), "s", i).copies == 2 for i in range(20))
    assert all(fate(Faults(), "s", i).delays == (0,) for i in range(20))
    order = shuffle(f, "s", 3, 10)
    assert sorted(order) == list(range(10)) and order == shuffle(f, "s", 3, 10)
    assert shuffle(Faults(), "s", 3, 10) == list(range(10))
    with pytest.raises(ValueError, match="duplicate must be a probability"):
        Faults(duplicate=1.5)
    with pytest.raises(ValueError, match="max_delay must be a whole number"):
        Faults(max_delay=0)


def test_a_stream_duplicates_delays_and_reorders() -> None:
    s: FaultyStream[int] = FaultyStream(Faults(duplicate=0.5, delay=0.5, reorder=True, seed=1), "x")
    out: list[int] = []
    for tick in range(40):
        for k in range(3):
            s.push(tick * 3 + k)
        out += s.due()
        s.advance()
    for _ in range(5):
        out += s.due()
        s.advance()
    assert sorted(set(out)) == list(range(120))  # nothing lost
    assert len(out) == 120 + s.stats.duplicated and s.held == 0
    assert s.stats.duplicated > 0 and s.stats.delayed > 0 and s.stats.reordered > 0
    assert out != sorted(out)


def test_faulty_links_around_the_in_memory_bus() -> None:
    bus = InMemoryBus()
    faults = Faults(duplicate=1.0, delay=0.0, seed=3)
    coord = FaultyCoordinatorLink(bus, faults)
    got: list[object] = []
    agent = FaultyAgentLink(bus.agent_link("G1"), Faults(delay=1.0, max_delay=1, seed=3))
    agent.connect(got.append, got.append, got.append)
    coord.announce(Announcement(1, 0.0, ()))
    assert got == []  # held for one tick on the agent's side (both copies)
    agent.tick()
    assert got == [Announcement(1, 0.0, ())] * 2
    agent.send_bid(Bid.of("G1", 0.0, {}, serial=1))
    assert bus.drain().bids == []  # held
    agent.tick()
    inbox = coord.drain()
    assert [b.agent for b in inbox.bids] == ["G1", "G1"]  # duplicated on the coordinator's side
    assert agent.agent == "G1" and agent.up


# ------------------------------------------------------------------------------------ messages
def test_agents_of_a_process_decode_a_repeated_announcement_once() -> None:
    cache = DecodeCache()
    first = cache.decode(wire.encode(ANN))
    assert cache.decode(wire.encode(ANN)) is first
    asg = cache.decode(wire.encode(ASSIGNMENT))
    assert isinstance(asg, Assignment) and asg.announcement is first and cache.reused == 2
    other = Announcement(5, 2.0, ANN.tasks[:2])
    assert cache.decode(wire.encode(other)) == other and cache.known == other


ANN = Announcement(
    4,
    1.5,
    (
        TaskInfo("T1", "inspect", {"location": [60.0, 10.5, 2.0]}, 2.0, 0.0, False),
        TaskInfo("P1", "pick_and_deliver", {"pickup": "bay", "dropoff": [1, 2, 0]}, 1.0, 3.0, True),
        TaskInfo("T3", "inspect", {"location": [1e-3, -4.0, 0.0], "note": {"a": [True]}}),
    ),
)
ASSIGNMENT = Assignment(2.0, 7, {"R1": "T1", "R2": None}, ANN)
ACK = ProgressAck("R1", (("T1", "done", 2.25), ("P1", "committed", 1.0)))


def same(a: wire.Message, b: wire.Message) -> bool:
    return wire.to_dict(a) == wire.to_dict(b)


@pytest.fixture()
def star(zenoh_ready: None) -> Iterator[tuple[ZenohCoordinatorLink, list[ZenohAgentLink]]]:
    """A coordinator and agents R1, R2 (clients) on loopback, in this process."""
    coord, endpoint = coordinator("mine")
    links: list[ZenohAgentLink] = []
    try:
        mailbox = Mailbox()
        for a in ("R1", "R2"):
            links.append(ZenohAgentLink("mine", a, settings=ZenohSettings.agent([endpoint]),
                                        mailbox=mailbox))  # fmt: skip
        yield coord, links
    finally:
        close_all([*links, coord])


class Received:
    """An agent's handlers that keep what they get."""

    def __init__(self, link: AgentLink) -> None:
        self.link = link
        self.messages: list[wire.Message] = []
        link.connect(self.messages.append, self.messages.append, self.messages.append)


def test_every_message_round_trips_between_two_sessions(
    star: tuple[ZenohCoordinatorLink, list[ZenohAgentLink]],
) -> None:
    coord, (r1, r2) = star
    g1, g2 = Received(r1), Received(r2)
    assert coord.wait_for_agents({"R1", "R2"}, WAIT_S)
    assert r1.wait_for_coordinator(WAIT_S) and r1.up and r2.up
    coord.announce(ANN)
    coord.assign(ASSIGNMENT)
    coord.acknowledge(ACK)
    assert pump(r1.mailbox, lambda: len(g1.messages) == 3 and len(g2.messages) == 2)
    # each key keeps its order; messages on different keys may overtake each other
    by_type = {type(m).__name__: m for m in g1.messages}
    assert sorted(by_type) == ["Announcement", "Assignment", "ProgressAck"]
    for sent in (ANN, ASSIGNMENT, ACK):
        assert same(by_type[type(sent).__name__], sent)
    (ann2,) = [m for m in g2.messages if isinstance(m, Announcement)]
    assert same(ann2, ANN)
    bid = Bid.aligned("R1", 1.5, ANN, [0.5, math.nan, math.inf], committed_to="P1")
    status = zenoh_child.STATUS
    progress = Progress("R1", "P1", "committed", 2.0)
    r1.send_bid(bid)
    r1.send_status(status)
    r1.send_progress(progress)
    r2.share_prediction(2.0, zenoh_child.PREDICTION)

    def arrived(inbox: CoordinatorInbox) -> bool:
        return bool(inbox.bids and inbox.statuses and inbox.progress)

    assert coord.wait(arrived, WAIT_S)
    inbox = coord.drain()
    assert same(inbox.bids[0], bid) and inbox.bids[0].serial == 4
    assert np.isnan(inbox.bids[0].costs[1]) and np.isinf(inbox.bids[0].costs[2])
    assert inbox.statuses == [status] and inbox.progress == [progress]
    assert coord.drain() == CoordinatorInbox()
    assert wait_until(lambda: bool(r1.predictions(2.0, 0.1)))
    (pred,) = r1.predictions(2.0, 0.1)
    np.testing.assert_array_equal(pred, zenoh_child.PREDICTION)
    assert r2.predictions(2.0, 0.1) == []  # its own is not among the others'
    bus = InMemoryBus()  # the same answer as the in-memory bus
    bus.share_prediction("R2", 2.0, zenoh_child.PREDICTION)
    for t in (2.0, 2.2, 9.0):
        mem = bus.predictions("R1", t, 0.1, near=np.zeros(2))
        net = r1.predictions(t, 0.1, near=np.zeros(2))
        assert len(mem) == len(net) == 1
        np.testing.assert_array_equal(mem[0], net[0])
    assert coord.stats.dropped == 0 and r1.stats.dropped == 0 and r2.stats.dropped == 0


def test_assignments_name_an_unchanged_announcement_and_carry_a_new_one(
    star: tuple[ZenohCoordinatorLink, list[ZenohAgentLink]],
) -> None:
    coord, (r1, _) = star
    g1 = Received(r1)
    assert coord.wait_for_agents({"R1"}, WAIT_S) and r1.wait_for_coordinator(WAIT_S)
    coord.embed_every = 3
    ann = Announcement(1, 0.0, ANN.tasks, epoch=new_epoch())  # not any other test's
    sizes = []
    for k in range(1, 5):  # carried, named, named, carried (every 3rd)
        before = coord.stats.sent_bytes
        coord.assign(Assignment(k * 0.5, k, {"R1": "T1", "R2": None}, ann))
        sizes.append(coord.stats.sent_bytes - before)
    assert sizes[1] == sizes[2] < len(wire.encode(ann)) < sizes[0] == sizes[3]
    assert pump(r1.mailbox, lambda: len(g1.messages) == 4)
    got = [m for m in g1.messages if isinstance(m, Assignment)]
    assert sorted(m.round for m in got) == [1, 2, 3, 4]
    assert all(m.announcement == ann for m in got) and r1.stats.unresolved == 0
    # naming an announcement this end never saw (another program's, say): dropped, counted
    unknown = Announcement(2, 0.0, ANN.tasks, epoch=ann.epoch)
    data = wire.encode(Assignment(3.0, 5, {"R1": "T3"}, unknown), embed=False)
    coord.session.put("btmission/mine/assign", data)
    assert wait_until(lambda: r1.stats.unresolved == 1)
    assert "announcement 2 of epoch" in r1.stats.last_problem and r1.stats.malformed == 0
    coord.announce(unknown)  # once seen, an assignment naming it is followed
    assert pump(r1.mailbox, lambda: any(isinstance(m, Announcement) for m in g1.messages))
    coord.session.put("btmission/mine/assign", data)
    assert pump(r1.mailbox, lambda: any(getattr(m, "round", 0) == 5 for m in g1.messages))
    assert coord.stats.dropped == 0


def test_every_message_round_trips_between_two_processes(zenoh_ready: None) -> None:
    coord, endpoint = coordinator("mine")
    r2 = ZenohAgentLink("mine", "R2", settings=ZenohSettings.agent([endpoint]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.zenoh_child", "mine", endpoint],
        cwd=ROOT,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        r2.connect(lambda m: None, lambda m: None, lambda m: None)
        assert coord.wait_for_agents({"R1"}, 60.0), "the child agent did not connect"
        coord.announce(ANN)

        def answered(inbox: CoordinatorInbox) -> bool:
            return bool(inbox.bids and inbox.statuses and inbox.progress)

        assert coord.wait(answered, WAIT_S)
        inbox = coord.drain()
        assert same(inbox.bids[0], zenoh_child.bid_for(ANN))
        assert inbox.statuses == [zenoh_child.STATUS] and inbox.progress == [zenoh_child.PROGRESS]
        assert wait_until(lambda: bool(r2.predictions(2.0, 0.1)))
        np.testing.assert_array_equal(r2.predictions(2.0, 0.1)[0], zenoh_child.PREDICTION)
        coord.assign(ASSIGNMENT)
        assert coord.wait(lambda inbox: bool(inbox.statuses), WAIT_S)
        (echo,) = coord.drain().statuses
        assert same(echo, zenoh_child.echo_status(ASSIGNMENT)) and echo.task == "T1"
        coord.acknowledge(ACK)
        out, err = proc.communicate(timeout=WAIT_S)
        assert proc.returncode == 0, err
        assert out.strip() == f"ack {json.dumps([list(k) for k in ACK.keys])}"
        assert coord.stats.dropped == 0
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=WAIT_S)
        close_all([r2, coord])


# ------------------------------------------------------------------------------------ auction
def auction_mission(tmp_path: Path, agents: int, tasks: int, window: float, timeout: float = 3.0,
                    rate: float = 2.0) -> Mission:  # fmt: skip
    lines = [
        "mission: net",
        "version: 1",
        "world:",
        "  map: {generate: empty, size: [40, 30, 1]}",
        "  resolution: 0.5",
        "agents:",
        *[
            f"  - {{id: G{i + 1}, library: ground, start: [{1 + 2 * i}, 1, 0]}}"
            for i in range(agents)
        ],
        "tasks:",
        *[
            f"  - {{id: T{j + 1}, type: inspect, location: [{3 + (7 * j) % 35}, {2 + (5 * j) % 26}, 0]}}"
            for j in range(tasks)
        ],
        "task_types:",
        "  inspect: {goal: at_goal(location), cost: path_cost(location)}",
        f"coordination: {{auction_rate_hz: {rate}, agent_timeout_s: {timeout}, bid_window_s: {window}}}",
        "default_behavior: {goal: at_goal(home), idle_timeout_s: 2}",
        "runtime: {controller: track}",
    ]
    return mission_text("\n".join(lines), tmp_path)


class Bidder:
    """A stand-in agent: it bids fixed costs, takes the task it is assigned (the newest
    assignment wins: older rounds arriving late are ignored), finishes it after ``work`` of its
    ticks, and resends the completion every tick until acknowledged."""

    def __init__(self, link: AgentLink, costs: dict[str, float], work: int = 2) -> None:
        self.link = link
        self.id = link.agent
        self.costs = costs
        self.work = work
        self.now = 0.0
        self.task: str | None = None
        self.held = 0
        self.finished: set[str] = set()
        self.outbox: dict[tuple[str, str, float], Progress] = {}
        self.round = 0
        self.handled = 0
        link.connect(self.on_announcement, self.on_assignment, self.on_ack)

    def on_announcement(self, ann: Announcement) -> None:
        self.handled += 1
        costs = {t: self.costs[t] for t in ann.ids if t not in self.finished}
        self.link.send_bid(Bid.of(self.id, self.now, costs, serial=ann.serial))

    def on_assignment(self, a: Assignment) -> None:
        self.handled += 1
        if a.round < self.round or self.id not in a.tasks:
            return
        self.round = a.round
        task = a.tasks[self.id]
        if task != self.task and task not in self.finished:
            self.task, self.held = task, 0

    def on_ack(self, ack: ProgressAck) -> None:
        self.handled += 1
        for k in ack.keys:
            self.outbox.pop(k, None)

    def tick(self, now: float) -> None:
        self.now = now
        if self.task is not None:
            self.held += 1
            if self.held >= self.work:
                p = Progress(self.id, self.task, "done", now)
                self.outbox[(p.task, p.event, p.time_s)] = p
                self.finished.add(self.task)
                self.task = None
        for p in self.outbox.values():
            self.link.send_progress(p)


class Recording:
    """A coordinator link that counts what it passes on, per agent (to know what the agents
    must receive before a step is over)."""

    def __init__(self, inner: CoordinatorLink) -> None:
        self.inner = inner
        self.broadcasts = 0
        self.acks: dict[str, int] = {}

    def announce(self, announcement: Announcement) -> None:
        self.broadcasts += 1
        self.inner.announce(announcement)

    def assign(self, assignment: Assignment) -> None:
        self.broadcasts += 1
        self.inner.assign(assignment)

    def acknowledge(self, ack: ProgressAck) -> None:
        self.acks[ack.agent] = self.acks.get(ack.agent, 0) + 1
        self.inner.acknowledge(ack)

    def drain(self) -> CoordinatorInbox:
        return self.inner.drain()

    def expected(self, agent: str) -> int:
        return self.broadcasts + self.acks.get(agent, 0)


class Fleet:
    """A coordinator and bidders over the in-memory bus or Zenoh, stepped in lock step; the
    Zenoh one waits (bounded) until everything sent has arrived before each step goes on."""

    def __init__(self, mission: Mission, costs: dict[str, dict[str, float]], net: bool,
                 faults: Faults | None = None, work: int = 2) -> None:  # fmt: skip
        self.events: list[tuple[str, dict[str, Any]]] = []
        self.links: list[Any] = []
        self.zcoord: ZenohCoordinatorLink | None = None
        self.mailbox = Mailbox()
        if net:
            self.zcoord, endpoint = coordinator(mission.spec.mission)
            self.links.append(self.zcoord)
            base: CoordinatorLink = self.zcoord
            agent_links: list[AgentLink] = []
            for a in costs:
                link = ZenohAgentLink(mission.spec.mission, a, mailbox=self.mailbox,
                                      settings=ZenohSettings.agent([endpoint]))  # fmt: skip
                self.links.append(link)
                agent_links.append(link)
        else:
            bus = InMemoryBus()
            base = bus
            agent_links = [bus.agent_link(a) for a in costs]
        self.recording = Recording(base)
        self.faulty = FaultyCoordinatorLink(self.recording, faults) if faults else None
        link: CoordinatorLink = self.faulty if self.faulty is not None else self.recording
        self.coordinator = Coordinator(mission, link, lambda: 0.0,
                                       lambda ev: self.events.append((ev.kind, ev.to_data())))  # fmt: skip
        self.bidders = [Bidder(al, costs[al.agent], work) for al in agent_links]
        if self.zcoord is not None:
            assert self.zcoord.wait_for_agents(set(costs), WAIT_S)
            assert all(wait_until(lambda al=al: al.up) for al in agent_links)

    def settle(self) -> None:
        """Over Zenoh: every message sent so far has been received and handled."""
        if self.zcoord is None:
            return
        zc = self.zcoord

        def done() -> bool:
            return all(b.handled == self.recording.expected(b.id) for b in self.bidders) and (
                zc.stats.received == sum(b.link.stats.sent for b in self.bidders)  # type: ignore[attr-defined]
            )

        assert pump(self.mailbox, done), "messages did not arrive in time"

    def step(self, now: float) -> Any:
        for b in self.bidders:
            b.tick(now)
        self.settle()
        result = self.coordinator.step(now)
        self.settle()
        return result

    def close(self) -> None:
        close_all(self.links)

    def done_by(self) -> dict[str, tuple[str, str | None]]:
        return {t.id: (t.state.value, t.agent) for t in self.coordinator.state.pool}


def distance_costs(mission: Mission) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for a in mission.spec.agents:
        out[a.id] = {
            t.id: round(math.dist(a.start[:2], t.model_extra["location"][:2]), 3)  # type: ignore[index]
            for t in mission.spec.tasks
        }
    return out


@pytest.mark.parametrize("size", [(3, 5), (8, 20)])
def test_an_auction_round_over_zenoh_assigns_as_the_in_memory_bus(
    zenoh_ready: None, tmp_path: Path, size: tuple[int, int]
) -> None:
    mission = auction_mission(tmp_path, *size, window=0.2)
    costs = distance_costs(mission)
    results = {}
    for net in (False, True):
        fleet = Fleet(mission, costs, net)
        try:
            assert fleet.step(0.0) is None  # announced; collecting bids for the window
            result = fleet.step(0.2)  # the window closes: allocate, assign
            assert result is not None
            results[net] = result
            if net:
                assert fleet.zcoord is not None and fleet.zcoord.stats.dropped == 0
                assert len(fleet.zcoord.drain().bids) == 0
        finally:
            fleet.close()
    mem, net_ = results[False], results[True]
    assert net_.assignments == mem.assignments
    assert len([t for t in mem.assignments.values() if t]) == min(size)
    assert net_.report.bids == mem.report.bids == size[0] * size[1]
    assert net_.report.stale_bids == net_.report.late_bids == 0


SCENARIO_COSTS = {  # each agent is cheapest for "its" task by far: one optimum
    "G1": {"T1": 1.0, "T2": 20.0, "T3": 30.0},
    "G2": {"T1": 20.0, "T2": 1.5, "T3": 20.0},
    "G3": {"T1": 30.0, "T2": 20.0, "T3": 2.0},
}
FAULTS = Faults(duplicate=0.35, delay=0.35, max_delay=2, reorder=True, seed=11)


def run_scenario(tmp_path: Path, net: bool, faults: Faults | None) -> tuple[Fleet, list[Any]]:
    mission = auction_mission(tmp_path, 3, 3, window=0.2, timeout=5.0)
    # a task takes 8 ticks (4 rounds): longer than the faults can keep an agent's first bid away
    # (≤ 1 round each way), so no agent finishes a task it only holds while another's bid is late
    fleet = Fleet(mission, SCENARIO_COSTS, net, faults, work=8)
    results = []
    try:
        for r in range(20):
            for t in (r * 0.5, r * 0.5 + 0.2):
                res = fleet.step(t)
                if res is not None:
                    results.append(res)
    finally:
        fleet.close()
    return fleet, results


@pytest.mark.parametrize("net", [False, True], ids=["in-memory", "zenoh"])
def test_duplicated_delayed_and_reordered_messages_leave_the_result_unchanged(
    tmp_path: Path, net: bool
) -> None:
    if net:
        need_zenoh()
    clean, clean_rounds = run_scenario(tmp_path, False, None)
    faulty, rounds = run_scenario(tmp_path, net, FAULTS)
    expected = {"T1": ("done", "G1"), "T2": ("done", "G2"), "T3": ("done", "G3")}
    assert clean.done_by() == expected
    assert faulty.done_by() == expected  # every task done, once, by the same agent
    done_events = [d for k, d in faulty.events if k == "task" and d["state"] == "done"]
    assert sorted(d["task"] for d in done_events) == ["T1", "T2", "T3"]
    assert [d for k, d in faulty.events if k == "warning"] == []
    for res in rounds:  # no task is ever held by two agents at once
        held = [t for t in res.assignments.values() if t is not None]
        assert len(held) == len(set(held))
    assert faulty.faulty is not None
    stats = [faulty.faulty.incoming.stats, faulty.faulty.outgoing.stats]
    assert sum(s.duplicated for s in stats) > 5 and sum(s.delayed for s in stats) > 5
    assert sum(s.reordered for s in stats) > 0
    assert clean_rounds[-1].assignments == rounds[-1].assignments


# ------------------------------------------------------------------------------------ bad input
def test_bad_payloads_are_dropped_and_counted(
    star: tuple[ZenohCoordinatorLink, list[ZenohAgentLink]], monkeypatch: pytest.MonkeyPatch
) -> None:
    coord, (r1, _) = star
    g1 = Received(r1)
    assert coord.wait_for_agents({"R1"}, WAIT_S)
    raw = r1.session  # another session than the coordinator's: its puts cross the network
    good = wire.encode(Bid.of("R1", 1.0, {"T1": 2.0}, serial=1))
    raw.put("btmission/mine/bids/R1", b"\xff not json")
    raw.put("btmission/mine/bids/R1", b'{"v": 2, "kind": "bid"}')
    raw.put("btmission/mine/bids/R1", wire.encode(zenoh_child.STATUS))  # kind ≠ channel
    raw.put("btmission/mine/bids/R2", good)  # R1's bid on R2's key
    raw.put("btmission/mine/bids/R1", good)
    assert coord.wait(lambda inbox: bool(inbox.bids), WAIT_S)
    assert wait_until(lambda: coord.stats.malformed == 2 and coord.stats.mismatched == 2)
    assert [b.agent for b in coord.drain().bids] == ["R1"]
    assert "kind" in coord.stats.last_problem or "agent" in coord.stats.last_problem
    monkeypatch.setenv("BTMISSION_MAX_MESSAGE_BYTES", "2000")
    coord.session.put("btmission/mine/announce", b"x" * 5000)
    raw.put("btmission/mine/bids/R1", b"[" * 3000)
    assert wait_until(lambda: coord.stats.oversized == 1 and r1.stats.oversized == 1)
    assert "the payload is 5,000, the limit is 2,000" in r1.stats.last_problem
    monkeypatch.delenv("BTMISSION_MAX_MESSAGE_BYTES")
    coord.announce(ANN)  # the links still work
    assert pump(r1.mailbox, lambda: len(g1.messages) == 1) and same(g1.messages[0], ANN)
    assert coord.stats.dropped == 5 and coord.stats.errors == 0 and r1.stats.errors == 0


def test_a_cut_agent_link_drops_both_ways_and_comes_back(
    star: tuple[ZenohCoordinatorLink, list[ZenohAgentLink]],
) -> None:
    coord, (r1, r2) = star
    g1, g2 = Received(r1), Received(r2)
    assert coord.wait_for_agents({"R1", "R2"}, WAIT_S) and r1.wait_for_coordinator(WAIT_S)
    r1.set_link(False)
    assert not r1.up and r2.up and r1.coordinator_seen
    coord.announce(ANN)
    r1.send_bid(Bid.of("R1", 1.0, {"T1": 1.0}, serial=4))
    r2.send_bid(Bid.of("R2", 1.0, {"T1": 2.0}, serial=4))
    assert pump(r2.mailbox, lambda: len(g2.messages) == 1)
    assert coord.wait(lambda inbox: bool(inbox.bids), WAIT_S)
    assert wait_until(lambda: r1.stats.cut == 2)  # its bid, and the announcement
    assert g1.messages == [] and [b.agent for b in coord.drain().bids] == ["R2"]
    r1.set_link(True)
    assert r1.up
    coord.announce(ANN)
    r1.send_bid(Bid.of("R1", 2.0, {"T1": 1.0}, serial=4))
    assert pump(r1.mailbox, lambda: len(g1.messages) == 1 and len(g2.messages) == 2)
    assert coord.wait(lambda inbox: bool(inbox.bids), WAIT_S)
    assert [b.agent for b in coord.drain().bids] == ["R1"]


def test_an_agent_sees_the_coordinator_go_and_come_back(zenoh_ready: None) -> None:
    coord, endpoint = coordinator("mine")
    r1 = ZenohAgentLink("mine", "R1", settings=ZenohSettings.agent([endpoint]))
    try:
        g1 = Received(r1)
        assert r1.wait_for_coordinator(WAIT_S) and r1.up
        coord.close()
        assert wait_until(lambda: not r1.up), "the coordinator's token did not go"
        again = ZenohCoordinatorLink("mine", settings=ZenohSettings.coordinator([endpoint]))
        try:  # the client reconnects by itself; its subscriptions and token come back with it
            assert r1.wait_for_coordinator(WAIT_S), "the agent did not reconnect"
            assert again.wait_for_agents({"R1"}, WAIT_S)
            again.announce(ANN)
            assert pump(r1.mailbox, lambda: len(g1.messages) == 1)
        finally:
            again.close()
    finally:
        close_all([r1, coord])


# ------------------------------------------------------------------------------------ conformance
@pytest.mark.parametrize("net", [False, True], ids=["in-memory", "zenoh"])
def test_both_transports_behave_alike_up_and_cut(net: bool) -> None:
    """The in-memory bus's own link test (tests/unit/runtime/test_bid_window.py), run on both transports:
    what arrives, and what a cut link drops both ways."""
    links: list[Any] = []
    if net:
        need_zenoh()
        zc, endpoint = coordinator("mine")
        za = ZenohAgentLink("mine", "G1", settings=ZenohSettings.agent([endpoint]))
        links = [za, zc]
        coordinator_side: CoordinatorLink = zc
        agent_side: AgentLink = za

        def settle(agent_gets: int, coordinator_gets: int) -> None:
            assert pump(za.mailbox, lambda: len(got) == agent_gets)
            assert wait_until(lambda: zc.stats.received == coordinator_gets)

        def cut(up: bool) -> None:
            za.set_link(up)

        def dropped() -> int:
            return za.stats.cut
    else:
        bus = InMemoryBus()
        coordinator_side, agent_side = bus, bus.agent_link("G1")

        def settle(agent_gets: int, coordinator_gets: int) -> None:
            pass

        def cut(up: bool) -> None:
            bus.set_link("G1", up)

        def dropped() -> int:
            return bus.dropped

    try:
        got: list[object] = []
        agent_side.connect(got.append, got.append, got.append)
        if net:
            assert zc.wait_for_agents({"G1"}, WAIT_S) and za.wait_for_coordinator(WAIT_S)
        assert agent_side.up
        coordinator_side.announce(Announcement(1, 0.0, ()))
        agent_side.send_progress(Progress("G1", "A", "done", 1.0))
        coordinator_side.acknowledge(ProgressAck("G1", (("A", "done", 1.0),)))
        settle(2, 1)
        assert sorted(type(m).__name__ for m in got) == ["Announcement", "ProgressAck"]
        assert coordinator_side.drain().progress == [Progress("G1", "A", "done", 1.0)]
        cut(False)
        assert not agent_side.up
        agent_side.send_status(AgentStatus("G1", 1.0, (0, 0, 0), "HOLD", False, 1.0, None, ""))
        coordinator_side.acknowledge(ProgressAck("G1", ()))
        assert wait_until(lambda: dropped() == 2)
        assert coordinator_side.drain().statuses == [] and len(got) == 2
        cut(True)
        assert agent_side.up
        agent_side.send_status(AgentStatus("G1", 2.0, (0, 0, 0), "HOLD", False, 1.0, None, ""))
        settle(2, 2)
        assert [s.time_s for s in coordinator_side.drain().statuses] == [2.0]
    finally:
        close_all(links)


# ------------------------------------------------------------------------------------ sockets
def test_nothing_listens_beyond_loopback(zenoh_ready: None) -> None:
    before = set(own_sockets())  # other tests' sockets in this process are not ours to judge
    coord, endpoint = coordinator("mine")
    r1 = ZenohAgentLink("mine", "R1", settings=ZenohSettings.agent([endpoint], admin_space=True))
    try:
        assert r1.wait_for_coordinator(WAIT_S)
        assert locators(coord.session) == [endpoint] and endpoint.startswith("tcp/127.0.0.1:")
        assert locators(r1.session) == []  # a client listens on nothing
        for link in r1.session.info.links():
            assert is_loopback(link.src) and is_loopback(link.dst), (link.src, link.dst)
        sockets = [s for s in own_sockets() if s not in before]
        port = int(endpoint.rsplit(":", 1)[1])
        assert any(a.endswith(f":{port}") for _, a, _ in sockets)  # the check sees it
        assert [s for s in sockets if not is_loopback_address(s[1])] == []  # no 0.0.0.0, no UDP
    finally:
        close_all([r1, coord])


# ------------------------------------------------------------------------------------ security
def test_access_control_lets_an_agent_publish_only_as_itself(
    zenoh_ready: None, tmp_path: Path
) -> None:
    """User name + password authentication and the rules of btmission.transport.acl, enforced by
    Zenoh on loopback: R1 gets its messages and is heard, but cannot bid as R2 nor announce as
    the coordinator; a session without a password is refused."""
    (tmp_path / "users.txt").write_text("R1:r1-secret\nR2:r2-secret\n")
    coord_cfg = {
        "access_control": access_control("mine", ["R1", "R2"]),
        "transport": {"auth": {"usrpwd": {"dictionary_file": str(tmp_path / "users.txt")}}},
    }
    (tmp_path / "coordinator.json5").write_text(json.dumps(coord_cfg))
    for a in ("R1", "R2"):
        auth = {"transport": {"auth": {"usrpwd": {"user": a, "password": f"{a.lower()}-secret"}}}}
        (tmp_path / f"{a}.json5").write_text(json.dumps(auth))
    coord, endpoint = coordinator("mine", config_file=str(tmp_path / "coordinator.json5"))
    links: list[ZenohAgentLink] = []
    try:
        for a in ("R1", "R2"):
            settings = ZenohSettings.agent([endpoint], config_file=str(tmp_path / f"{a}.json5"))
            links.append(ZenohAgentLink("mine", a, settings=settings, mailbox=Mailbox()))
        r1, r2 = links
        g1, g2 = Received(r1), Received(r2)
        assert coord.wait_for_agents({"R1", "R2"}, WAIT_S) and r1.wait_for_coordinator(WAIT_S)
        coord.announce(ANN)
        assert pump(r1.mailbox, lambda: len(g1.messages) == 1)
        assert pump(r2.mailbox, lambda: len(g2.messages) == 1)
        fake = wire.encode(Announcement(99, 0.0, ()))
        r1.session.put("btmission/mine/bids/R2", wire.encode(Bid.of("R2", 1.0, {}, serial=4)))
        r1.session.put("btmission/mine/announce", fake)
        r1.send_bid(Bid.of("R1", 1.0, {"T1": 1.0}, serial=4))
        assert coord.wait(lambda inbox: bool(inbox.bids), WAIT_S)
        assert not coord.wait(lambda inbox: len(inbox.bids) > 1, 0.3)  # R2's never comes
        assert [b.agent for b in coord.drain().bids] == ["R1"] and coord.stats.dropped == 0
        assert r2.dispatch(0.3) == 0 and len(g2.messages) == 1  # nor the fake announcement
        with pytest.raises(TransportError, match="cannot open a Zenoh session"):
            open_session(ZenohSettings.agent([endpoint], connect_timeout_s=0.5))
    finally:
        close_all([*links, coord])


def test_access_rules_are_per_agent_and_deny_by_default() -> None:
    acl = access_control("mine", ["R1", "R2"], identity="cert_common_names")
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert acl["subjects"] == [{"id": "agent.R1", "cert_common_names": ["R1"]},
                               {"id": "agent.R2", "cert_common_names": ["R2"]}]  # fmt: skip
    ids = [r["id"] for r in acl["rules"]]
    assert len(ids) == len(set(ids)) == 14
    (pub,) = [r for r in acl["rules"] if r["id"] == "btmission.mine.R1.publishes"]
    assert pub["key_exprs"] == [
        keys.key("mine", ch, "R1") for ch in ("bids", "progress", "status", "predict")
    ]
    assert acl["policies"][1] == {
        "rules": [i for i in ids if ".R2." in i],
        "subjects": ["agent.R2"],
    }
    with pytest.raises(ValueError, match="identity must be"):
        access_control("mine", ["R1"], identity="zid")  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------ waits
def test_every_wait_is_bounded(zenoh_ready: None) -> None:
    coord, endpoint = coordinator("mine")
    r1 = ZenohAgentLink("mine", "R1", settings=ZenohSettings.agent([endpoint]))
    try:
        for call in (
            lambda: coord.wait(lambda inbox: False, math.inf),
            lambda: coord.wait_for_bids(1, 1, -1.0),
            lambda: r1.dispatch(math.nan),
            lambda: r1.wait_for_coordinator(math.inf),
        ):
            with pytest.raises(ValueError, match="must be a finite number of seconds"):
                call()
        assert coord.wait_for_bids(1, 1, 0.05) is False
        assert coord.wait_for_agents({"R9"}, 0.05) is False
        assert r1.dispatch(0.05) == 0
    finally:
        close_all([r1, coord])


def test_no_coordinator_or_a_taken_port_are_clear_errors(zenoh_ready: None) -> None:
    coord, endpoint = coordinator("mine")
    try:
        with pytest.raises(TransportError) as err:
            ZenohCoordinatorLink("mine", settings=ZenohSettings.coordinator([endpoint]))
        assert str(err.value).startswith(f"cannot open a Zenoh session (peer; listen {endpoint}):")
    finally:
        coord.close()
    with pytest.raises(TransportError) as err:  # nobody listens there now
        open_session(ZenohSettings.agent([endpoint], connect_timeout_s=0.2))
    assert str(err.value).startswith(f"cannot open a Zenoh session (client; connect {endpoint}):")
    assert ".rs:" not in str(err.value)


def test_closed_links_refuse_to_send(zenoh_ready: None) -> None:
    coord, endpoint = coordinator("mine")
    r1 = ZenohAgentLink("mine", "R1", settings=ZenohSettings.agent([endpoint]))
    close_all([r1, coord])
    close_all([r1, coord])  # idempotent
    with pytest.raises(TransportError, match="closed"):
        coord.announce(ANN)
    with pytest.raises(TransportError, match="closed"):
        r1.send_bid(Bid.of("R1", 0.0, {}))
