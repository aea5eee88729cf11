"""Figures of the control examples (matplotlib, imported lazily; draw from logs, never compute).

Each ``plot_*`` function takes the log of a scenario in :mod:`~btmission.control.examples` (or a
DPHR result) and returns a matplotlib ``Figure``; :data:`FIGURES` maps the names used by
``btmission control plot NAME`` to a function that runs the scenario and draws it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from btmission.control.examples import (
    CorridorLog,
    ExplorationLog,
    FlightLog,
    HeadOnLog,
    corridor_flight,
    explore_tunnel,
    head_on,
    waypoint_flight,
)

__all__ = [
    "FIGURES",
    "plot_corridor",
    "plot_dphr",
    "plot_exploration",
    "plot_head_on",
    "plot_waypoint_flight",
]


def _figure(rows: int, cols: int, size: tuple[float, float]) -> tuple[Any, Any]:
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, no global state

    fig = Figure(figsize=size, layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    return fig, axes


def plot_waypoint_flight(log: FlightLog) -> Any:
    """Positions and the three inputs with their bounds (seed 002 eq. 1-2)."""
    from btmission.control.nmpc import NmpcConfig

    cfg = NmpcConfig()
    fig, ax = _figure(2, 2, (10, 6))
    t = np.arange(len(log.states)) * log.dt_s
    tu = t[:-1]
    for i, name in enumerate("xyz"):
        ax[0, 0].plot(t, log.states[:, i], label=name)
        ax[0, 0].axhline(log.goal[i], ls=":", color=f"C{i}")
    ax[0, 0].set(title="position (dotted: set-point)", xlabel="t [s]", ylabel="m")
    ax[0, 0].legend()
    ax[0, 1].plot(tu, log.inputs[:, 0])
    for bound in (cfg.thrust_min, cfg.thrust_max):
        ax[0, 1].axhline(bound, ls="--", color="grey")
    ax[0, 1].set(title="thrust T (dashed: bounds)", xlabel="t [s]", ylabel="m/s²")
    ax[1, 0].plot(tu, log.inputs[:, 1], label="φ_ref")
    ax[1, 0].plot(tu, log.inputs[:, 2], label="θ_ref")
    for bound in (-cfg.tilt_max_rad, cfg.tilt_max_rad):
        ax[1, 0].axhline(bound, ls="--", color="grey")
    ax[1, 0].set(title="attitude references", xlabel="t [s]", ylabel="rad")
    ax[1, 0].legend()
    rates = np.abs(np.diff(np.vstack([cfg.hover_input, log.inputs]), axis=0))[:, 1:]
    ax[1, 1].plot(tu, rates[:, 0], label="|Δφ_ref|")
    ax[1, 1].plot(tu, rates[:, 1], label="|Δθ_ref|")
    ax[1, 1].axhline(cfg.rate_max_rad, ls="--", color="grey")
    ax[1, 1].set(title="input change per step (eq. 2 limit dashed)", xlabel="t [s]", ylabel="rad")
    ax[1, 1].legend()
    return fig


def plot_corridor(log: CorridorLog) -> Any:
    """Top view of the corridor flight, the forces and the adaptive weight (eq. 3-4, Alg. 1)."""
    from btmission.control.apf import ApfConfig

    r_c = ApfConfig().r_critical_m
    fig, ax = _figure(3, 1, (10, 8))
    s = log.flight.states
    half = log.width_m / 2
    ax[0, 0].plot(s[:, 0], s[:, 1], label="MAV")
    for y in (-half, half):
        ax[0, 0].axhline(y, color="k")
    for y in (-half + r_c, half - r_c):
        ax[0, 0].axhline(y, color="r", ls=":")
    ax[0, 0].set(
        title="top view (walls black, r_c from the walls dotted)", xlabel="x [m]", ylabel="y [m]"
    )
    ax[0, 0].set_aspect("equal")
    t = np.arange(len(log.forces)) * log.flight.dt_s
    ax[1, 0].plot(t, np.linalg.norm(log.forces, axis=1), label="‖F‖ (≤ 1)")
    ax[1, 0].plot(t, np.linalg.norm(log.repulsive, axis=1), label="‖F^r_k‖ after Alg. 1")
    ax[1, 0].plot(t, np.minimum(log.repulsive_raw_norm, 5.0), label="‖F^r‖ eq. 3 (clipped at 5)")
    ax[1, 0].set(xlabel="t [s]", title="forces")
    ax[1, 0].legend(fontsize=8)
    ax[2, 0].plot(t, log.q_position, label="Q_p (eq. 4)")
    ax[2, 0].plot(
        np.arange(len(log.clearance)) * log.flight.dt_s, log.clearance, label="clearance [m]"
    )
    ax[2, 0].axhline(r_c, color="r", ls=":", label="r_c")
    ax[2, 0].set(xlabel="t [s]")
    ax[2, 0].legend(fontsize=8)
    return fig


def plot_head_on(log: HeadOnLog) -> Any:
    """Paths and distance of two unicycles passing head-on (seed 003 eq. 11-12)."""
    fig, ax = _figure(1, 2, (11, 4))
    ax[0, 0].plot(log.a[:, 0], log.a[:, 1], label="A →")
    ax[0, 0].plot(log.b[:, 0], log.b[:, 1], label="← B")
    ax[0, 0].set(title="paths (y exaggerated)", xlabel="x [m]", ylabel="y [m]")
    ax[0, 0].legend(loc="lower right")
    t = np.arange(len(log.distance)) * log.dt_s
    ax[0, 1].plot(t, log.distance, label="distance")
    ax[0, 1].axhline(log.r_obs_m, color="r", ls=":", label="r_obs")
    ax[0, 1].set(title=f"closest approach {log.distance.min():.3f} m", xlabel="t [s]", ylabel="m")
    ax[0, 1].legend()
    return fig


def plot_dphr(bend: str = "left") -> Any:
    """The depth image, the deepest cluster and its centroid (the paper's Fig. 3)."""
    from btmission.control.dphr import deepest_point_heading
    from btmission.control.scenes import bending_tunnel, depth_image

    img = depth_image(bending_tunnel(bend), [0.0, 0.0, 1.5], noise_m=0.02, dropout=0.05)
    res = deepest_point_heading(img)
    fig, ax = _figure(1, 2, (11, 4))
    shown = ax[0, 0].imshow(img, cmap="viridis")
    fig.colorbar(shown, ax=ax[0, 0], label="depth [m] (0 = no return)")
    ax[0, 0].plot(*res.centroid, "o", ms=12, mfc="none", mec="w", mew=2)
    ax[0, 0].axvline((img.shape[1] - 1) / 2, color="w", ls=":")
    ax[0, 0].set(title=f"tunnel bending {bend}: ψ̇_ref = {res.yaw_rate:+.3f} rad/s")
    ax[0, 1].imshow(res.mask, cmap="gray")
    ax[0, 1].set(title="deepest k-means cluster (reduced image)")
    return fig


def plot_exploration(log: ExplorationLog) -> Any:
    """Top view of a COMPRA run: outbound path, breadcrumbs and the return (Alg. 2)."""
    fig, ax = _figure(1, 1, (7, 7))
    a = ax[0, 0]
    a.plot(*log.tunnel_left.T, "k")
    a.plot(*log.tunnel_right.T, "k")
    modes = np.array([*log.modes, log.modes[-1]])
    for mode, colour in (("explore", "C0"), ("return", "C1")):
        sel = modes[: len(log.positions)] == mode
        a.plot(log.positions[sel, 0], log.positions[sel, 1], ".", color=colour, ms=4, label=mode)
    if len(log.breadcrumbs):
        a.plot(log.breadcrumbs[:, 0], log.breadcrumbs[:, 1], "x", color="C3", label="breadcrumbs")
    a.plot(*log.positions[-1, :2], "v", color="k", ms=10, label="land")
    reach = np.abs(log.positions[:, :2]).max() + 3
    a.set(
        xlim=(-5, reach),
        ylim=(-reach, reach),
        title="COMPRA: explore, return, land",
        xlabel="x [m]",
        ylabel="y [m]",
    )
    a.set_aspect("equal")
    a.legend()
    return fig


FIGURES: dict[str, Callable[[], Any]] = {
    "nmpc": lambda: plot_waypoint_flight(waypoint_flight()),
    "apf": lambda: plot_corridor(corridor_flight()),
    "dphr": plot_dphr,
    "unicycle": lambda: plot_head_on(head_on()),
    "compra": lambda: plot_exploration(explore_tunnel()),
}
"""Name → run the scenario and draw it."""
