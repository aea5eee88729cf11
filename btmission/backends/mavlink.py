"""MAVLink vehicles as a :class:`~btmission.vehicles.provider.VehicleProvider` (scheme ``mavlink``).

One process drives every MAVLink vehicle of a mission (as MAVSDK-Python 4 does too; up to 3.x it
started a ``mavsdk_server`` per drone): the agents' ``backend:`` URLs (:mod:`btmission.backends.mavlink_url`) name the links, several
vehicles may share one link (told apart by ``?sysid=``), and **one I/O thread** serves them all:

* it waits on every link's socket at once (``select``), parses what arrives with pymavlink and
  files it into the vehicle's state (heartbeat, LOCAL_POSITION_NED, ATTITUDE, EXTENDED_SYS_STATE,
  SYS_STATUS, DISTANCE_SENSOR, HOME_POSITION, EKF_STATUS_REPORT, STATUSTEXT, COMMAND_ACK);
* it streams each vehicle's latest setpoint at a fixed rate (``setpoint_hz``, 20 Hz by default:
  PX4 wants more than 2 Hz before and during OFFBOARD) — but only while the mission keeps
  renewing it: a setpoint older than ``setpoint_stale_s`` is no longer sent, so a mission whose
  control loop has stopped lets the autopilot's offboard-loss failsafe act;
* it sends a GCS HEARTBEAT on every link once a second (PX4's data-link-loss and ArduPilot's GCS
  failsafes watch it).

Both streams are due on absolute deadlines and the thread sends before it reads, so a loaded
machine delays a setpoint but does not lower the rate; a stream that still falls short becomes a
``warning`` event (:meth:`MavlinkProvider.step`; :mod:`btmission.backends.mavlink_schedule`).

The vehicles of a run connect concurrently (:meth:`MavlinkProvider.attach_all`,
:mod:`btmission.backends.mavlink_connect`): every link opens at once, every vehicle's requests go
out as soon as it is heard, and the run waits about as long as its slowest vehicle needs.

Commands (arm, mode, take-off, land) are COMMAND_LONGs that wait for their COMMAND_ACK
(``ack_timeout_s``), are sent again (with ``confirmation`` counting up) when no answer comes, are
waited for while the autopilot says IN_PROGRESS and retried after a pause while it says
TEMPORARILY_REJECTED; a refusal comes back as an ``Ack`` naming the MAV_RESULT and the
autopilot's STATUSTEXT (:func:`~btmission.backends.mavlink_modes.ack_of`), typed transient (a
refusal the vehicle may take back: TEMPORARILY_REJECTED, DENIED, FAILED, no answer) or final
(UNSUPPORTED, a mode the vehicle does not have), so the run retries only what may succeed. A
command whose effect already shows (armed, in the mode) is accepted without sending anything, and
an arming refused by the pre-arm checks is not sent again until a back-off has passed (0.5 s,
doubling to 4 s): the refusal's reason is answered meanwhile.

Frames: the mission world is ENU, z up; each vehicle's local NED frame has its origin at the
agent's start (or ``origin`` option), north along world +y
(:class:`~btmission.backends.mavlink_frames.LocalFrame`).

Time: real vehicles live on the wall clock; simulated ones may run faster (mavsim ``--speed``,
ArduPilot SITL ``--speedup``, PX4_SIM_SPEED_FACTOR) and the run's clock then runs as much faster
(``time_scale``). Telemetry times are the run clock's when the message arrived (0 for a message
that came while the vehicles connected: the clock restarts when the mission starts). Link loss is
judged in wall time (``heartbeat_timeout_s``, whatever ``time_scale``): a busy machine's pause
lasts as long on the wall clock at any speed-up, and must not read as a lost link because the
vehicles run four times faster.
"""

from __future__ import annotations

import collections
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from btmission.backends.mavlink_connect import ConnectTimes, FleetConnect
from btmission.backends.mavlink_frames import (
    GeodeticOrigin,
    LocalFrame,
    agent_frame,
    mission_geodetic_origin,
)
from btmission.backends.mavlink_pauses import VehicleClockWatch
from btmission.backends.mavlink_schedule import StreamStats
from btmission.backends.mavlink_signing import load_key, signing_counters
from btmission.backends.mavlink_url import parse_mavlink_url
from btmission.spec.common import config_from
from btmission.spec.vehicleref import SIM, VehicleRef
from btmission.types import FloatArray, Vec3
from btmission.vehicles.base import Ack, Mode, Sensors, VehicleKind
from btmission.vehicles.clock import ScaledWallClock
from btmission.vehicles.provider import (
    AttachOptions,
    AttachRequest,
    ProviderBase,
    Vehicle,
    VehicleEvent,
)

if TYPE_CHECKING:
    from btmission.backends.sim import SimConfig
    from btmission.backends.simworld import SimWorld
    from btmission.spec.mission import Mission
    from btmission.world.voxel import VoxelMap

from btmission.backends.mavlink_link import (
    MavlinkError,
    MavlinkOptions,
    _LinkIO,
)
from btmission.backends.mavlink_vehicle import MavlinkVehicle


class MavlinkProvider(ProviderBase):
    """MAVLink vehicles for a run (module docstring)."""

    realtime = True

    def __init__(
        self,
        options: MavlinkOptions | None = None,
        ground_at: Callable[[FloatArray], float] | None = None,
        progress: Callable[[str], None] | None = None,
        *,
        geodetic: GeodeticOrigin | None = None,
        sensors: MapSensorsAtReports | None = None,
        frames: Mapping[str, LocalFrame] | None = None,
    ) -> None:
        """``geodetic``: where the world's origin is on Earth (``world.origin``): a vehicle
        that knows no global origin gets its own (SET_GPS_GLOBAL_ORIGIN). ``sensors``: map
        sensors for each vehicle (``runtime.mavlink.map_sensors``), else none. ``frames``: each
        agent's world ↔ local NED frame (its ``origin:`` in the mission); an agent without one
        has its start as origin, north along world +y."""
        self.options = options or MavlinkOptions()
        self._frames = dict(frames or {})
        self._sensors = sensors
        self.clock = ScaledWallClock(self.options.time_scale)
        self._io = _LinkIO(self.clock, self.options)
        self._ground_at = ground_at
        self._progress = progress
        self.vehicles: dict[str, MavlinkVehicle] = {}
        self._clock_watch = VehicleClockWatch(self.options.time_scale)
        self._closed = False
        self._connect = FleetConnect(
            self._io, self.clock, self.options, frames=self._frames, geodetic=geodetic,
            ground_at=ground_at, progress=self._note,
        )  # fmt: skip

    def _note(self, text: str) -> None:
        if self._progress is not None:  # (read when said: a test may set it later)
            self._progress(text)

    def warm_up(self) -> None:
        """The map sensors' kernels, if the vehicles have them
        (:meth:`MapSensorsAtReports.warm_up`); the links' code is plain Python."""
        if self._sensors is not None:
            self._sensors.warm_up()

    def prepare(self, vehicles: Sequence[VehicleRef]) -> None:
        """Start opening every link (each on a helper thread; a TCP one retried until its
        vehicle listens), so that vehicles that start on a connection (ArduPilot SITL waits for
        its TCP client) boot and warm up their estimators together. A link that cannot be
        opened is reported by :meth:`attach_all`, naming its agent."""
        for url in dict.fromkeys(v.url for v in vehicles):
            try:
                self._connect.open(parse_mavlink_url(url))
            except ValueError:
                continue

    def start(self) -> None:
        """The mission starts now: the run clock restarts at zero (connecting took its time),
        and what the vehicles told before counts as told at the start (t = 0), not at a time
        of the connecting clock that the mission's never shows."""
        self.clock.restart()
        for vehicle in self.vehicles.values():
            st = vehicle.state
            st.heartbeat_at = min(st.heartbeat_at, 0.0)
            st.position_at = min(st.position_at, 0.0)
            st.range_at = min(st.range_at, 0.0)

    def attach(
        self,
        agent_id: str,
        kind: VehicleKind,
        start: Vec3,
        ref: VehicleRef = SIM,
        options: AttachOptions = AttachOptions(),
    ) -> Vehicle:
        """Connect ``agent_id``'s vehicle at ``ref``'s URL (:meth:`attach_all` for one)."""
        return self.attach_all([AttachRequest(agent_id, kind, start, ref, options)])[0]

    def attach_all(self, requests: Sequence[AttachRequest]) -> list[Vehicle]:
        """Connect every requested vehicle at once (:mod:`btmission.backends.mavlink_connect`),
        within one ``connect_timeout_s``: for each, an autopilot's heartbeat (the ``?sysid=``
        one, else the first not taken), of the right type, its telemetry streams asked, a
        position estimate. Its frame is the one the provider was given for its agent
        (``frames``), else its origin is its start, north along world +y. Raises
        :class:`MavlinkError` naming every vehicle that could not be connected and what it
        lacked (:attr:`~btmission.vehicles.provider.VehicleUnavailable.failures`)."""
        connected = self._connect.connect(requests, self._check_io)
        out = []
        for vehicle in connected:
            self.vehicles[vehicle.id] = vehicle
            sensors = self._sensors(vehicle) if self._sensors is not None else None
            out.append(Vehicle(vehicle.id, vehicle.kind, vehicle, sensors, link_ok=vehicle.link_ok))
        return out

    @property
    def connect_times(self) -> dict[str, ConnectTimes]:
        """When each vehicle was heard, first asked, and connected (wall seconds after its
        :meth:`attach_all` began): what ``btmission bench mavlink`` reports."""
        return dict(self._connect.times)

    def _check_io(self) -> None:
        if self._io.error is not None:
            raise MavlinkError(f"the MAVLink I/O thread stopped: {self._io.error!r}")

    def step(self, dt: float) -> list[VehicleEvent]:
        """Nothing to integrate: real time passes on its own. Returns a ``warning`` for each
        vehicle whose setpoint stream fell short since the last step (below 80 % of
        ``setpoint_hz`` over a second, or a gap over 0.2 s, vehicle time: at most one per
        vehicle per 10 s), and for one heard again after a link loss whose own clock stood
        still or went back meanwhile (:class:`~btmission.backends.mavlink_pauses.
        VehicleClockWatch`). Raises if the I/O thread died."""
        self._check_io()
        said: list[tuple[MavlinkVehicle, str]] = []
        watch = self._clock_watch
        for vehicle in self.vehicles.values():
            text = watch.check(vehicle.id, vehicle.link_ok(), vehicle.state.boot)
            if text is not None:
                said.append((vehicle, text))
        warnings = self._io.take_warnings()
        if warnings:
            by_state = {id(v.state): v for v in self.vehicles.values()}
            for st, text in warnings:
                heard = by_state.get(id(st))
                if heard is not None:  # (not: a vehicle being attached, its stream not begun)
                    said.append((heard, text))
        now = self.clock.now()
        out = []
        for vehicle, text in said:
            p = vehicle.telemetry().position  # the world's frame
            out.append(
                VehicleEvent(
                    now, vehicle.id, "warning", "", (float(p[0]), float(p[1]), float(p[2])),
                    message=f"{vehicle.id}: {text}",
                )
            )  # fmt: skip
        return out

    def stream_stats(self) -> dict[str, StreamStats]:
        """Each vehicle's setpoint stream so far: sends, slots skipped after stalls, worst gap,
        last and lowest rate over a second, and how often it fell short (vehicle time)."""
        return {agent: v.state.health.stats(v.state.schedule) for agent, v in self.vehicles.items()}

    def rejected(self) -> dict[str, int]:
        """Messages refused on every link with signing on, by reason: unsigned, a bad
        signature or a replay."""
        out: collections.Counter[str] = collections.Counter()
        for link in self._io.links.values():
            if self.options.signing_key is not None:
                counts = signing_counters(link.conn)
                counts.pop("signed_ok")
                out.update(counts)
        return {k: v for k, v in out.items() if v}

    def close(self) -> None:
        """Leave every vehicle safe, then close the links: a vehicle still flying is told to
        HOLD and then (``on_stop: land``, the default) to LAND, each waited for until its
        COMMAND_ACK refuses it or the telemetry shows the mode; setpoints stop. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._connect.cancel()
        try:
            self.stop_vehicles()
            if self._progress is not None:
                for agent, stats in self.stream_stats().items():
                    if stats.warnings:
                        self._progress(
                            f"{agent}: setpoints fell short {stats.long_gaps + stats.low_windows} "
                            f"time(s): worst gap {stats.worst_gap_s:.2f} s, lowest rate "
                            f"{stats.lowest_rate_hz or 0.0:.1f} Hz of "
                            f"{self.options.setpoint_hz:g}, {stats.sent} sent"
                        )
            refused = self.rejected()
            if refused and self._progress is not None:
                self._progress(
                    "MAVLink messages refused: "
                    + ", ".join(
                        f"{why.replace('_', ' ')} {n}" for why, n in sorted(refused.items())
                    )
                )
        finally:
            self._io.close()

    def stop_vehicles(self) -> dict[str, list[Ack]]:
        """HOLD (then LAND) every vehicle that is armed and off the ground, and disarm every
        drone armed on the ground (:meth:`close`): a run that stops leaves no motors armed (on
        real PX4 stopping left drones that were about to take off armed)."""
        out: dict[str, list[Ack]] = {}
        for vehicle in self.vehicles.values():
            vehicle.state.setpoint = None  # nothing more is streamed
            if self._io.error is not None or not vehicle.link_ok():
                continue
            tel = vehicle.telemetry()
            if not tel.armed:
                continue
            if tel.mode is Mode.LAND and not tel.landed:
                if self._progress is not None:  # (a HOLD would stop the descent)
                    self._progress(f"{vehicle.id}: the run stopped: landing (LAND), left to it")
                continue
            if tel.landed and vehicle.kind is VehicleKind.MULTIROTOR:
                ack = vehicle.wait(vehicle.disarm)
                out[vehicle.id] = [ack]
                if self._progress is not None:
                    said = "accepted" if ack else "refused: " + ack.reason
                    self._progress(
                        f"{vehicle.id}: the run stopped: armed on the ground, DISARM {said}"
                    )
                continue
            acks = [vehicle.set_mode_and_wait(Mode.HOLD)]
            if self.options.on_stop == "land" and vehicle.kind is VehicleKind.MULTIROTOR:
                acks.append(vehicle.set_mode_and_wait(Mode.LAND))
            out[vehicle.id] = acks
            if self._progress is not None:
                said = ", then ".join(
                    f"{what} {'accepted' if a else 'refused: ' + a.reason}"
                    for what, a in zip(("HOLD", "LAND"), acks, strict=False)
                )
                self._progress(f"{vehicle.id}: the run stopped: {said}")
        return out


class MapSensorsAtReports:
    """Each vehicle's map sensors (``runtime.mavlink.map_sensors``):
    :class:`~btmission.backends.mapsensors.MapSensors` ray-cast in ``world`` at the pose the
    vehicle reports, seeing no other vehicle, their draws (dust, noise) from one generator."""

    def __init__(self, world: SimWorld, config: SimConfig, rng: np.random.Generator) -> None:
        self.world = world
        self.config = config
        self.rng = rng

    def __call__(self, vehicle: MavlinkVehicle) -> Sensors:
        from btmission.backends.mapsensors import MapSensors

        return MapSensors(self.world, self.config, self.rng, vehicle.telemetry)

    def warm_up(self) -> None:
        """Load the LiDAR's scan kernel for the arrays a MAVLink vehicle gives it — its
        reported position (a :class:`~btmission.backends.mavlink_frames.LocalFrame`'s world
        point, as :meth:`MavlinkVehicle.telemetry` has it) and no other bodies, writable
        arrays where the simulator's are read-only: another signature than a simulated run's —
        with a generator of its own (the run's draws stay the run's)."""
        from btmission.backends.mapsensors import MapSensors, SensorPose
        from btmission.backends.mavlink_frames import local_frame

        pose = SensorPose(0.0, local_frame((0.0, 0.0, 0.0)).to_world((0.0, 0.0, -1.0)), 0.0)
        MapSensors(self.world, self.config, np.random.default_rng(0), lambda: pose).lidar()


def mavlink_provider(mission: Mission, voxel_map: VoxelMap, seed: int) -> MavlinkProvider:
    """The ``mavlink`` entry point of ``btmission.providers``: the mission's
    ``runtime.mavlink`` settings, its ``world.origin``; ground heights from the mission map when
    a vehicle has no downward range finder; with ``map_sensors``, each vehicle's LiDAR and
    camera ray-cast in the mission map at the pose it reports
    (:class:`~btmission.backends.mapsensors.MapSensors`, as SITL users get from Gazebo)."""
    from btmission.backends.sim_provider import mission_artifacts, sim_config
    from btmission.backends.simworld import SimWorld

    spec = mission.spec.runtime.mavlink
    options = config_from(MavlinkOptions, spec, signing_key=load_key())
    world = SimWorld(voxel_map, mission_artifacts(mission))
    sensors = None
    if spec.map_sensors:
        sensors = MapSensorsAtReports(world, sim_config(mission), np.random.default_rng(seed))
    return MavlinkProvider(
        options,
        ground_at=world.ground_z,
        progress=_to_stderr,
        geodetic=mission_geodetic_origin(mission),
        sensors=sensors,
        frames={a.id: agent_frame(mission, a.id) for a in mission.agents},
    )


def _to_stderr(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
