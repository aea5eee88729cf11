"""The auction's pieces built from a mission: each task's announcement, the task pool, each
agent's bidder.

The auction (:mod:`btmission.allocation`) is pure: it works on tasks, bids and cost expressions,
not on mission files. These adapters read a loaded :class:`~btmission.spec.mission.Mission` —
its tasks and task types, its coordination settings, and each agent's capability library (which
task types it can do, :func:`~btmission.synthesis.mission_tree.can_do`) — and build the
allocation's objects from it, for the run (the coordinator's pool, each agent's bidder) and for
``btmission auction``::

    from btmission.runtime.mission_auction import bidder_for_agent, pool_from_mission
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

from btmission.allocation.bidder import Bidder, CostProvider, Point
from btmission.allocation.tasks import TaskInfo, TaskPool
from btmission.spec.mission import Mission, Task


def task_info(task: Task, mission: Mission) -> TaskInfo:
    """A mission task, with its effective priority, whether its type has a commit point and its
    type's ``max_attempts``."""
    tt = mission.task_types[task.type]
    return TaskInfo(
        task.id,
        task.type,
        dict(task.fields),
        task.priority,
        task.at,
        tt.commit_after is not None,
        tt.max_attempts,
    )


def pool_from_mission(mission: Mission) -> TaskPool:
    """Every task of the mission file, each open from its ``at`` time."""
    return TaskPool().add_all(task_info(t, mission) for t in mission.tasks)


def bidder_for_agent(
    mission: Mission,
    agent_id: str,
    provider: CostProvider | None = None,
    *,
    types: Collection[str] | None = None,
    places: Mapping[str, Point] | None = None,
) -> Bidder:
    """The bidder of ``agent_id``: the task types its library can do (only those in ``types``,
    if given), the mission's participation and switch cost, path costs from ``provider``
    (straight lines by default) and the named ``places`` task fields may refer to."""
    # synthesis is imported here, not above: the coordinator's pool does not need it
    from btmission.synthesis.mission_tree import can_do

    lib = mission.library_of(agent_id).library
    doable = {
        name: tt
        for name, tt in mission.task_types.items()
        if can_do(lib, tt.goals) is None and (types is None or name in types)
    }
    coord = mission.spec.coordination
    return Bidder(
        doable, provider, coord.participation, switch_cost=coord.switch_cost, places=places
    )
