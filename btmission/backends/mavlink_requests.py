"""A connect's requests to one vehicle and their answers (:mod:`btmission.backends.mavlink_connect`).

Every telemetry stream and message a connecting vehicle is asked for is a :class:`_Request`; one
command's requests go out in batches (:class:`_Commands`) whose answers are told apart by their
order, sent again with a back-off when not all came.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from btmission.backends._pymavlink import mavlink
from btmission.backends.mavlink_link import MavlinkOptions, _Pending


@dataclass
class _Request:
    """One COMMAND_LONG a connect sends and waits for (sent again with a back-off)."""

    command: int
    params: tuple[float, ...]
    what: str
    """What it asks, for messages (``stream LOCAL_POSITION_NED``)."""
    sends: int = 0
    next_wall: float = 0.0
    """Not sent again before this (a TEMPORARILY_REJECTED one waits)."""
    result: int | None = None
    settled_wall: float = math.inf
    """When it was answered, or given up."""

    @property
    def settled(self) -> bool:
        return self.settled_wall < math.inf


@dataclass
class _Commands:
    """One command's requests to one vehicle, sent in batches (:mod:`btmission.backends.mavlink_connect`, step 3).

    COMMAND_ACK names the command but not the request, so the answers to a batch are told apart
    by their order: once as many have come as were sent, the i-th is the i-th request's. A batch
    that is not fully answered in time is sent again whole when nothing came (lost, or a silent
    vehicle), or — when some answers came and which ones were lost is unknown — its requests are
    sent again one at a time, which costs a round trip each but cannot be mistaken."""

    pending: _Pending
    """Where the I/O thread files this command's answers (:attr:`_State.pending`)."""
    options: MavlinkOptions
    refused: Callable[[_Request, int], None]
    queue: list[_Request] = field(default_factory=list)
    batch: list[_Request] = field(default_factory=list)
    got: list[int] = field(default_factory=list)
    """The answers to the batch in flight, in order."""
    due: float = math.inf
    """When the batch in flight is sent again (or given up) if not fully answered."""
    one_by_one: bool = False
    seen: int = 0
    answered: bool = False
    """Anything at all was answered (the vehicle hears commands)."""
    first_sent: float = math.inf

    def step(self, wall: float, send: Callable[[_Request], None]) -> None:
        """Read the answers that came, settle a fully answered batch, send what is due."""
        opts = self.options
        answers = self.pending.answers[self.seen :]
        self.seen += len(answers)
        for result in answers:
            self.answered = True
            if result == mavlink.MAV_RESULT_IN_PROGRESS:  # its final answer will follow
                self.due = max(self.due, wall + opts.in_progress_timeout_s)
            elif self.batch:
                self.got.append(result)
        if self.batch and len(self.got) >= len(self.batch):
            for r, result in zip(self.batch, self.got, strict=False):
                if (
                    result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                    and r.sends <= opts.command_retries
                ):
                    r.next_wall = wall + self._wait(r)
                    self.queue.append(r)  # asked again after a pause
                    continue
                r.result, r.settled_wall = result, wall
                if result != mavlink.MAV_RESULT_ACCEPTED:
                    self.refused(r, result)
            self.batch, self.got = [], []
        elif self.batch and wall >= self.due:
            if self.got:  # some answers came, which ones is unknown: one at a time now
                self.one_by_one = True
            self.queue[:0] = self.batch
            self.batch, self.got = [], []
        if self.batch:
            return
        ready = [r for r in self.queue if wall >= r.next_wall]
        for r in ready:
            if r.sends > opts.command_retries:  # no answer to any of its sends: given up
                r.settled_wall = wall
                self.queue.remove(r)
        ready = [r for r in ready if not r.settled]
        if self.one_by_one:
            ready = ready[:1]
        for r in ready:
            self.queue.remove(r)
            send(r)
            r.sends += 1
            self.first_sent = min(self.first_sent, wall)
        if ready:
            self.batch = ready
            self.due = wall + max(self._wait(r) for r in ready)

    def _wait(self, r: _Request) -> float:
        """``ack_timeout_s`` after the first send, then twice and four times it."""
        return self.options.ack_timeout_s * min(4.0, 2.0 ** max(0, r.sends - 1))
