"""Zenoh access control for a mission: each agent may publish as itself only (pure).

:func:`access_control` builds the ``access_control`` section of the *coordinator's* Zenoh
configuration (the session the agents connect to): everything is denied unless a rule allows it,
and each agent, identified by its authenticated user name or its TLS certificate's common name,
is allowed exactly what its :class:`~btmission.transport.zenoh_link.ZenohAgentLink` does:

* publish its bids, progress, status and predictions (``bids/<agent>`` …) — not another's;
* subscribe to the announcements, the assignments, its own acknowledgements and the agents'
  predictions, and receive them;
* declare its liveliness token and watch the coordinator's;
* hear the coordinator's subscriptions to what it publishes (Zenoh routes a publication only to
  a session that has declared interest in it).

Messages an agent is not allowed are dropped by Zenoh before they reach the coordinator. The
identities come from Zenoh's authentication: user name and password (``transport/auth/usrpwd``)
or mutual TLS (``transport/link/tls`` with ``enable_mtls``). See docs/distributed.md.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, Literal

from btmission.transport import keys

Identity = Literal["usernames", "cert_common_names"]


def agent_rules(mission: str, agent: str) -> list[dict[str, Any]]:
    """The rules that let ``agent`` of ``mission`` do its part (module docstring)."""
    m = keys.mission_prefix(mission)
    own = [
        keys.key(mission, ch, agent) for ch in (keys.BIDS, keys.PROGRESS, keys.STATUS, keys.PREDICT)
    ]
    hears = [
        keys.key(mission, keys.ANNOUNCE),
        keys.key(mission, keys.ASSIGN),
        keys.key(mission, keys.ACK, agent),
        keys.every_agent(mission, keys.PREDICT),
    ]
    coordinator = keys.coordinator_token(mission)
    interest = [keys.every_agent(mission, ch) for ch in (*keys.TO_COORDINATOR, keys.PREDICT)]

    def rule(name: str, flow: str, messages: list[str], exprs: list[str]) -> dict[str, Any]:
        return {
            "id": f"{m.replace('/', '.')}.{agent}.{name}",
            "permission": "allow",
            "flows": [flow],
            "messages": messages,
            "key_exprs": exprs,
        }

    return [
        rule("publishes", "ingress", ["put"], own),
        rule("subscribes", "ingress", ["declare_subscriber"], hears),
        rule("receives", "egress", ["put"], hears),
        rule("token", "ingress", ["liveliness_token"], [keys.agent_token(mission, agent)]),
        rule(
            "watches",
            "ingress",
            ["declare_liveliness_subscriber", "liveliness_query"],
            [coordinator],
        ),
        rule("sees", "egress", ["liveliness_token"], [coordinator]),
        rule("is-heard", "egress", ["declare_subscriber"], interest),
    ]


def access_control(
    mission: str, agents: Iterable[str], identity: Identity = "usernames"
) -> dict[str, Any]:
    """The coordinator's ``access_control`` section for ``agents`` (each known to Zenoh by the
    user name or certificate common name equal to its id)."""
    if identity not in ("usernames", "cert_common_names"):
        raise ValueError(f"identity must be usernames or cert_common_names, got {identity!r}")
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for agent in agents:
        mine = agent_rules(mission, agent)
        rules += mine
        subjects.append({"id": f"agent.{agent}", identity: [agent]})
        policies.append({"rules": [r["id"] for r in mine], "subjects": [f"agent.{agent}"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
