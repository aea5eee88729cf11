"""The benchmark maps of seed 004, rebuilt from the paper's descriptions (the paper gives figures,
not coordinates, so these are our reconstructions; ``docs/dispatch.md`` shows and explains them).

``static_map("npr" | "spr")`` — Fig. 6, the static planning benchmark: six terminals on each half
of the map, each reached by a short branch off a trunk; the two trunks meet in a single-lane
central bottleneck W0 — M — E0 ("when the vehicles cross the bottleneck in the middle", §6.1.2):
no pause node inside it, so trucks can only pass each other at its ends (pause nodes PW0, PE0)
or further out, where a pause node hangs off every trunk node. Vehicles moving right to left
(loaded) take twice as long per segment as those moving left to right (§6.1).
In the SPR variant the left terminals are prioritised; in NPR none are. A terminal-to-terminal path
has 8-12 segments (10 on average; the paper's averages imply about 11).

``mine_map()`` — Fig. 1, the dynamic planning mine: a single prioritised offloading site O at the
top, three pause nodes near it, a steep spiralling ramp (six segments, two passing bays) down to
the mining level, where a drive with three junctions leads to six loading sites. Speeds (§6.2):
30 km/h outbound, 20 km/h inbound, 10 km/h inbound on the ramp; pause-node spurs 20 km/h both ways.
Typical traversals: ~6-7 min outbound, ~14-15 min inbound (the paper: ~500 s and ~800 s).

``mine_table6`` — the same mine with every distance scaled by :data:`TABLE6_SCALE` = 0.7, a
*calibration* to Table 6: its two-truck row (C = 23.7 traversals in 14,400 s, i_t + i_p = 0.059,
loading 2-5 min and offloading 30-60 s, 255 s per round trip on average) leaves 14,400 ×
(1 − 0.059) / 11.85 − 255 ≈ 888 s of driving per round trip (the 3-5 truck rows give 925-940 s,
pause-spur detours included); ``mine`` drives 1,249 s per round trip (mean over the six loading
sites of Π0 out and back), so 0.7 × 1,249 = 874 s. The paper's text ("outbound on the order of
500 s, inbound on the order of 800 s", 1,300 s) disagrees with its own Table 6 unless those
traversal times include the waits on the way (the text says the outbound one does): Table 6's
five-truck row gives 14,400 × (1 − 0.074) / 8.7 − 255 ≈ 1,278 s per round trip, waits included.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import replace

from btmission.dispatch.topomap import Node, NodeKind, Segment, TopoMap

KMH = 1.0 / 3.6
"""m/s per km/h."""

TABLE6_SCALE = 0.7
"""Distance scale of ``mine_table6``: Table 6's ≈ 888 s of driving per round trip over ``mine``'s
1,249 s (see the module docstring; a calibration, not a number the paper gives)."""


def _dist(a: Node, b: Node) -> float:
    assert a.xy is not None and b.xy is not None
    return math.hypot(a.xy[0] - b.xy[0], a.xy[1] - b.xy[1])


def _components_without(
    names: Sequence[str], edges: Sequence[tuple[str, str]], cut: int
) -> dict[str, int]:
    """Component label of every node once edge ``cut`` is removed (for orienting segments)."""
    adj: dict[str, list[str]] = {n: [] for n in names}
    for k, (a, b) in enumerate(edges):
        if k != cut:
            adj[a].append(b)
            adj[b].append(a)
    label: dict[str, int] = {}
    for start in names:
        if start in label:
            continue
        stack = [start]
        label[start] = len(set(label.values()))
        while stack:
            x = stack.pop()
            for y in adj[x]:
                if y not in label:
                    label[y] = label[start]
                    stack.append(y)
    return label


def _holds(
    names: Sequence[str], edges: Sequence[tuple[str, str]], k: int, targets: Iterable[str]
) -> tuple[bool, bool]:
    """Whether the a-side and the b-side of edge k (once cut) hold any of ``targets``."""
    label = _components_without(names, edges, k)
    a, b = edges[k]
    t = set(targets)
    return any(label[x] == label[a] for x in t), any(label[x] == label[b] for x in t)


def static_map(variant: str = "npr", speed_mps: float = 2.5, slow_factor: float = 2.0) -> TopoMap:
    """Fig. 6 (see the module docstring). ``variant``: ``npr`` or ``spr`` (left terminals prioritised)."""
    if variant not in ("npr", "spr"):
        raise ValueError(f"unknown static map variant '{variant}' (expected npr or spr)")
    # M is a corridor point of the single-lane bottleneck W0 — M — E0: no pause node there
    nodes: list[Node] = [Node("M", NodeKind.TRANSIT, xy=(0.0, 0.0))]
    edges: list[tuple[str, str]] = []
    for side, sign, tag in (("left", -1.0, "W"), ("right", 1.0, "E")):
        prev = "M"
        for k in range(4):
            x = sign * 15.0 * (k + 1)
            trunk = f"{tag}{k}"
            nodes.append(Node(trunk, NodeKind.TRANSIT, xy=(x, 0.0)))
            edges.append((prev, trunk))
            pause = f"P{tag}{k}"
            nodes.append(Node(pause, NodeKind.PAUSE, xy=(x + sign * 5.0, -8.0)))
            edges.append((trunk, pause))
            if k > 0:
                for branch, dy in (("n", 1.0), ("s", -1.0)):
                    mid = f"{tag}{k}{branch}"
                    term = f"{'L' if side == 'left' else 'R'}{k}{branch}"
                    nodes.append(Node(mid, NodeKind.TRANSIT, xy=(x, dy * 12.0)))
                    prio = variant == "spr" and side == "left"
                    nodes.append(Node(term, NodeKind.TERMINAL, prio, xy=(x, dy * 24.0), group=side))
                    edges += [(trunk, mid), (mid, term)]
            prev = trunk
    names = [n.name for n in nodes]
    by_name = {n.name: n for n in nodes}
    lefts = [n.name for n in nodes if n.group == "left"]
    rights = [n.name for n in nodes if n.group == "right"]
    segs = []
    for k, (a, b) in enumerate(edges):
        fast = round(_dist(by_name[a], by_name[b]) / speed_mps, 3)
        a_right, b_right = _holds(names, edges, k, rights)
        a_left, b_left = _holds(names, edges, k, lefts)
        # a→b is leftward when it lies on a right-terminal → left-terminal path
        t_ab = fast * slow_factor if (a_right and b_left) else fast
        t_ba = fast * slow_factor if (b_right and a_left) else fast
        segs.append(Segment(a, b, t_ab, t_ba))
    desc = (
        "Seed 004 Fig. 6 static benchmark map "
        + ("(SPR: left terminals prioritised)" if variant == "spr" else "(NPR: no priorities)")
        + "; right-to-left segments take twice as long"
    )
    return TopoMap.build(f"static_{variant}", nodes, segs, desc)


def mine_map(scale: float = 1.0, name: str = "mine") -> TopoMap:
    """Fig. 1 (see the module docstring): the dynamic planning mine. ``scale`` multiplies every
    distance (and so every traversal time; the speeds stay §6.2's)."""
    if scale <= 0:
        raise ValueError("the mine's scale must be > 0")
    out_v, in_v, ramp_in_v = 30 * KMH, 20 * KMH, 10 * KMH
    nodes: list[Node] = [
        Node("O", NodeKind.TERMINAL, True, xy=(0.0, 0.0)),
        Node("J0", NodeKind.TRANSIT, xy=(100.0, 0.0)),
        Node("P0", NodeKind.PAUSE, xy=(100.0, 40.0)),
        Node("P1", NodeKind.PAUSE, xy=(100.0, -40.0)),
        Node("J1", NodeKind.TRANSIT, xy=(200.0, 0.0)),
        Node("P2", NodeKind.PAUSE, xy=(200.0, 40.0)),
        Node("R0", NodeKind.TRANSIT, xy=(300.0, 0.0)),
    ]
    edges: list[tuple[str, str]] = [("O", "J0"), ("J0", "P0"), ("J0", "P1"), ("J0", "J1")]
    edges += [("J1", "P2"), ("J1", "R0")]
    ramp = ["R0"]
    for k in range(1, 7):  # a spiral drawn as a zig-zag going down
        x = 300.0 + (250.0 if k % 2 else 0.0)
        nodes.append(Node(f"R{k}", NodeKind.TRANSIT, xy=(x, -120.0 * k)))
        edges.append((ramp[-1], f"R{k}"))
        ramp.append(f"R{k}")
    for k in (2, 4):  # passing bays on the ramp, 40 m off it
        nodes.append(Node(f"PR{k}", NodeKind.PAUSE, xy=(340.0, -120.0 * k)))
        edges.append((f"R{k}", f"PR{k}"))
    prev = "R6"
    for k in range(1, 4):
        junction = f"M{k}"
        x = 300.0 + 500.0 * k
        nodes.append(Node(junction, NodeKind.TRANSIT, xy=(x, -720.0)))
        edges.append((prev, junction))
        for branch, dy in (("n", 1.0), ("s", -1.0)):
            nodes.append(Node(f"L{k}{branch}", NodeKind.TERMINAL, xy=(x, -720.0 + dy * 200.0)))
            edges.append((junction, f"L{k}{branch}"))
        prev = junction
    nodes.append(Node("PM1", NodeKind.PAUSE, xy=(1000.0, -760.0)))
    edges.append(("M1", "PM1"))
    # shift into positive coordinates (the simulator's voxel mine starts at the origin)
    nodes = [
        replace(n, xy=(scale * n.xy[0] + 50.0, scale * (n.xy[1] + 1000.0))) if n.xy else n
        for n in nodes
    ]
    names = [n.name for n in nodes]
    by_name = {n.name: n for n in nodes}
    ramp_edges = {frozenset((ramp[i], ramp[i + 1])) for i in range(len(ramp) - 1)}
    segs = []
    for k, (a, b) in enumerate(edges):
        d = _dist(by_name[a], by_name[b])
        if NodeKind.PAUSE in (by_name[a].kind, by_name[b].kind):
            segs.append(Segment(a, b, round(d / in_v, 2), round(d / in_v, 2)))
            continue
        a_has_o, b_has_o = _holds(names, edges, k, ["O"])
        inbound_v = ramp_in_v if frozenset((a, b)) in ramp_edges else in_v
        t_ab = d / (inbound_v if b_has_o else out_v)  # a→b towards O is inbound
        t_ba = d / (inbound_v if a_has_o else out_v)
        segs.append(Segment(a, b, round(t_ab, 2), round(t_ba, 2)))
    desc = (
        "Seed 004 Fig. 1 mine: prioritised offloading site O, pause nodes near it, a spiral ramp "
        "(R0-R6) to six loading sites; 30 km/h out, 20 km/h in, 10 km/h in on the ramp"
    )
    if scale != 1.0:
        desc += f"; distances scaled by {scale:g}"
    return TopoMap.build(name, nodes, segs, desc)


def mine_table6_map() -> TopoMap:
    """``mine`` scaled to the trip length Table 6 implies (:data:`TABLE6_SCALE`)."""
    return mine_map(TABLE6_SCALE, "mine_table6")


BUILTIN_MAPS = {
    "static_npr": lambda: static_map("npr"),
    "static_spr": lambda: static_map("spr"),
    "mine": mine_map,
    "mine_table6": mine_table6_map,
}
"""Maps known by name to the CLI (``--map static_npr``); any other ``--map`` is a YAML file."""
