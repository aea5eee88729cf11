"""pymavlink, imported once for MAVLink 2 with the ArduPilot dialect (a superset of common).

pymavlink picks its wire protocol and dialect from environment variables when ``mavutil`` is
first imported (``MAVLINK20``, ``MAVLINK_DIALECT``); importing it through this module makes every
connection the provider and the MAVLink simulator open speak MAVLink 2 from the first byte (signing
needs it) and understand ArduPilot's messages (EKF_STATUS_REPORT) as well as the common ones.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")
os.environ.setdefault("MAVLINK_DIALECT", "ardupilotmega")

from pymavlink import mavutil

mavutil.set_dialect("ardupilotmega")

from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

CURRENT_MODE_ID = 436
"""CURRENT_MODE (MAVLink common, message 436): the autopilot's mode, streamed at any rate asked —
PX4 refuses to send HEARTBEAT faster than 1 Hz, so its mode changes are seen sooner here."""


def _current_mode_class() -> type:
    """The dialect's CURRENT_MODE message, registered when the dialect predates it (pymavlink
    2.4.50's ``ardupilotmega`` and ``common`` lack it; its ``development`` dialect has it). The
    definition is the message's own (MAVLink XML: ``standard_mode`` uint8, ``custom_mode`` and
    ``intended_custom_mode`` uint32; CRC extra 193)."""
    known = mavlink.mavlink_map.get(CURRENT_MODE_ID)
    if known is not None:
        return known  # type: ignore[no-any-return]
    import struct

    class MAVLink_current_mode_message(mavlink.MAVLink_message):  # type: ignore[misc,name-defined]
        # (pymavlink's generated layout, attribute for attribute)
        id = CURRENT_MODE_ID
        msgname = "CURRENT_MODE"
        fieldnames = ["standard_mode", "custom_mode", "intended_custom_mode"]  # noqa: RUF012
        ordered_fieldnames = ["custom_mode", "intended_custom_mode", "standard_mode"]  # noqa: RUF012
        fieldtypes = ["uint8_t", "uint32_t", "uint32_t"]  # noqa: RUF012
        fielddisplays_by_name: dict[str, str] = {}  # noqa: RUF012
        fieldenums_by_name: dict[str, str] = {"standard_mode": "MAV_STANDARD_MODE"}  # noqa: RUF012
        fieldunits_by_name: dict[str, str] = {}  # noqa: RUF012
        native_format = bytearray(b"<IIB")
        orders = [2, 0, 1]  # noqa: RUF012
        lengths = [1, 1, 1]  # noqa: RUF012
        array_lengths = [0, 0, 0]  # noqa: RUF012
        crc_extra = 193
        unpacker = struct.Struct("<IIB")
        instance_field = None
        instance_offset = -1

        def __init__(self, standard_mode: int, custom_mode: int, intended_custom_mode: int):
            mavlink.MAVLink_message.__init__(self, CURRENT_MODE_ID, "CURRENT_MODE")
            self._fieldnames = self.fieldnames
            self._instance_field = None
            self._instance_offset = -1
            self.standard_mode = standard_mode
            self.custom_mode = custom_mode
            self.intended_custom_mode = intended_custom_mode

        def pack(self, mav: object, force_mavlink1: bool = False) -> bytes:
            return self._pack(  # type: ignore[no-any-return]
                mav,
                self.crc_extra,
                self.unpacker.pack(self.custom_mode, self.intended_custom_mode, self.standard_mode),
                force_mavlink1=force_mavlink1,
            )

    mavlink.mavlink_map[CURRENT_MODE_ID] = MAVLink_current_mode_message
    return MAVLink_current_mode_message


CurrentMode = _current_mode_class()
"""CURRENT_MODE's message class (``CurrentMode(standard_mode, custom_mode, intended)``, sent
with ``mav.send``)."""

__all__ = ["CURRENT_MODE_ID", "CurrentMode", "mavlink", "mavutil"]
