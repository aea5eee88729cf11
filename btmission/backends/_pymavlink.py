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

__all__ = ["mavlink", "mavutil"]
