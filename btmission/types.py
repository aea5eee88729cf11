"""Value types shared across layers: one definition each, no behaviour.

Everything here is plain data that both the vehicle interface (:mod:`btmission.vehicles.base`)
and the algorithms (:mod:`btmission.control`, :mod:`btmission.localization` ...) use, so that the
interface does not have to import an algorithm to name its types:

* :data:`FloatArray` — a NumPy array of ``float64`` (positions, velocities, point clouds);
* :data:`Vec3` — a world-frame 3-vector as a plain tuple (metres, z up);
* :class:`CameraIntrinsics` and :class:`Detection` — what a depth camera and an object detector
  deliver (the inputs of the seed 002 object localiser, :mod:`btmission.control.compra`);
* :func:`recorder` and :func:`record` — a frozen dataclass built without its per-field
  assignment (records a run builds by the thousand per second).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar, cast

import numpy as np
from numpy.typing import NDArray

__all__ = ["CameraIntrinsics", "Detection", "FloatArray", "Vec3", "record", "recorder"]

_R = TypeVar("_R")


def recorder(cls: type[_R]) -> Callable[..., _R]:
    """A builder of ``cls``, a frozen dataclass: ``recorder(cls)(**fields)`` is
    ``cls(**fields)`` minus the generated ``__init__``'s ``object.__setattr__`` per field (a
    12-field record: about half the time). Its arguments are keyword-only and named after the
    fields, so a missing or unknown field raises the ``TypeError`` the dataclass would. Made
    once per class (and kept); every field must be given, its default too. A class it cannot
    build that way (``slots``, a ``__post_init__``, an ``InitVar`` or a field out of
    ``__init__``) gets ``cls`` itself."""
    built = _RECORDERS.get(cls)
    if built is not None:
        return built
    declared = getattr(cls, "__dataclass_fields__", {})
    fields = dataclasses.fields(cast(Any, cls)) if declared else ()  # (no ClassVar pseudo-fields)
    names = tuple(f.name for f in fields)
    if (
        not names
        or hasattr(cls, "__post_init__")
        or "__slots__" in cls.__dict__
        or any(not f.init for f in fields)
        or any(f._field_type is dataclasses._FIELD_INITVAR for f in declared.values())  # type: ignore[attr-defined]
        or not all(n.isidentifier() and not n.startswith("_") for n in names)
    ):
        built = cls
    else:
        src = (
            f"def {cls.__name__}(*, {', '.join(names)}):\n"
            "    out = new(cls)\n"
            "    d = out.__dict__\n"
            + "".join(f"    d[{n!r}] = {n}\n" for n in names)
            + "    return out\n"
        )
        scope: dict[str, Any] = {"new": object.__new__, "cls": cls}
        exec(src, scope)  # (the dataclasses module makes __init__ the same way)
        built = scope[cls.__name__]
        built.__qualname__ = f"recorder({cls.__qualname__})"
    _RECORDERS[cls] = built
    return built


_RECORDERS: dict[type[Any], Callable[..., Any]] = {}


def record(cls: type[_R], **fields: Any) -> _R:
    """``cls(**fields)`` through :func:`recorder` (hot paths keep ``recorder(cls)`` and call it
    directly: this adds a dictionary of the keywords)."""
    return recorder(cls)(**fields)


FloatArray = NDArray[np.float64]
"""A NumPy array of float64."""

Vec3 = tuple[float, float, float]
"""A 3-vector (x, y, z) as a plain tuple."""


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of the depth image the boxes are aligned to (pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError("focal lengths must be positive")


@dataclass(frozen=True)
class Detection:
    """One detector output: class, probability Pr_CL and BB = (x_min, y_min, Wd, Ht) in pixels."""

    t: float
    label: str
    probability: float
    bbox: tuple[float, float, float, float]
