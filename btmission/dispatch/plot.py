"""Pictures of fleet missions and maps (matplotlib, Agg backend, imported lazily).

:func:`gantt_png` draws a fleet mission as in seed 004 Fig. 3: one row per vehicle, a light-blue
box for every initial stop time and a green box for every segment traversal (darker for
prioritised missions), pause-node visits labelled, and an optional red line at the current time.
:func:`map_png` draws a topological map with the node colours of Fig. 1 (terminals red,
transit blue, pause yellow).
"""

from __future__ import annotations

import io
import textwrap
from collections.abc import Sequence
from typing import Any

from btmission.dispatch.evaluate import timeline
from btmission.dispatch.missions import Mission
from btmission.dispatch.topomap import NodeKind, TopoMap

STOP_COLOUR = "#9fd3f0"
MOVE_COLOUR = "#5cb85c"
PRIO_COLOUR = "#2e7d32"


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def gantt_png(
    tmap: TopoMap,
    fleet: Sequence[Mission | Sequence[Mission]],
    title: str = "",
    now: float | None = None,
    labels: list[str] | None = None,
) -> bytes:
    """A Fig. 3-style chart of ``fleet`` as PNG bytes: one row per vehicle, stops (with the
    pause node's name), drives, and prioritised drives in their own colour. A row may be one
    mission or a vehicle's successive missions."""
    plt = _pyplot()
    rows = [[m] if isinstance(m, Mission) else list(m) for m in fleet]
    n = len(rows)
    fig, ax = plt.subplots(figsize=(11, 0.55 * n + 1.4), dpi=110)
    t_max = 0.0
    for row, missions in enumerate(rows):
        y = n - 1 - row
        for m in missions:
            t_max = max(t_max, _gantt_row(ax, tmap, m, y))
    names = labels or [
        f"v{k + 1}: {tmap.nodes[ms[0].start].name}→{tmap.nodes[ms[-1].end].name}"
        for k, ms in enumerate(rows)
    ]
    ax.set_yticks(range(n))
    ax.set_yticklabels(list(reversed(names)), fontsize=8)
    ax.set_xlabel("time (s)")
    ax.set_xlim(0, max(t_max * 1.02, 1.0))
    if now is not None:
        ax.axvline(now, color="red", linewidth=1.5)
    ax.set_title(title or f"fleet mission on {tmap.name}", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    return _png(plt, fig)


def _gantt_row(ax: Any, tmap: TopoMap, m: Mission, y: float) -> float:
    """Draw one mission on row ``y``; returns its end time."""
    arr, dep = timeline(tmap, [int(x) for x in m.nodes], list(m.waits), m.t0)
    colour = PRIO_COLOUR if m.prioritized else MOVE_COLOUR
    for i in range(m.items):
        if dep[i] > arr[i]:
            ax.broken_barh([(arr[i], dep[i] - arr[i])], (y - 0.35, 0.7), color=STOP_COLOUR)
            if tmap.is_pause[int(m.nodes[i])]:
                ax.text(
                    (arr[i] + dep[i]) / 2, y, tmap.nodes[int(m.nodes[i])].name,
                    ha="center", va="center", fontsize=6,
                )  # fmt: skip
        ax.broken_barh(
            [(dep[i], arr[i + 1] - dep[i])], (y - 0.35, 0.7),
            facecolor=colour, edgecolor="white", linewidth=0.4,
        )  # fmt: skip
    return float(arr[-1])


def map_png(tmap: TopoMap, title: str = "") -> bytes:
    """The map with Fig. 1 colours (needs node positions ``xy``)."""
    plt = _pyplot()
    missing = [n.name for n in tmap.nodes if n.xy is None]
    if missing:
        raise ValueError(f"nodes without xy cannot be drawn: {', '.join(missing[:5])}")
    fig, ax = plt.subplots(figsize=(9, 6), dpi=110)
    colour = {NodeKind.TERMINAL: "#d9534f", NodeKind.TRANSIT: "#337ab7", NodeKind.PAUSE: "#f0c419"}
    for s in tmap.segments:
        a, b = tmap.nodes[tmap.id(s.a)].xy, tmap.nodes[tmap.id(s.b)].xy
        assert a is not None and b is not None
        ax.plot([a[0], b[0]], [a[1], b[1]], color="#888", linewidth=1, zorder=1)
    for nd in tmap.nodes:
        assert nd.xy is not None
        size = 90 if nd.prioritized else 50
        edge = "black" if nd.prioritized else "none"
        ax.scatter(*nd.xy, s=size, color=colour[nd.kind], edgecolors=edge, zorder=2)
        ax.annotate(nd.name, nd.xy, fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(textwrap.fill(title or tmap.description or tmap.name, 100), fontsize=9)
    ax.axis("off")
    fig.tight_layout()
    return _png(plt, fig)


def _png(plt: Any, fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()
