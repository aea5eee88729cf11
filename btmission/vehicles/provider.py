"""Where vehicles come from: the :class:`VehicleProvider` interface and its registry.

A run never builds vehicles itself. Each agent's ``backend:`` in the mission is read once, by
the file model, into a :class:`~btmission.spec.vehicleref.VehicleRef` (``sim``,
``mavlink+udp://127.0.0.1:14540`` ...); its **scheme** (``sim``, ``mavlink``) names a provider,
registered in the ``btmission.providers`` entry-point group like capability libraries are in
``btmission.libraries`` (docs/providers.md)::

    [project.entry-points."btmission.providers"]
    sim = "btmission.backends.sim_provider:sim_provider"

The entry point's object is a :class:`ProviderPlugin` — or just its :data:`ProviderFactory`:
called with the mission, its map and the run's seed, it returns the :class:`VehicleProvider` for
the run. Only the provider reads a reference's address: its plugin's ``check_address`` says
what is wrong with one before anything runs. The provider then

* is :meth:`~VehicleProvider.warm_up`\\ ed: it loads the compiled kernels its vehicles run in
  the loop (the simulator's model and LiDAR), so that the loop does not stall at its first
  steps;
* is :meth:`~VehicleProvider.prepare`\\ d with every agent's reference (a real provider opens
  all its links at once, so that vehicles boot together);
* :meth:`~VehicleProvider.attach`\\ es one :class:`Vehicle` per agent: its
  :class:`~btmission.vehicles.base.Backend` (commands, setpoints, telemetry), its
  :class:`~btmission.vehicles.base.Sensors` if it has any, and — in a simulator only — ground
  truth the report uses (odometer, clearance to the rock). A run asks for them all at once
  (:meth:`~VehicleProvider.attach_all`, one :class:`AttachRequest` per agent): a real provider
  connects every vehicle concurrently, so that a fleet connects in the time of its slowest
  vehicle, not of the sum (:class:`ProviderBase`'s attaches them one after the other);
* owns the run's :attr:`~VehicleProvider.clock`: simulated time for the simulator, the wall clock
  (with :attr:`~VehicleProvider.realtime` True) for real vehicles;
* is :meth:`~VehicleProvider.start`\\ ed once every vehicle is attached (the mission's time
  starts: a real provider's clock restarts at zero; the run reads the clock only from then on,
  and stamps what happens before, while vehicles connect, at 0);
* is :meth:`~VehicleProvider.step`\\ ped once per runner step: the simulator integrates its
  physics by ``dt`` and reports collisions; a real provider pumps its inbox (or does nothing:
  real time passes on its own);
* is :meth:`~VehicleProvider.close`\\ d at the end (sockets, threads).

Every provider has all these phases and the capability query (:data:`PHASES`);
:class:`ProviderBase` gives the ones a simulator need not write.

One run has one clock, so every agent of a mission uses the same provider (scheme): simulated
time cannot be mixed with the wall clock
(:func:`btmission.runtime.runcheck.backend_problems` refuses such a fleet).
Entry points are loaded when a run is built, and by ``validate`` for a reference with an
address (to check it).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from btmission.errors import BtmissionError
from btmission.spec.vehicleref import SIM, VehicleRef
from btmission.types import FloatArray, Vec3
from btmission.vehicles.base import Backend, Sensors, VehicleKind

if TYPE_CHECKING:
    from btmission.spec.mission import Mission
    from btmission.vehicles.clock import Clock
    from btmission.world.voxel import VoxelMap

ENTRY_POINT_GROUP = "btmission.providers"


@dataclass(frozen=True)
class VehicleEvent:
    """Something the provider detected while stepping: a ``collision`` of ``vehicle`` with
    ``other`` (``rock`` or another vehicle's id) at ``position``, or a ``warning`` about
    ``vehicle`` (``message``: e.g. its setpoint stream fell short; ``other`` empty)."""

    time_s: float
    vehicle: str
    kind: str
    other: str
    position: tuple[float, float, float]
    message: str = ""


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


@dataclass(frozen=True)
class AttachOptions:
    """What the run says of an agent's vehicle besides its kind and start; a provider uses what
    applies to it and ignores the rest."""

    yaw: float = 0.0
    """Heading to spawn at (rad, counter-clockwise from world +x): simulators only."""
    v_max: float | None = None
    """A ground robot's top speed (m/s): the navigator's ``speed_m_s``. None: the model's."""


@dataclass(frozen=True)
class AttachRequest:
    """One agent's vehicle, as :meth:`VehicleProvider.attach_all` is asked for it (the arguments
    of :meth:`VehicleProvider.attach`)."""

    agent_id: str
    kind: VehicleKind
    start: Vec3
    ref: VehicleRef = SIM
    options: AttachOptions = AttachOptions()


PHASES = (
    "warm_up", "prepare", "attach", "attach_all", "start", "step", "close", "fleet_sensing",
)  # fmt: skip
"""The provider's phases, in the order a run calls them, and its one capability query (every
provider has them all; :class:`ProviderBase` gives the ones most need not write)."""


@runtime_checkable
class VehicleProvider(Protocol):
    """Creates or connects the vehicles of a run, owns its clock and advances it (module
    docstring). A run calls :meth:`warm_up` and :meth:`prepare` once, :meth:`attach_all` once
    with every agent (which :class:`ProviderBase` answers by calling :meth:`attach` for each),
    :meth:`start` once, :meth:`step` every step and :meth:`close` at the end (:data:`PHASES`);
    :class:`ProviderBase` has the phases most providers need not write."""

    @property
    def clock(self) -> Clock:
        """The run's time: :class:`~btmission.vehicles.clock.SimClock` in a simulator,
        :class:`~btmission.vehicles.clock.ScaledWallClock` with real vehicles."""
        ...

    @property
    def realtime(self) -> bool:
        """True when time passes on its own (real vehicles): the runner paces its steps
        against the wall clock instead of running as fast as it can."""
        ...

    def warm_up(self) -> None:
        """While the run is built, before :meth:`prepare`: load the compiled (numba) kernels
        this provider runs in the loop — its vehicles' model, their sensors — from the cache
        (compiled if missing), so that the loop's first steps do not stall (a real-time run
        would miss its deadlines). Run them once on throwaway inputs with the argument types of
        a run's (another dtype, layout or read-only flag is another signature: compiled again
        at the first step), touching none of the run's vehicles, time or random draws."""
        ...

    def prepare(self, vehicles: Sequence[VehicleRef]) -> None:
        """Before the first :meth:`attach`, with every agent's reference: a real provider opens
        all its links at once, so that vehicles boot together."""
        ...

    def attach(
        self,
        agent_id: str,
        kind: VehicleKind,
        start: Vec3,
        ref: VehicleRef = SIM,
        options: AttachOptions = AttachOptions(),
    ) -> Vehicle:
        """The vehicle of ``agent_id``: spawned at ``start`` (a simulator) or connected where
        ``ref`` (the agent's ``backend:``) says (a real vehicle is where it is)."""
        ...

    def attach_all(self, requests: Sequence[AttachRequest]) -> list[Vehicle]:
        """Every agent's vehicle, in the order asked: what :meth:`attach` gives one agent, for
        the whole fleet at once, so that a real provider connects its vehicles concurrently
        (:class:`ProviderBase`: one :meth:`attach` after the other). Raises
        :class:`VehicleUnavailable` naming each vehicle that could not be had (its
        :attr:`~VehicleUnavailable.failures`)."""
        ...

    def start(self) -> None:
        """Every vehicle is attached: the mission's time starts (a real provider's clock
        restarts at zero, however long connecting took; the run reads :attr:`clock` only
        after this)."""
        ...

    def step(self, dt: float) -> Sequence[VehicleEvent]:
        """Advance by ``dt`` seconds: the simulator integrates its physics; a real provider
        pumps its inbox or does nothing. Returns what happened meanwhile (collisions,
        warnings)."""
        ...

    def close(self) -> None:
        """Release sockets, threads and vehicles (idempotent)."""
        ...

    def fleet_sensing(self) -> FleetSensing | None:
        """The provider's offer to a fleet's batched control step, if it ray-casts its
        vehicles' LiDAR itself (the simulator: :class:`FleetSensing`); None otherwise."""
        ...


class BodyTable(Protocol):
    """Every vehicle's body sphere at one step, as :meth:`FleetSensing.bodies` gives it."""

    @property
    def key(self) -> tuple[int, int]:
        """Changes when the table does: (step, vehicles)."""
        ...

    @property
    def index(self) -> dict[str, int]:
        """Agent id → its row."""
        ...

    @property
    def centres(self) -> FloatArray: ...

    @property
    def radii(self) -> FloatArray: ...


class FleetSensing(Protocol):
    """What a provider that ray-casts its vehicles' LiDAR itself (the simulator) offers the run's
    fleet control step (:mod:`btmission.runtime.fleetstep`), which then computes every covered
    drone's scan, avoidance and route following in one compiled call, to the bit what each
    vehicle's own sensors and navigator would."""

    cells: tuple[FloatArray, NDArray[np.int64], FloatArray, float, NDArray[np.int64]]
    """The rock-face points sorted into cells: points, starts, lower corner, cell size, dims
    (:mod:`btmission.world._surface_kernels`)."""
    lidar_range_m: float
    sphere: FloatArray
    """The unit points another vehicle's body gives in a scan (scaled to its radius)."""

    def covers(self, backend: Backend, sensors: Sensors | None) -> bool:
        """Whether this vehicle (its backend and the sensors its navigator reads) is one whose
        LiDAR the batch computes exactly: a multirotor of this provider, its sensors its own."""
        ...

    def bodies(self) -> BodyTable:
        """Every vehicle's body sphere now."""
        ...

    def true_poses(self, backends: Sequence[Backend]) -> FloatArray:
        """Where these vehicles truly are, ``(n, 4)``: x, y, z, yaw (the scans' origins)."""
        ...


class ProviderBase:
    """The phases a provider without kernels, links or a clock of its own to restart need not
    write: :meth:`warm_up`, :meth:`prepare` and :meth:`start` do nothing, :meth:`attach_all`
    attaches the vehicles one after the other, and it offers no :class:`FleetSensing`."""

    if TYPE_CHECKING:  # every provider writes its own (:class:`VehicleProvider`)

        def attach(
            self,
            agent_id: str,
            kind: VehicleKind,
            start: Vec3,
            ref: VehicleRef = SIM,
            options: AttachOptions = AttachOptions(),
        ) -> Vehicle: ...

    def warm_up(self) -> None:
        """No compiled kernels of its own to load."""

    def prepare(self, vehicles: Sequence[VehicleRef]) -> None:
        """Nothing to open ahead of the vehicles."""

    def attach_all(self, requests: Sequence[AttachRequest]) -> list[Vehicle]:
        """:meth:`attach` for each request in turn (a simulator's vehicles are spawned at once;
        nothing to wait for concurrently). A vehicle that cannot be had stops it, named in the
        error's :attr:`~VehicleUnavailable.failures`."""
        out = []
        for r in requests:
            try:
                out.append(self.attach(r.agent_id, r.kind, r.start, r.ref, r.options))
            except VehicleUnavailable as exc:
                if exc.failures:
                    raise
                raise VehicleUnavailable(str(exc), {r.agent_id: str(exc)}) from exc
        return out

    def start(self) -> None:
        """The clock is the provider's own and starts with it."""

    def fleet_sensing(self) -> FleetSensing | None:
        """No batched LiDAR: each vehicle's sensors are its own."""
        return None


ProviderFactory = Callable[["Mission", "VoxelMap", int], VehicleProvider]
"""Makes a run's provider: ``factory(mission, voxel_map, seed)``."""


@dataclass(frozen=True)
class ProviderPlugin:
    """What a ``btmission.providers`` entry point names (a bare :data:`ProviderFactory` is
    taken as ``ProviderPlugin(factory)``)."""

    create: ProviderFactory
    """Makes the run's provider."""
    check_address: Callable[[VehicleRef], str | None] | None = None
    """What is wrong with an agent's reference (None: nothing), asked by ``validate`` and
    ``run`` before anything is built; without it a reference must be ``<scheme>`` or
    ``<scheme>://<address>``."""


def missing_phases(provider: object) -> list[str]:
    """The :data:`PHASES` ``provider`` lacks (a provider from a plugin written for an older
    btmission may)."""
    return [name for name in PHASES if not callable(getattr(provider, name, None))]


BUILT_IN = {
    "sim": "btmission.backends.sim_provider:sim_provider",
    "fake": "btmission.backends.fake:fake_provider",
    "mavlink": "btmission.backends.mavlink_url:MAVLINK",
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
    the wrong type ...). ``run`` reports it at the agent's ``backend:`` line (exit 2) — at each
    failing agent's line when :attr:`failures` names several."""

    def __init__(self, message: str, failures: Mapping[str, str] | None = None) -> None:
        super().__init__(message)
        self.failures: dict[str, str] = dict(failures or {})
        """Agent id → why its vehicle could not be had (each message names its agent), in
        the mission's order; empty when the provider did not say which agent."""


class ProviderError(BtmissionError, LookupError):
    """No provider is installed for a scheme."""


def unknown_scheme_message(scheme: str, installed: Sequence[str]) -> str:
    known = ", ".join(f"'{s}'" for s in installed) or "none"
    return (
        f"no vehicle provider for scheme '{scheme}' is installed; "
        f"installed: {known} (entry-point group '{ENTRY_POINT_GROUP}')"
    )


def load_provider(
    scheme: str, installed: Mapping[str, metadata.EntryPoint] | None = None
) -> ProviderPlugin:
    """Load ``scheme``'s provider plugin (imports the module its entry point names) from the
    ``installed`` providers (default: :func:`installed_providers`, looked up now)."""
    eps = installed_providers() if installed is None else installed
    if scheme not in eps:
        raise ProviderError(unknown_scheme_message(scheme, list(eps)))
    loaded = eps[scheme].load()
    return loaded if isinstance(loaded, ProviderPlugin) else ProviderPlugin(loaded)


def provider_factory(scheme: str) -> ProviderFactory:
    """The factory of ``scheme``'s provider (imports its module)."""
    return load_provider(scheme).create
