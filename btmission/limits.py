"""Resource budgets: how much any input file or option may make btmission read, build or run.

A hostile or mistaken input (a YAML "billion laughs", a zip bomb posing as a voxel map, a map of
10 km at 1 cm) must be refused with a message naming the limit, before the memory or the time is
spent. Each budget has a default that covers every real mission we know of by a wide margin, and
an environment variable that raises (or lowers) it, e.g. ``BTMISSION_MAX_VOXELS=200000000``.
The table of budgets is in docs/mission-format.md ("Limits").

The values are read from the environment each time they are used, so a test or a shell can change
them without reloading anything. A value that is not a positive number is ignored (with one
warning on stderr) and the default applies.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Budget:
    """One named limit: its default, the environment variable that overrides it, what it bounds."""

    env: str
    default: float
    what: str
    integer: bool = True

    @property
    def value(self) -> float:
        """The limit in force: the environment's value when it is a positive number, else the
        default."""
        text = os.environ.get(self.env)
        if text is None or not text.strip():
            return self.default
        try:
            v = float(text.replace("_", ""))
        except ValueError:
            v = math.nan
        if not (math.isfinite(v) and v > 0 and (not self.integer or v == int(v))):
            _warn_once(f"btmission: ignoring {self.env}={text!r} (expected a positive "
                       f"{'whole ' if self.integer else ''}number); using {self.show(self.default)}")  # fmt: skip
            return self.default
        return int(min(v, _LARGEST)) if self.integer else v

    @property
    def limit(self) -> int:
        """The limit as a whole number (for the integer budgets)."""
        return int(self.value)

    def show(self, v: float | None = None) -> str:
        v = self.value if v is None else v
        return f"{int(v):,}" if self.integer else f"{v:g}"

    def exceeded(self, what: str, got: float) -> str:
        """``"<what> is <got>, the limit is <limit> (raise it with BTMISSION_...)"``."""
        shown = f"{int(got):,}" if self.integer and got == int(got) else f"{got:g}"
        return f"{what} is {shown}, the limit is {self.show()} (set {self.env} to change it)"


_LARGEST = 2**62
"""Integer budgets are capped here: "no limit" in effect, and still a valid size for read()."""

_warned: set[str] = set()


def _warn_once(message: str) -> None:
    if message not in _warned:
        _warned.add(message)
        print(message, file=sys.stderr)


# ------------------------------------------------------------------------------------ budgets
MAX_FILE_BYTES = Budget(
    "BTMISSION_MAX_FILE_BYTES", 4_000_000, "size of a library, mission or topological map YAML file"
)
MAX_YAML_ALIAS_NODES = Budget(
    "BTMISSION_MAX_YAML_ALIAS_NODES",
    100_000,
    "items a YAML file may repeat through aliases (*name), counted after expansion",
)
MAX_YAML_DEPTH = Budget("BTMISSION_MAX_YAML_DEPTH", 100, "nesting depth of a YAML file")
MAX_VOXELS = Budget(
    "BTMISSION_MAX_VOXELS",
    40_000_000,
    "voxels of a map (generated, loaded or voxelized from a point cloud), and elements of any "
    "array in a map or place database file",
)
MAX_POINTS = Budget(
    "BTMISSION_MAX_POINTS", 20_000_000, "points of a point cloud (.ply, .pcd, place database)"
)
MAX_TOPOMAP_NODES = Budget(
    "BTMISSION_MAX_TOPOMAP_NODES",
    2_000,
    "nodes of a topological map (the path matrix is nodes × nodes: 3,000 nodes took 12 s and "
    "320 MB, 20,000 would need 1.5 GB for one of its arrays)",
)
MAX_AGENTS = Budget("BTMISSION_MAX_AGENTS", 1_000, "agents of a mission")
MAX_TASKS = Budget("BTMISSION_MAX_TASKS", 10_000, "tasks of a mission")
MIN_STEP_S = Budget(
    "BTMISSION_MIN_STEP_S", 0.001, "smallest simulator time step runtime.sim.step_s (s)", False
)
MAX_TEXT_CHARS = Budget(
    "BTMISSION_MAX_TEXT_CHARS", 1_000_000, "characters of a text field in a .npz file (meta...)"
)
MAX_LOG_BYTES = Budget(
    "BTMISSION_MAX_LOG_BYTES", 1_000_000_000, "size of an event log that `report` reads"
)
MAX_MESSAGE_BYTES = Budget(
    "BTMISSION_MAX_MESSAGE_BYTES",
    16_000_000,
    "size of one coordinator/agent message on the wire (an announcement of 10,000 tasks is "
    "about 1.5 MB)",
)
MAX_REQUEST_BYTES = Budget(
    "BTMISSION_MAX_REQUEST_BYTES", 65_536, "size of one request body to the operator console"
)

BUDGETS: tuple[Budget, ...] = (
    MAX_FILE_BYTES,
    MAX_YAML_ALIAS_NODES,
    MAX_YAML_DEPTH,
    MAX_VOXELS,
    MAX_POINTS,
    MAX_TOPOMAP_NODES,
    MAX_AGENTS,
    MAX_TASKS,
    MIN_STEP_S,
    MAX_TEXT_CHARS,
    MAX_LOG_BYTES,
    MAX_MESSAGE_BYTES,
    MAX_REQUEST_BYTES,
)


# ------------------------------------------------------------------------------------ checks
def grid_shape(size: Sequence[float], resolution: float) -> tuple[int, int, int]:
    """The voxel grid shape of ``size`` metres at ``resolution`` m (each side rounded up).

    Raises :class:`ValueError` with a message for the user when a number is not finite and
    positive, or the grid would hold more than :data:`MAX_VOXELS` voxels (checked before anything
    is allocated)."""
    if len(size) != 3:
        raise ValueError(f"size must be three numbers [x, y, z] in metres, got {list(size)}")
    vals = [float(v) for v in size]
    if not all(math.isfinite(v) and v > 0 for v in vals):
        raise ValueError(f"size must be three finite numbers > 0 (m), got {_nums(vals)}")
    res = float(resolution)
    if not (math.isfinite(res) and res > 0):
        raise ValueError(f"resolution must be a finite number > 0 (m), got {res:g}")
    if not all(math.isfinite(v / res) for v in vals):  # 1e300 m at 1e-300 m
        raise ValueError(
            f"{_nums(vals)} m at {res:g} m makes more voxels than can be counted; the limit is "
            f"{MAX_VOXELS.show()} (set {MAX_VOXELS.env} to change it)"
        )
    shape = tuple(max(1, math.ceil(v / res - 1e-9)) for v in vals)
    check_voxels(shape, f"{_nums(vals)} m at {res:g} m")
    return shape[0], shape[1], shape[2]


def check_voxels(shape: Sequence[int], what: str = "the map") -> None:
    """Raise :class:`ValueError` when a grid of ``shape`` exceeds :data:`MAX_VOXELS`."""
    n = math.prod(int(s) for s in shape)
    if n > MAX_VOXELS.limit:
        dims = " × ".join(_count(int(s)) for s in shape)
        raise ValueError(
            f"{what} makes {dims} = {_count(n)} voxels; the limit is {MAX_VOXELS.show()} "
            f"(set {MAX_VOXELS.env} to change it)"
        )


def _count(n: int) -> str:
    """``1,234,567``; past 10^15 ``1.23e+301`` (a 300-digit count helps nobody)."""
    if n < 10**15:
        return f"{n:,}"
    digits = str(n)  # not float(n): it overflows past 1e308
    return f"{digits[0]}.{digits[1:3]}e+{len(digits) - 1}"


def _nums(vals: Sequence[float]) -> str:
    return " × ".join(f"{v:g}" for v in vals)
