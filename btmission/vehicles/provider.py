"""Where vehicles come from: the :class:`VehicleProvider` interface and its registry.

A run never builds vehicles itself. Each agent's ``backend:`` in the mission is a URL (``sim``,
``mavlink+udp://127.0.0.1:14540`` ...); its **scheme** (``sim``, ``mavlink``) names a provider,
registered in the ``btmission.providers`` entry-point group like capability libraries are in
``btmission.libraries`` (docs/providers.md)::

    [project.entry-points."btmission.providers"]
    sim = "btmission.backends.sim:sim_provider"

The entry point's object is a :data:`ProviderFactory`: called with the mission, its map and the
run's seed, it returns the :class:`VehicleProvider` for the run. The provider then

* :meth:`~VehicleProvider.attach`\\ es one :class:`Vehicle` per agent: its
  :class:`~btmission.vehicles.base.Backend` (commands, setpoints, telemetry), its
  :class:`~btmission.vehicles.base.Sensors` if it has any, and — in a simulator only — ground
  truth the report uses (odometer, clearance to the rock);
* owns the run's :attr:`~VehicleProvider.clock`: simulated time for the simulator, the wall clock
  (with :attr:`~VehicleProvider.realtime` True) for real vehicles;
* is :meth:`~VehicleProvider.step`\\ ped once per runner step: the simulator integrates its
  physics by ``dt`` and reports collisions; a real provider pumps its inbox (or does nothing:
  real time passes on its own);
* is :meth:`~VehicleProvider.close`\\ d at the end (sockets, threads).

Two optional methods a real provider may have: ``prepare(urls)``, called with every agent's URL
before the first ``attach`` (open all links at once, so vehicles boot together), and ``start()``,
called once every vehicle is attached (the mission's time starts: the clock restarts at zero).

One run has one clock, so every agent of a mission uses the same provider (scheme): simulated
time cannot be mixed with the wall clock
(:func:`btmission.runtime.runcheck.backend_problems` refuses such a fleet).
Entry points are loaded only when a run is built; ``validate`` just looks the scheme up.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import metadata
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from btmission.errors import BtmissionError
from btmission.types import Vec3
from btmission.vehicles.base import Backend, Sensors, VehicleKind

if TYPE_CHECKING:
    from btmission.spec.mission import Mission
    from btmission.vehicles.clock import Clock
    from btmission.world.voxel import VoxelMap

ENTRY_POINT_GROUP = "btmission.providers"


def scheme_of(backend: str) -> str:
    """The provider scheme of an agent's ``backend:`` URL: ``mavlink+udp://…`` → ``mavlink`` (a
    ``+transport`` suffix picks the provider's transport, not another provider),
    ``sim`` → ``sim``."""
    return backend.split("://", 1)[0].split("+", 1)[0]


@dataclass(frozen=True)
class VehicleEvent:
    """Something the provider detected while stepping: a ``collision`` of ``vehicle`` with
    ``other`` (``rock`` or another vehicle's id) at ``position``."""

    time_s: float
    vehicle: str
    kind: str
    other: str
    position: tuple[float, float, float]


@dataclass(frozen=True)
class Vehicle:
    """One agent's vehicle, as a provider hands it out."""

    id: str
    kind: VehicleKind
    backend: Backend
    sensors: Sensors | None = None
    odometer_m: Callable[[], float] | None = None
    """Ground truth: distance travelled so far (m). None on a real robot."""
    clearance_m: Callable[[], float | None] | None = None
    """Ground truth: smallest clearance to the rock since the last call (None: nothing near).
    None (no hook) on a real robot."""
    link_ok: Callable[[], bool] | None = None
    """Whether the vehicle is heard (its autopilot's heartbeats arrive); None when the link
    cannot fail (a simulator in this process). While it is False the agent's tree pauses."""


@runtime_checkable
class VehicleProvider(Protocol):
    """Creates or connects the vehicles of a run, owns its clock and advances it (module
    docstring)."""

    clock: Clock
    """The run's time: :class:`~btmission.vehicles.clock.SimClock` in a simulator,
    :class:`~btmission.vehicles.clock.WallClock` with real vehicles."""
    realtime: bool
    """True when time passes on its own (real vehicles): the runner paces its steps against
    the wall clock instead of running as fast as it can."""

    def attach(
        self, agent_id: str, kind: VehicleKind, start: Vec3, *, url: str = "", **options: Any
    ) -> Vehicle:
        """The vehicle of ``agent_id``: spawned at ``start`` (a simulator) or connected at
        ``url`` (the agent's ``backend:``; a real vehicle is where it is). ``options`` are
        provider-specific (the simulator's ``v_max`` for a ground robot); unknown ones are
        ignored."""
        ...

    def step(self, dt: float) -> Sequence[VehicleEvent]:
        """Advance by ``dt`` seconds: the simulator integrates its physics; a real provider
        pumps its inbox or does nothing. Returns what happened meanwhile (collisions)."""
        ...

    def close(self) -> None:
        """Release sockets, threads and vehicles (idempotent)."""
        ...


ProviderFactory = Callable[["Mission", "VoxelMap", int], VehicleProvider]
"""What a ``btmission.providers`` entry point names: ``factory(mission, voxel_map, seed)``."""


BUILT_IN = {
    "sim": "btmission.backends.sim:sim_provider",
    "fake": "btmission.backends.fake:fake_provider",
    "mavlink": "btmission.backends.mavlink:mavlink_provider",
}
"""Providers of the core package, found even by an install made before the entry-point group
existed (an editable install is not re-read until it is reinstalled); also declared in
pyproject.toml."""


def installed_providers() -> dict[str, metadata.EntryPoint]:
    """Every provider by scheme (not loaded): the built-in ``sim``, ``fake`` and ``mavlink``, and the
    ``btmission.providers`` entry points. A scheme registered twice (the same distribution seen from two paths, or a
    plugin claiming ``sim``) counts once: the first one found."""
    out = {
        name: metadata.EntryPoint(name, value, ENTRY_POINT_GROUP)
        for name, value in BUILT_IN.items()
    }
    for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        out.setdefault(ep.name, ep)
    return out


class VehicleUnavailable(BtmissionError, RuntimeError):
    """A provider could not give an agent its vehicle (nothing answers at its URL, a vehicle of
    the wrong type ...). ``run`` reports it at the agent's ``backend:`` line (exit 2)."""


class ProviderError(BtmissionError, LookupError):
    """No provider is installed for a scheme."""


def unknown_scheme_message(scheme: str, installed: Sequence[str]) -> str:
    known = ", ".join(f"'{s}'" for s in installed) or "none"
    return (
        f"no vehicle provider for scheme '{scheme}' is installed; "
        f"installed: {known} (entry-point group '{ENTRY_POINT_GROUP}')"
    )


def provider_factory(scheme: str) -> ProviderFactory:
    """Load the factory of ``scheme``'s provider (imports its module)."""
    eps = installed_providers()
    if scheme not in eps:
        raise ProviderError(unknown_scheme_message(scheme, list(eps)))
    factory: ProviderFactory = eps[scheme].load()
    return factory
