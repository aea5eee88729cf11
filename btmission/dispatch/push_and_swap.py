"""Push and swap (Luna & Bekris, IJCAI 2011), the static-planning peer of seed 004 §6.1.1.

Written from the paper's description (no code copied). Agents live on graph vertices, at most one
per vertex, and move one at a time along an edge into an empty vertex. Agents are solved one by
one in the given order; solved agents form the set U, which a later push must not disturb:

* **push** — move the agent r along its shortest path; when the next vertex holds an agent, push
  that agent (and any agents behind it) towards the nearest empty vertex reachable without
  crossing r or an agent of U. When that fails (the blocker is in U, or nothing can move) —
* **swap** — r and the blocker s exchange places: the pair is pushed together (multi-push) to the
  nearest vertex of degree ≥ 3 where two neighbours can be cleared (clear), the six-move swap
  primitive runs there, and every move made to get there is replayed backwards with r and s
  exchanged, so all other agents end where they were and r and s have traded places.
* **resolve** — if the swap displaced an agent of U, it is removed from U and solved again after
  r (our simplification of the paper's resolve, with a global move cap as the safety net).

The clear step is simplified: occupied neighbours of the swap vertex are pushed, one at a time, to
the nearest empty vertex not through the swap vertex, the follower or the neighbours already
cleared; the paper's clear also tries moving the pair a step back. Vertex types (terminal, pause,
transit) mean nothing to push and swap, which is why its plans reverse direction and park vehicles
anywhere — the reason the paper finds it unsuitable for mines.

What a swap costs: when r stands next to s and the swap vertex is d hops back, the pair moves
2d times to get there, the primitive takes 6 moves and the replay 2d more; r's last step onto
s's vertex and s's first step off it are no longer needed, so the swap adds 4d + 4 items to what
the two would drive along Π0. On the §6.1 instances every pair needs exactly one swap: the first
of the two to be solved drives to the vertex next to its goal, where its partner still stands in a
dead-end terminal it cannot be pushed out of (``PasResult.swaps`` counts them).

The result is a sequential plan (one move at a time). Its number of moves is the number of mission
items ξ compared in Table 5; its *serial* duration (the sum of the moves' traversal times) is
reported too, as the plan has no parallel schedule.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from btmission.dispatch.topomap import TopoMap
from btmission.errors import BtmissionError


@dataclass(frozen=True)
class PasResult:
    """Outcome of push and swap: success, the moves (agent, from, to) and their statistics."""

    success: bool
    moves: tuple[tuple[int, int, int], ...]
    items: int
    """ξ: the number of moves (segment traversals)."""
    serial_duration: float
    """Sum of the moves' traversal times (the plan executes one move at a time)."""
    reason: str = ""
    swaps: int = 0
    """Number of swap operations (each exchanges two agents; see the module docstring)."""


class _Fail(BtmissionError):
    pass


class PushAndSwap:
    """One push-and-swap run on ``tmap`` (see the module docstring)."""

    def __init__(
        self,
        tmap: TopoMap,
        starts: Sequence[int],
        goals: Sequence[int],
        max_moves: int | None = None,
    ) -> None:
        if len(starts) != len(goals):
            raise ValueError("one goal per agent")
        if len(set(starts)) != len(starts) or len(set(goals)) != len(goals):
            raise ValueError("start and goal vertices must be distinct per agent")
        if len(starts) > tmap.n - 2:
            raise ValueError("push and swap needs at least two empty vertices")
        self.tmap = tmap
        self.goal = list(goals)
        self.pos = list(starts)
        self.occ = [-1] * tmap.n
        for a, p in enumerate(starts):
            self.occ[p] = a
        self.moves: list[tuple[int, int, int]] = []
        self.max_moves = max_moves if max_moves is not None else 200 * tmap.n * max(len(starts), 1)
        self.deg3 = [v for v in range(tmap.n) if len(tmap.neighbors[v]) >= 3]
        self.swaps = 0

    # --------------------------------------------------------------------------- primitives
    def _move(self, a: int, to: int) -> None:
        frm = self.pos[a]
        assert self.occ[to] == -1 and to in self.tmap.neighbors[frm]
        self.occ[frm], self.occ[to] = -1, a
        self.pos[a] = to
        self.moves.append((a, frm, to))
        if len(self.moves) > self.max_moves:
            raise _Fail("move cap reached")

    def _nearest_empty(self, v: int, blocked: set[int]) -> list[int] | None:
        """BFS path from v to the nearest empty vertex, not entering ``blocked``."""
        prev = {v: -1}
        queue = deque([v])
        while queue:
            x = queue.popleft()
            if x != v and self.occ[x] == -1:
                path = [x]
                while prev[path[-1]] != -1:
                    path.append(prev[path[-1]])
                return path[::-1]
            for y in self.tmap.neighbors[x]:
                if y not in prev and y not in blocked:
                    prev[y] = x
                    queue.append(y)
        return None

    def _push_away(self, v: int, blocked: set[int]) -> bool:
        """Empty vertex v by shifting the agents on the path to the nearest empty vertex."""
        path = self._nearest_empty(v, blocked)
        if path is None:
            return False
        for i in range(len(path) - 2, -1, -1):
            a = self.occ[path[i]]
            if a != -1:
                self._move(a, path[i + 1])
        return True

    # --------------------------------------------------------------------------- push
    def _push(self, r: int, solved: set[int]) -> bool:
        """Move r towards its goal; False when blocked by U or nothing can be pushed."""
        while self.pos[r] != self.goal[r]:
            v = int(self.tmap.next_hop[self.pos[r], self.goal[r]])
            if self.occ[v] != -1:
                if self.occ[v] in solved:
                    return False
                blocked = {self.pos[r]} | {self.pos[u] for u in solved}
                if not self._push_away(v, blocked):
                    return False
            self._move(r, v)
        return True

    # --------------------------------------------------------------------------- swap
    def _multipush(self, r: int, s: int, w: int) -> bool:
        """Move the adjacent pair (r, s) together until one of them stands on w."""
        leader, follower = (s, r) if self._through(self.pos[r], w, self.pos[s]) else (r, s)
        while self.pos[leader] != w:
            v = int(self.tmap.next_hop[self.pos[leader], w])
            if v == self.pos[follower]:  # w lies behind: swap roles
                leader, follower = follower, leader
                continue
            if self.occ[v] != -1 and not self._push_away(v, {self.pos[leader], self.pos[follower]}):
                return False
            old = self.pos[leader]
            self._move(leader, v)
            self._move(follower, old)
        return True

    def _through(self, a: int, b: int, x: int) -> bool:
        """Whether Π0(a, b) passes through x."""
        return x in self.tmap.path(a, b)

    def _clear(self, w: int, follower_pos: int) -> list[int] | None:
        """Two empty neighbours of w other than the follower's vertex, emptying them if needed."""
        empty: list[int] = []
        nbrs = [n for n in self.tmap.neighbors[w] if n != follower_pos]
        for n in nbrs:
            if self.occ[n] == -1:
                empty.append(n)
        for n in nbrs:
            if len(empty) >= 2:
                break
            if n in empty:
                continue
            if self._push_away(n, {w, follower_pos, *empty}):
                empty.append(n)
        return empty[:2] if len(empty) >= 2 else None

    def _swap(self, r: int, solved: set[int]) -> bool:
        """Exchange r with the agent blocking its next step (module docstring)."""
        v = int(self.tmap.next_hop[self.pos[r], self.goal[r]])
        s = self.occ[v]
        if s == -1:
            return True
        p = self.pos[r]
        order = sorted(self.deg3, key=lambda x: (self.tmap.hops[p, x], x))
        for w in order:
            mark = len(self.moves)
            snapshot = (list(self.pos), list(self.occ))
            try:
                ok = self._multipush(r, s, w)
                if ok:
                    lead = self.occ[w]
                    follow = s if lead == r else r
                    cleared = self._clear(w, self.pos[follow])
                    ok = cleared is not None
            except _Fail:
                raise
            if not ok:
                del self.moves[mark:]
                self.pos, self.occ = snapshot
                continue
            assert cleared is not None
            before = self.moves[mark:]
            n1, n2 = cleared
            f = self.pos[follow]
            self._move(lead, n1)
            self._move(follow, w)
            self._move(follow, n2)
            self._move(lead, w)
            self._move(lead, f)
            self._move(follow, w)
            for a, frm, to in reversed(before):  # replay backwards, r and s exchanged
                b = s if a == r else r if a == s else a
                assert self.pos[b] == to
                self._move(b, frm)
            if s in solved:
                solved.discard(s)
            self.swaps += 1
            return True
        return False

    # --------------------------------------------------------------------------- main loop
    def run(self) -> PasResult:
        solved: set[int] = set()
        todo = deque(range(len(self.goal)))
        try:
            while todo:
                r = todo.popleft()
                while self.pos[r] != self.goal[r]:
                    if not self._push(r, solved) and not self._swap(r, solved):
                        return self._result(False, f"agent {r}: neither push nor swap works")
                solved.add(r)
                for u in range(len(self.goal)):  # resolve: agents of U a swap displaced
                    if u not in solved and u not in todo and u != r:
                        todo.appendleft(u)
        except _Fail as exc:
            return self._result(False, str(exc))
        return self._result(all(p == g for p, g in zip(self.pos, self.goal)), "")

    def _result(self, success: bool, reason: str) -> PasResult:
        dur = sum(float(self.tmap.ttime[f, t]) for _, f, t in self.moves)
        return PasResult(success, tuple(self.moves), len(self.moves), dur, reason, self.swaps)


def push_and_swap(
    tmap: TopoMap, starts: Sequence[int], goals: Sequence[int], max_moves: int | None = None
) -> PasResult:
    """Solve the static instance (starts → goals) with push and swap."""
    return PushAndSwap(tmap, starts, goals, max_moves).run()
