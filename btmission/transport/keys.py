"""The Zenoh key expressions of a mission: where each coordinator/agent message is published.

Every key starts with ``btmission/<mission>/``, then names a *channel*; channels that one agent
publishes (or that is addressed to one agent) end with the agent's id::

    btmission/<mission>/announce            coordinator → agents   announcement
    btmission/<mission>/assign              coordinator → agents   assignment
    btmission/<mission>/end                 coordinator → agents   end (the mission is over)
    btmission/<mission>/ack/<agent>         coordinator → agent    ack (of its progress reports)
    btmission/<mission>/bids/<agent>        agent → coordinator    bid
    btmission/<mission>/progress/<agent>    agent → coordinator    progress
    btmission/<mission>/status/<agent>      agent → coordinator    status
    btmission/<mission>/predict/<agent>     agent → agents         prediction

plus two liveliness tokens (Zenoh's presence tokens, gone when their session is):
``btmission/<mission>/alive/coordinator`` and ``btmission/<mission>/alive/agents/<agent>``.

The payload on each key is the JSON of :mod:`btmission.links.wire` (format version
``WIRE_VERSION``) whose ``kind`` is the channel's (:data:`KINDS`); on a per-agent key, the
message's ``agent`` field is that agent. A receiver drops anything else.

Mission names and agent ids become one chunk of a key each, so they must be
:func:`valid_name`: 1-128 characters out of letters, digits, ``_``, ``-`` and ``.``, not starting
with ``.`` or ``-`` (every mission and agent id a mission file accepts is one). That keeps Zenoh's
special characters (``/``, ``*``, ``$``, ``?``, ``#``, ``@``) and spaces out of the keys, so a
name can never widen a subscription or address another agent. Everything here is pure.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Final

from btmission.errors import BtmissionError

ROOT: Final = "btmission"
"""The first chunk of every key."""

ANNOUNCE: Final = "announce"
ASSIGN: Final = "assign"
ACK: Final = "ack"
BIDS: Final = "bids"
PROGRESS: Final = "progress"
STATUS: Final = "status"
PREDICT: Final = "predict"
END: Final = "end"

KINDS: Final[dict[str, str]] = {
    ANNOUNCE: "announcement",
    ASSIGN: "assignment",
    ACK: "ack",
    BIDS: "bid",
    PROGRESS: "progress",
    STATUS: "status",
    PREDICT: "prediction",
    END: "end",
}
"""Channel → the wire ``kind`` of the messages published on it."""

BROADCAST: Final = frozenset({ANNOUNCE, ASSIGN, END})
"""Channels without an agent chunk (one key for every agent)."""

PER_AGENT: Final = frozenset(KINDS) - BROADCAST
"""Channels with an agent chunk."""

TO_COORDINATOR: Final = (BIDS, PROGRESS, STATUS)
"""What the coordinator subscribes to (every agent's)."""

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,127}")


class KeyExprError(BtmissionError, ValueError):
    """A mission name, agent id, channel or key that cannot be used (the text says why)."""


def valid_name(name: str) -> bool:
    """Whether ``name`` can be a mission name or an agent id in a key (module docstring)."""
    return isinstance(name, str) and _NAME.fullmatch(name) is not None


def check_name(name: str, what: str = "name") -> str:
    """``name`` if :func:`valid_name`, else :class:`KeyExprError` naming ``what`` and the rule."""
    if not valid_name(name):
        raise KeyExprError(
            f"{what} {name!r} cannot be used in a Zenoh key: use 1-128 letters, digits, '_', "
            "'-' or '.', not starting with '.' or '-'"
        )
    return name


def mission_prefix(mission: str) -> str:
    """``btmission/<mission>``."""
    return f"{ROOT}/{check_name(mission, 'mission')}"


def key(mission: str, channel: str, agent: str | None = None) -> str:
    """The key of ``channel`` in ``mission`` (with ``agent`` for a per-agent channel)."""
    if channel in BROADCAST:
        if agent is not None:
            raise KeyExprError(f"channel '{channel}' has no agent chunk (got agent {agent!r})")
        return f"{mission_prefix(mission)}/{channel}"
    if channel in PER_AGENT:
        if agent is None:
            raise KeyExprError(f"channel '{channel}' needs an agent id")
        return f"{mission_prefix(mission)}/{channel}/{check_name(agent, 'agent id')}"
    raise KeyExprError(f"unknown channel {channel!r} (expected one of: {', '.join(KINDS)})")


def every_agent(mission: str, channel: str) -> str:
    """The subscription to a per-agent channel of every agent: ``btmission/<m>/<channel>/*``."""
    if channel not in PER_AGENT:
        raise KeyExprError(f"channel {channel!r} is not a per-agent channel")
    return f"{mission_prefix(mission)}/{channel}/*"


def everything(mission: str) -> str:
    """Every key of ``mission``: ``btmission/<mission>/**`` (a monitor's subscription)."""
    return f"{mission_prefix(mission)}/**"


def coordinator_token(mission: str) -> str:
    """The coordinator's liveliness token."""
    return f"{mission_prefix(mission)}/alive/coordinator"


def agent_token(mission: str, agent: str) -> str:
    """An agent's liveliness token."""
    return f"{mission_prefix(mission)}/alive/agents/{check_name(agent, 'agent id')}"


def agent_tokens(mission: str) -> str:
    """Every agent's liveliness token (a liveliness subscription)."""
    return f"{mission_prefix(mission)}/alive/agents/*"


@dataclass(frozen=True)
class Parsed:
    """A message key taken apart."""

    mission: str
    channel: str
    agent: str | None

    @property
    def kind(self) -> str:
        """The wire kind expected on this key."""
        return KINDS[self.channel]


def parse(text: str) -> Parsed:
    """The parts of a message key (:func:`key`); :class:`KeyExprError` for anything else."""
    parts = str(text).split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise KeyExprError(
            f"{text!r} is not a btmission key (expected '{ROOT}/<mission>/<channel>')"
        )
    mission, channel, rest = parts[1], parts[2], parts[3:]
    check_name(mission, "mission")
    if channel in BROADCAST and not rest:
        return Parsed(mission, channel, None)
    if channel in PER_AGENT and len(rest) == 1:
        return Parsed(mission, channel, check_name(rest[0], "agent id"))
    raise KeyExprError(f"{text!r} is not a btmission message key")
