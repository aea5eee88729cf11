"""An agent in a process of its own, for tests/unit/transport/test_transport.py's two-process round trip.

``python -m tests.zenoh_child MISSION ENDPOINT`` connects agent R1 to the coordinator at ENDPOINT
and answers: an announcement with :func:`bid_for`, :func:`STATUS`, :func:`PROGRESS` and a
prediction (:data:`PREDICTION`); an assignment with :func:`echo_status`; an acknowledgement by
printing ``ack <json>`` and exiting 0. Exit 1 if nothing ends it within 60 s (every wait is
bounded); the test also ends it by its PID.
"""

from __future__ import annotations

import json
import math
import sys
import time

import numpy as np

from btmission.allocation.auction import Announcement, Bid
from btmission.allocation.loop import Progress
from btmission.links.bus import AgentStatus, Assignment, ProgressAck

AGENT = "R1"
STATUS = AgentStatus(AGENT, 1.25, (1.0, -2.5, 0.125), "OFFBOARD", True, 0.875, None, "takeoff")
PROGRESS = Progress(AGENT, "T1", "failed", 2.5, "follow_path: no path (blocked)")
PREDICTION = np.array([[0.0, 0.0, 1.0], [0.5, 0.25, 1.0], [1.0, 0.5, 1.5]])


def bid_for(ann: Announcement) -> Bid:
    """R1's bid: 0.5, 1.5, ... with 'no bid' (NaN) on the second task and 'cannot' (inf) on the
    third."""
    costs = [j + 0.5 for j in range(len(ann))]
    if len(costs) > 2:
        costs[1], costs[2] = math.nan, math.inf
    return Bid.aligned(AGENT, 1.5, ann, costs, committed_to=None)


def echo_status(a: Assignment) -> AgentStatus:
    return AgentStatus(AGENT, a.time_s, (3.0, 4.0, 0.0), f"round {a.round}", False, math.nan,
                       a.tasks.get(AGENT), "echo", vehicle_link=False)  # fmt: skip


def main(mission: str, endpoint: str) -> int:
    from btmission.transport.zenoh_link import ZenohAgentLink
    from btmission.transport.zenoh_session import ZenohSettings

    acked: list[ProgressAck] = []
    link = ZenohAgentLink(mission, AGENT, settings=ZenohSettings.agent([endpoint]))
    try:

        def on_announcement(ann: Announcement) -> None:
            link.send_bid(bid_for(ann))
            link.send_status(STATUS)
            link.send_progress(PROGRESS)
            link.share_prediction(2.0, PREDICTION)

        def on_assignment(a: Assignment) -> None:
            link.send_status(echo_status(a))

        link.connect(on_announcement, on_assignment, acked.append)
        deadline = time.monotonic() + 60.0
        while not acked and time.monotonic() < deadline:
            link.dispatch(0.1)
        if not acked:
            return 1
        print("ack", json.dumps([list(k) for k in acked[0].keys]), flush=True)
        return 0
    finally:
        link.close()


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1], sys.argv[2]))
