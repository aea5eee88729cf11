"""Topological mine maps (seed 004 §3.1): nodes, segments with per-direction times, the path matrix.

A topological map is a bidirectional graph ``T = {P, E}``. Every node is a *terminal* (loading or
offloading site; prioritised or not), a *pause* (swap) node where a vehicle may stop to let another
pass, or a *transit* node where paths branch. Every segment joins two nodes and has a traversal
time per direction, so a loaded truck can be slower one way than the other. The paper's maps
contain no loops; :meth:`TopoMap.build` refuses a map with one, naming the nodes of the loop.

Because the map is a tree the shortest path between two nodes is the only simple path, and the
*path matrix* Π0 is computed once (``next_hop[i, j]`` is the node after ``i`` on Π0(i, j)).

The map file format (YAML, ``docs/dispatch.md``) — reading, checking and writing map files — is
at the file layer, :mod:`btmission.spec.topomap`; this module is the map the algorithms use.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

from btmission import limits
from btmission.errors import BtmissionError


class NodeKind(IntEnum):
    """The three disjoint node sets of §3.1: terminals T, pause nodes S, transit nodes Q."""

    TERMINAL = 0
    PAUSE = 1
    TRANSIT = 2


class TopoMapError(BtmissionError, ValueError):
    """The map is not usable (unknown node, loop, disconnected, bad time...).

    ``path`` is the item in the map file the problem is about, when there is one.
    """

    def __init__(self, message: str, path: Sequence[str | int] = ()) -> None:
        super().__init__(message)
        self.path = tuple(path)


@dataclass(frozen=True)
class Node:
    """One node: its name, kind, whether it is a prioritised terminal, plot position and group."""

    name: str
    kind: NodeKind
    prioritized: bool = False
    xy: tuple[float, float] | None = None
    group: str = ""
    """Free label (e.g. ``left``/``right`` for the static benchmark map's two halves)."""


@dataclass(frozen=True)
class Segment:
    """A segment pair: the segments a→b and b→a, with their traversal times in seconds."""

    a: str
    b: str
    t_ab: float
    t_ba: float


@dataclass(frozen=True, eq=False)
class TopoMap:
    """A checked, loop-free topological map with its path matrix Π0.

    Build with :meth:`build` (or read a map file with
    :func:`btmission.spec.topomap.load_topomap`); the arrays are indexed by node index
    (the order the nodes were given in).
    """

    name: str
    nodes: tuple[Node, ...]
    segments: tuple[Segment, ...]
    index: Mapping[str, int]
    kind: NDArray[np.int8]
    """Node kind (:class:`NodeKind` values) per node."""
    prioritized: NDArray[np.bool_]
    """True for prioritised terminals (T^P)."""
    ttime: NDArray[np.float64]
    """``ttime[i, j]``: traversal time of segment i→j in s; ``inf`` when i and j are not joined."""
    edge: NDArray[np.int32]
    """``edge[i, j]``: index of the segment pair joining i and j, -1 if none."""
    neighbors: tuple[tuple[int, ...], ...]
    next_hop: NDArray[np.int32]
    """Path matrix: ``next_hop[i, j]`` is the node after i on Π0(i, j) (``j`` itself if adjacent,
    -1 on the diagonal)."""
    dist: NDArray[np.float64]
    """``dist[i, j]``: traversal time of Π0(i, j) in s."""
    hops: NDArray[np.int32]
    """``hops[i, j]``: number of segments (mission items) on Π0(i, j)."""
    description: str = ""
    pause_neighbors: tuple[tuple[int, ...], ...] = field(default=())
    """For each node, its adjacent pause nodes (used by the pause-visit insertion of Alg. 3)."""
    is_pause: tuple[bool, ...] = field(default=())
    """Per node: a pause node? (a tuple: the GA's mutations index it in tight Python loops)."""
    is_transit: tuple[bool, ...] = field(default=())

    # ----------------------------------------------------------------------------- building
    @classmethod
    def build(
        cls,
        name: str,
        nodes: Sequence[Node],
        segments: Sequence[Segment],
        description: str = "",
    ) -> TopoMap:
        """Check the graph and compute Π0. Raises :class:`TopoMapError` naming the problem.

        Checks: at least two nodes, unique names, segment ends exist, no self-loop or repeated
        segment, times > 0, connected, loop-free (the loop's nodes are named).
        """
        budget = limits.MAX_TOPOMAP_NODES
        if len(nodes) > budget.limit:  # Π0 is n × n: time and memory grow with n²
            raise TopoMapError(budget.exceeded("the number of nodes", len(nodes)), ("nodes",))
        if len(nodes) < 2:
            raise TopoMapError("a map needs at least two nodes", ("nodes",))
        index: dict[str, int] = {}
        for i, nd in enumerate(nodes):
            if nd.name in index:
                raise TopoMapError(f"duplicate node '{nd.name}'", ("nodes", nd.name))
            if nd.prioritized and nd.kind is not NodeKind.TERMINAL:
                raise TopoMapError(
                    f"node '{nd.name}': only terminals can be prioritized", ("nodes", nd.name)
                )
            index[nd.name] = i
        n = len(nodes)
        ttime = np.full((n, n), np.inf)
        edge = np.full((n, n), -1, dtype=np.int32)
        adj: list[list[int]] = [[] for _ in range(n)]
        parent = list(range(n))  # union-find for the loop check

        def root(x: int) -> int:
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        for k, s in enumerate(segments):
            where = ("segments", k)
            for end in (s.a, s.b):
                if end not in index:
                    raise TopoMapError(f"segment {s.a}-{s.b}: unknown node '{end}'", where)
            a, b = index[s.a], index[s.b]
            if a == b:
                raise TopoMapError(f"segment {s.a}-{s.b} joins a node to itself", where)
            if edge[a, b] >= 0:
                raise TopoMapError(f"segment {s.a}-{s.b} is given twice", where)
            for t in (s.t_ab, s.t_ba):
                if not (np.isfinite(t) and t > 0):
                    raise TopoMapError(
                        f"segment {s.a}-{s.b}: traversal times must be > 0 s (got {t})", where
                    )
            ra, rb = root(a), root(b)
            if ra == rb:
                loop = _tree_path(adj, a, b)
                names = " → ".join(nodes[i].name for i in [*loop, b])
                raise TopoMapError(
                    f"segment {s.a}-{s.b} closes a loop ({names}); maps must be loop-free "
                    "(seed 004 §3.1)",
                    where,
                )
            parent[ra] = rb
            ttime[a, b], ttime[b, a] = s.t_ab, s.t_ba
            edge[a, b] = edge[b, a] = k
            adj[a].append(b)
            adj[b].append(a)
        comps = {root(i) for i in range(n)}
        if len(comps) > 1:
            first = root(0)
            cut = sorted(nodes[i].name for i in range(n) if root(i) != first)
            raise TopoMapError(
                f"the map is not connected: {', '.join(cut[:8])}{' ...' if len(cut) > 8 else ''} "
                f"cannot be reached from {nodes[0].name}",
                ("segments",),
            )
        next_hop, dist, hops = _path_matrix(adj, ttime)
        kind = np.array([int(nd.kind) for nd in nodes], dtype=np.int8)
        pause_nb = tuple(tuple(j for j in adj[i] if kind[j] == NodeKind.PAUSE) for i in range(n))
        return cls(
            name=name,
            nodes=tuple(nodes),
            segments=tuple(segments),
            index=index,
            kind=kind,
            prioritized=np.array([nd.prioritized for nd in nodes], dtype=bool),
            ttime=ttime,
            edge=edge,
            neighbors=tuple(tuple(a) for a in adj),
            next_hop=next_hop,
            dist=dist,
            hops=hops,
            description=description,
            pause_neighbors=pause_nb,
            is_pause=tuple(bool(k == NodeKind.PAUSE) for k in kind),
            is_transit=tuple(bool(k == NodeKind.TRANSIT) for k in kind),
        )

    # ----------------------------------------------------------------------------- queries
    @property
    def n(self) -> int:
        """Number of nodes."""
        return len(self.nodes)

    def id(self, name: str) -> int:
        """Index of the node called ``name`` (KeyError with the known names otherwise)."""
        try:
            return self.index[name]
        except KeyError:
            raise KeyError(f"no node '{name}' in map '{self.name}'") from None

    def path(self, i: int, j: int) -> list[int]:
        """Π0(i, j) as node indices, both ends included."""
        out = [i]
        while i != j:
            i = int(self.next_hop[i, j])
            out.append(i)
        return out

    def nodes_of(self, kind: NodeKind, group: str | None = None) -> list[int]:
        """Indices of the nodes of ``kind`` (optionally only those of ``group``), in map order."""
        return [
            i
            for i, nd in enumerate(self.nodes)
            if nd.kind is kind and (group is None or nd.group == group)
        ]

    @property
    def terminals(self) -> list[int]:
        return self.nodes_of(NodeKind.TERMINAL)

    @property
    def pauses(self) -> list[int]:
        return self.nodes_of(NodeKind.PAUSE)


def _tree_path(adj: Sequence[Sequence[int]], a: int, b: int) -> list[int]:
    """The path from b to a in the forest ``adj`` (BFS), as a list starting at b."""
    prev = {b: -1}
    queue = deque([b])
    while queue:
        x = queue.popleft()
        if x == a:
            break
        for y in adj[x]:
            if y not in prev:
                prev[y] = x
                queue.append(y)
    out: list[int] = []
    x = a
    while x != -1:
        out.append(x)
        x = prev[x]
    return out[::-1]


def _path_matrix(
    adj: Sequence[Sequence[int]], ttime: NDArray[np.float64]
) -> tuple[NDArray[np.int32], NDArray[np.float64], NDArray[np.int32]]:
    """Π0 for a tree: one BFS per target node gives every node's next hop towards it."""
    n = len(adj)
    next_hop = np.full((n, n), -1, dtype=np.int32)
    dist = np.zeros((n, n))
    hops = np.zeros((n, n), dtype=np.int32)
    for target in range(n):
        seen = [False] * n
        seen[target] = True
        queue = deque([target])
        while queue:
            x = queue.popleft()
            for y in adj[x]:
                if not seen[y]:
                    seen[y] = True
                    next_hop[y, target] = x
                    dist[y, target] = ttime[y, x] + dist[x, target]
                    hops[y, target] = hops[x, target] + 1
                    queue.append(y)
    return next_hop, dist, hops
