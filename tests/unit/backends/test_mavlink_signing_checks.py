"""MAVLink 2 signing, beyond tests/unit/backends/test_mavlink_signing.py: why the check is replaced (pymavlink's
own is fooled by a forgery), a new stream's timestamp window, outgoing signatures, key length."""

from __future__ import annotations

import time
from typing import Any

import pytest

from btmission.backends._pymavlink import mavlink, mavutil
from btmission.backends.mavlink_signing import (
    SigningKeyError,
    enable_signing,
    signing_counters,
)

KEY = bytes(range(32))
EPOCH_2015 = 1420070400


class _Sink:
    def __init__(self) -> None:
        self.data = bytearray()

    def write(self, b: bytes) -> None:
        self.data += b


class _Conn:
    """What enable_signing needs of a pymavlink connection, without a socket."""

    setup_signing = mavutil.mavfile.setup_signing

    def __init__(self) -> None:
        self.mav = mavlink.MAVLink(_Sink(), srcSystem=1, srcComponent=1)
        self.mav.robust_parsing = True  # as mavutil's connections parse


def _now_ts() -> int:
    return int((time.time() - EPOCH_2015) * 100_000)


def _sender(key: bytes | None, timestamp: int | None = None) -> Any:
    mav = mavlink.MAVLink(_Sink(), srcSystem=255, srcComponent=190)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.link_id = 3
        mav.signing.timestamp = _now_ts() if timestamp is None else timestamp
    return mav


def _heartbeat(mav: Any) -> bytes:
    return bytes(mav.heartbeat_encode(6, 8, 0, 0, 4).pack(mav))


def _forged(timestamp: int) -> bytes:
    """A message signed for the right stream with a far-future timestamp and a wrong
    signature."""
    buf = bytearray(_heartbeat(_sender(KEY, timestamp)))
    buf[-1] ^= 0xFF
    return bytes(buf)


def _accepts(conn: Any, packet: bytes) -> bool:
    msg = conn.mav.parse_char(packet)
    return msg is not None and msg.get_type() == "HEARTBEAT"


def test_a_key_must_be_32_bytes() -> None:
    with pytest.raises(SigningKeyError, match="32 bytes, got 5"):
        enable_signing(_Conn(), b"short")


# ------------------------------------------------------------------ checks
def test_pymavlinks_own_check_is_fooled_by_the_forgery() -> None:
    """Why enable_signing replaces the check: the stock one lets the forgery move the window."""
    rx = _Conn()
    rx.setup_signing(KEY, sign_outgoing=True, allow_unsigned_callback=None)
    tx = _sender(KEY)
    assert _accepts(rx, _heartbeat(tx))
    assert not _accepts(rx, _forged(_now_ts() + 10**12))
    assert not _accepts(rx, _heartbeat(tx))


def test_a_new_stream_far_in_the_past_is_a_replay() -> None:
    rx = _Conn()
    enable_signing(rx, KEY)
    assert not _accepts(rx, _heartbeat(_sender(KEY, timestamp=_now_ts() - 10 * 6_000_000)))
    assert signing_counters(rx)["replay"] == 1


def test_outgoing_messages_are_signed() -> None:
    conn = _Conn()
    enable_signing(conn, KEY)
    packet = _heartbeat(conn.mav)
    assert packet[2] & mavlink.MAVLINK_IFLAG_SIGNED
    rx = _Conn()
    enable_signing(rx, KEY)
    assert _accepts(rx, packet)
