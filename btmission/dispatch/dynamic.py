"""Dynamic fleet mission planning (seed 004 §5, §6.2): a sequence of static plans, in simulated time.

Vehicles shuttle between loading sites and the single prioritised offloading site. When a vehicle
has been loaded or offloaded (random durations in [T_L^min, T_L^max] and [T_O^min, T_O^max]) it
requests re-planning; requests wait in a FIFO queue and the optimiser serves one at a time:

1. **Target selection** for the requesting vehicle v_r: from a loading site the primary
   destination is the offloading site; from the offloading site it is a random loading site
   (among those no other vehicle targets — our choice; the paper picks at random). The primary
   destination is also the *current* one unless another vehicle targets it; then the current
   destination is the nearest untargeted pause node (secondary destination). Inbound missions are
   prioritised (Π0, never stop after starting). Vehicles parked at — or driving to — a secondary
   destination whose primary destination is now free get their onward mission in the same plan.
2. **Causality**: the optimisation takes ``opt_time_s`` of simulated time, during which vehicles
   keep moving; the plan is made for the situation at its end, t_done. Only mission items that
   start after t_done may change, and every new mission departs after t_done (its first stop time
   is at least t_done minus its start).
3. The GA (Alg. 1-3) optimises this static fleet mission. If it finds a feasible one (score > 0)
   that becomes the current fleet mission at t_done; otherwise v_r's request goes to the back of
   the queue (§7).
4. **Settling** (ours, ``DynamicConfig.settle``): before adoption every free stop time of the GA's
   best plan is shortened as far as the plan stays collision-free without finishing later
   (:func:`settle_waits`). Eq. 2 scores a plan by when its *last* vehicle arrives, so a stop of a
   vehicle that does not finish last is a plateau of the fitness: the GA's mutations let it drift
   (up to the slack) and selection never pulls it back, and trucks idled at terminals and pause
   nodes for no reason. Settling moves along that plateau only (the score never drops); the
   paper's idle fractions (i_t ≈ 0.018 at 2 trucks, with 6 s of optimisation per request) imply
   plans without such idle stops.

Metrics (Table 6): C, terminal-to-terminal traversals per vehicle; i_t, the fraction of time
vehicles idle at terminals after loading/offloading (queue, optimisation and initial stop time);
i_p, the fraction of time at pause nodes. The simulation is a pure discrete-event loop; the GA runs
for a wall-clock budget (and/or a generation cap) while simulated time is charged ``opt_time_s``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from btmission.dispatch.evaluate import DEFAULT_GRAZING_WINDOW_S, Evaluator, default_beta, timeline
from btmission.dispatch.ga import GAParams, default_wait_max, optimize
from btmission.dispatch.missions import FleetMission, Mission, fleet_items, make_mission
from btmission.dispatch.topomap import TopoMap


@dataclass(frozen=True)
class DynamicConfig:
    """A dynamic run. Durations in s; defaults from §6.2 (4 h, loading 2-5 min, offloading 30-60 s)."""

    vehicles: int
    duration_s: float = 4 * 3600.0
    load_s: tuple[float, float] = (120.0, 300.0)
    offload_s: tuple[float, float] = (30.0, 60.0)
    opt_time_s: float = 3.0
    """Simulated time one optimisation takes (the plan applies this long after the request)."""
    ga: GAParams = GAParams(budget_s=0.5)
    delta: float = DEFAULT_GRAZING_WINDOW_S
    seed: int | None = 0
    settle: bool = True
    """Shorten the adopted plan's idle stops (:func:`settle_waits`); False: the GA's plan as is."""

    def __post_init__(self) -> None:
        if self.vehicles < 1:
            raise ValueError("at least one vehicle")
        if self.duration_s <= 0 or self.opt_time_s <= 0:
            raise ValueError("duration and optimisation time must be > 0 s")
        for lo, hi in (self.load_s, self.offload_s):
            if not 0 <= lo <= hi:
                raise ValueError("processing ranges must be [min, max] with 0 <= min <= max")


@dataclass
class _Vehicle:
    track: Mission
    primary: int
    arrive_at: float
    """When the vehicle reaches the end of its track."""
    phase: str = "driving"  # driving | processing | waiting | parked
    ready_at: float = 0.0
    """End of loading/offloading (phase processing) or when it finished (phase waiting)."""
    history: list[Mission] = field(default_factory=list)
    traversals: int = 0
    idle_terminal_s: float = 0.0


@dataclass(frozen=True)
class DynamicResult:
    """Table 6 metrics of one run, plus what the optimiser did."""

    vehicles: int
    duration_s: float
    traversals_per_vehicle: float
    """C."""
    idle_terminal: float
    """i_t."""
    idle_pause: float
    """i_p."""
    optimisations: int
    failures: int
    histories: tuple[tuple[Mission, ...], ...]


class DynamicPlanner:
    """The §5 loop on ``tmap`` (one prioritised terminal: the offloading site)."""

    def __init__(
        self, tmap: TopoMap, cfg: DynamicConfig, starts: Sequence[int] | None = None
    ) -> None:
        prio = [t for t in tmap.terminals if tmap.prioritized[t]]
        if len(prio) != 1:
            raise ValueError(
                f"dynamic planning needs exactly one prioritized terminal (offloading site); "
                f"map '{tmap.name}' has {len(prio)}"
            )
        self.tmap = tmap
        self.cfg = cfg
        self.offload = prio[0]
        self.loading = [t for t in tmap.terminals if t != self.offload]
        if starts is None and cfg.vehicles > len(self.loading):
            raise ValueError(
                f"{cfg.vehicles} vehicles but only {len(self.loading)} loading sites to start at"
            )
        self.rng = np.random.default_rng(cfg.seed)
        self.wait_max = cfg.ga.wait_max if cfg.ga.wait_max is not None else default_wait_max(tmap)
        if starts is None:
            starts = [int(x) for x in self.rng.choice(self.loading, cfg.vehicles, replace=False)]
        elif len(starts) != cfg.vehicles:
            raise ValueError(f"{cfg.vehicles} vehicles but {len(starts)} start nodes")
        self.veh = [
            _Vehicle(
                make_mission(tmap, [s]), primary=s, arrive_at=0.0, phase="waiting", ready_at=0.0
            )
            for s in starts
        ]
        for v in self.veh:
            v.history.append(v.track)
        self.queue: deque[int] = deque(range(cfg.vehicles))  # §5 fn. 4: requests at time 0
        self.optimisations = 0
        self.failures = 0
        self.on_adopt: Callable[[float, FleetMission, FleetMission, set[int]], None] | None = None
        """Called with (t_done, tracks before, fleet mission adopted, changed vehicles)."""

    # ------------------------------------------------------------------------- planning
    def targets(self, skip: int) -> set[int]:
        return {v.track.end for k, v in enumerate(self.veh) if k != skip}

    def pause_for(self, near: int, taken: set[int]) -> int | None:
        free = [p for p in self.tmap.pauses if p not in taken]
        if not free:
            return None
        return min(free, key=lambda p: (self.tmap.dist[p, near], p))

    def _new_track(self, k: int, dest: int, t_done: float, prioritized: bool) -> Mission:
        """Π0 from where vehicle k is (or will be) to ``dest``, appended to its current track."""
        v = self.veh[k]
        here = v.track.end
        path = self.tmap.path(here, dest)
        if v.phase != "driving" or v.track.items == 0:
            base_nodes, base_waits, t0, head = [], [], v.arrive_at, 0
        else:  # still driving to its secondary destination: append to the current track
            base_nodes = [int(x) for x in v.track.nodes[:-1]]
            base_waits = [float(x) for x in v.track.waits[:-1]]
            t0, head = v.track.t0, len(base_nodes)
        arr_here = v.arrive_at
        min_wait = max(0.0, t_done - arr_here)
        first = min_wait + self.rng.random() * 0.5 * self.wait_max  # random initial stop (§5)
        waits = [*base_waits, first, *([0.0] * (len(path) - 1))]
        return make_mission(
            self.tmap,
            base_nodes + path,
            waits,
            t0=t0,
            prioritized=prioritized,
            frozen=head,
            min_wait=min_wait,
            head=head,
        )

    def _existing(self, m: Mission, t_done: float) -> Mission:
        """The current track with items starting before t_done frozen (causality)."""
        arr, _ = timeline(self.tmap, [int(x) for x in m.nodes], list(m.waits), m.t0)
        k = sum(1 for i in range(m.items) if arr[i] < t_done)
        if m.prioritized:
            k = max(k, m.head)
        min_wait = max(0.0, t_done - arr[m.head]) if k == m.head and m.head < m.items else 0.0
        return make_mission(
            self.tmap, m.nodes, m.waits, t0=m.t0, prioritized=m.prioritized, frozen=k,
            min_wait=min_wait, head=m.head,
        )  # fmt: skip

    def plan(
        self, r: int, t_now: float, primary: int | None = None
    ) -> tuple[FleetMission, set[int], dict[int, int]]:
        """The static fleet mission to optimise for v_r's request (made at ``t_now``).

        ``primary``: v_r's primary destination; None picks it as the §6.2 shuttle does (a free
        loading site from the offloading site, else the offloading site). Missions to a
        prioritised terminal are inbound (prioritised)."""
        t_done = t_now + self.cfg.opt_time_s
        tracks: dict[int, Mission] = {}
        primaries: dict[int, int] = {}
        vr = self.veh[r]
        at = vr.track.end
        taken = self.targets(r)
        if primary is not None:
            inbound = bool(self.tmap.prioritized[primary])
        elif at == self.offload:
            free = [x for x in self.loading if x not in taken]
            primary = int(self.rng.choice(free if free else self.loading))
            inbound = False
        else:
            primary, inbound = self.offload, True
        current = primary
        if primary in taken:
            current = self.pause_for(self.offload if inbound else primary, taken) or primary
        tracks[r] = self._new_track(r, current, t_done, inbound)
        primaries[r] = primary
        taken = {tracks[r].end} | self.targets(r)
        changed = {r}
        # vehicles at (or driving to) a secondary destination whose primary is now free
        waiting = sorted(
            (k for k, v in enumerate(self.veh) if k != r and v.track.end != v.primary),
            key=lambda k: (self.veh[k].arrive_at, k),
        )
        for k in waiting:
            v = self.veh[k]
            taken_k = taken - {v.track.end}
            if v.primary in taken_k:
                continue
            tracks[k] = self._new_track(k, v.primary, t_done, v.primary == self.offload)
            taken = (taken - {v.track.end}) | {v.primary}
            changed.add(k)
        fleet = tuple(
            tracks[k] if k in tracks else self._existing(v.track, t_done)
            for k, v in enumerate(self.veh)
        )
        return fleet, changed, primaries

    # ------------------------------------------------------------------------- simulation
    def _arrive(self, k: int, t: float) -> None:
        v = self.veh[k]
        if v.track.end == v.primary and v.track.items > 0:
            lo, hi = self.cfg.offload_s if v.primary == self.offload else self.cfg.load_s
            v.phase, v.ready_at = "processing", t + lo + self.rng.random() * (hi - lo)
            v.traversals += 1
        else:
            v.phase = "parked"

    def run(self, progress: Callable[[float], None] | None = None) -> DynamicResult:
        T = self.cfg.duration_s
        t = 0.0
        pending: tuple[int, float, FleetMission | None, set[int], dict[int, int]] | None = None
        while True:
            if pending is None and self.queue:
                r = self.queue.popleft()
                fleet0, changed, prim = self.plan(r, t)
                pending = (r, t + self.cfg.opt_time_s, self.optimise(fleet0, t), changed, prim)
            times = [pending[1]] if pending else []
            for v in self.veh:
                if v.phase == "driving":
                    times.append(v.arrive_at)
                elif v.phase == "processing":
                    times.append(v.ready_at)
            if not times:
                break
            t = max(t, min(times))
            if t > T:
                break
            if progress is not None:
                progress(t)
            for k, v in enumerate(self.veh):
                if v.phase == "driving" and v.arrive_at <= t:
                    self._arrive(k, t)
            for k, v in enumerate(self.veh):
                if v.phase == "processing" and v.ready_at <= t:
                    v.phase = "waiting"
                    self.queue.append(k)
            if pending is not None and pending[1] <= t:
                r, _, best, changed, prim = pending
                pending = None
                if best is None:
                    self.failures += 1
                    self.queue.append(r)
                else:
                    if self.on_adopt is not None:
                        before = tuple(v.track for v in self.veh)
                        self.on_adopt(t, before, best, changed)
                    self.adopt(best, changed, prim, r)
        for v in self.veh:  # idle time of vehicles still waiting at a terminal at the end
            if v.phase == "waiting":
                v.idle_terminal_s += max(0.0, T - v.ready_at)
        return self._result()

    def optimise(self, fleet0: FleetMission, t_now: float) -> FleetMission | None:
        self.optimisations += 1
        t_done = t_now + self.cfg.opt_time_s
        ev = Evaluator(
            self.tmap,
            fleet_items(fleet0),
            default_beta(self.tmap, fleet0, self.wait_max),
            self.cfg.delta,
            t_ref=t_done,
        )
        res = optimize(self.tmap, fleet0, ev, self.cfg.ga, self.rng)
        if not res.feasible:
            return None
        return settle_waits(res.best, ev) if self.cfg.settle else res.best

    def adopt(self, fleet: FleetMission, changed: set[int], prim: dict[int, int], r: int) -> None:
        for k, m in enumerate(fleet):
            v = self.veh[k]
            arr, dep = timeline(self.tmap, [int(x) for x in m.nodes], list(m.waits), m.t0)
            if k in changed:
                if k == r:
                    v.primary = prim[r]
                    # queue + optimisation + initial stop time, counted up to the end of the run
                    v.idle_terminal_s += max(0.0, min(dep[0], self.cfg.duration_s) - v.ready_at)
                if m.head == 0:
                    v.history.append(m)
                else:
                    v.history[-1] = m
                v.phase = "driving"
            elif m.items > 0:
                v.history[-1] = m
            m_clean = replace(m, frozen=0, min_wait=0.0)
            v.track = m_clean
            v.arrive_at = arr[-1]

    def _result(self) -> DynamicResult:
        T = self.cfg.duration_s
        L = self.cfg.vehicles
        pause_s = 0.0
        for v in self.veh:
            for j, m in enumerate(v.history):
                arr, dep = timeline(self.tmap, [int(x) for x in m.nodes], list(m.waits), m.t0)
                last = j == len(v.history) - 1
                for i, x in enumerate(m.nodes):
                    if i == len(m.nodes) - 1 and not last:
                        continue  # the next mission starts here and counts the stay
                    if self.tmap.is_pause[int(x)]:
                        pause_s += max(0.0, min(dep[i], T) - min(arr[i], T))
        return DynamicResult(
            vehicles=L,
            duration_s=T,
            traversals_per_vehicle=sum(v.traversals for v in self.veh) / L,
            idle_terminal=sum(v.idle_terminal_s for v in self.veh) / L / T,
            idle_pause=pause_s / L / T,
            optimisations=self.optimisations,
            failures=self.failures,
            histories=tuple(tuple(v.history) for v in self.veh),
        )


def settle_waits(fleet: FleetMission, ev: Evaluator, steps: int = 12) -> FleetMission:
    """``fleet`` with every free stop time made as short as it can be (a feasible plan stays
    feasible and its last vehicle arrives no later, so eq. 2's score never drops).

    Vehicle by vehicle, stop by stop (the mutable slots, from the first), the stop time goes to
    its lower bound if that keeps the plan feasible, else to the shortest feasible value found by
    bisection (``steps`` halvings) between the bound and the current value; repeated (at most
    three sweeps) while something changed. An infeasible ``fleet`` is returned unchanged.
    """
    cur = list(fleet)
    n_c, _, t_end = ev.raw(fleet)
    if n_c:
        return fleet

    def trial(k: int, i: int, w: float) -> tuple[bool, list[Mission], float]:
        waits = cur[k].waits.copy()
        waits[i] = w
        out = list(cur)
        out[k] = replace(cur[k], waits=waits)
        nc, _, te = ev.raw(tuple(out))
        return nc == 0 and te <= t_end + 1e-9, out, te

    for _ in range(3):
        changed = False
        for k in range(len(cur)):
            for i in (int(x) for x in cur[k].slots):
                now = float(cur[k].waits[i])
                lo = cur[k].min_wait if i == cur[k].frozen else 0.0
                if now <= lo + 1e-6:
                    continue
                ok, out, te = trial(k, i, lo)
                if not ok:  # lo infeasible, now feasible: bisect for the shortest feasible stop
                    found = None
                    hi = now
                    for _ in range(steps):
                        mid = 0.5 * (lo + hi)
                        ok_mid, out_mid, te_mid = trial(k, i, mid)
                        if ok_mid:
                            hi, found = mid, (out_mid, te_mid)
                        else:
                            lo = mid
                    if found is None or hi > now - 0.5:
                        continue
                    out, te = found
                cur, t_end, changed = out, te, True
        if not changed:
            break
    return tuple(cur)


def run_dynamic(
    tmap: TopoMap, cfg: DynamicConfig, progress: Callable[[float], None] | None = None
) -> DynamicResult:
    """One dynamic run (see the module docstring)."""
    return DynamicPlanner(tmap, cfg).run(progress)


def executed_tracks(result: DynamicResult) -> FleetMission:
    """Each vehicle's whole run as one track (its missions joined end to start), e.g. to check
    with the evaluator that the executed dynamic plan never had a collision."""
    return join_histories(result.histories)


def join_histories(histories: Sequence[Sequence[Mission]]) -> FleetMission:
    """One track per vehicle from its successive missions (each starting where the last ended)."""
    out = []
    for hist in histories:
        nodes: list[int] = [int(hist[0].nodes[0])]
        waits: list[float] = []
        for m in hist:  # waits holds one stop time per item so far
            if m.items:
                waits.append(float(m.waits[0]))
                waits.extend(float(x) for x in m.waits[1:-1])
                nodes.extend(int(x) for x in m.nodes[1:])
        waits.append(0.0)
        out.append(Mission(np.asarray(nodes, np.int32), np.asarray(waits), hist[0].t0))
    return tuple(out)


def mean_std(xs: list[float]) -> tuple[float, float]:
    """Mean and (population) standard deviation, as Table 6 reports them."""
    if not xs:
        return math.nan, math.nan
    m = sum(xs) / len(xs)
    return m, math.sqrt(sum((x - m) ** 2 for x in xs) / len(xs))
