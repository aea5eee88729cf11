"""MAVLink 2 message signing for the provider and the MAVLink vehicle simulator.

The key (32 bytes) never lives in a mission file: it comes from a file or the environment
(:func:`load_key`): 64 hex digits are the key itself; anything else is a passphrase whose
SHA-256 is the key (MAVProxy's ``signing setup`` convention), so the same passphrase set up in
MAVProxy or QGroundControl works here.

pymavlink's ``check_signature`` moves a stream's replay window (its last timestamp) forward
*before* it compares the signature, so one forged message with a far-future timestamp makes every
later genuine message look like a replay. :func:`enable_signing` replaces it on the connection
with a check that verifies the signature first and only then advances the window (the order the
MAVLink signing specification implies), and counts what it refuses.
"""

from __future__ import annotations

import hashlib
import os
import re
import struct
import types
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from btmission.errors import BtmissionError

KEY_ENV = "BTMISSION_MAVLINK_KEY"
KEY_FILE_ENV = "BTMISSION_MAVLINK_KEY_FILE"
MAX_KEY_FILE_BYTES = 4096
_HEX_KEY = re.compile(r"[0-9a-fA-F]{64}")
_NEW_STREAM_SLACK = 6000 * 1000
"""A new stream's first timestamp may be this far behind ours (one minute, 10 µs units)."""


class SigningKeyError(BtmissionError, ValueError):
    """The signing key file or variable is missing, empty or unreadable."""


def key_from_text(text: str) -> bytes:
    """64 hex digits → those 32 bytes; any other text → SHA-256 of it (a passphrase)."""
    text = text.strip()
    if not text:
        raise SigningKeyError("the signing key is empty")
    if _HEX_KEY.fullmatch(text):
        return bytes.fromhex(text)
    return hashlib.sha256(text.encode()).digest()


def load_key(path: str | Path | None = None, env: Mapping[str, str] | None = None) -> bytes | None:
    """The signing key from ``path``, else ``$BTMISSION_MAVLINK_KEY_FILE``, else
    ``$BTMISSION_MAVLINK_KEY``; None when none is given (no signing)."""
    env = os.environ if env is None else env
    if path is None and env.get(KEY_FILE_ENV):
        path = env[KEY_FILE_ENV]
    if path is not None:
        p = Path(path)
        try:
            if not p.is_file():
                raise SigningKeyError(f"{p}: no such file (the MAVLink signing key)")
            if p.stat().st_size > MAX_KEY_FILE_BYTES:
                raise SigningKeyError(
                    f"{p}: {p.stat().st_size} bytes; a signing key file holds 64 hex digits or "
                    f"a passphrase (at most {MAX_KEY_FILE_BYTES} bytes)"
                )
            text = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise SigningKeyError(f"{p}: cannot read the signing key ({exc})") from None
        try:
            return key_from_text(text)
        except SigningKeyError as exc:
            raise SigningKeyError(f"{p}: {exc}") from None
    if env.get(KEY_ENV):
        return key_from_text(env[KEY_ENV])
    return None


_UNPACK_TS = struct.Struct("<IH")


def _check_signature(self: Any, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
    """Signature first, then the replay window (module docstring)."""
    signing = self.signing
    digest = hashlib.sha256(signing.secret_key + bytes(msgbuf[:-6])).digest()[:6]
    if digest != bytes(msgbuf[-6:]):
        signing.bad_signature_count = getattr(signing, "bad_signature_count", 0) + 1
        by_system = getattr(signing, "bad_by_system", None)
        if by_system is None:
            by_system = signing.bad_by_system = {}
        by_system[src_system] = by_system.get(src_system, 0) + 1
        return False
    low, high = _UNPACK_TS.unpack(bytes(msgbuf[-12:-6]))
    timestamp = low + (high << 32)
    stream = (msgbuf[-13], src_system, src_component)
    last = signing.stream_timestamps.get(stream)
    if (last is not None and timestamp <= last) or (
        last is None and timestamp + _NEW_STREAM_SLACK < signing.timestamp
    ):
        signing.replay_count = getattr(signing, "replay_count", 0) + 1
        return False
    signing.stream_timestamps[stream] = timestamp
    signing.timestamp = max(signing.timestamp, timestamp)
    return True


def enable_signing(conn: Any, key: bytes, *, link_id: int | None = None) -> None:
    """Sign what ``conn`` (a pymavlink connection) sends and accept only messages signed with
    ``key``, with the signature verified before the replay window moves."""
    if len(key) != 32:
        raise SigningKeyError(f"a MAVLink signing key is 32 bytes, got {len(key)}")
    conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=_refuse, link_id=link_id)
    conn.mav.check_signature = types.MethodType(_check_signature, conn.mav)


def parser_like(conn: Any) -> Any:
    """A fresh MAVLink parser that accepts what ``conn`` accepts: the same signing state (key,
    replay window, counters) when signing is on. For reading a datagram from an unknown sender
    on its own, without mixing its bytes into ``conn``'s buffer."""
    mav = conn.mav
    parser = type(mav)(None, srcSystem=mav.srcSystem, srcComponent=mav.srcComponent)
    parser.robust_parsing = True
    parser.signing = mav.signing
    if mav.signing.secret_key is not None:
        parser.check_signature = types.MethodType(_check_signature, parser)
    return parser


def _refuse(mav: Any, msg_id: int) -> bool:
    """No unsigned message is accepted (given as pymavlink's callback so that it counts them)."""
    return False


def signing_counters(conn: Any) -> dict[str, int]:
    """What a signed link accepted and refused so far."""
    s = conn.mav.signing
    return {
        "signed_ok": int(s.goodsig_count),
        "unsigned_refused": int(s.reject_count) - int(s.badsig_count),
        "bad_signature": int(getattr(s, "bad_signature_count", 0)),
        "replay": int(getattr(s, "replay_count", 0)),
    }


def rejections(conn: Any) -> tuple[dict[int, int], int]:
    """What a signed link refused so far, for telling a wrong key from a silent vehicle: the
    messages whose signature failed, per source system id, and the unsigned messages (whose
    sender pymavlink does not say)."""
    s = conn.mav.signing
    if s.secret_key is None:
        return {}, 0
    unsigned = int(s.reject_count) - int(s.badsig_count)
    return dict(getattr(s, "bad_by_system", {})), unsigned
