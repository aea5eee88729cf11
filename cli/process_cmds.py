"""``btmission coordinator`` and ``btmission agent``: one mission spread over processes, linked by
Zenoh (docs/distributed.md). ``btmission run --processes`` (:func:`run_processes`) starts them
all on this machine, with ``mavsim`` serving the vehicles, and merges their logs."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

import click

from btmission.cli.common import (
    NON_NEGATIVE,
    POSITIVE,
    SEED,
    BadInput,
    ChecksFailed,
    echo_diagnostics,
    handle_spec_errors,
    internal_error_sink,
)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def _zenoh_or_exit() -> None:
    from btmission.transport.zenoh_session import NEEDS_NET, zenoh_available

    if not zenoh_available():
        raise BadInput(NEEDS_NET)


def _endpoints(values: Sequence[str], option: str) -> tuple[str, ...]:
    from btmission.transport.zenoh_session import check_endpoint, is_loopback

    out = []
    for v in values:
        try:
            out.append(check_endpoint(v))
        except ValueError as exc:
            raise BadInput(f"{option} {v}: {exc}") from None
        if option == "--listen" and not is_loopback(v):
            click.echo(
                f"warning: {option} {v} is reachable from other machines: use Zenoh's TLS and "
                "access control there (docs/distributed.md, 'Real deployments')",
                err=True,
            )
    return tuple(out)


def _session(
    mission_file: Path,
    *,
    seed: int,
    controller: str | None,
    log_dir: Path,
    log_file: Path | None,
    backends: dict[str, str],
    speed: float | None,
) -> Any:
    """A :class:`RunSession` for one part of the mission (loaded, with the backends and the
    time scale given on the command line)."""
    from btmission.cli.run_cmds import _StderrNotes
    from btmission.runtime.distribution import with_backends
    from btmission.runtime.session import RunSession

    session = RunSession(
        mission_file,
        seed=seed,
        controller=controller,
        realtime=True,
        log_dir=log_dir,
        log_path=log_file,
        observers=[_StderrNotes()],  # warnings and leaf errors as they come, once each
        handle_signals=True,
        notify=lambda text: click.echo(f"\n{text}", err=True),
    )
    mission = session.load()
    echo_diagnostics(session.warnings)
    services = [
        f"{lib.implementations.library} ({', '.join(lib.implementations.services)})"
        for lib in mission.libraries.values()
        if lib.implementations is not None and lib.implementations.services
    ]
    if services:
        raise BadInput(
            f"{mission_file}: its libraries have run-wide services that every agent calls in "
            f"one process: {', '.join(services)}; run it in one process (btmission run)"
        )
    unknown = sorted(set(backends) - {a.id for a in mission.agents})
    if unknown:
        raise BadInput(f"{mission_file}: no agent {unknown[0]} in this mission")
    session.mission = with_backends(mission, backends, speed)
    return session


def _check_log_file(log_file: Path | None) -> None:
    if log_file is not None and log_file.exists():
        raise BadInput(f"--log-file {log_file}: exists already (a log is never overwritten)")


_common = [
    click.option("--seed", default=0, show_default=True, type=SEED, help="Run seed (the log's)."),
    click.option(
        "--controller",
        type=click.Choice(["nmpc", "track"]),
        help="Path following (default: the mission's runtime.controller).",
    ),
    click.option(
        "--log",
        "log_dir",
        type=click.Path(file_okay=False, path_type=Path),
        default=Path("runs"),
        show_default=True,
        help="Directory for this process's event log.",
    ),
    click.option(
        "--log-file",
        type=click.Path(dir_okay=False, path_type=Path),
        help="This process's event log (instead of a new file in --log).",
    ),
    click.option(
        "--speed",
        type=POSITIVE,
        help="Mission time per wall second: the vehicles' speed-up, as mavsim --speed [default: "
        "the mission's runtime.mavlink.time_scale].",
    ),
    click.option(
        "--zenoh-config",
        type=click.Path(dir_okay=False, exists=True, path_type=Path),
        help="A Zenoh JSON5 configuration to start from (TLS, user/password, access control); "
        "the endpoints and scouting options given here override its own.",
    ),
    click.option("--quiet", is_flag=True, help="Print only the summary at the end."),
]


def common_options(fn: Any) -> Any:
    for option in reversed(_common):
        fn = option(fn)
    return fn


# ------------------------------------------------------------------------------- coordinator
@click.command("coordinator")
@click.argument("mission_file", metavar="MISSION", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--listen",
    multiple=True,
    default=(DEFAULT_ENDPOINT,),
    show_default=True,
    help="Zenoh endpoint the agents connect to (repeatable). Another host's interface "
    "(tcp/10.0.0.2:7447) for robots on a network.",
)
@click.option(
    "--wait-agents",
    type=NON_NEGATIVE,
    default=60.0,
    show_default=True,
    help="Wall seconds to wait for every agent of the mission before its clock starts; then it "
    "starts with those connected (the others join when they come).",
)
@click.option(
    "--until", type=POSITIVE, help="Stop at this mission time (s) even if the mission goes on."
)
@click.option(
    "--resume",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    help="Restart a coordinator that was stopped or killed: rebuild the tasks, holders and "
    "commitments from its log, continue its mission clock, and go on writing that log.",
)
@common_options
@handle_spec_errors
def coordinator_cmd(
    mission_file: Path,
    listen: tuple[str, ...],
    wait_agents: float,
    until: float | None,
    resume: Path | None,
    seed: int,
    controller: str | None,
    log_dir: Path,
    log_file: Path | None,
    speed: float | None,
    zenoh_config: Path | None,
    quiet: bool,
) -> None:
    """Run a mission's coordinator: the auction, the task pool and the event log, for agents
    in other processes or on other machines (btmission agent), over Zenoh.

    It listens on --listen (127.0.0.1 unless told otherwise; multicast scouting is off), waits
    for the mission's agents, then runs the auction rounds on the wall clock (sped up as the
    vehicles are). The mission ends when every task is settled and every agent it hears is at
    rest; the agents are told, and their processes stop. Ctrl-C or SIGTERM ends it the same way,
    with its log closed.

    \b
    Example (four terminals, or see run --processes):
      btmission mavsim --mission docs/examples/processes_small.yaml
      btmission coordinator docs/examples/processes_small.yaml
      btmission agent docs/examples/processes_small.yaml --id R1
      btmission agent docs/examples/processes_small.yaml --id R2

    Exit status: 0 every task done, 1 tasks left open, 2 bad input (a port in use),
    130 / 143 stopped by SIGINT / SIGTERM.
    """
    from btmission.runtime.distribution import Part
    from btmission.transport.zenoh_link import ZenohCoordinatorLink
    from btmission.transport.zenoh_session import TransportError, ZenohSettings

    _zenoh_or_exit()
    _check_log_file(log_file)
    if resume is not None and log_file is not None:
        raise click.UsageError("--resume goes on writing that log: no --log-file")
    endpoints = _endpoints(listen, "--listen")
    session = _session(
        mission_file, seed=seed, controller=controller, log_dir=log_dir,
        log_file=resume or log_file, backends={}, speed=speed,
    )  # fmt: skip
    mission = session.mission
    resumed = _resumable(resume, mission) if resume is not None else None
    settings = ZenohSettings.coordinator(
        endpoints, config_file=str(zenoh_config) if zenoh_config else None
    )
    try:
        link = ZenohCoordinatorLink(mission.name, settings=settings)
    except TransportError as exc:
        raise BadInput(str(exc)) from None
    try:
        click.echo(f"coordinator of {mission.name}: listening on {', '.join(endpoints)}")
        sys.stdout.flush()
        ids = [a.id for a in mission.agents]
        if wait_agents > 0 and not link.wait_for_agents(ids, wait_agents):
            missing = sorted(set(ids) - link.agents)
            click.echo(
                f"warning: {', '.join(missing)} not connected after {wait_agents:g} s; starting "
                "without (an agent joins when it connects)",
                err=True,
            )
        part = Part(coordinator_link=link, live_agents=lambda: link.agents)
        restore = None
        if resumed is not None:
            started, last_s, recovered = resumed
            part.started_unix, part.resumed_from, part.resumed_at_s = started, str(resume), last_s

            def restore(run: Any) -> None:
                run.coordinator.restore(recovered)
                click.echo(
                    f"coordinator: resumed {resume} at {last_s:.1f} s (round {recovered.round})",
                    err=True,
                )

        session.part = part
        code = _run_part(session, until, quiet, "coordinator", prepare=restore)
    finally:
        link.close()
    if code:
        sys.exit(code)


# ------------------------------------------------------------------------------------ agent
@click.command("agent")
@click.argument("mission_file", metavar="MISSION", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--id",
    "agent_ids",
    multiple=True,
    required=True,
    help="The mission's agent this process runs (repeatable: several agents in one process).",
)
@click.option(
    "--connect",
    multiple=True,
    default=(DEFAULT_ENDPOINT,),
    show_default=True,
    help="The coordinator's Zenoh endpoint (repeatable).",
)
@click.option(
    "--backend",
    help="The agent's vehicle, instead of the mission's backend: (one --id): e.g. "
    "mavlink+udp://127.0.0.1:14640, a vehicle btmission mavsim serves.",
)
@click.option(
    "--wait-coordinator",
    type=NON_NEGATIVE,
    default=60.0,
    show_default=True,
    help="Wall seconds to wait for the coordinator's first assignment (it sets this process's "
    "mission clock) before the agents start on their own clock.",
)
@common_options
@handle_spec_errors
def agent_cmd(
    mission_file: Path,
    agent_ids: tuple[str, ...],
    connect: tuple[str, ...],
    backend: str | None,
    wait_coordinator: float,
    seed: int,
    controller: str | None,
    log_dir: Path,
    log_file: Path | None,
    speed: float | None,
    zenoh_config: Path | None,
    quiet: bool,
) -> None:
    """Run agents of a mission (their trees, bids, navigation and vehicles) in this process,
    linked to the mission's coordinator (btmission coordinator) over Zenoh.

    Each agent flies the vehicle its backend names (or --backend): a MAVLink autopilot, real or
    served by btmission mavsim, so that every process's vehicles share one simulated world.
    The agents keep executing their task when the link to the coordinator is lost, and their
    progress reports wait until it returns. The process ends when the coordinator says the
    mission is over, or on Ctrl-C / SIGTERM (its log closed, its vehicles told to land).

    \b
    Example:
      btmission agent docs/examples/processes_small.yaml --id R1 --connect tcp/127.0.0.1:7447

    Exit status: 0 the mission completed, 1 it ended with tasks open (or the coordinator cannot
    be reached), 2 bad input, 130 / 143 stopped by SIGINT / SIGTERM.
    """
    from btmission.runtime.distribution import Part
    from btmission.transport.zenoh_link import agent_links
    from btmission.transport.zenoh_session import TransportError, ZenohSettings

    _zenoh_or_exit()
    _check_log_file(log_file)
    ids = tuple(dict.fromkeys(agent_ids))
    if backend is not None and len(ids) != 1:
        raise click.UsageError("--backend names one agent's vehicle: give exactly one --id")
    endpoints = _endpoints(connect, "--connect")
    backends = {ids[0]: backend} if backend is not None else {}
    session = _session(
        mission_file, seed=seed, controller=controller, log_dir=log_dir, log_file=log_file,
        backends=backends, speed=speed,
    )  # fmt: skip
    mission = session.mission
    known = [a.id for a in mission.agents]
    for a in ids:
        if a not in known:
            raise BadInput(
                f"--id {a}: no such agent in {mission_file} (agents: {', '.join(known)})"
            )
    for a in mission.agents:
        if a.id in ids and a.vehicle.scheme != "mavlink":
            raise BadInput(
                f"agent {a.id}'s backend is {a.backend}, a simulator that lives in one process: "
                "give --backend with a MAVLink vehicle (one btmission mavsim serves, run "
                "--processes does it for you)"
            )
    settings = ZenohSettings.agent(
        endpoints, config_file=str(zenoh_config) if zenoh_config else None
    )
    try:
        links = agent_links(mission.name, ids, settings, shared_session=True)
    except TransportError as exc:
        raise ChecksFailed(f"cannot reach the coordinator: {exc}") from None
    from btmission.transport.zenoh_link import close_all

    try:
        session.part = Part(
            agents=ids, agent_links=dict(zip(ids, links)), sync_timeout_s=wait_coordinator
        )
        code = _run_part(session, None, quiet, "agents " + ", ".join(ids))
    finally:
        close_all(links)
    if code:
        sys.exit(code)


def _resumable(log: Path, mission: Any) -> tuple[float, float, Any]:
    """What a coordinator restarted from ``log`` continues from: when its mission's clock was
    zero (Unix s), the time of its last event, and the state rebuilt from it. A cut last line
    (the process was killed while writing it) is dropped from the file first."""
    from btmission.runtime.events import LogError, read_events
    from btmission.runtime.recovery import recover

    try:
        contents = read_events(log)
    except LogError as exc:
        raise BadInput(str(exc)) from None
    events = contents.events
    head = events[0]
    if head.get("mission") != mission.name or head.get("part") != "coordinator":
        raise BadInput(
            f"--resume {log}: not a log of {mission.name}'s coordinator (mission "
            f"{head.get('mission')!r}, part {head.get('part', 'one process')!r})"
        )
    ended = [e for e in events if e.kind == "end"]
    if ended:
        raise BadInput(f"--resume {log}: that run has ended ({ended[-1].get('reason')})")
    built = [e for e in events if e.kind == "built" and e.get("started_unix") is not None]
    if not built:
        raise BadInput(f"--resume {log}: the coordinator was stopped before it had started")
    if contents.truncated:  # keep every whole line; the cut one cannot be read anyway
        data = log.read_bytes()
        log.write_bytes(data[: data.rfind(b"\n") + 1])
    return float(built[-1].get("started_unix")), events[-1].t, recover(mission, events)


def _run_part(
    session: Any,
    until: float | None,
    quiet: bool,
    what: str,
    prepare: Callable[[Any], None] | None = None,
) -> int:
    """Run one part of the mission and print its end; returns the exit status. ``prepare(run)``
    is called once the run is built, before its first step."""
    from btmission.runtime.session import RunStopped
    from btmission.vehicles.provider import VehicleUnavailable

    try:
        with session, internal_error_sink(session.record_internal_error):
            try:
                run = session.start()
            except VehicleUnavailable as exc:
                raise ChecksFailed(f"{exc}; nothing was run") from None
            if run is not None:
                if prepare is not None:
                    prepare(run)
                if not quiet:
                    click.echo(f"{what}: running; log {session.log_path}", err=True)
                session.run(until)
    except RunStopped as stop:
        click.echo(f"{what}: {stop.reason}", err=True)
        return stop.code
    result = session.result
    if result is not None:
        click.echo(
            f"{what}: {result.reason} at {result.time_s:.1f} s; done {', '.join(result.done) or 'none'}"
            + (f"; open {', '.join(result.open)}" if result.open else ""),
            err=quiet is False,
        )
    click.echo(f"log: {session.log_path}", err=True)
    return int(session.exit_code)


# ---------------------------------------------------------------------------- run --processes
def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port nobody uses on 127.0.0.1 now (TCP or UDP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _Child:
    """A process this launcher started: its output goes to a file; ended by its PID only."""

    def __init__(self, name: str, argv: list[str], out: Path) -> None:
        self.name = name
        self.out_path = out
        self._out: IO[str] = out.open("w")
        self.proc = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=self._out, text=True, start_new_session=True
        )
        self.lines: list[str] = []
        self._ready = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            self._out.write(line)
            self._out.flush()
            self._ready.set()
        self._ready.set()

    def wait_line(self, prefix: str, timeout_s: float) -> str | None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for line in self.lines:
                if line.startswith(prefix):
                    return line
            if self.proc.poll() is not None and not self._reader.is_alive():
                return None
            time.sleep(0.05)
        return None

    def signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)

    def stop(self, grace_s: float) -> int:
        """SIGTERM, then SIGKILL after ``grace_s``; its exit status."""
        self.signal(signal.SIGTERM)
        try:
            return self.proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(10)

    def close(self) -> None:
        self._reader.join(timeout=2)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._out.close()

    def tail(self, n: int = 5) -> str:
        try:
            lines = self.out_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])


def run_processes(
    mission_file: Path, *, log_dir: Path, seed: int, controller: str | None,
    speed: float | None, quiet: bool, no_png: bool, listen: str | None,
) -> int:  # fmt: skip
    """``run --processes``: mavsim (for the agents whose vehicles it can serve), the
    coordinator and one process per agent on this machine; their logs merged into one."""
    from btmission.backends.mavlink_url import parse_mavlink_url
    from btmission.runtime.session import RunSession, log_path_for

    _zenoh_or_exit()
    probe = RunSession(mission_file, log_dir=None)
    mission = probe.load()
    echo_diagnostics(probe.warnings)
    backends: dict[str, str] = {}
    served: list[str] = []
    for a in mission.agents:
        scheme = a.vehicle.scheme
        if scheme == "sim":
            backends[a.id] = f"mavlink+udp://127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
            served.append(a.id)
        elif scheme == "mavlink":
            address = parse_mavlink_url(a.backend)
            if address.transport in ("udp", "tcp") and address.host.startswith("127."):
                served.append(a.id)
        else:
            raise BadInput(
                f"agent {a.id}: backend {a.backend} cannot be flown from another process "
                "(run --processes serves simulator and loopback MAVLink agents with mavsim)"
            )
    scale = speed if speed is not None else mission.spec.runtime.mavlink.time_scale
    log_dir.mkdir(parents=True, exist_ok=True)
    merged = log_path_for(log_dir, mission.name, seed)  # the merged log; the parts beside it
    out = merged.with_name(f"{merged.stem}-processes")
    out.mkdir()
    endpoint = listen or f"tcp/127.0.0.1:{free_port()}"
    me = [sys.executable, "-m", "btmission"]
    common = ["--seed", str(seed), "--speed", f"{scale:g}", "--quiet"]
    if controller:
        common += ["--controller", controller]
    children: list[_Child] = []
    stop_asked: list[int] = []

    def on_signal(signum: int, frame: Any) -> None:
        stop_asked.append(signum)

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}

    def note(text: str) -> None:
        if not quiet:
            click.echo(text, err=True)

    try:
        if served:
            argv = [*me, "mavsim", "--mission", str(mission_file), "--speed", f"{scale:g}"]
            for aid, url in backends.items():
                argv += ["--backend", f"{aid}={url}"]
            sim = _Child("mavsim", [*argv, "--quiet"], out / "mavsim.txt")
            children.append(sim)
            if sim.wait_line("ready", 60) is None:
                raise ChecksFailed(f"mavsim did not start:\n{sim.tail()}")
            note(f"mavsim (pid {sim.proc.pid}) serves {', '.join(served)} at {scale:g}x")
        argv = [*me, "coordinator", str(mission_file), "--listen", endpoint,
                "--log-file", str(out / "coordinator.jsonl"), *common]  # fmt: skip
        coordinator = _Child("coordinator", argv, out / "coordinator.txt")
        children.append(coordinator)
        if coordinator.wait_line("coordinator of", 60) is None:
            raise ChecksFailed(f"the coordinator did not start:\n{coordinator.tail()}")
        note(f"coordinator (pid {coordinator.proc.pid}) listens on {endpoint}")
        agents: list[_Child] = []
        for a in mission.agents:
            argv = [*me, "agent", str(mission_file), "--id", a.id, "--connect", endpoint,
                    "--log-file", str(out / f"{a.id}.jsonl"), *common]  # fmt: skip
            if a.id in backends:
                argv += ["--backend", backends[a.id]]
            child = _Child(a.id, argv, out / f"{a.id}.txt")
            children.append(child)
            agents.append(child)
            note(f"agent {a.id} (pid {child.proc.pid})")
        note(f"logs in {out}")
        passed = 0
        follow = _Progress(out / "coordinator.jsonl", note)
        failed: list[_Child] = []
        while coordinator.proc.poll() is None:
            follow.poll()
            if not failed and all(c.proc.poll() not in (None, 0) for c in agents):
                failed = agents  # every agent failed: nothing can do the tasks
                for child in agents:
                    click.echo(f"agent {child.name} exited {child.proc.returncode}:", err=True)
                    click.echo(child.tail(3), err=True)
                coordinator.signal(signal.SIGTERM)
            while passed < len(stop_asked):  # each signal on to the coordinator (a second
                coordinator.signal(stop_asked[passed])  # one stops it at once); it ends the
                passed += 1  # mission, and the agents follow
            time.sleep(0.2)
        code = coordinator.proc.returncode
        deadline = time.monotonic() + 30
        for child in agents:
            try:
                child.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                note(f"agent {child.name} still running after the mission's end: stopping it")
                child.stop(10)
    finally:
        for child in reversed(children):
            if child.proc.poll() is None:
                child.stop(10)
            child.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
    if failed:
        raise ChecksFailed(f"every agent process failed (their output is in {out})")
    return _merge_and_report(mission, out, merged, code, quiet, no_png)


class _Progress:
    """``run --processes`` without --quiet: what the coordinator's log says as it grows (tasks
    done or failed, agents dropped), one line each."""

    def __init__(self, log: Path, note: Callable[[str], None]) -> None:
        self.log = log
        self.note = note
        self._pos = 0

    def poll(self) -> None:
        try:
            with self.log.open("rb") as f:
                f.seek(self._pos)
                data = f.read()
        except OSError:
            return
        end = data.rfind(b"\n") + 1  # whole lines only (the last may be being written)
        self._pos += end
        for line in data[:end].splitlines():
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            t, kind = ev.get("t", 0.0), ev.get("ev")
            if kind == "task" and ev.get("state") in ("done", "failed", "unreachable"):
                by = f" by {ev['agent']}" if ev.get("agent") else ""
                self.note(f"{t:7.1f} s  {ev.get('task')} {ev.get('state')}{by}")
            elif kind == "round" and ev.get("dropped"):
                self.note(f"{t:7.1f} s  not heard from: {', '.join(ev['dropped'])}")


def _merge_and_report(
    mission: Any, out: Path, merged: Path, code: int, quiet: bool, no_png: bool
) -> int:
    from btmission.runtime.events import LogError
    from btmission.runtime.report import format_report, format_warnings, merge_log_files

    agents = [out / f"{a.id}.jsonl" for a in mission.agents if (out / f"{a.id}.jsonl").exists()]
    try:
        rep = merge_log_files(out / "coordinator.jsonl", agents, merged)
    except (LogError, ValueError) as exc:
        click.echo(f"cannot merge the logs in {out}: {exc}", err=True)
        return code or 1
    click.echo(f"log: {merged} (merged from {out})", err=True)
    if not no_png:
        from btmission.cli.run_cmds import _write_pngs

        try:
            for p in _write_pngs(rep, merged.parent, merged.stem):
                click.echo(f"wrote {p}", err=True)
        except Exception as exc:  # a figure must never hide the report
            click.echo(f"note: could not draw the PNGs ({exc})", err=True)
    for w in format_warnings(rep):
        click.echo(w, err=True)
    click.echo(format_report(rep))
    return code


__all__ = ["agent_cmd", "coordinator_cmd", "free_port", "run_processes"]
