"""Helpers of the Zenoh transport tests: skip-or-fail without eclipse-zenoh, loopback links on a
port the system picks, bounded pumping of agents' mailboxes, and the process's own sockets.

Skip or fail: without eclipse-zenoh (the ``net`` extra) the tests that need it are skipped with
the reason; when ``CI`` is set (CI installs the extra through ``make``) they fail instead, as the
browser tests do for chromium (tests/browser.py), so CI can never silently skip them.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from btmission.transport.zenoh_link import ZenohCoordinatorLink
from btmission.transport.zenoh_plumbing import Mailbox
from btmission.transport.zenoh_session import (
    ZenohSettings,
    locators,
    loopback,
    zenoh_available,
)
from tests.load import margin

WAIT_S = 20.0 * margin()
"""Every wait on the network is bounded by this (it only matters when something is broken),
stretched on a busy machine (:func:`tests.load.margin`)."""

MISSING = "eclipse-zenoh is not installed: pip install 'btmission[net]' (make installs it)"


def need_zenoh() -> None:
    """Skip the calling test without eclipse-zenoh, or fail it when ``CI`` is set."""
    if zenoh_available():
        return
    if os.environ.get("CI"):
        pytest.fail(f"{MISSING} (CI is set: the transport tests must run, not skip)", pytrace=False)
    pytest.skip(MISSING)


def coordinator(mission: str, **kw: object) -> tuple[ZenohCoordinatorLink, str]:
    """A coordinator link listening on 127.0.0.1 at a port the system picks, and that endpoint
    (read back from the session's admin space: no race for a free port)."""
    settings = ZenohSettings.coordinator([loopback(0)], admin_space=True, **kw)  # type: ignore[arg-type]
    link = ZenohCoordinatorLink(mission, settings=settings)
    try:
        (endpoint,) = locators(link.session)
    except Exception:
        link.close()
        raise
    return link, endpoint


def pump(mailbox: Mailbox, until: Callable[[], bool], timeout_s: float = WAIT_S) -> bool:
    """Dispatch ``mailbox`` (handlers run here) until ``until()`` holds; False after
    ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        mailbox.dispatch(0.02)
        if until():
            return True
        if time.monotonic() > deadline:
            return False


def wait_until(cond: Callable[[], bool], timeout_s: float = WAIT_S) -> bool:
    """Poll ``cond`` every 10 ms until it holds; False after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def own_sockets() -> list[tuple[str, str, str]]:
    """This process's listening TCP sockets and its UDP sockets as ``(protocol, local address,
    state)``, from /proc (Linux): what others could reach."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found = []
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        path = Path(f"/proc/self/net/{proto}")
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            f = line.split()
            listening = f[3] == "0A" or proto.startswith("udp")
            if f[9] in inodes and listening:
                found.append((proto, _address(f[1]), f[3]))
    return found


def _address(hex_addr: str) -> str:
    host, port = hex_addr.split(":")
    raw = bytes.fromhex(host)
    if len(raw) == 4:
        ip = ".".join(str(b) for b in raw[::-1])
    else:  # IPv6: four little-endian 32-bit words
        words = [raw[i : i + 4][::-1] for i in range(0, 16, 4)]
        full = b"".join(words).hex()
        ip = ":".join(full[i : i + 4] for i in range(0, 32, 4))
    return f"{ip}:{int(port, 16)}"


def is_loopback_address(addr: str) -> bool:
    ip = addr.rsplit(":", 1)[0]
    return ip.startswith("127.") or ip == "0000:0000:0000:0000:0000:0000:0000:0001"
