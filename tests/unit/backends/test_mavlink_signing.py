"""MAVLink 2 signing: keys from files and the environment, and the replay window that a forged
message must not move (pymavlink checks the timestamp before the signature)."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import pytest

from btmission.backends._pymavlink import mavlink
from btmission.backends.mavlink_signing import (
    KEY_ENV,
    KEY_FILE_ENV,
    SigningKeyError,
    enable_signing,
    key_from_text,
    load_key,
    signing_counters,
)

KEY = bytes(range(32))


class Conn:
    """The part of a pymavlink connection signing uses, without a socket."""

    def __init__(self, sysid: int) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self.mav.robust_parsing = True

    def setup_signing(self, key: bytes, sign_outgoing: bool, allow_unsigned_callback: Any,
                      link_id: Any) -> None:  # fmt: skip
        s = self.mav.signing
        s.secret_key, s.sign_outgoing = key, sign_outgoing
        s.allow_unsigned_callback = allow_unsigned_callback
        s.link_id, s.timestamp = link_id or 1, 1_000_000


def heartbeat(conn: Conn) -> bytes:
    msg = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3)
    return bytes(msg.pack(conn.mav))


def received(conn: Conn, data: bytes) -> list[Any]:
    return [m for m in conn.mav.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]


def test_keys_are_hex_or_a_passphrase_from_a_file_or_the_environment(tmp_path: Path) -> None:
    assert key_from_text(KEY.hex()) == KEY
    assert key_from_text("  correct horse \n") == hashlib.sha256(b"correct horse").digest()
    f = tmp_path / "k"
    f.write_text(KEY.hex() + "\n")
    assert load_key(f, env={}) == KEY
    assert load_key(env={KEY_FILE_ENV: str(f)}) == KEY
    assert load_key(env={KEY_ENV: "pass"}) == hashlib.sha256(b"pass").digest()
    assert load_key(env={}) is None
    with pytest.raises(SigningKeyError, match="no such file"):
        load_key(tmp_path / "missing", env={})
    (tmp_path / "empty").write_text("\n")
    with pytest.raises(SigningKeyError, match="empty: the signing key is empty"):
        load_key(tmp_path / "empty", env={})


def test_signed_messages_pass_and_others_are_counted() -> None:
    sender, receiver, stranger = Conn(1), Conn(255), Conn(1)
    enable_signing(sender, KEY)  # type: ignore[arg-type]
    enable_signing(receiver, KEY)  # type: ignore[arg-type]
    enable_signing(stranger, bytes(32))  # type: ignore[arg-type]
    assert len(received(receiver, heartbeat(sender))) == 1
    assert received(receiver, heartbeat(stranger)) == []
    unsigned = Conn(1)
    assert received(receiver, heartbeat(unsigned)) == []
    counts = signing_counters(receiver)
    assert counts == {"signed_ok": 1, "unsigned_refused": 1, "bad_signature": 1, "replay": 0}


def test_a_forged_far_future_message_does_not_move_the_replay_window() -> None:
    sender, receiver = Conn(1), Conn(255)
    enable_signing(sender, KEY)  # type: ignore[arg-type]
    enable_signing(receiver, KEY)  # type: ignore[arg-type]
    assert len(received(receiver, heartbeat(sender))) == 1
    forger = Conn(1)
    enable_signing(forger, bytes(32))  # type: ignore[arg-type]
    forger.mav.signing.link_id = sender.mav.signing.link_id
    forger.mav.signing.timestamp = sender.mav.signing.timestamp + 10**9  # far in the future
    assert received(receiver, heartbeat(forger)) == []
    # the genuine sender goes on: still accepted (pymavlink's own check would call it a replay)
    assert len(received(receiver, heartbeat(sender))) == 1
    # and a true replay is refused
    again = heartbeat(sender)
    assert len(received(receiver, again)) == 1 and received(receiver, again) == []
    assert signing_counters(receiver)["replay"] == 1
