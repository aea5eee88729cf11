"""The client side of ``btmission bench mavlink``: one ground station process that connects N
vehicles and streams their position setpoints (``python -m btmission.bench.mavlink_client``).

Two clients do the same work, each in its own process so that its CPU time is its own:

* ``btmission``: :class:`~btmission.backends.mavlink.MavlinkProvider` (one I/O thread for every
  vehicle) attaches them all at once (``attach_all``, as a run does), which asks each for
  LOCAL_POSITION_NED, ATTITUDE, EXTENDED_SYS_STATE, SYS_STATUS and DISTANCE_SENSOR at
  ``telemetry_hz`` and waits for its first position;
* ``mavsdk``: MAVSDK-Python 4 (PyPI ``mavsdk`` ≥ 4: the MAVSDK C++ library in this process
  through its C wrapper, no ``mavsdk_server``): one ``Mavsdk`` ground station with one
  ``udpin://`` connection per vehicle, and per vehicle a ``Telemetry`` asking the same streams
  (``set_rate_position_velocity_ned``, ``_attitude_euler``, ``_landed_state``, ``_battery``,
  ``_distance_sensor``: MAVSDK asks BATTERY_STATUS where btmission asks SYS_STATUS; the requests
  go out together, asynchronously) and subscribed to them, and an ``Offboard``; connected when
  every vehicle is discovered, has acknowledged its rates and sent a first position.

Then a control loop renews every vehicle's position setpoint (its position when connected)
``setpoint_hz`` times a second on absolute deadlines, through ``set_position_setpoint``
(btmission streams the latest setpoint on its own deadlines) or ``Offboard.set_position_ned``
(MAVSDK sends it at once and re-sends the latest every 50 ms when no new one comes): one second
to warm up, then ``seconds`` measured. Neither arms the vehicles nor switches their mode.

Output, one JSON line each: ``{"event": "connected", "connect_s", "heard_s"}``, then
``{"event": "measuring"}`` when the window opens and ``{"event": "done", "t0", "t1", "cpu_s",
"wall_s", "telemetry"}``: the window in ``time.time()`` seconds (the vehicles stamp arrivals in
that clock), this process's CPU seconds over it (every thread: the library's, the control
loop's) and each vehicle's LOCAL_POSITION_NED count over it. Errors go to stderr, exit 1.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

CLIENTS = ("btmission", "mavsdk")
WARMUP_S = 1.0
CONNECT_TIMEOUT_S = 60.0


def _emit(**fields: Any) -> None:
    print(json.dumps(fields), flush=True)


def _control(renew: Sequence[Callable[[], None]], duration: float, period: float) -> None:
    """Renew every setpoint once a period, on absolute deadlines, for ``duration`` seconds."""
    end = time.perf_counter() + duration
    due = time.perf_counter()
    while due < end:
        for r in renew:
            r()
        due += period
        delay = due - time.perf_counter()
        if delay > 0:
            time.sleep(delay)


def _window(
    renew: Sequence[Callable[[], None]], seconds: float, period: float,
    positions: Callable[[], list[int]],
) -> None:  # fmt: skip
    """The warm-up, then the measured window (module docstring)."""
    _control(renew, WARMUP_S, period)
    _emit(event="measuring")
    p0 = positions()
    cpu0, t0, wall0 = time.process_time(), time.time(), time.perf_counter()
    _control(renew, seconds, period)
    wall = time.perf_counter() - wall0
    cpu, t1 = time.process_time() - cpu0, time.time()
    telemetry = [b - a for a, b in zip(p0, positions(), strict=True)]
    _emit(event="done", t0=t0, t1=t1, cpu_s=cpu, wall_s=wall, telemetry=telemetry)


def run_btmission(
    urls: Sequence[tuple[str, str]], seconds: float, setpoint_hz: float, telemetry_hz: float
) -> None:
    import numpy as np

    from btmission.backends.mavlink import MavlinkOptions, MavlinkProvider
    from btmission.spec.vehicleref import VehicleRef
    from btmission.vehicles.base import VehicleKind
    from btmission.vehicles.provider import AttachRequest

    provider = MavlinkProvider(
        MavlinkOptions(
            setpoint_hz=setpoint_hz, telemetry_hz=telemetry_hz, connect_timeout_s=CONNECT_TIMEOUT_S
        )
    )
    try:
        requests = [
            AttachRequest(agent, VehicleKind.MULTIROTOR, (5.0 + 3.0 * i, 5.0, 0.0), VehicleRef.parse(url))
            for i, (agent, url) in enumerate(urls)
        ]  # fmt: skip
        t0 = time.perf_counter()
        provider.prepare([r.ref for r in requests])  # as a run connects: all at once
        vehicles = [v.backend for v in provider.attach_all(requests)]
        connect_s = time.perf_counter() - t0
        heard_s = max(t.heard_s for t in provider.connect_times.values())
        _emit(event="connected", connect_s=connect_s, heard_s=heard_s)
        states = [v.state for v in vehicles]  # type: ignore[attr-defined]

        def renewer(v: Any) -> Callable[[], None]:
            target = np.asarray(v.telemetry().position, dtype=float)
            return lambda: v.set_position_setpoint(target)

        _window(
            [renewer(v) for v in vehicles], seconds, 1.0 / setpoint_hz,
            lambda: [st.positions for st in states],
        )  # fmt: skip
    finally:
        provider.close()


def run_mavsdk(
    urls: Sequence[tuple[str, str]], seconds: float, setpoint_hz: float, telemetry_hz: float
) -> None:
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.offboard import Offboard, PositionNedYaw
    from mavsdk.plugins.telemetry import Telemetry

    from btmission.backends.mavlink_url import parse_mavlink_url

    count = len(urls)
    lock = threading.Lock()
    positions = [0] * count
    latest: dict[tuple[int, str], Any] = {}
    first = [threading.Event() for _ in range(count)]
    rates_left = [count * 5]
    rates_done = threading.Event()
    failures: list[str] = []

    def on_rate(result: Any, _user: Any = None) -> None:
        if getattr(result, "name", "SUCCESS") != "SUCCESS":
            failures.append(str(result))
        with lock:
            rates_left[0] -= 1
            if rates_left[0] == 0:
                rates_done.set()

    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        t0 = time.perf_counter()
        for _agent, url in urls:
            address = parse_mavlink_url(url)
            result = mavsdk.add_any_connection(f"udpin://{address.host}:{address.port}")
            if int(result) != 0:
                raise RuntimeError(f"MAVSDK could not open udpin://{address.host}:{address.port}: {result}")  # fmt: skip
        deadline = t0 + CONNECT_TIMEOUT_S
        while True:
            systems = mavsdk.get_systems()
            if len(systems) >= count and all(s.is_connected() for s in systems):
                break
            if time.perf_counter() > deadline:
                raise RuntimeError(f"MAVSDK found {len(systems)} of {count} vehicle(s)")
            time.sleep(0.005)
        heard_s = time.perf_counter() - t0
        systems.sort(key=lambda s: s.get_system_id())
        telemetries = [Telemetry(s) for s in systems]
        offboards = [Offboard(s) for s in systems]
        for i, tel in enumerate(telemetries):

            def on_position(data: Any, _user: Any = None, i: int = i) -> None:
                latest[i, "position"] = data
                positions[i] += 1
                first[i].set()

            tel.subscribe_position_velocity_ned(on_position)
            for name in ("attitude_euler", "landed_state", "battery", "distance_sensor"):
                tel_subscribe = getattr(tel, f"subscribe_{name}")
                tel_subscribe(lambda data, _user=None, key=(i, name): latest.__setitem__(key, data))
            for name in ("position_velocity_ned", "attitude_euler", "landed_state", "battery",
                         "distance_sensor"):  # fmt: skip
                getattr(tel, f"set_rate_{name}_async")(telemetry_hz, on_rate)
        for event in (rates_done, *first):
            if not event.wait(max(deadline - time.perf_counter(), 0.0)):
                raise RuntimeError("MAVSDK: a vehicle did not acknowledge its rates or send a position")  # fmt: skip
        if failures:
            raise RuntimeError(f"MAVSDK: setting telemetry rates failed: {failures[:3]}")
        connect_s = time.perf_counter() - t0
        _emit(event="connected", connect_s=connect_s, heard_s=heard_s)

        def renewer(i: int) -> Callable[[], None]:
            p = latest[i, "position"].position
            target = PositionNedYaw(p.north_m, p.east_m, p.down_m, 0.0)
            offboard = offboards[i]
            return lambda: offboard.set_position_ned(target)

        _window([renewer(i) for i in range(count)], seconds, 1.0 / setpoint_hz, lambda: list(positions))  # fmt: skip
    finally:
        mavsdk.destroy()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m btmission.bench.mavlink_client")
    parser.add_argument("client", choices=CLIENTS)
    parser.add_argument("--urls", required=True, help="JSON list of [agent, url]")
    parser.add_argument("--seconds", type=float, required=True)
    parser.add_argument("--setpoint-hz", type=float, default=20.0)
    parser.add_argument("--telemetry-hz", type=float, default=50.0)
    args = parser.parse_args(argv)
    urls = [(str(a), str(u)) for a, u in json.loads(args.urls)]
    run = run_btmission if args.client == "btmission" else run_mavsdk
    try:
        run(urls, args.seconds, args.setpoint_hz, args.telemetry_hz)
    except Exception as exc:  # the benchmark shows it and stops
        print(f"{args.client} client: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
