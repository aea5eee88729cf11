"""The fleet dispatcher as a service of a running mission (seed 004 §5, driven by the trucks' trees).

:mod:`btmission.dispatch.dynamic` simulates the §6.2 shuttle on its own: it decides where every
vehicle goes next and draws the loading times. In a mission, those decisions belong to the
agents — the auction gives a truck a haul, its behaviour tree asks for a mission to the pickup,
loads, asks for a mission to the dropoff — so :class:`FleetDispatcher` keeps only the planner's
part, with the same rules:

* requests (truck, primary destination) wait in a **FIFO queue** and are served one at a time;
* serving one builds the static fleet mission of :meth:`DynamicPlanner.plan
  <btmission.dispatch.dynamic.DynamicPlanner.plan>` — Π0 from where the truck is (or will be),
  a secondary destination (nearest free pause node) when the primary one is targeted by another
  truck, onward missions for trucks parked at a secondary destination whose primary is now free —
  and optimises it with the GA (Alg. 1-3);
* **causality**: the optimisation is charged ``opt_time_s`` of mission time; the plan is made for
  t_done = request time + ``opt_time_s`` and only items starting after t_done change;
* a failed optimisation puts the request at the back of the queue (§7).

Time is the mission's clock: the runtime calls :meth:`FleetDispatcher.step` every step. The GA
itself runs for at most ``GAParams.max_generations`` generations (and ``budget_s`` of wall time as
a safety net), so that a run is reproducible for a seed.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from btmission.dispatch.dynamic import DynamicConfig, DynamicPlanner
from btmission.dispatch.missions import FleetMission, Mission, make_mission
from btmission.dispatch.topomap import TopoMap

PARK = -1
"""Request goal meaning "the nearest free pause node"."""

Event = Callable[..., None]


@dataclass(frozen=True)
class _Pending:
    truck: int
    goal: int
    t_done: float
    best: FleetMission | None
    changed: frozenset[int]
    primaries: Mapping[int, int]


class FleetDispatcher:
    """Seed 004 §5 dynamic planning for trucks whose destinations come from their trees.

    Args:
        tmap: the topological map (exactly one prioritised terminal: the offloading site).
        starts: truck name → node it starts at (stopped there).
        cfg: ``opt_time_s``, the GA settings and the seed (``vehicles``, ``duration_s`` and the
            loading ranges are not used: the trucks load and offload themselves).
        events: ``events(kind, **data)`` for observers: ``dispatch`` events when a request is
            queued, a plan adopted or an optimisation failed.
    """

    def __init__(
        self,
        tmap: TopoMap,
        starts: Mapping[str, int],
        cfg: DynamicConfig,
        events: Event | None = None,
    ) -> None:
        if not starts:
            raise ValueError("the dispatcher needs at least one truck")
        self.names = list(starts)
        self._index = {name: k for k, name in enumerate(self.names)}
        self.planner = DynamicPlanner(
            tmap, replace(cfg, vehicles=len(self.names)), [starts[n] for n in self.names]
        )
        self.tmap = tmap
        self.cfg = cfg
        self._events = events or (lambda kind, **data: None)
        self.queue: deque[tuple[int, int]] = deque()
        self.pending: _Pending | None = None
        self.adopted = 0
        self.failed = 0
        self._deferred: set[tuple[int, int]] = set()

    # ------------------------------------------------------------------ the trucks' interface
    def request(self, truck: str, goal: int) -> None:
        """Queue a request: ``truck`` wants a mission to node ``goal`` (or :data:`PARK`). A truck
        has at most one request waiting: a new goal replaces the queued one."""
        k = self._index[truck]
        if self.pending is not None and self.pending.truck == k and self.pending.goal == goal:
            return
        for i, (kk, g) in enumerate(self.queue):
            if kk == k:
                if g != goal:
                    self.queue[i] = (k, goal)
                return
        self.queue.append((k, goal))
        self._events("dispatch", truck=truck, event="requested", goal=self._name(goal))

    def park(self, truck: str) -> None:
        """Ask to be parked out of the way: see :meth:`park_target`."""
        self.request(truck, PARK)

    def withdraw(self, truck: str) -> None:
        """The truck no longer wants what it asked for (its task was given to another truck):
        drop its queued request and any plan being optimised for it, and make the end of its
        current schedule its destination, so that no later plan sends it on to the old goal.
        The schedule itself is kept: it is part of the collision-free fleet plan."""
        k = self._index[truck]
        dropped = [g for kk, g in self.queue if kk == k]
        self.queue = deque((kk, g) for kk, g in self.queue if kk != k)
        if self.pending is not None and self.pending.truck == k:
            dropped.append(self.pending.goal)
            self.pending = None
        v = self.planner.veh[k]
        if dropped or v.primary != v.track.end:
            v.primary = v.track.end
            self._events("dispatch", truck=truck, event="withdrawn",
                         goal=", ".join(self._name(g) for g in dropped) or None)  # fmt: skip

    def mission(self, truck: str) -> Mission:
        """The truck's current mission (its last adopted one; a 0-item one before any)."""
        return self.planner.veh[self._index[truck]].track

    def primary(self, truck: str) -> int:
        """The primary destination of that mission (its end may be a secondary destination)."""
        return self.planner.veh[self._index[truck]].primary

    def waiting(self, truck: str) -> bool:
        """Whether the truck has a request queued or being optimised."""
        k = self._index[truck]
        return any(kk == k for kk, _ in self.queue) or (
            self.pending is not None and self.pending.truck == k
        )

    def wanted(self, node: int, by_other_than: str) -> bool:
        """Whether another truck is heading for ``node`` as its destination, or asks to."""
        k = self._index[by_other_than]
        if any(kk != k and g == node for kk, g in self.queue):
            return True
        if self.pending is not None and self.pending.truck != k and self.pending.goal == node:
            return True
        return any(
            j != k and v.primary == node and v.track.end != node
            for j, v in enumerate(self.planner.veh)
        )

    def park_target(self, truck: str) -> int | None:
        """Where :meth:`park` sends the truck: where it stands if that is a pause node no other
        truck targets, else the nearest such pause node; when every pause node is targeted, a
        non-prioritised terminal no other truck targets (where it stands, or the nearest).
        None: nowhere is free."""
        k = self._index[truck]
        here = self.mission(truck).end
        taken = self.planner.targets(k)
        tm = self.tmap
        if tm.is_pause[here] and here not in taken:
            return here
        pause = self.planner.pause_for(here, taken)
        if pause is not None:
            return pause
        free = [t for t in tm.terminals if not tm.prioritized[t] and t not in taken]
        if not free:
            return None
        return min(free, key=lambda t: (tm.dist[here, t], t))

    # ------------------------------------------------------------------ the runtime's
    def step(self, now: float) -> None:
        """Advance to mission time ``now``: note arrivals, adopt a finished optimisation, start
        the next one."""
        for v in self.planner.veh:
            if v.phase == "driving" and v.arrive_at <= now:
                v.phase = "waiting" if v.track.end == v.primary else "parked"
                v.ready_at = v.arrive_at
        p = self.pending
        if p is not None and p.t_done <= now:
            self.pending = None
            if p.best is None:
                self.failed += 1
                self.queue.append((p.truck, p.goal))
                self._events("dispatch", truck=self.names[p.truck], event="failed",
                             goal=self._name(p.goal))  # fmt: skip
            else:
                self._adopt(p)
        if self.pending is None and self.queue:
            self._serve(now)

    def _adopt(self, p: _Pending) -> None:
        assert p.best is not None
        before = tuple(v.track for v in self.planner.veh)
        if self.planner.on_adopt is not None:
            self.planner.on_adopt(p.t_done, before, p.best, set(p.changed))
        self.planner.adopt(p.best, set(p.changed), dict(p.primaries), p.truck)
        self.adopted += 1
        self._deferred.discard((p.truck, p.goal))
        for k, m in enumerate(p.best):
            old = before[k]
            same = (
                k not in p.changed
                and m.t0 == old.t0
                and np.array_equal(m.nodes, old.nodes)
                and np.array_equal(m.waits, old.waits)
            )
            if same:
                continue  # the GA may also change other trucks' missions (after t_done)
            self._events(
                "dispatch",
                truck=self.names[k],
                event="adopted",
                goal=self._name(self.planner.veh[k].primary),
                to=self.tmap.nodes[m.end].name,
                items=m.items,
                depart=round(m.t0 + float(m.waits[m.head]), 3) if m.items else None,
                arrive=round(self.planner.veh[k].arrive_at, 3),
                mission=mission_record(self.tmap, m),
            )

    def _serve(self, now: float) -> None:
        k, goal = self.queue.popleft()
        v = self.planner.veh[k]
        name = self.names[k]
        if v.phase == "driving" and not self.tmap.is_pause[v.track.end]:
            # a new destination while driving to a terminal: it may not stop there mid-mission
            # (initial stop times only at the start and at pause nodes, §3.2), so the request
            # waits until it has arrived; the queue moves on meanwhile
            self.queue.append((k, goal))
            return
        target = self.park_target(name) if goal == PARK else goal
        taken = self.planner.targets(k)
        if target is None or (target in taken and self.planner.pause_for(target, taken) is None):
            # nowhere to go (every place is targeted): wait until a truck moves on, without
            # spending an optimisation that cannot succeed
            self.queue.append((k, goal))
            if (k, goal) not in self._deferred:
                self._deferred.add((k, goal))
                self._events("dispatch", truck=name, event="deferred", goal=self._name(goal),
                             reason="every pause node is taken")  # fmt: skip
            return
        self._deferred.discard((k, goal))
        if target == v.track.end:  # already there (or driving there): nothing to optimise
            if v.primary != target:
                v.primary = target
                self._events("dispatch", truck=name, event="adopted", goal=self._name(goal),
                             to=self.tmap.nodes[target].name, items=0)  # fmt: skip
            return
        fleet0, changed, prim = self.planner.plan(k, now, target)
        best = self.planner.optimise(fleet0, now)
        self.pending = _Pending(
            k, goal, now + self.cfg.opt_time_s, best, frozenset(changed), dict(prim)
        )

    def _name(self, goal: int) -> str:
        return "park" if goal == PARK else self.tmap.nodes[goal].name


def mission_record(tmap: TopoMap, m: Mission) -> dict[str, Any]:
    """A mission as JSON for the event log: node names, stop times, start time, whether it is
    prioritised, and ``head`` (> 0: it continues the truck's previous mission, whose first
    ``head`` items it keeps)."""
    return {
        "nodes": [tmap.nodes[int(x)].name for x in m.nodes],
        "waits": [round(float(w), 3) for w in m.waits],
        "t0": round(float(m.t0), 3),
        "prioritized": bool(m.prioritized),
        "head": int(m.head),
    }


def missions_from_records(tmap: TopoMap, records: Sequence[Mapping[str, Any]]) -> list[Mission]:
    """A truck's successive missions from its ``adopted`` records, in log order (a record with
    ``head`` > 0 replaces the mission it continues)."""
    out: list[Mission] = []
    for r in records:
        m = make_mission(
            tmap,
            [tmap.id(n) for n in r["nodes"]],
            list(r["waits"]),
            t0=float(r["t0"]),
            prioritized=bool(r.get("prioritized", False)),
            head=int(r.get("head", 0)),
        )
        if m.head > 0 and out:
            out[-1] = m
        else:
            out.append(m)
    return out
