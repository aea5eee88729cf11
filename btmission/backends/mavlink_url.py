"""MAVLink connection URLs, as an agent's ``backend:`` names them (pure: no sockets, no pymavlink).

One URL per vehicle, in the form MAVSDK and QGroundControl users know, with the transport in the
scheme::

    mavlink+udp://127.0.0.1:14540              listen on this address (what PX4 SITL's offboard
                                               port 14540 and ArduPilot's 14550 send to)
    mavlink+udpout://192.168.1.20:14550        send to this address (the vehicle listens)
    mavlink+tcp://127.0.0.1:5760               connect to a TCP server (ArduPilot SITL's port)
    mavlink+tcpin://0.0.0.0:5760               accept one TCP connection
    mavlink+serial:///dev/ttyACM0?baud=921600  a serial port (telemetry radio, USB)

and, after ``?``, ``sysid=`` / ``compid=`` to pick one vehicle behind a router that forwards
several on one link (default: the first autopilot heard), ``baud=`` for a serial port (default
57600). :func:`parse_mavlink_url` checks all of it and says what is wrong in one line;
:meth:`MavlinkAddress.device` gives the device string pymavlink's ``mavlink_connection`` takes.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING
from urllib.parse import parse_qsl

from btmission.errors import BtmissionError
from btmission.spec.vehicleref import VehicleRef
from btmission.vehicles.provider import ProviderPlugin

if TYPE_CHECKING:
    from btmission.spec.mission import Mission
    from btmission.vehicles.provider import VehicleProvider
    from btmission.world.voxel import VoxelMap

TRANSPORTS = ("udp", "udpout", "tcp", "tcpin", "serial")
"""The transports of ``mavlink+<transport>://``."""

DEFAULT_BAUD = 57600
_PYMAVLINK_PREFIX = {"udp": "udpin", "udpout": "udpout", "tcp": "tcp", "tcpin": "tcpin"}
_HOST_RE = re.compile(r"^[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")  # fmt: skip
EXAMPLE = "mavlink+udp://127.0.0.1:14540"


class MavlinkUrlError(BtmissionError, ValueError):
    """A ``backend:`` MAVLink URL that cannot be used (the message says what to write)."""


@dataclass(frozen=True)
class MavlinkAddress:
    """Where one vehicle is (a parsed :func:`parse_mavlink_url`)."""

    transport: str
    """udp (listen), udpout, tcp (connect), tcpin (accept) or serial."""
    host: str = ""
    port: int = 0
    device_path: str = ""
    """The serial port (``/dev/ttyACM0``); empty for network transports."""
    baud: int = DEFAULT_BAUD
    sysid: int | None = None
    """The vehicle's MAVLink system id, when the link carries several (None: the first heard)."""
    compid: int | None = None

    def device(self) -> str:
        """The device string of pymavlink's ``mavutil.mavlink_connection(device, baud=...)``."""
        if self.transport == "serial":
            return self.device_path
        return f"{_PYMAVLINK_PREFIX[self.transport]}:{self.host}:{self.port}"

    def url(self) -> str:
        """The URL again, normalised (query keys in a fixed order, defaults left out)."""
        query = []
        if self.transport == "serial":
            base = f"mavlink+serial://{self.device_path}"
            if self.baud != DEFAULT_BAUD:
                query.append(f"baud={self.baud}")
        else:
            host = f"[{self.host}]" if ":" in self.host else self.host
            base = f"mavlink+{self.transport}://{host}:{self.port}"
        if self.sysid is not None:
            query.append(f"sysid={self.sysid}")
        if self.compid is not None:
            query.append(f"compid={self.compid}")
        return base + ("?" + "&".join(query) if query else "")


def is_mavlink_url(text: str) -> bool:
    """Whether ``text`` means MAVLink at all (its scheme starts with ``mavlink``)."""
    return text.startswith("mavlink")


def parse_mavlink_url(text: str) -> MavlinkAddress:
    """Parse a ``backend:`` MAVLink URL (module docstring). Raises :class:`MavlinkUrlError`."""
    old = re.match(r"^mavlink:/{0,2}(udp|udpin|udpout|tcp|tcpin|serial):(.+)$", text)
    if old is not None:  # the form of pymavlink's device strings
        kind = "udp" if old.group(1) == "udpin" else old.group(1)
        raise MavlinkUrlError(f"write the transport in the scheme: mavlink+{kind}://{old.group(2)}")
    m = re.match(r"^mavlink(?:\+([A-Za-z0-9]+))?://(.*)$", text)
    if m is None:
        raise MavlinkUrlError(f"expected a MAVLink URL such as {EXAMPLE}")
    transport, rest = m.group(1), m.group(2)
    if transport is None:
        raise MavlinkUrlError(
            f"say the transport in the scheme, e.g. {EXAMPLE} "
            f"(mavlink+{', mavlink+'.join(TRANSPORTS)})"
        )
    if transport not in TRANSPORTS:
        raise MavlinkUrlError(
            f"unknown MAVLink transport '{transport}' (expected one of: {', '.join(TRANSPORTS)})"
        )
    where, _, query = rest.partition("?")
    params = _query(query, transport)
    sysid = _int_param(params, "sysid", 1, 255)
    compid = _int_param(params, "compid", 0, 255)
    if transport == "serial":
        if not where.startswith("/") or len(where) < 2:
            raise MavlinkUrlError(
                "a serial URL names the port's path: mavlink+serial:///dev/ttyACM0?baud=921600"
            )
        baud = _int_param(params, "baud", 1, 10_000_000)
        return MavlinkAddress(
            "serial",
            device_path=where,
            baud=DEFAULT_BAUD if baud is None else baud,
            sysid=sysid,
            compid=compid,
        )
    host, port = _host_port(where, transport)
    return MavlinkAddress(transport, host=host, port=port, sysid=sysid, compid=compid)


def _query(query: str, transport: str) -> dict[str, str]:
    allowed = ("sysid", "compid", "baud") if transport == "serial" else ("sysid", "compid")
    out: dict[str, str] = {}
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError:
        raise MavlinkUrlError(
            f"cannot read the query '?{query}' (expected key=value&...)"
        ) from None
    for key, value in pairs:
        if key not in allowed:
            raise MavlinkUrlError(
                f"unknown parameter '{key}' (a {transport} URL takes: {', '.join(allowed)})"
            )
        if key in out:
            raise MavlinkUrlError(f"parameter '{key}' is given twice")
        out[key] = value
    return out


def _int_param(params: dict[str, str], key: str, low: int, high: int) -> int | None:
    if key not in params:
        return None
    text = params[key]
    if not re.fullmatch(r"[0-9]{1,9}", text) or not low <= int(text) <= high:
        raise MavlinkUrlError(f"{key} must be a whole number from {low} to {high}, got '{text}'")
    return int(text)


def _host_port(where: str, transport: str) -> tuple[str, int]:
    example = f"mavlink+{transport}://127.0.0.1:14540"
    m = re.fullmatch(r"\[([^\]]+)\]:([^:]*)|([^:\[\]]*):([^:]*)", where)
    if m is None:
        raise MavlinkUrlError(f"expected host:port with a port number, e.g. {example}")
    host = m.group(1) or m.group(3) or ""
    port_text = m.group(2) if m.group(1) else m.group(4)
    if not host:
        raise MavlinkUrlError(f"the host is missing, e.g. {example} (0.0.0.0: every interface)")
    if m.group(1):
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise MavlinkUrlError(f"'{host}' is not an IPv6 address") from None
    elif not _HOST_RE.match(host):
        raise MavlinkUrlError(f"'{host}' is not a host name or an IP address")
    if port_text is None or not re.fullmatch(r"[0-9]{1,5}", port_text):
        raise MavlinkUrlError(f"expected host:port with a port number, e.g. {example}")
    port = int(port_text)
    if not 1 <= port <= 65535:
        raise MavlinkUrlError(f"port {port} is out of range (1 to 65535)")
    return host, port


def address_problem(vehicle: VehicleRef) -> str | None:
    """What is wrong with an agent's MAVLink reference, in one line naming it (None: nothing).
    ``validate`` and ``run`` ask before anything is built (the provider's ``check_address``)."""
    try:
        parse_mavlink_url(vehicle.url)
    except MavlinkUrlError as exc:
        return f"MAVLink URL '{vehicle.url}': {exc}"
    return None


def _create(mission: Mission, voxel_map: VoxelMap, seed: int) -> VehicleProvider:
    from btmission.backends.mavlink import mavlink_provider  # pymavlink: only to fly

    return mavlink_provider(mission, voxel_map, seed)


MAVLINK = ProviderPlugin(_create, check_address=address_problem)
"""The ``mavlink`` entry point of ``btmission.providers``: this module checks the URLs (light:
``validate`` loads it), :func:`btmission.backends.mavlink.mavlink_provider` flies them."""
