"""``btmission mavsim``: serve simulated PX4 or ArduPilot vehicles over MAVLink on 127.0.0.1."""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path
from types import FrameType
from typing import Any

import click

from btmission.cli.common import BadInput, FiniteFloat, handle_spec_errors


class _EkfDelay(FiniteFloat):
    """``--ekf-delay``: seconds in [0, 3600], or ``sitl`` (the firmware's SITL's)."""

    def __init__(self) -> None:
        super().__init__(0, 3600)

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, str) and value.strip().lower() == "sitl":
            return "sitl"
        return float(super().convert(value, param, ctx))


@click.command("mavsim")
@click.option(
    "--mission",
    "mission_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Serve one vehicle per agent whose backend is a mavlink+udp/tcp URL, at that URL, "
    "spawned at the agent's start in the mission's world.",
)
@click.option(
    "--count", type=click.IntRange(1, 100), help="Serve N vehicles 3 m apart in an empty world."
)
@click.option(
    "--autopilot",
    type=click.Choice(["px4", "ardupilot"]),
    help="Firmware behaviour: PX4 (OFFBOARD, UDP 14540+i) or ArduPilot (GUIDED, TCP 5760+10i) "
    "[default: as the SITLs serve them: ardupilot for a mission's mavlink+tcp agents, else px4].",
)
@click.option(
    "--transport",
    type=click.Choice(["udp", "tcp"]),
    help="For --count: UDP (the ground station listens, PX4 SITL's way) or TCP (the vehicle "
    "listens, ArduPilot SITL's way) [default: the firmware's].",
)
@click.option(
    "--port",
    type=click.IntRange(1, 65535),
    help="First port for --count: vehicle i at PORT + i (UDP) or PORT + 10 i (TCP) "
    "[default: 14540 for UDP, 5760 for TCP].",
)
@click.option(
    "--host",
    default="127.0.0.1",
    show_default=True,
    help="Address to serve on (an IPv4 address of this machine). Anything but loopback makes "
    "the vehicles reachable from the network: a warning is printed.",
)
@click.option(
    "--speed",
    type=FiniteFloat(0.1, 50),
    help="Simulated seconds per wall second [default: the mission's runtime.mavlink.time_scale, "
    "else 1]; the run's time_scale must match.",
)
@click.option(
    "--ekf-delay", type=_EkfDelay(), default="0", show_default=True, metavar="SECONDS|sitl",
    help="Seconds before the estimator is ready: arming and GUIDED refused, no "
    "LOCAL_POSITION_NED until then. 'sitl': as long as the firmware's SITL took (ArduCopter "
    "42 s, PX4 4 s of vehicle time).",
)  # fmt: skip
@click.option(
    "--datalink-loss", type=FiniteFloat(0, 3600, min_open=True), metavar="SECONDS",
    help="PX4: land after SECONDS without the ground station's heartbeat while flying "
    "(NAV_DLL_ACT = land after COM_DL_LOSS_T) [default: off, as the firmware ships it].",
)  # fmt: skip
@click.option(
    "--offboard-loss", type=click.Choice(["position", "hold"]), default="position",
    show_default=True,
    help="PX4's offboard-loss action (COM_OBL_RC_ACT): 'position', the firmware's default, "
    "flies Position mode, which without RC sinks and says CRITICAL until the setpoints "
    "return; 'hold' holds.",
)  # fmt: skip
@click.option(
    "--gcs-failsafe", type=FiniteFloat(0, 3600, min_open=True), metavar="SECONDS",
    help="ArduPilot: land after SECONDS without the ground station's heartbeat while flying "
    "(FS_GCS_ENABLE = land after FS_GCS_TIMEOUT) [default: off, as the firmware ships it].",
)  # fmt: skip
@click.option("--refuse-arm", default="", help="A pre-arm check that always fails with this text.")
@click.option(
    "--refuse-arm-times", type=click.IntRange(0), default=0, show_default=True,
    help="Refuse only each vehicle's first N arming commands (the --refuse-arm text, else "
    "'sensors not ready'), then arm: a refusal the run retries and gets over.",
)  # fmt: skip
@click.option(
    "--signing-key-file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="MAVLink 2 signing key (64 hex digits or a passphrase); also BTMISSION_MAVLINK_KEY_FILE "
    "or BTMISSION_MAVLINK_KEY. Unsigned or badly signed messages are dropped and counted.",
)
@click.option(
    "--hover-thrust", type=FiniteFloat(0.05, 1.0), default=0.5, show_default=True,
    help="Normalised throttle that hovers (attitude setpoints).",
)  # fmt: skip
@click.option(
    "--seed", type=click.IntRange(0), default=0, show_default=True,
    help="Seed of the simulator's sensor noise.",
)  # fmt: skip
@click.option("--quiet", is_flag=True, help="Print only the ready line and errors.")
@click.option(
    "--duration", type=FiniteFloat(0, min_open=True), help="Stop after this many wall seconds."
)
@click.option(
    "--backend",
    "backends",
    multiple=True,
    metavar="AGENT=URL",
    help="With --mission: serve AGENT's vehicle at this mavlink+udp/tcp URL instead of its "
    "backend (repeatable); how an agent of a simulator mission gets a vehicle another process "
    "can fly (run --processes uses it).",
)
@click.option(
    "--arrivals",
    is_flag=True,
    hidden=True,
    help="For btmission bench mavlink: note when each setpoint arrives; a line "
    "'arrivals T0 T1' on standard input prints those between T0 and T1 (time.time() seconds) "
    "as one JSON line {agent: [times]}; the end of standard input stops the simulator.",
)
@handle_spec_errors
def mavsim(
    mission_path: Path | None,
    count: int | None,
    autopilot: str | None,
    transport: str | None,
    port: int | None,
    host: str,
    speed: float | None,
    ekf_delay: float | str,
    datalink_loss: float | None,
    offboard_loss: str,
    gcs_failsafe: float | None,
    refuse_arm: str,
    refuse_arm_times: int,
    signing_key_file: Path | None,
    hover_thrust: float,
    seed: int,
    quiet: bool,
    duration: float | None,
    backends: tuple[str, ...],
    arrivals: bool,
) -> None:
    """Simulated MAVLink vehicles for flying missions without hardware.

    Each vehicle is one of the embedded simulator's, behind a MAVLink 2 endpoint that behaves
    like PX4 or ArduPilot SITL: heartbeats, requested streams, COMMAND_ACKs with the firmware's
    refusals, PX4's offboard rules and failsafes or ArduPilot's GUIDED. Everything binds
    127.0.0.1 (see --host). Prints one line per vehicle (agent, URL, sysid, firmware, kind),
    then "ready"; Ctrl-C or SIGTERM stops it, printing the simulated time and, with signing, the
    messages each vehicle accepted and refused. Example:

    \b
      btmission mavsim --mission missions/mine_inspection_px4.yaml --speed 4 &
      btmission run missions/mine_inspection_px4.yaml
    """
    from btmission.backends.mavlink_modes import Autopilot
    from btmission.backends.mavlink_signing import SigningKeyError, load_key
    from btmission.mavsim import (
        SITL_EKF_DELAY_S,
        MavSim,
        MavSimConfig,
        shared_endpoints,
        vehicles_in_a_row,
    )
    from btmission.world.minegen import empty_world

    if (mission_path is None) == (count is None):
        raise BadInput("give either --mission FILE or --count N")
    if backends and mission_path is None:
        raise BadInput("--backend goes with --mission")
    if mission_path is not None and (transport is not None or port is not None):
        raise BadInput("--transport and --port go with --count; --mission serves each agent at "
                       "its backend URL")  # fmt: skip
    _check_host(host)
    ap = Autopilot(autopilot or "px4")
    try:
        key = load_key(signing_key_file)
    except SigningKeyError as exc:
        raise BadInput(str(exc)) from None
    if mission_path is not None:
        from btmission.mavsim import mission_vehicles
        from btmission.missions import load_mission
        from btmission.world.build import world_from_spec

        mission = _with_backends(load_mission(mission_path), backends)
        specs = mission_vehicles(mission)
        if not specs:
            raise BadInput(
                f"{mission_path}: no agent has a mavlink+udp:// or mavlink+tcp:// backend to serve"
            )
        if autopilot is None and all(s.address.transport == "tcp" for s in specs):
            ap = Autopilot.ARDUPILOT
        specs = mission_vehicles(mission, ap)  # (numbered as ap's SITLs number them)
        elsewhere = [s for s in specs if s.address.host != host]
        if elsewhere:
            far = elsewhere[0]
            raise BadInput(
                f"{mission_path}: agent {far.agent_id}: its backend is at {far.address.host}, "
                f"but mavsim serves on {host} (--host {far.address.host} to serve there)"
            )
        voxel_map = world_from_spec(mission.spec.world, mission.base_dir)
        if speed is None:
            speed = mission.spec.runtime.mavlink.time_scale
    else:
        assert count is not None
        specs = vehicles_in_a_row(count, ap, base_port=port, transport=transport, host=host)
        if any(s.address.port > 65535 for s in specs):
            raise BadInput(f"--port {port}: {count} vehicles do not fit below port 65536")
        voxel_map = empty_world((10.0 + 3.0 * count, 20.0, 10.0), 0.5)
    clashes = shared_endpoints(specs)
    if clashes:
        raise BadInput(f"{mission_path}: " + "; ".join(clashes))
    speed = 1.0 if speed is None else speed
    if ekf_delay == "sitl":
        ekf_delay = SITL_EKF_DELAY_S[ap]
    assert isinstance(ekf_delay, float)
    config = MavSimConfig(
        specs, voxel_map, autopilot=ap, speed=speed, ekf_delay_s=ekf_delay,
        refuse_arm=refuse_arm, refuse_arm_times=refuse_arm_times, signing_key=key,
        hover_thrust=hover_thrust, seed=seed, datalink_loss_s=datalink_loss,
        gcs_failsafe_s=gcs_failsafe, offboard_loss_action=offboard_loss,
    )  # fmt: skip
    try:
        sim = MavSim(config)
    except OSError as exc:
        raise BadInput(f"cannot serve the vehicles: {exc.strerror or exc}") from None
    for ep in [] if quiet else sim.endpoints:
        click.echo(
            f"{ep.agent_id}  {ep.url}  sysid {ep.sysid}  {ep.autopilot.value} {ep.kind.value}"
        )
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    if arrivals:
        stamps = sim.stamp_arrivals()
        threading.Thread(
            target=_answer_arrivals, args=(stamps, stop), name="arrivals", daemon=True
        ).start()
    sim.start()
    click.echo(f"ready ({len(sim.endpoints)} vehicle(s), {ap.value}, speed {speed:g}x)")
    sys.stdout.flush()
    t0 = time.monotonic()
    try:
        while not stop.wait(0.2):
            if sim.error is not None:
                raise sim.error
            if duration is not None and time.monotonic() - t0 >= duration:
                break
    finally:
        sim.stop()
        for s, handler in previous.items():
            signal.signal(s, handler)
    late = f", {sim.late_steps} late step(s)" if sim.late_steps else ""
    if sim.pauses:
        late += f", paused {sim.paused_s:.1f} s wall in {sim.pauses} freeze(s)"
    if quiet:
        return
    click.echo(f"stopped after {sim.simulator.time_s:.1f} simulated s ({sim.steps} steps{late})")
    for agent, counts in sim.counters().items():
        click.echo(f"{agent} signing: " + ", ".join(f"{k} {v}" for k, v in counts.items()))


def _answer_arrivals(stamps: dict[str, list[float]], stop: threading.Event) -> None:
    """``--arrivals``: answer 'arrivals T0 T1' lines on standard input until it ends."""
    import json

    for line in sys.stdin:
        words = line.split()
        if len(words) == 3 and words[0] == "arrivals":
            t0, t1 = float(words[1]), float(words[2])
            window = {aid: [t for t in list(ts) if t0 <= t <= t1] for aid, ts in stamps.items()}
            click.echo(json.dumps(window))
            sys.stdout.flush()
    stop.set()


def _with_backends(mission: Any, backends: tuple[str, ...]) -> Any:
    """``mission`` with ``AGENT=URL`` backends (checked: a known agent, a MAVLink URL)."""
    from btmission.backends.mavlink_url import parse_mavlink_url
    from btmission.runtime.distribution import with_backends

    out: dict[str, str] = {}
    ids = [a.id for a in mission.agents]
    for item in backends:
        agent, sep, url = item.partition("=")
        if not sep or agent not in ids:
            raise BadInput(
                f"--backend {item}: expected AGENT=URL with AGENT one of {', '.join(ids)}"
            )
        try:
            parse_mavlink_url(url)
        except ValueError as exc:
            raise BadInput(f"--backend {item}: {exc}") from None
        out[agent] = url
    return with_backends(mission, out, None) if out else mission


def _check_host(host: str) -> None:
    """``--host`` must be an IPv4 address; anything but loopback is served with a warning."""
    import ipaddress

    try:
        address = ipaddress.IPv4Address(host)
    except ValueError:
        raise BadInput(f"--host {host!r}: expected an IPv4 address such as 127.0.0.1") from None
    if not address.is_loopback:
        click.secho(
            f"warning: serving simulated vehicles on {host}: anyone who reaches this address "
            "can command them",
            err=True,
            fg="yellow",
        )
