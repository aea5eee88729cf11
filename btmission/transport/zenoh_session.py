"""Zenoh sessions for the coordinator <-> agent links (the ``net`` extra): the settings, opening one.

:class:`ZenohSettings` builds the Zenoh configuration: explicit ``listen`` and ``connect``
endpoints (the coordinator listens on ``tcp/127.0.0.1:7447`` by default, agents connect to it as
clients), multicast and gossip scouting off unless asked for, optionally a Zenoh JSON5 file for
TLS, authentication and access control. :func:`open_session` opens one, bounded by
``connect_timeout_s``; :func:`locators` reads where a session listens. Also here: the
transport's errors (:class:`TransportError`, :class:`ZenohMissing`), importing Zenoh only when a
session is opened (:func:`import_zenoh`, :func:`zenoh_available`) and the endpoint helpers
(:func:`check_endpoint`, :func:`loopback`, :func:`is_loopback`). The links over these sessions
are :mod:`btmission.transport.zenoh_link`. See docs/distributed.md.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, Final, cast

from btmission.errors import BtmissionError

if TYPE_CHECKING:
    import zenoh

NEEDS_NET: Final = (
    "the Zenoh transport needs the net extra: pip install 'btmission[net]' (make installs it)"
)
DEFAULT_PORT: Final = 7447
DEFAULT_ENDPOINT: Final = f"tcp/127.0.0.1:{DEFAULT_PORT}"
MODES: Final = ("peer", "client")


class TransportError(BtmissionError, RuntimeError):
    """The transport cannot do what was asked (the text says why and what to do)."""


class ZenohMissing(TransportError):
    """eclipse-zenoh is not installed (:data:`NEEDS_NET`)."""


def zenoh_available() -> bool:
    """Whether eclipse-zenoh can be imported (without importing it)."""
    return importlib.util.find_spec("zenoh") is not None


def import_zenoh() -> ModuleType:
    """The ``zenoh`` module, or :class:`ZenohMissing` saying how to install it."""
    try:
        import zenoh
    except ImportError:
        raise ZenohMissing(NEEDS_NET) from None
    return zenoh


def _bounded(timeout_s: float, what: str = "timeout_s") -> float:
    t = float(timeout_s)
    if not (math.isfinite(t) and t >= 0):
        raise ValueError(f"{what} must be a finite number of seconds ≥ 0, got {timeout_s!r}")
    return t


# ------------------------------------------------------------------------------------ config
_ENDPOINT = re.compile(r"[a-z][a-z0-9-]*/\S+")


def check_endpoint(endpoint: str) -> str:
    """``endpoint`` if it looks like a Zenoh endpoint ``<protocol>/<address>`` (e.g.
    ``tcp/127.0.0.1:7447``, ``tls/base.local:7447``), else :class:`ValueError`."""
    if not isinstance(endpoint, str) or not _ENDPOINT.fullmatch(endpoint):
        raise ValueError(
            f"{endpoint!r} is not a Zenoh endpoint (expected <protocol>/<address>, e.g. "
            f"{DEFAULT_ENDPOINT})"
        )
    return endpoint


def loopback(port: int = DEFAULT_PORT, protocol: str = "tcp") -> str:
    """``tcp/127.0.0.1:<port>`` (port 0: one the system picks)."""
    if not (isinstance(port, int) and 0 <= port <= 65535):
        raise ValueError(f"port must be 0-65535, got {port!r}")
    return f"{protocol}/127.0.0.1:{port}"


def is_loopback(endpoint: str) -> bool:
    """Whether ``endpoint``'s address is a loopback one (127.x.x.x, localhost, [::1])."""
    address = endpoint.split("/", 1)[-1].split("#", 1)[0].split("?", 1)[0]
    host = address.rsplit(":", 1)[0] if not address.startswith("[") else address[1:].split("]")[0]
    return host == "localhost" or host == "::1" or host.startswith("127.")


@dataclass(frozen=True)
class ZenohSettings:
    """How to open a Zenoh session (module docstring). The defaults are a coordinator's:
    :meth:`coordinator` and :meth:`agent` give each side's."""

    mode: str = "peer"
    """``peer`` (the coordinator; agents in a mesh) or ``client`` (an agent of a star)."""
    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Endpoints to accept sessions on (ignored in client mode)."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to."""
    multicast_scouting: bool = False
    """Find other sessions by UDP multicast (Zenoh's default; off here unless asked for)."""
    gossip_scouting: bool = False
    """Learn other peers' locators from connected ones (a mesh of peers needs it)."""
    config_file: str | None = None
    """A Zenoh JSON5 configuration to start from (TLS, authentication, access control ...); the
    settings above override its mode, endpoints and scouting."""
    options: tuple[tuple[str, str], ...] = ()
    """Raw ``(key, JSON5 value)`` configuration entries, applied last (as zenoh's ``--cfg``)."""
    connect_timeout_s: float = 5.0
    """A client waits this long for one of its ``connect`` endpoints, then opening fails."""
    shared_memory: bool = True
    """Let sessions on one host pass large payloads through shared memory (Zenoh's default)."""
    admin_space: bool = False
    """Serve Zenoh's read-only admin space (``@/<zid>/**``): :func:`locators` needs it."""

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        for ep in (*self.listen, *self.connect):
            check_endpoint(ep)
        if self.mode == "client" and not self.connect:
            raise ValueError("a client needs at least one connect endpoint")
        _bounded(self.connect_timeout_s, "connect_timeout_s")
        if self.config_file is not None and not Path(self.config_file).is_file():
            raise ValueError(f"Zenoh config file {self.config_file} does not exist")

    @classmethod
    def coordinator(cls, listen: Iterable[str] = (DEFAULT_ENDPOINT,), **kw: Any) -> ZenohSettings:
        """A coordinator: a peer listening on ``listen``."""
        return cls(mode="peer", listen=tuple(listen), **kw)

    @classmethod
    def agent(cls, connect: Iterable[str] = (DEFAULT_ENDPOINT,), **kw: Any) -> ZenohSettings:
        """An agent: a client of the coordinator at ``connect`` (it routes for its clients, so
        predictions reach the other agents through it)."""
        return cls(mode="client", listen=(), connect=tuple(connect), **kw)

    def with_(self, **changes: Any) -> ZenohSettings:
        return replace(self, **changes)

    def entries(self) -> list[tuple[str, str]]:
        """The configuration entries these settings write, as ``(key, JSON5 value)``."""
        out = [
            ("mode", json.dumps(self.mode)),
            ("listen/endpoints", json.dumps(list(self.listen) if self.mode == "peer" else [])),
            ("connect/endpoints", json.dumps(list(self.connect))),
            ("scouting/multicast/enabled", json.dumps(self.multicast_scouting)),
            ("scouting/gossip/enabled", json.dumps(self.gossip_scouting)),
        ]
        if self.mode == "client":
            out.append(("connect/timeout_ms", json.dumps(round(self.connect_timeout_s * 1000))))
        if not self.shared_memory:
            out.append(("transport/shared_memory/enabled", "false"))
        if self.admin_space:
            out.append(("adminspace/enabled", "true"))
            out.append(("adminspace/permissions", '{"read": true, "write": false}'))
        return out + list(self.options)

    def config(self) -> zenoh.Config:
        """The :class:`zenoh.Config` (:class:`TransportError` for a bad entry or file)."""
        z = import_zenoh()
        try:
            cfg = z.Config.from_file(self.config_file) if self.config_file else z.Config()
        except Exception as exc:
            raise TransportError(f"Zenoh config file {self.config_file}: {exc}") from None
        for k, v in self.entries():
            try:
                cfg.insert_json5(k, v)
            except Exception as exc:
                raise TransportError(f"Zenoh configuration {k} = {v}: {exc}") from None
        return cast("zenoh.Config", cfg)


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """A Zenoh session for ``settings``; :class:`TransportError` (with the endpoints) when it
    cannot be opened, e.g. a port already taken or no coordinator to connect to."""
    z = import_zenoh()
    cfg = settings.config()
    try:
        return cast("zenoh.Session", z.open(cfg))
    except Exception as exc:
        where = ", ".join(
            [f"listen {ep}" for ep in settings.listen if settings.mode == "peer"]
            + [f"connect {ep}" for ep in settings.connect]
        )
        raise TransportError(
            f"cannot open a Zenoh session ({settings.mode}; {where or 'no endpoints'}): "
            f"{_first_line(exc)}"
        ) from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    first = text[0] if text else type(exc).__name__
    return re.sub(r"\s+at /\S+\.rs:\d+\.?$", "", first)  # Zenoh appends its source location


def locators(session: zenoh.Session, timeout_s: float = 2.0) -> list[str]:
    """The endpoints ``session`` accepts connections on, from its admin space (open it with
    ``admin_space=True``). :class:`TransportError` when the admin space does not answer."""
    zid = str(session.zid())
    for reply in session.get(f"@/{zid}/*", timeout=_bounded(timeout_s)):
        ok = reply.ok
        if ok is None or str(ok.key_expr).rsplit("/", 1)[-1] not in ("peer", "client", "router"):
            continue
        try:
            info = json.loads(ok.payload.to_bytes())
        except ValueError:
            continue
        return [str(x) for x in info.get("locators", [])]
    raise TransportError(
        "the session's admin space did not answer: open it with ZenohSettings(admin_space=True)"
    )


__all__ = [
    "DEFAULT_ENDPOINT",
    "NEEDS_NET",
    "TransportError",
    "ZenohMissing",
    "ZenohSettings",
    "check_endpoint",
    "import_zenoh",
    "is_loopback",
    "locators",
    "loopback",
    "open_session",
    "zenoh_available",
]
