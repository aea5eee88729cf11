"""Task allocation: the task pool, the auctioneer, exact assignment solvers and bidders.

Seed 003 §IV-V and seed 000 §IV-B: every round the auctioneer announces the open tasks, collects
the agents' bids (cost estimates, eq. 8-10) and solves the assignment (eq. 6-7) that assigns the
most tasks at the least total cost, with priorities and multi-stage commit points.

    from btmission.allocation import AuctionState, AuctionConfig, TaskPool, auction_round

The allocation works on tasks and bids, not on mission files: the pool and the bidders of a
mission are built by :mod:`btmission.runtime.mission_auction`.
"""

from btmission.allocation.auction import (
    Announcement,
    AuctionConfig,
    AuctionState,
    Bid,
    Change,
    RoundReport,
    announce,
    auction_round,
)
from btmission.allocation.bidder import AgentState, Bidder, CostProvider, StraightLine, k_bt
from btmission.allocation.loop import AuctionLoop, Inbox, ManualClock, Progress, WallClock
from btmission.allocation.solvers import AssignmentProblem, Matching, evaluate, solve
from btmission.allocation.tasks import PoolTask, TaskEvent, TaskInfo, TaskPool, TaskState

__all__ = [
    "AgentState",
    "Announcement",
    "AssignmentProblem",
    "AuctionConfig",
    "AuctionLoop",
    "AuctionState",
    "Bid",
    "Bidder",
    "Change",
    "CostProvider",
    "Inbox",
    "ManualClock",
    "Matching",
    "PoolTask",
    "Progress",
    "RoundReport",
    "StraightLine",
    "TaskEvent",
    "TaskInfo",
    "TaskPool",
    "TaskState",
    "WallClock",
    "announce",
    "auction_round",
    "evaluate",
    "k_bt",
    "solve",
]
