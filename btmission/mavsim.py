# mypy: disable-error-code="no-any-return"
"""A MAVLink vehicle simulator: the embedded simulator's vehicles served as PX4 or ArduPilot
autopilots on 127.0.0.1 (``btmission mavsim``), so the MAVLink provider is tested end to end
without hardware.

Each vehicle is a :class:`~btmission.backends.sim.Simulator` vehicle (the same physics as
``backend: sim``) behind a MAVLink 2 endpoint that behaves, as seen over the link, like the real
firmware's SITL:

* **transports** as the SITLs have them: PX4 sends to a client that listens on UDP
  (``mavlink+udp://127.0.0.1:14540`` + i), ArduPilot listens on TCP (5760 + 10 i); system ids
  too: PX4 instance i is sysid i + 1 (``MAV_SYS_ID``), every ArduPilot TCP vehicle sysid 1, as
  each ArduCopter SITL instance was (4.7.0-dev, three instances) (:func:`sitl_sysid`; a URL's
  ``?sysid=`` wins);
* **HEARTBEAT** at 1 Hz with the firmware's ``autopilot``, ``type``, armed flag and
  ``custom_mode`` (:mod:`btmission.backends.mavlink_modes`) — faster when asked on ArduPilot;
  PX4 refuses (MAV_RESULT_FAILED) as the firmware does — other messages only when asked
  (``MAV_CMD_SET_MESSAGE_INTERVAL``, ``MAV_CMD_REQUEST_MESSAGE``): CURRENT_MODE (the mode
  between heartbeats; PX4 only, at most 2 Hz whatever rate is asked and once on each change,
  :data:`PX4_CURRENT_MODE_S`, as PX4 v1.16 SITL sent it; ArduCopter 4.7.0-dev SITL refused
  its stream, DENIED with "No ap_message for mavlink id (436)", and so does mavsim's ArduPilot,
  :data:`ARDUPILOT_UNKNOWN_MESSAGES`), LOCAL_POSITION_NED (in the
  vehicle's NED frame, origin where it was spawned), ATTITUDE, EXTENDED_SYS_STATE, SYS_STATUS,
  BATTERY_STATUS, DISTANCE_SENSOR (downward; a PX4 vehicle on the ground reads 65533 cm, above
  its declared 10000 cm maximum, as PX4 SIH does), HOME_POSITION, EKF_STATUS_REPORT /
  ESTIMATOR_STATUS;
* every COMMAND_LONG answered by a COMMAND_ACK, a refusal preceded by a STATUSTEXT saying why;
  PX4 answers a DO_SET_MODE twice, as the firmware does: ACCEPTED at once (its MAVLink module),
  then on the next step the real result (its commander), which may be a refusal;
* **PX4 rules**: OFFBOARD only after setpoints have streamed at more than 2 Hz for a second
  (TEMPORARILY_REJECTED otherwise, "Switching to Offboard is currently not available", as PX4
  v1.16 SITL answered), except that a disarmed drone takes it without setpoints (ACCEPTED,
  shown as OFFBOARD) and then refuses to arm (TEMPORARILY_REJECTED, "Arming denied: Resolve
  system health failures first") until they stream, as the SITL did; when they stop for
  ``COM_OF_LOSS_T`` (1 s), the firmware's default offboard-loss action, Position mode, which
  without RC sinks and says CRITICAL (PX4 v1.16 SITL: 5.2 m to 0.1 m, custom mode 196608), or
  HOLD (:attr:`MavSimConfig.offboard_loss_action`); OFFBOARD again by itself once they stream
  for a second,
  NAV_TAKEOFF to an AMSL altitude (accepted while disarmed, as PX4 v1.16 SITL did: the drone
  shows Takeoff and leaves the ground only once armed), automatic disarming (the embedded simulator's rules,
  :mod:`btmission.backends.autopilot`);
* **ArduPilot rules**: GUIDED (copter 4, rover 15) takes targets that do not time out (position)
  or stop after 3 s (velocity) or 1 s (attitude, ``GUID_TIMEOUT``); a landed copter leaves the
  ground only with NAV_TAKEOFF (altitude above home, in GUIDED, armed); arming needs the EKF;
* **link-loss failsafes off, as the firmwares ship them**: PX4's ``NAV_DLL_ACT`` defaults to 0
  (no data-link-loss action; read on PX4 v1.16 SITL's parameters) and ArduCopter's
  ``FS_GCS_ENABLE`` to 0 (ArduCopter's source; on ArduCopter 4.7.0-dev SITL a copter whose
  ground station froze for 8 s braked and flew on), so a vehicle that stops hearing its ground
  station flies on. :attr:`MavSimConfig.datalink_loss_s` (``--datalink-loss``: PX4 lands after
  ``COM_DL_LOSS_T``) and :attr:`MavSimConfig.gcs_failsafe_s` (``--gcs-failsafe``: ArduPilot
  lands after ``FS_GCS_TIMEOUT``) turn them on; like the firmwares', they start once a ground
  station has been heard, and only while flying;
* **landing as the firmwares land**: PX4 descends in AUTO.LAND at 0.7 m/s (``MPC_LAND_SPEED``),
  below 1 m at 0.3 m/s (``MPC_LAND_CRWL`` below ``MPC_LAND_ALT3``, as with SIH's distance
  sensor), says LANDING until its land detector's ON_GROUND (:data:`PX4_LAND_DETECT_S` after
  touchdown: 7.5 s from 2 m, where PX4 v1.16 SIH took 7.2-12.3 s) and disarms 2 s later
  (``COM_DISARM_LAND``), then shows the mode in use before LAND (OFFBOARD, or Hold after a
  HOLD then LAND; MANUAL if neither), as PX4 v1.16 SITL did after "Disarmed by landing" — a
  drone disarmed in OFFBOARD stays there and refuses to arm until setpoints stream; ArduCopter
  descends in LAND at 0.5 m/s (``LAND_SPEED``) and disarms about 0.5 s after touchdown
  (ArduCopter 4.7.0-dev SITL) — the embedded simulator's own (0.7 m/s all the way, disarmed
  2 s after touchdown) is neither;
* **ArduCopter's modes** (:mod:`btmission.backends.mavlink_modes`): a copter keeps its mode when
  it disarms — one that landed in LAND stays in LAND, one in GUIDED stays in GUIDED — and
  refuses to arm in LAND, BRAKE and the other modes that do not allow it ("Arm: Mode not
  armable", :data:`~btmission.backends.mavlink_modes.COPTER_NOT_ARMABLE`); it accepts LAND
  (DO_SET_MODE or NAV_LAND) while disarmed on the ground, as ArduCopter's ModeLand allows
  entry there (ArduCopter's source); BRAKE holds its
  position and altitude; LOITER takes its climb rate from the throttle stick, and with no RC
  (SITL's default throttle is 1000 µs, the stick at the bottom) it sinks at
  :data:`LOITER_SINK_M_S` until it lands;
* ground robots (PX4 rover, ArduRover) are armed over MAVLink and drive on velocity targets
  only when armed and in OFFBOARD / GUIDED;
* only ``MAV_FRAME_LOCAL_NED`` position targets are simulated (others are ignored and counted);
* **an estimator that starts as the SITLs' do, when asked**: for ``ekf_delay_s`` after start
  (0 by default, for fast tests; :data:`SITL_EKF_DELAY_S`, ``--ekf-delay sitl``, is what the
  SITLs took: 42 s ArduCopter, 4 s PX4) arming is refused with the pre-arm message
  (TEMPORARILY_REJECTED on PX4), and no LOCAL_POSITION_NED is sent, asked for or not, as
  ArduCopter sends none before EKF3 has an origin and PX4 none before its local position is
  valid (``xy_valid``; its MAVLink stream's source);
* faults for tests: a pre-arm check that always fails or fails the first N
  arming commands, a link that drops,
  MAVLink 2 signing (unsigned or badly signed messages dropped and counted).

Time runs ``speed`` times faster than the wall clock (``--speed``; PX4_SIM_SPEED_FACTOR and
ArduPilot's ``--speedup`` do the same); every timeout and message rate is in simulated time.

**A frozen simulator pauses its clock.** The SITLs are lockstep: frozen with ``kill -STOP`` and
resumed with ``kill -CONT``, their clock resumes where it stopped, so the vehicle sees no link
loss and takes no failsafe (ArduCopter 4.7.0-dev SITL frozen 8 s wall flew on; PX4 v1.16 SITL
likewise). A step that finds the loop more than :data:`FREEZE_S` behind the wall clock drops the
missed time (``paused_s``, printed at exit) instead of running the missed steps in a burst;
smaller lateness (a busy machine) is still caught up, so the simulator keeps time under load.

**Its own ground station only.** A UDP vehicle sends to the address it was given (where the
ground station listens) and hears only that address; it moves to another one only on a valid
MAVLink frame from there that is a ground station's HEARTBEAT (``MAV_TYPE_GCS``), correctly
signed when signing is on — a ground station restarted elsewhere. Anything else from another
address (garbage, an unsigned frame, a vehicle's or a command) is dropped and counted
(``strangers``); it neither diverts the telemetry nor reaches the autopilot. (Without signing
anyone who can send a GCS heartbeat can take the vehicle over, as on the real firmware: sign.)

**Setpoint arrivals** (for ``btmission bench mavlink``): :meth:`MavSim.stamp_arrivals` notes
when each setpoint addressed to a vehicle reached its socket, from the kernel's receive stamp
(``SO_TIMESTAMPNS``; on TCP, or where the kernel gives none, when it was read), so a stream is
measured where the autopilot gets it, not when the simulator's loop got round to reading it.

**On time under load.** Each step reads at most :data:`RECEIVE_PER_STEP` datagrams (messages
on TCP) per vehicle before it steps the physics and sends what is due, so a backlog or a flood
of incoming datagrams delays what is read, not the simulation and its telemetry.
"""

from __future__ import annotations

import math
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from btmission.backends._pymavlink import CURRENT_MODE_ID, CurrentMode, mavlink, mavutil
from btmission.backends.autopilot import STREAM_MIN_HZ, STREAM_MIN_S
from btmission.backends.mavlink_frames import LocalFrame
from btmission.backends.mavlink_modes import (
    Autopilot,
    armable,
    custom_mode_of_command,
    mode_of,
    mode_request,
)
from btmission.backends.mavlink_setpoints import (
    POSITION_IGNORE,
    VELOCITY_IGNORE,
    YAW_IGNORE,
    YAW_RATE_IGNORE,
    AttitudeTarget,
    attitude_from_target,
)
from btmission.backends.mavlink_signing import enable_signing, parser_like, signing_counters
from btmission.backends.mavlink_url import MavlinkAddress
from btmission.backends.sim import SimConfig, Simulator, SimVehicle
from btmission.vehicles.base import Ack, LandedState, Mode, VehicleKind
from btmission.world.voxel import VoxelMap

G = 9.81
SPOOL_S = 1.0
"""An ArduCopter take-off spools its motors up this long before it leaves the ground (SITL shows
the copter ON_GROUND for about a second after NAV_TAKEOFF)."""
RECEIVE_PER_STEP = 32
"""Datagrams (UDP) or messages (TCP) a vehicle reads per simulation step at most (module
docstring): at 50 steps a second, far above what a ground station sends."""
PX4_RANGE_MAX_CM = 10000
"""The maximum PX4 SIH's downward range finder declares (DISTANCE_SENSOR ``max_distance``)."""
PX4_RANGE_ON_GROUND_CM = 65533
"""What it reads on the ground (the vehicle a few cm below its origin): out of its declared
range, i.e. no reading — a ground station that takes it as real puts the ground 655 m down."""
PX4_LAND_SPEED_M_S = 0.7
"""How fast a PX4 vehicle descends in AUTO.LAND (``MPC_LAND_SPEED``'s default; SIH: at most
0.8 m/s; the landed state says it is landing)."""
PX4_LAND_CRAWL_M_S = 0.3
"""... and below :data:`PX4_LAND_CRAWL_ALT_M` above the ground (``MPC_LAND_CRWL``, used when a
distance sensor gives the height, as SIH's does)."""
PX4_LAND_CRAWL_ALT_M = 1.0
"""``MPC_LAND_ALT3``'s default."""
PX4_LAND_DETECT_S = 3.0
"""A PX4 vehicle's land detector says ON_GROUND ("Landing detected") this long after touchdown
(its ground-contact, maybe-landed and landed stages, ``LNDMC_TRIG_TIME`` 1 s the last), until
then LANDING. Set so that a LAND from 2 m (4.5 s of descent here) takes 7.5 s, within the
7.2-12.3 s PX4 v1.16 SIH took from about 2 m to "Landing detected"."""
PX4_CURRENT_MODE_S = 0.5
"""PX4 sends CURRENT_MODE at most this often, whatever rate was asked, and once on each mode
change (PX4 v1.16 SITL, asked for 50 Hz: ACCEPTED, about 2 Hz; it sends it when its vehicle
status is published)."""
PX4_DISARM_LAND_S = 2.0
"""A landed PX4 vehicle disarms this long after its landing is detected (``COM_DISARM_LAND``;
PX4 v1.16 SIH: "Landing detected", then "Disarmed by landing" 2.0 s later)."""
COPTER_LAND_SPEED_M_S = 0.5
"""How fast an ArduCopter descends in LAND near the ground (``LAND_SPEED``, 50 cm/s; ArduCopter
4.7.0-dev SITL: 0.5 m/s)."""
COPTER_DISARM_LAND_S = 0.5
"""A landed ArduCopter disarms this long after touching down (ArduCopter 4.7.0-dev SITL: about
0.5 s after touchdown, where PX4 waits 2 s)."""
MAV_LANDED_STATE = {
    LandedState.UNDEFINED: mavlink.MAV_LANDED_STATE_UNDEFINED,
    LandedState.ON_GROUND: mavlink.MAV_LANDED_STATE_ON_GROUND,
    LandedState.IN_AIR: mavlink.MAV_LANDED_STATE_IN_AIR,
    LandedState.TAKEOFF: mavlink.MAV_LANDED_STATE_TAKEOFF,
    LandedState.LANDING: mavlink.MAV_LANDED_STATE_LANDING,
}
"""The simulator's landed state as EXTENDED_SYS_STATE says it."""
PX4_POSITION_SINK_M_S = 0.8
"""How fast PX4's Position mode sank without RC after an offboard loss (PX4 v1.16 SITL with
default parameters, ``COM_OBL_RC_ACT`` 0: 5.2 m to 0.1 m, at up to 0.8 m/s)."""
PX4_POSCTL = 3 << 16
"""PX4's Position mode (``custom_mode``: main mode 3), as its HEARTBEAT shows it (196608)."""
OFFBOARD_LOSS_ACTIONS = ("position", "hold")
LOITER_SINK_M_S = 2.5
"""How fast an ArduCopter in LOITER descends with no RC input (throttle at 1000 µs, full down:
``PILOT_SPEED_DN``, whose default 0 means ``PILOT_SPEED_UP``, 250 cm/s)."""
COPTER_LOITER = 5
"""ArduCopter's LOITER (``custom_mode``): none of the backend's modes, simulated here on the
simulator's HOLD (module docstring)."""
COPTER_LAND = 9
"""ArduCopter's LAND (``custom_mode``)."""
SO_TIMESTAMPNS = 35
"""Linux's socket option for the kernel's receive time of each datagram (a ``struct timespec``
in the ancillary data; Python's socket module does not name it)."""
_TIMESPEC = struct.Struct("@qq")
SITL_EKF_DELAY_S = {Autopilot.ARDUPILOT: 42.0, Autopilot.PX4: 4.0}
"""How long each firmware's SITL took to have a position estimate (``--ekf-delay sitl``):
ArduCopter 4.7.0-dev SITL, default parameters, took about 42 s of vehicle time before EKF3 used
its simulated GPS (LOCAL_POSITION_NED only then: 10.4 s wall at ``--speedup 4``); PX4 v1.16 SIH
said "Ready for takeoff" 3.9-4.3 s after it started, in eleven starts (docs/mavlink.md, "Flown on
real PX4 SITL"; an earlier note of 30 s counted the whole start-up script)."""
ARDUPILOT_UNKNOWN_MESSAGES = frozenset({CURRENT_MODE_ID})
"""Messages ArduCopter does not have (4.7.0-dev SITL answered SET_MESSAGE_INTERVAL for
CURRENT_MODE, 436, with MAV_RESULT_DENIED and the STATUSTEXT "No ap_message for mavlink id
(436)", and never sent it): asked for, they are refused likewise."""
PX4_UDP_BASE = 14540
ARDUPILOT_TCP_BASE = 5760
BOOT_EPOCH_S = 0.0
FREEZE_S = 1.0
"""A simulator loop this many wall seconds behind was frozen (a ``kill -STOP``, a suspended
machine, a debugger): it drops the missed time instead of catching up (module docstring)."""


@dataclass(frozen=True)
class VehicleSpec:
    """One simulated vehicle: the agent it serves, where it is spawned, where it is served."""

    agent_id: str
    kind: VehicleKind
    start: tuple[float, float, float]
    address: MavlinkAddress
    sysid: int


@dataclass(frozen=True)
class MavSimConfig:
    vehicles: tuple[VehicleSpec, ...]
    voxel_map: VoxelMap
    autopilot: Autopilot = Autopilot.PX4
    speed: float = 1.0
    step_s: float = 0.02
    ekf_delay_s: float = 0.0
    """The estimator is not ready for this long after start (simulated seconds; module
    docstring; :data:`SITL_EKF_DELAY_S` what the SITLs took)."""
    refuse_arm: str = ""
    """A pre-arm check that always fails with this text (see :attr:`refuse_arm_times`)."""
    refuse_arm_times: int = 0
    """When > 0, the pre-arm check fails only on each vehicle's first this many arming commands,
    then passes (a refusal the run retries and gets over); its text is :attr:`refuse_arm`, or
    ``Preflight Fail: sensors not ready`` (PX4) / ``PreArm: sensors not ready`` (ArduPilot)."""
    signing_key: bytes | None = None
    hover_thrust: float = 0.5
    home_amsl_m: float = 0.0
    offboard_loss_s: float = 1.0
    offboard_loss_action: str = "position"
    """PX4's offboard-loss action (``COM_OBL_RC_ACT``): ``position``, the firmware's default
    (0), flies Position mode, which without RC sinks (:data:`PX4_POSITION_SINK_M_S`) and says
    CRITICAL, until the setpoints return and PX4 goes back to OFFBOARD; ``hold`` (5) holds."""
    datalink_loss_s: float | None = None
    """PX4's data-link-loss failsafe: land after this many seconds without the ground station's
    heartbeat (``NAV_DLL_ACT`` = land after ``COM_DL_LOSS_T``); None, the firmware's default
    (``NAV_DLL_ACT`` 0), takes no action."""
    gcs_failsafe_s: float | None = None
    """ArduPilot's GCS failsafe: land after this many seconds without the ground station's
    heartbeat (``FS_GCS_ENABLE`` = land after ``FS_GCS_TIMEOUT``); None, the firmware's default
    (``FS_GCS_ENABLE`` 0), takes no action."""
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speed) and 0 < self.speed <= 50):
            raise ValueError(f"speed must be in (0, 50], got {self.speed}")
        if self.refuse_arm_times < 0:
            raise ValueError(f"refuse_arm_times must be ≥ 0, got {self.refuse_arm_times}")
        for name in ("datalink_loss_s", "gcs_failsafe_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive or None (off), got {value}")
        if self.offboard_loss_action not in OFFBOARD_LOSS_ACTIONS:
            raise ValueError(
                f"offboard_loss_action must be one of {', '.join(OFFBOARD_LOSS_ACTIONS)}, "
                f"got {self.offboard_loss_action!r}"
            )
        if not self.vehicles:
            raise ValueError("no vehicles to simulate")


@dataclass(frozen=True)
class Endpoint:
    agent_id: str
    url: str
    sysid: int
    autopilot: Autopilot
    kind: VehicleKind


@dataclass
class _Guided:
    """ArduPilot GUIDED's current target (what the vehicle keeps flying to)."""

    kind: str = "hold"  # hold | position | velocity | attitude
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw: float | None = None
    yaw_rate: float = 0.0
    attitude: tuple[float, float, float] = (G, 0.0, 0.0)
    since: float = 0.0
    taking_off: bool = False
    spool_until: float = 0.0
    """A take-off's motors spool up until then: the copter is still on the ground."""
    braking: bool = False
    """Holding after a velocity target expired: zero velocity until stopped, then the position
    where it stopped (flying back to where the target expired would overshoot)."""


class _SimulatedAutopilot:
    """One vehicle's MAVLink endpoint and autopilot behaviour (module docstring)."""

    def __init__(self, sim: MavSim, spec: VehicleSpec, backend: SimVehicle) -> None:
        self.sim = sim
        self.spec = spec
        self.backend = backend
        self.cfg = sim.config
        self.autopilot = sim.config.autopilot
        self.frame = LocalFrame(spec.start)
        self.peer: tuple[str, int] | None = None
        """The ground station's UDP address (where this vehicle sends; module docstring)."""
        self.strangers = 0
        """UDP datagrams from another address than the peer's, dropped."""
        self.conn = self._open(spec.address)
        self.intervals: dict[int, float] = {}
        self.next_send: dict[int, float] = {}
        self.next_heartbeat = 0.0
        self.heartbeat_s = 1.0
        self.gcs_heartbeat_at = math.inf
        """When a ground station's HEARTBEAT last came; the link-loss failsafes wait for the
        first (PX4's and ArduCopter's do)."""
        self.drop_until = -math.inf
        self.guided = _Guided()
        self.failsafe_note = ""
        self.received = 0
        self.setpoints = 0
        """Setpoints received (SET_POSITION_TARGET_LOCAL_NED, SET_ATTITUDE_TARGET)."""
        self.last_setpoint_t = -math.inf
        self.arrivals: list[float] | None = None
        """Wall times (``time.time()``) the setpoints arrived, once :meth:`MavSim.stamp_arrivals`
        asked for them."""
        self._received_at = 0.0
        self._kernel_stamps = False
        self.stream_since = math.inf
        """Since when setpoints have come at least every 0.5 s (PX4's OFFBOARD entry rule)."""
        self.ground = spec.kind is VehicleKind.GROUND
        self.ignored_frames = 0
        """SET_POSITION_TARGET_LOCAL_NED in another frame than MAV_FRAME_LOCAL_NED (ignored)."""
        self.rover_armed = False
        """A ground robot's arming (the embedded simulator's robots drive whenever told)."""
        self.arm_refusals_left = self.cfg.refuse_arm_times
        """Arming commands still to refuse (:attr:`MavSimConfig.refuse_arm_times`)."""
        self.later: list[Any] = []
        """COMMAND_LONGs acknowledged at once whose real answer comes on the next step (PX4's
        DO_SET_MODE: module docstring)."""
        self.gps_origin: tuple[int, int, int] | None = None
        """GPS_GLOBAL_ORIGIN (degE7, degE7, mm) once SET_GPS_GLOBAL_ORIGIN gave one (the vehicles
        have no GPS: until then they know no global origin and do not answer a request)."""
        self.copter = self.autopilot is Autopilot.ARDUPILOT and spec.kind is VehicleKind.MULTIROTOR
        """An ArduCopter: its modes are tracked beyond the simulator's (:meth:`_track_mode`)."""
        self.loiter = False
        """The copter's HOLD is LOITER (asked for as such), not BRAKE: it sinks without RC."""
        self.kept_land = False
        """The copter disarmed in LAND and stays in LAND (the simulator shows MANUAL)."""
        self.takeoff_asked: float | None = None
        """A disarmed PX4 drone was sent NAV_TAKEOFF (to this height above home): it shows
        Takeoff and takes off once armed (:meth:`step`)."""
        self.mode_sent = -1
        """The ``custom_mode`` the last CURRENT_MODE carried (PX4 sends one on each change)."""
        self.before_land = Mode.MANUAL
        """The PX4 drone's mode before a LAND (:meth:`_track_px4_mode`)."""
        self.touchdown_at = -math.inf
        """When the simulator's vehicle last touched down (:meth:`landed_state`)."""
        self.offboard_asked = False
        """A disarmed PX4 drone was put in OFFBOARD before setpoints streamed: it shows OFFBOARD
        and refuses to arm until they do, then the simulator's OFFBOARD takes over
        (:meth:`step`; module docstring)."""
        self.seen_mode = backend.telemetry().mode
        """The simulator's mode when :meth:`_track_mode` last looked."""
        self.unknown_messages = (
            ARDUPILOT_UNKNOWN_MESSAGES if self.autopilot is Autopilot.ARDUPILOT else frozenset()
        )
        """Messages the firmware does not have: a stream or a request of one is refused."""

    def _open(self, address: MavlinkAddress) -> Any:
        src = {"source_system": self.spec.sysid, "source_component": 1}
        if address.transport == "udp":  # the client listens: send to it (PX4 SITL)
            conn = mavutil.mavlink_connection(f"udpout:{address.host}:{address.port}", **src)
            try:
                conn.port.bind((address.host, 0))  # its own address: loopback, any free port
                self.peer = (socket.gethostbyname(address.host), address.port)
            except OSError:
                conn.close()
                raise
        elif address.transport == "tcp":  # the client connects: listen (ArduPilot SITL)
            if address.port:  # a port in use fails here, before pymavlink would leak a socket
                with socket.socket() as probe:
                    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                    probe.bind((address.host, address.port))
            conn = mavutil.mavlink_connection(f"tcpin:{address.host}:{address.port}", **src)
            conn.recv = _reaccepting_recv(conn)
        else:
            raise ValueError(f"mavsim serves udp and tcp, not {address.transport}")
        conn.WIRE_PROTOCOL_VERSION = "2.0"
        if self.cfg.signing_key is not None:
            enable_signing(conn, self.cfg.signing_key)
        return conn

    @property
    def url(self) -> str:
        a = self.spec.address
        port = a.port
        if a.transport == "tcp":
            port = self.conn.listen.getsockname()[1]
        return f"mavlink+{a.transport}://{a.host}:{port}"

    # ------------------------------------------------------------------ helpers
    @property
    def state(self) -> Any:
        return self.sim.simulator.vehicle(self.spec.agent_id)

    def now(self) -> float:
        return self.sim.simulator.time_s

    def _boot_ms(self) -> int:
        return int(self.now() * 1000) & 0xFFFFFFFF

    def send(self, fn: Callable[[Any], None]) -> None:
        if self.now() < self.drop_until:
            return
        try:
            fn(self.conn.mav)
        except OSError:
            pass

    def text(self, severity: int, message: str) -> None:
        self.send(lambda mav: mav.statustext_send(severity, message[:50].encode()))

    def armed(self) -> bool:
        return self.rover_armed if self.ground else bool(self.backend.telemetry().armed)

    def _streamed(self) -> None:
        """A setpoint arrived now: PX4 counts the stream whatever it is used for."""
        t = self.now()
        self.setpoints += 1
        if self.arrivals is not None:
            self.arrivals.append(self._received_at)
        if t - self.last_setpoint_t > 1.0 / STREAM_MIN_HZ:
            self.stream_since = t
        self.last_setpoint_t = t

    def streaming(self) -> bool:
        """Setpoints at more than 2 Hz for a second (PX4's condition for OFFBOARD)."""
        t = self.now()
        return t - self.last_setpoint_t <= 1.0 / STREAM_MIN_HZ and t - self.stream_since >= (
            STREAM_MIN_S
        )

    def ekf_ready(self) -> bool:
        return self.now() >= self.cfg.ekf_delay_s

    def position_known(self) -> bool:
        """Whether it has a local position to send (LOCAL_POSITION_NED): once the estimator is
        ready; before, neither firmware sends one (module docstring)."""
        return self.ekf_ready()

    def position_fallback(self) -> bool:
        """PX4's offboard-loss failsafe is on, with its default action: Position mode
        (:attr:`MavSimConfig.offboard_loss_action`)."""
        return (
            self.autopilot is Autopilot.PX4
            and not self.ground
            and self.cfg.offboard_loss_action == "position"
            and bool(self.state.offboard_lost)
            and self.backend.telemetry().mode is Mode.HOLD
        )

    def landed_state(self) -> LandedState:
        """The landed state the firmware reports: PX4's land detector says ON_GROUND only
        :data:`PX4_LAND_DETECT_S` after touchdown (LANDING until then)."""
        tel = self.backend.telemetry()
        state = tel.landed_state
        if (
            self.autopilot is Autopilot.PX4
            and not self.ground
            and state is LandedState.ON_GROUND
            and tel.armed
            and self.now() - self.touchdown_at < PX4_LAND_DETECT_S
        ):
            return LandedState.LANDING
        return state

    def custom_mode(self) -> int:
        if self.position_fallback():
            return PX4_POSCTL
        mode = self.backend.telemetry().mode
        if self.copter:
            if self.kept_land and mode is Mode.MANUAL:
                mode = Mode.LAND
            if self.loiter and mode is Mode.HOLD:
                return COPTER_LOITER
        if self.autopilot is Autopilot.ARDUPILOT and mode in (Mode.TAKEOFF, Mode.OFFBOARD):
            mode = Mode.OFFBOARD  # GUIDED
        if self.offboard_asked:
            mode = Mode.OFFBOARD
        elif self.takeoff_asked is not None:
            mode = Mode.TAKEOFF
        try:
            return mode_request(self.autopilot, self.spec.kind, mode).custom_mode
        except Exception:
            return 0

    def _track_mode(self) -> None:
        """ArduCopter keeps its mode when it disarms, where the simulator (PX4's rules) goes to
        MANUAL: a copter that landed in LAND stays in LAND (and refuses to arm there), one
        disarmed in BRAKE or LOITER stays there. Called before each step and each send."""
        if self.autopilot is Autopilot.PX4 and not self.ground:
            self._track_px4_mode()
            return
        if not self.copter:
            return
        tel = self.backend.telemetry()
        mode = tel.mode
        if mode is Mode.MANUAL and not tel.armed and self.seen_mode is not Mode.MANUAL:
            if self.seen_mode is Mode.LAND:
                self.kept_land = True
            elif self.seen_mode is Mode.HOLD:
                self.backend.set_mode(Mode.HOLD)  # (BRAKE or LOITER, on the ground)
                mode = Mode.HOLD
        if mode is not Mode.MANUAL:
            self.kept_land = False
        if mode is not Mode.HOLD:
            self.loiter = False
        self.seen_mode = mode

    def _track_px4_mode(self) -> None:
        """PX4 keeps the mode last asked that allows arming where the simulator goes to
        MANUAL: a drone disarmed by landing shows the mode in use before LAND (OFFBOARD when
        LAND was asked from OFFBOARD, Hold after a HOLD then LAND; PX4 v1.16 SITL), and a
        disarmed drone in OFFBOARD whose setpoints stopped stays in OFFBOARD (it refuses to
        arm until they stream again, :attr:`offboard_asked`)."""
        tel = self.backend.telemetry()
        mode, seen = tel.mode, self.seen_mode
        if mode is Mode.MANUAL and not tel.armed and seen is not Mode.MANUAL:
            if seen is Mode.LAND and self.before_land is Mode.HOLD:  # disarmed by landing
                self.backend.set_mode(Mode.HOLD)
                mode = Mode.HOLD
            elif seen is Mode.OFFBOARD or (seen is Mode.LAND and self.before_land is Mode.OFFBOARD):
                self.offboard_asked = True
        if self.offboard_asked:
            self.before_land = Mode.OFFBOARD
        elif mode is Mode.TAKEOFF:
            self.before_land = Mode.HOLD  # (PX4 holds once a take-off is done)
        elif mode in (Mode.OFFBOARD, Mode.MANUAL) or (
            mode is Mode.HOLD and not self.state.offboard_lost  # (its failsafe's: not asked)
        ):
            self.before_land = mode
        self.seen_mode = mode

    # ------------------------------------------------------------------ receive
    def receive(self, budget: int = RECEIVE_PER_STEP) -> None:
        """Decide the commands held from the last step, then read and handle at most
        ``budget`` datagrams (UDP) or messages (TCP)."""
        self._decide_later()
        if self.peer is not None:
            self._receive_udp(budget)
            return
        for _ in range(budget):
            try:
                msg = self.conn.recv_msg()
            except (OSError, ConnectionError):
                return
            if msg is None:
                return
            self._received_at = time.time()
            if self.now() < self.drop_until:
                continue  # the link is down: nothing arrives
            if msg.get_type() == "BAD_DATA":
                continue
            self.received += 1
            self._handle(msg)

    def _receive_udp(self, budget: int) -> None:
        port = self.conn.port
        for _ in range(budget):
            try:
                if self._kernel_stamps:
                    data, addr = self._recv_stamped(port)
                else:
                    data, addr = port.recvfrom(65535)
                    self._received_at = time.time()
            except (BlockingIOError, InterruptedError, ConnectionRefusedError):
                return
            except OSError:
                return
            if self.now() < self.drop_until:
                continue  # the link is down: nothing arrives
            if addr == self.peer:
                msgs = self.conn.mav.parse_buffer(data) or ()
            else:
                msgs = self._from_stranger(data, addr)
            for msg in msgs:
                if msg.get_type() == "BAD_DATA":
                    continue
                self.received += 1
                self._handle(msg)

    def stamp_arrivals(self) -> list[float]:
        """Start noting setpoint arrivals (:meth:`MavSim.stamp_arrivals`); returns the list."""
        if self.peer is not None:
            try:
                self.conn.port.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
                self._kernel_stamps = True
            except OSError:
                self._kernel_stamps = False
        self.arrivals = []
        return self.arrivals

    def _recv_stamped(self, port: socket.socket) -> tuple[bytes, Any]:
        data, ancillary, _flags, addr = port.recvmsg(65535, 64)
        self._received_at = time.time()
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                sec, nsec = _TIMESPEC.unpack_from(payload)
                self._received_at = sec + nsec * 1e-9
        return data, addr

    def _from_stranger(self, data: bytes, addr: tuple[str, int]) -> list[Any]:
        """A datagram from another address than the peer's: the new peer if it is a ground
        station's valid (and, with signing, correctly signed) HEARTBEAT, else dropped (module
        docstring). Parsed on its own, so its bytes never mix with the peer's."""
        if data[:1] in (b"\xfd", b"\xfe"):
            msgs = parser_like(self.conn).parse_buffer(data) or []
            first = msgs[0] if msgs else None
            if (
                first is not None
                and first.get_type() == "HEARTBEAT"
                and first.type == mavlink.MAV_TYPE_GCS
            ):
                self.peer = addr
                self.conn.destination_addr = addr
                self.conn.resolved_destination_addr = addr[0]
                return msgs
        self.strangers += 1
        return []

    def _for_me(self, msg: Any) -> bool:
        target = getattr(msg, "target_system", 0)
        return target in (0, self.spec.sysid)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            if msg.type == mavlink.MAV_TYPE_GCS:
                self.gcs_heartbeat_at = self.now()
            return
        if not self._for_me(msg):
            return
        if kind == "COMMAND_LONG":
            if msg.command == mavlink.MAV_CMD_DO_SET_MODE and self.autopilot is Autopilot.PX4:
                # PX4's MAVLink module acknowledges a mode change at once; its commander
                # decides on its next cycle and answers again (which may be a refusal)
                self._ack(msg, mavlink.MAV_RESULT_ACCEPTED)
                self.later.append(msg)
                return
            self._ack(msg, self._command(msg))
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self._position_target(msg)
        elif kind == "SET_ATTITUDE_TARGET":
            self._attitude_target(msg)
        elif kind == "SET_GPS_GLOBAL_ORIGIN":
            self.gps_origin = (msg.latitude, msg.longitude, msg.altitude)
            self._send_message(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)

    def _ack(self, msg: Any, result: int) -> None:
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        self.send(lambda mav: mav.command_ack_send(msg.command, result, 0, 0, src_sys, src_comp))

    def _decide_later(self) -> None:
        """The commands whose real answer comes a step after their first (PX4's mode changes)."""
        later, self.later = self.later, []
        for msg in later:
            self._ack(msg, self._command(msg))

    # ------------------------------------------------------------------ commands
    def _refuse(self, text: str, result: int = mavlink.MAV_RESULT_DENIED) -> int:
        self.text(mavlink.MAV_SEVERITY_CRITICAL, text)
        return result

    def _command(self, msg: Any) -> int:
        c = msg.command
        if c == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = int(msg.param1), msg.param2
            if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:  # always sent; only its rate changes
                if self.autopilot is Autopilot.PX4:  # PX4 keeps it at 1 Hz ("stream not found")
                    return mavlink.MAV_RESULT_FAILED
                self.heartbeat_s = 1.0 if interval_us <= 0 else interval_us / 1e6
                self.next_heartbeat = min(self.next_heartbeat, self.now() + self.heartbeat_s)
                return mavlink.MAV_RESULT_ACCEPTED
            if msg_id in self.unknown_messages:  # ArduPilot: no ap_message for it
                self.text(mavlink.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({msg_id})")
                return mavlink.MAV_RESULT_DENIED
            if interval_us < 0:
                self.intervals.pop(msg_id, None)
            else:
                self.intervals[msg_id] = 1.0 if interval_us == 0 else interval_us / 1e6
                self.next_send[msg_id] = self.now()
            return mavlink.MAV_RESULT_ACCEPTED
        if c == mavlink.MAV_CMD_REQUEST_MESSAGE:
            if int(msg.param1) in self.unknown_messages:
                return mavlink.MAV_RESULT_FAILED  # (ArduPilot's answer, without a text)
            if not self._send_message(int(msg.param1)):
                return mavlink.MAV_RESULT_UNSUPPORTED
            return mavlink.MAV_RESULT_ACCEPTED
        if c == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm_disarm(msg.param1 > 0.5, int(msg.param2) == 21196)
        if c == mavlink.MAV_CMD_DO_SET_MODE:
            return self._set_mode(custom_mode_of_command(self.autopilot, msg.param2, msg.param3))
        if c == mavlink.MAV_CMD_NAV_TAKEOFF:
            return self._takeoff(msg.param7)
        if c == mavlink.MAV_CMD_NAV_LAND:
            if self.copter and not self.armed():  # LAND on the ground (_set_copter_mode)
                return self._set_mode(COPTER_LAND)
            return self._result(self.backend.land())
        return mavlink.MAV_RESULT_UNSUPPORTED

    def _result(self, ack: Any) -> int:
        if ack.accepted:
            return mavlink.MAV_RESULT_ACCEPTED
        return self._refuse(ack.reason)

    def _arm_disarm(self, arm: bool, force: bool) -> int:
        tel = self.backend.telemetry()
        if not arm:
            if not self.armed():
                return mavlink.MAV_RESULT_ACCEPTED
            if self.ground:
                self.rover_armed = False
                self.backend.set_velocity_setpoint(np.zeros(3), 0.0)
                return mavlink.MAV_RESULT_ACCEPTED
            if not tel.landed and not force:
                return self._refuse(
                    "Disarming denied: not landed"
                    if self.autopilot is Autopilot.PX4
                    else "Arm: disarm refused, vehicle flying",
                    mavlink.MAV_RESULT_DENIED
                    if self.autopilot is Autopilot.PX4
                    else mavlink.MAV_RESULT_FAILED,
                )
            return self._result(self.backend.disarm())
        if self.armed():
            return mavlink.MAV_RESULT_ACCEPTED  # already armed
        px4 = self.autopilot is Autopilot.PX4
        refuse = self.cfg.refuse_arm and not self.cfg.refuse_arm_times  # always
        if self.arm_refusals_left > 0:  # the first ones only
            self.arm_refusals_left -= 1
            refuse = True
        if refuse and not force:
            return self._refuse(
                ("Preflight Fail: " if px4 else "PreArm: ")
                + (self.cfg.refuse_arm or "sensors not ready"),
                mavlink.MAV_RESULT_DENIED if px4 else mavlink.MAV_RESULT_FAILED,
            )
        if not self.ekf_ready() and not force:
            if px4:
                return self._refuse(
                    "Arming denied: Preflight: estimator not ready",
                    mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
                )
            return self._refuse(
                "PreArm: EKF3 waiting for GPS config data", mavlink.MAV_RESULT_FAILED
            )
        if self.offboard_asked and not self.streaming() and not force:
            return self._refuse(
                "Arming denied: Resolve system health failures first",
                mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
            )
        if not armable(self.autopilot, self.spec.kind, self.custom_mode()):
            return self._refuse("Arm: Mode not armable", mavlink.MAV_RESULT_FAILED)
        if self.ground:
            self.rover_armed = True
            return mavlink.MAV_RESULT_ACCEPTED
        return self._result(self.backend.arm())

    def _set_mode(self, custom: int) -> int:
        if custom == self.custom_mode():
            return mavlink.MAV_RESULT_ACCEPTED  # already in that mode
        if self.copter:
            result = self._set_copter_mode(custom)
            self.seen_mode = self.backend.telemetry().mode
            return result
        return self._set_mode_of_backend(custom)

    def _set_copter_mode(self, custom: int) -> int:
        """An ArduCopter's mode change: LOITER on the simulator's HOLD, any other through
        :meth:`_set_mode_of_backend`; the modes kept on disarming are left."""
        self.kept_land = False
        self.loiter = False
        if custom == COPTER_LAND and not self.armed():
            # ModeLand allows entry on the ground: a disarmed copter shows LAND (and refuses
            # to arm there), on the simulator's MANUAL as a copter that landed in LAND does
            self.backend.set_mode(Mode.MANUAL)
            self.kept_land = True
            return mavlink.MAV_RESULT_ACCEPTED
        if custom != COPTER_LOITER:
            return self._set_mode_of_backend(custom)
        if not self.ekf_ready():
            return self._refuse("Mode change failed: requires position", mavlink.MAV_RESULT_FAILED)
        result = self._result(self.backend.set_mode(Mode.HOLD))
        self.loiter = result == mavlink.MAV_RESULT_ACCEPTED
        return result

    def _set_mode_of_backend(self, custom: int) -> int:
        mode = mode_of(self.autopilot, self.spec.kind, custom)
        if not isinstance(mode, Mode):
            return self._refuse(
                f"Mode change failed: {mode} not simulated", mavlink.MAV_RESULT_FAILED
            )
        if custom == self.custom_mode():
            return mavlink.MAV_RESULT_ACCEPTED  # already in that mode
        if self.autopilot is Autopilot.PX4:
            if mode in (Mode.OFFBOARD, Mode.HOLD, Mode.TAKEOFF) and not self.ekf_ready():
                name = {Mode.OFFBOARD: "Offboard", Mode.HOLD: "Hold", Mode.TAKEOFF: "Takeoff"}
                return self._refuse(
                    f"Switching to {name[mode]} is currently not available",
                    mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
                )
            self.offboard_asked = False  # (any mode asked for replaces them)
            self.takeoff_asked = None
            if mode is Mode.OFFBOARD:
                lost = self.state.offboard_lost
                if self.ground and not self.streaming():  # the robots' own rule is laxer
                    ack = Ack(False, "not streaming")
                else:
                    ack = self.backend.set_mode(Mode.OFFBOARD)
                if not ack.accepted:  # a refused request leaves PX4's failsafe as it was: its
                    self.state.offboard_lost = lost  # HOLD still ends when setpoints resume
                if not ack.accepted and not self.ground and not self.armed():
                    # PX4 v1.16 SITL: a disarmed drone takes OFFBOARD without setpoints (and
                    # then refuses to arm until they stream: _arm_disarm)
                    self.offboard_asked = True
                    return mavlink.MAV_RESULT_ACCEPTED
                if not ack.accepted:
                    return self._refuse(
                        "Switching to Offboard is currently not available",
                        mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
                    )
                return mavlink.MAV_RESULT_ACCEPTED
            if mode is Mode.TAKEOFF:
                return self._takeoff(math.nan)
            return self._result(self.backend.set_mode(mode))
        # ArduPilot
        if mode is Mode.OFFBOARD:  # GUIDED
            if not self.ekf_ready():
                return self._refuse(
                    "Mode change failed: requires position", mavlink.MAV_RESULT_FAILED
                )
            self._enter_guided(self.backend.telemetry().position.copy())
            return mavlink.MAV_RESULT_ACCEPTED
        if mode is Mode.HOLD and not self.ekf_ready():
            return self._refuse("Mode change failed: requires position", mavlink.MAV_RESULT_FAILED)
        if mode is Mode.MANUAL and not self.backend.telemetry().landed:
            return self._result(self.backend.set_mode(Mode.MANUAL))
        return self._result(self.backend.set_mode(mode))

    def _enter_guided(self, hold: np.ndarray) -> None:
        """ArduPilot GUIDED on the simulator's OFFBOARD: its targets are fed every step."""
        v = self.state
        t = self.now()
        self.guided = _Guided("hold", hold.copy(), since=t)
        v.sp_kind, v.sp_pos, v.sp_vel, v.sp_yaw = "position", hold.copy(), np.zeros(3), None
        v.sp_time, v.stream_since = t, -math.inf
        self.backend.set_mode(Mode.OFFBOARD)

    def _takeoff(self, param7: float) -> int:
        tel = self.backend.telemetry()
        if self.spec.kind is VehicleKind.GROUND:
            return self._refuse("Takeoff denied: not a multicopter", mavlink.MAV_RESULT_UNSUPPORTED)
        if self.autopilot is Autopilot.PX4:
            alt = 2.5 if math.isnan(param7) else param7 - self.cfg.home_amsl_m
            if not alt > 0:
                return self._refuse(f"Takeoff denied: altitude {alt:.1f} m below home")
            if not tel.armed:  # PX4 v1.16 SITL: ACCEPTED, in Takeoff; it leaves once armed
                self.offboard_asked = False
                self.takeoff_asked = alt
                return mavlink.MAV_RESULT_ACCEPTED
            return self._result(self.backend.takeoff(alt))
        if not tel.armed:
            return self._refuse("Takeoff refused: not armed", mavlink.MAV_RESULT_FAILED)
        mode = mode_of(self.autopilot, self.spec.kind, self.custom_mode())
        if mode is not Mode.OFFBOARD:
            return self._refuse("Takeoff: not in GUIDED mode", mavlink.MAV_RESULT_FAILED)
        if not tel.landed:
            return self._refuse("Takeoff: already flying", mavlink.MAV_RESULT_FAILED)
        target = tel.position.copy()
        target[2] = tel.ground_z + float(param7)
        self.guided = _Guided(
            "position", target, since=self.now(), taking_off=True, spool_until=self.now() + SPOOL_S
        )
        return mavlink.MAV_RESULT_ACCEPTED

    # ------------------------------------------------------------------ setpoints
    def _position_target(self, msg: Any) -> None:
        if msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:
            self.ignored_frames += 1  # only the frame the provider uses is simulated
            return
        mask = msg.type_mask
        t = self.now()
        self._streamed()
        position = self.frame.to_world((msg.x, msg.y, msg.z))
        velocity = self.frame.vector_to_world((msg.vx, msg.vy, msg.vz))
        yaw = None if mask & YAW_IGNORE else self.frame.yaw_to_world(msg.yaw)
        yaw_rate = 0.0 if mask & YAW_RATE_IGNORE else self.frame.yaw_rate_to_world(msg.yaw_rate)
        if mask & POSITION_IGNORE:
            kind = "velocity"
        else:
            kind = "position"
        if self.autopilot is Autopilot.ARDUPILOT:
            if mode_of(self.autopilot, self.spec.kind, self.custom_mode()) is not Mode.OFFBOARD:
                return  # GUIDED targets only count in GUIDED
            tel = self.backend.telemetry()
            if tel.landed and self.spec.kind is VehicleKind.MULTIROTOR:
                # as ArduCopter: a target leaves GUIDED's take-off submode, and on the ground
                # it does not lift off (a NAV_TAKEOFF followed at once by targets stays put)
                self.guided = _Guided("hold", tel.position.copy(), since=t)
                return
            self.guided = _Guided(
                kind,
                position if kind == "position" else self.backend.telemetry().position,
                velocity if not mask & VELOCITY_IGNORE else np.zeros(3),
                yaw,
                yaw_rate,
                since=t,
            )
            if (
                kind == "position"
                and self.backend.telemetry().landed
                and self.spec.kind is VehicleKind.MULTIROTOR
            ):
                self.guided.position = self.backend.telemetry().position.copy()
            return
        if self.ground:  # PX4 rover: drives on velocity setpoints, armed and in OFFBOARD
            drive = self.rover_armed and self.backend.telemetry().mode is Mode.OFFBOARD
            self.backend.set_velocity_setpoint(
                velocity if drive else np.zeros(3), yaw_rate if drive else 0.0
            )
        elif kind == "velocity":
            self.backend.set_velocity_setpoint(velocity, yaw_rate)
        else:
            vel = None if mask & VELOCITY_IGNORE else velocity
            self.backend.set_position_setpoint(position, vel, yaw)

    def _attitude_target(self, msg: Any) -> None:
        if self.spec.kind is VehicleKind.GROUND:
            return
        w, x, y, z = msg.q
        target = AttitudeTarget(msg.type_mask, (w, x, y, z), msg.body_yaw_rate, msg.thrust)
        thrust, roll, pitch, yaw_rate = attitude_from_target(
            self.frame, target, hover=self.cfg.hover_thrust
        )
        t = self.now()
        self._streamed()
        if self.autopilot is Autopilot.ARDUPILOT:
            if mode_of(self.autopilot, self.spec.kind, self.custom_mode()) is not Mode.OFFBOARD:
                return
            if self.backend.telemetry().landed and thrust <= G:
                return  # on the ground, only more than hover thrust lifts it (as ArduCopter)
            self.guided = _Guided("attitude", attitude=(thrust, roll, pitch),
                                  yaw_rate=yaw_rate, since=t)  # fmt: skip
            return
        self.backend.set_attitude_setpoint(thrust, roll, pitch, yaw_rate)

    # ------------------------------------------------------------------ per step
    def step(self) -> None:
        """The firmware's own logic this step (failsafes, GUIDED targets)."""
        self._track_mode()
        t = self.now()
        tel = self.backend.telemetry()
        flying = tel.armed and not tel.landed
        if not tel.landed:
            self.touchdown_at = math.inf
        elif self.touchdown_at == math.inf:
            self.touchdown_at = t
        if (
            self.ground
            and tel.mode is Mode.OFFBOARD
            and (
                self.autopilot is Autopilot.PX4
                and t - self.last_setpoint_t > self.cfg.offboard_loss_s
            )
        ):
            self.backend.set_mode(Mode.HOLD)
            self.failsafe_note = (
                f"offboard setpoints lost for more than {self.cfg.offboard_loss_s:g} s"
            )
            self.text(mavlink.MAV_SEVERITY_CRITICAL, "Failsafe: offboard lost, holding")
        if self.ground and not self.rover_armed:
            self.backend.set_velocity_setpoint(np.zeros(3), 0.0)
            return
        if self.autopilot is Autopilot.PX4:
            if self.position_fallback():  # no RC: Position mode sinks (seen 5.2 m -> 0.1 m)
                v = self.state
                v.hold[2] = max(v.hold[2] - PX4_POSITION_SINK_M_S * self.cfg.step_s, v.ground + 0.1)
            if self.offboard_asked and (
                self.backend.set_mode(Mode.OFFBOARD).accepted or tel.armed
            ):  # the setpoints stream now: the simulator's OFFBOARD (armed by force: its mode)
                self.offboard_asked = False
            if self.takeoff_asked is not None and tel.armed:  # armed in Takeoff: it takes off
                self.backend.takeoff(self.takeoff_asked)
                self.takeoff_asked = None
            dll = self.cfg.datalink_loss_s
            if (
                flying
                and dll is not None
                and self.gcs_heartbeat_at < t - dll
                and tel.mode is not Mode.LAND
            ):
                self.backend.land()
                self.failsafe_note = "data link lost: landing"
                self.text(mavlink.MAV_SEVERITY_CRITICAL, "Failsafe: no GCS link, landing")
            return
        gcs = self.cfg.gcs_failsafe_s
        if (
            flying
            and gcs is not None
            and self.gcs_heartbeat_at < t - gcs
            and tel.mode is not Mode.LAND
        ):
            self.backend.land()
            self.failsafe_note = "GCS failsafe: landing"
            self.text(mavlink.MAV_SEVERITY_CRITICAL, "GCS Failsafe On: LAND")
            return
        if self.loiter and flying and tel.mode is Mode.HOLD:  # no RC: the throttle stick is down
            v = self.state
            v.hold[2] = max(v.hold[2] - LOITER_SINK_M_S * self.cfg.step_s, v.ground - 1.0)
        if self.copter and tel.mode is Mode.OFFBOARD and not self.armed():
            self.state.sp_time = t  # GUIDED has no target timeout on the ground: it stays
        if tel.mode is not Mode.OFFBOARD or not self.armed():
            return
        g = self.guided
        if g.kind == "velocity" and t - g.since > 3.0:  # stop, then hold where it stopped
            self.guided = g = _Guided("hold", tel.position.copy(), since=t, braking=True)
        if g.braking and float(np.linalg.norm(tel.velocity)) < 0.1:
            g.position, g.braking = tel.position.copy(), False
        if g.kind == "attitude" and t - g.since > 1.0:
            self.guided = g = _Guided("hold", tel.position.copy(), since=t)
        if g.taking_off and not tel.landed and abs(tel.position[2] - g.position[2]) < 0.2:
            g.taking_off = False
        b = self.backend
        if g.taking_off and t < g.spool_until:  # spooling up: still on the ground
            ground = tel.position.copy()
            b.set_position_setpoint(ground, None, g.yaw)
        elif g.kind == "velocity" or g.braking:
            b.set_velocity_setpoint(g.velocity, g.yaw_rate)
        elif g.kind == "attitude":
            b.set_attitude_setpoint(*g.attitude, g.yaw_rate)
        elif self.spec.kind is VehicleKind.GROUND:
            b.set_velocity_setpoint(np.zeros(3), 0.0)
        else:
            b.set_position_setpoint(g.position, g.velocity if g.kind == "position" else None, g.yaw)

    # ------------------------------------------------------------------ telemetry
    def send_due(self) -> None:
        self._track_mode()  # (a disarm in this step shows in this step's heartbeat)
        t = self.now()
        if t >= self.next_heartbeat:
            self.next_heartbeat = t + self.heartbeat_s
            self._send_message(mavlink.MAVLINK_MSG_ID_HEARTBEAT)
        px4 = self.autopilot is Autopilot.PX4
        if px4 and CURRENT_MODE_ID in self.intervals and self.custom_mode() != self.mode_sent:
            self.next_send[CURRENT_MODE_ID] = t  # (PX4 sends it on each change)
        for msg_id, interval in list(self.intervals.items()):
            if px4 and msg_id == CURRENT_MODE_ID:
                interval = max(interval, PX4_CURRENT_MODE_S)
            if t + 1e-9 >= self.next_send.get(msg_id, 0.0):
                self.next_send[msg_id] = max(self.next_send.get(msg_id, t) + interval, t)
                self._send_message(msg_id)

    def _send_message(self, msg_id: int) -> bool:
        tel = self.backend.telemetry()
        ms = self._boot_ms()
        fr = self.frame
        px4 = self.autopilot is Autopilot.PX4
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            kind = self.spec.kind
            mav_type = (
                mavlink.MAV_TYPE_QUADROTOR
                if kind is VehicleKind.MULTIROTOR
                else mavlink.MAV_TYPE_GROUND_ROVER
            )
            ap = mavlink.MAV_AUTOPILOT_PX4 if px4 else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            armed = self.armed()
            if armed:
                base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            status = mavlink.MAV_STATE_ACTIVE if armed else mavlink.MAV_STATE_STANDBY
            if armed and self.failsafe_note and self.backend.telemetry().mode is Mode.LAND:
                status = mavlink.MAV_STATE_CRITICAL  # as PX4 and ArduCopter, in a failsafe
            if self.position_fallback():
                status = mavlink.MAV_STATE_CRITICAL
            custom = self.custom_mode()
            self.send(lambda mav: mav.heartbeat_send(mav_type, ap, base, custom, status))
        elif msg_id == CURRENT_MODE_ID:
            custom = self.mode_sent = self.custom_mode()
            self.send(lambda mav: mav.send(CurrentMode(0, custom, custom)))
        elif msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            if not self.position_known():
                return False
            p = fr.to_local(tel.position)
            v = fr.vector_to_local(tel.velocity)
            self.send(lambda mav: mav.local_position_ned_send(ms, *map(float, p), *map(float, v)))
        elif msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            yaw = fr.yaw_to_local(tel.yaw)
            rate = fr.yaw_rate_to_local(tel.yaw_rate)
            self.send(lambda mav: mav.attitude_send(ms, tel.roll, -tel.pitch, yaw, 0.0, 0.0, rate))
        elif msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            landed = MAV_LANDED_STATE[self.landed_state()]
            self.send(lambda mav: mav.extended_sys_state_send(0, landed))
        elif msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            pct = round(100 * tel.battery)
            mv = int(1000 * (13.2 + 3.6 * tel.battery))
            self.send(lambda mav: mav.sys_status_send(0, 0, 0, 500, mv, -1, pct, 0, 0, 0, 0, 0, 0))
        elif msg_id == mavlink.MAVLINK_MSG_ID_BATTERY_STATUS:
            pct = round(100 * tel.battery)
            volts = [int(1000 * (3.3 + 0.9 * tel.battery))] * 4 + [65535] * 6
            self.send(lambda mav: mav.battery_status_send(0, 0, 0, 2500, volts, -1, -1, -1, pct))
        elif msg_id == mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR:
            if self.spec.kind is VehicleKind.GROUND:
                return False
            most = PX4_RANGE_MAX_CM if px4 else 4000
            cm = min(round(100 * max(0.0, tel.height_above_ground)), most)
            if px4 and tel.landed:
                cm = PX4_RANGE_ON_GROUND_CM  # SIH's reading a few cm below its origin
            self.send(
                lambda mav: mav.distance_sensor_send(
                    ms,
                    1,
                    most,
                    cm,
                    mavlink.MAV_DISTANCE_SENSOR_LASER,
                    0,
                    mavlink.MAV_SENSOR_ROTATION_PITCH_270,
                    255,
                )
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
            alt_mm = int(1000 * self.cfg.home_amsl_m)
            self.send(
                lambda mav: mav.home_position_send(0, 0, alt_mm, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0)
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT and not px4:
            ok = self.ekf_ready()
            flags = (mavlink.EKF_ATTITUDE | mavlink.EKF_VELOCITY_HORIZ | mavlink.EKF_VELOCITY_VERT
                     | mavlink.EKF_POS_HORIZ_REL | mavlink.EKF_POS_VERT_ABS) if ok else mavlink.EKF_ATTITUDE  # fmt: skip
            self.send(lambda mav: mav.ekf_status_report_send(flags, 0.1, 0.1, 0.1, 0.1, 0.0))
        elif msg_id == mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS and px4:
            ok = self.ekf_ready()
            flags = (mavlink.ESTIMATOR_ATTITUDE | mavlink.ESTIMATOR_VELOCITY_HORIZ
                     | mavlink.ESTIMATOR_POS_HORIZ_REL | mavlink.ESTIMATOR_POS_VERT_ABS) if ok else mavlink.ESTIMATOR_ATTITUDE  # fmt: skip
            self.send(
                lambda mav: mav.estimator_status_send(
                    int(self.now() * 1e6), flags, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.5, 0.5
                )
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            if self.gps_origin is None:
                return False
            lat, lon, alt = self.gps_origin
            self.send(lambda mav: mav.gps_global_origin_send(lat, lon, alt, int(self.now() * 1e6)))
        elif msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            cap = (
                mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            )
            self.send(
                lambda mav: mav.autopilot_version_send(
                    cap, 0, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0
                )
            )
        else:
            return False
        return True

    def close(self) -> None:
        try:
            self.conn.close()
        except OSError:
            pass


class MavSim:
    """The simulator (module docstring): ``start()`` runs it in a thread, ``stop()`` ends it."""

    def __init__(self, config: MavSimConfig) -> None:
        self.config = config
        px4 = config.autopilot is Autopilot.PX4
        sim_config = SimConfig(
            step_s=config.step_s,
            land_speed_m_s=PX4_LAND_SPEED_M_S if px4 else COPTER_LAND_SPEED_M_S,
            land_crawl_m_s=PX4_LAND_CRAWL_M_S if px4 else None,
            land_crawl_alt_m=PX4_LAND_CRAWL_ALT_M,
            # (the simulator counts from touchdown, PX4 from its land detector's verdict)
            disarm_land_s=PX4_DISARM_LAND_S + PX4_LAND_DETECT_S if px4 else COPTER_DISARM_LAND_S,
        )
        self.simulator = Simulator(config.voxel_map, sim_config, seed=config.seed)
        self.autopilots: dict[str, _SimulatedAutopilot] = {}
        try:
            for spec in config.vehicles:
                if spec.kind is VehicleKind.GROUND:
                    backend = self.simulator.add_ground(spec.agent_id, spec.start)
                else:
                    backend = self.simulator.add_multirotor(spec.agent_id, spec.start)
                self.autopilots[spec.agent_id] = _SimulatedAutopilot(self, spec, backend)
        except BaseException:
            self.close()
            raise
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.steps = 0
        self.late_steps = 0
        self.paused_s = 0.0
        """Wall seconds the simulator was frozen and did not catch up (:meth:`run_forever`)."""
        self.pauses = 0
        self._wait: Callable[[float], object] = self._stop.wait
        """How the loop waits for its next step (a test's hand-moved clock replaces it)."""

    @property
    def endpoints(self) -> list[Endpoint]:
        return [
            Endpoint(a.spec.agent_id, a.url, a.spec.sysid, self.config.autopilot, a.spec.kind)
            for a in self.autopilots.values()
        ]

    def start(self) -> MavSim:
        self._thread = threading.Thread(target=self._guarded, name="mavsim", daemon=True)
        self._thread.start()
        return self

    def _guarded(self) -> None:
        try:
            self.run_forever()
        except BaseException as exc:
            self.error = exc

    def run_forever(self) -> None:
        """Step the vehicles in (scaled) real time until :meth:`stop`. A step that finds the
        loop less than :data:`FREEZE_S` behind the wall clock is late and the next ones catch
        up; more, and the simulator was frozen (stopped, suspended): the missed wall time is
        dropped (counted in :attr:`paused_s`) and the clock resumes where it stopped, as a
        lockstep SITL's does (module docstring)."""
        cfg = self.config
        wall0 = time.monotonic()
        while not self._stop.is_set():
            for ap in self.autopilots.values():
                ap.receive()
            for ap in self.autopilots.values():
                ap.step()
            self.simulator.step()
            self.steps += 1
            for ap in self.autopilots.values():
                ap.send_due()
            due = wall0 + self.simulator.time_s / cfg.speed
            delay = due - time.monotonic()
            if delay > 0:
                self._wait(delay)
            elif -delay > FREEZE_S:  # frozen: resume where it stopped
                wall0 -= delay
                self.paused_s -= delay
                self.pauses += 1
            else:
                self.late_steps += 1

    def drop_link(self, agent_id: str, seconds: float) -> None:
        """Fault: ``agent_id``'s vehicle neither sends nor hears anything for ``seconds``
        (simulated)."""
        ap = self.autopilots[agent_id]
        ap.drop_until = self.simulator.time_s + seconds

    def vehicle_state(self, agent_id: str) -> dict[str, Any]:
        ap = self.autopilots[agent_id]
        tel = ap.backend.telemetry()
        return {
            "position": tel.position.copy(),
            "velocity": tel.velocity.copy(),
            "yaw": tel.yaw,
            "mode": mode_of(ap.autopilot, ap.spec.kind, ap.custom_mode()),
            "armed": ap.armed(),
            "landed": tel.landed,
            "failsafe": ap.failsafe_note or ap.backend.failsafe,
            "received": ap.received,
            "strangers": ap.strangers,
            "setpoints": ap.setpoints,
            "ignored_frames": ap.ignored_frames,
        }

    def stamp_arrivals(self) -> dict[str, list[float]]:
        """From now on, note when each setpoint (SET_POSITION_TARGET_LOCAL_NED or
        SET_ATTITUDE_TARGET addressed to the vehicle) arrived, as ``time.time()`` seconds (module
        docstring); returns each vehicle's list, which the simulator's thread appends to."""
        return {aid: ap.stamp_arrivals() for aid, ap in self.autopilots.items()}

    def counters(self) -> dict[str, dict[str, int]]:
        if self.config.signing_key is None:
            return {}
        return {aid: signing_counters(ap.conn) for aid, ap in self.autopilots.items()}

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self.close()

    def close(self) -> None:
        for ap in self.autopilots.values():
            ap.close()

    def __enter__(self) -> MavSim:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _reaccepting_recv(conn: Any) -> Callable[[int | None], bytes]:
    """A TCP vehicle serves one ground station at a time and takes the next one when it hangs
    up (pymavlink's ``tcpin`` keeps the closed socket, so a reconnect would not be heard)."""

    def recv(n: int | None = None) -> bytes:
        if conn.port is None:
            try:
                port, _ = conn.listen.accept()
            except (BlockingIOError, InterruptedError):
                return b""
            port.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            port.setblocking(False)
            conn.port, conn.fd = port, port.fileno()
        try:
            data: bytes = conn.port.recv(n or 4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data:  # the ground station hung up: listen for the next one
            conn.port.close()
            conn.port, conn.fd = None, conn.listen.fileno()
        return data

    return recv


def default_address(
    autopilot: Autopilot,
    index: int,
    base: int | None = None,
    *,
    transport: str | None = None,
    host: str = "127.0.0.1",
) -> MavlinkAddress:
    """Where vehicle ``index`` is served by default: as its firmware's SITL does (PX4: UDP
    14540 + i; ArduPilot: TCP 5760 + 10 i), or over ``transport`` from ``base`` (ports
    ``base + i`` for UDP, ``base + 10 i`` for TCP)."""
    transport = transport or ("udp" if autopilot is Autopilot.PX4 else "tcp")
    if transport == "udp":
        return MavlinkAddress("udp", host, (PX4_UDP_BASE if base is None else base) + index)
    if transport == "tcp":
        return MavlinkAddress(
            "tcp", host, (ARDUPILOT_TCP_BASE if base is None else base) + 10 * index
        )
    raise ValueError(f"mavsim serves udp or tcp, not {transport}")


def vehicles_in_a_row(
    count: int,
    autopilot: Autopilot,
    *,
    base_port: int | None = None,
    transport: str | None = None,
    host: str = "127.0.0.1",
    spacing_m: float = 3.0,
    kind: VehicleKind = VehicleKind.MULTIROTOR,
    origin: Sequence[float] = (5.0, 5.0, 0.0),
) -> tuple[VehicleSpec, ...]:
    """``count`` vehicles 3 m apart along +x (``--count N``), numbered as the SITLs number
    them (:func:`sitl_sysid`)."""
    out = []
    for i in range(count):
        address = default_address(autopilot, i, base_port, transport=transport, host=host)
        start = (float(origin[0]) + spacing_m * i, float(origin[1]), float(origin[2]))
        out.append(
            VehicleSpec(f"V{i + 1}", kind, start, address, sitl_sysid(autopilot, address, i))
        )
    return tuple(out)


def sitl_sysid(autopilot: Autopilot | None, address: MavlinkAddress, index: int) -> int:
    """Vehicle ``index``'s system id as the SITLs give it: every ArduCopter SITL instance is
    sysid 1, each on its own TCP port (ArduCopter 4.7.0-dev SITL, three instances), where PX4
    SITL instance i is ``MAV_SYS_ID`` = i + 1. Vehicles sharing a UDP port need distinct ones,
    so a UDP vehicle is i + 1 whatever the firmware."""
    if autopilot is Autopilot.ARDUPILOT and address.transport == "tcp":
        return 1
    return index + 1


def mission_vehicles(mission: Any, autopilot: Autopilot | None = None) -> tuple[VehicleSpec, ...]:
    """One vehicle per agent of ``mission`` whose backend is a ``mavlink+udp`` or
    ``mavlink+tcp`` URL, served at that URL (``--mission``): spawned at the agent's start, a
    ground robot if its library drives one, sysid from the URL's ``?sysid=``, else as
    ``autopilot``'s SITL numbers it (:func:`sitl_sysid`; the i-th such agent i + 1 when no
    autopilot is given)."""
    from btmission.backends.mavlink_url import parse_mavlink_url

    out: list[VehicleSpec] = []
    for agent in mission.agents:
        if agent.vehicle.scheme != "mavlink":
            continue
        address = parse_mavlink_url(agent.backend)
        if address.transport not in ("udp", "tcp"):
            continue
        impl = mission.library_of(agent.id).implementations
        kind = VehicleKind.of(impl.vehicle if impl is not None else None)
        start = (float(agent.start[0]), float(agent.start[1]), float(agent.start[2]))
        sysid = address.sysid or sitl_sysid(autopilot, address, len(out))
        out.append(VehicleSpec(agent.id, kind, start, address, sysid))
    return tuple(out)


def shared_endpoints(specs: Sequence[VehicleSpec]) -> list[str]:
    """Why these vehicles cannot all be served: two on one TCP port (a port has one listener),
    or two with one sysid on one UDP port (the ground station could not tell them apart)."""
    seen: dict[tuple[Any, ...], str] = {}
    out = []
    for s in specs:
        a = s.address
        key: tuple[Any, ...] = (a.transport, a.host, a.port)
        if a.transport == "udp":
            key += (s.sysid,)
        if key in seen:
            what = "TCP port" if a.transport == "tcp" else f"UDP port and sysid {s.sysid}"
            out.append(f"{s.agent_id} and {seen[key]} share the {what} {a.host}:{a.port}")
        seen.setdefault(key, s.agent_id)
    return out
