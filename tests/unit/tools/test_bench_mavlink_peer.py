"""``btmission bench mavlink`` beside its peer, MAVSDK-Python 4: the setpoint stream measured where
it arrives, the side-by-side table, and the run without MAVSDK (a note, btmission alone)."""

from __future__ import annotations

import csv
import dataclasses
import socket
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.backends._pymavlink import mavlink
from btmission.backends.mavlink_modes import Autopilot
from btmission.bench import mavlink as bench
from btmission.bench.mavlink import (
    INSTALL_NOTE,
    MavlinkPoint,
    arrival_stats,
    markdown,
    mavsdk_version,
    side_by_side,
)
from btmission.cli.main import cli
from btmission.mavsim import MavSim, MavSimConfig, vehicles_in_a_row
from btmission.world.minegen import empty_world
from tests.mavlink_helpers import free_port

PERIOD = 0.05


def _grid(t0: float, n: int, period: float = PERIOD) -> list[float]:
    return [t0 + period * i for i in range(n)]


def test_a_regular_stream_is_full_rate_without_jitter() -> None:
    stats = arrival_stats([_grid(100.0, 21), _grid(100.01, 20)], 100.0, 101.0, PERIOD)
    assert stats.rate == pytest.approx(20.5)
    assert stats.jitter_p99_ms == pytest.approx(0.0, abs=1e-6)
    assert stats.worst_gap_ms == pytest.approx(50.0, abs=1e-6)


def test_a_gap_an_extra_send_and_the_window_edges_count() -> None:
    late = _grid(0.0, 10) + _grid(0.75, 6)  # 300 ms between 0.45 and 0.75
    doubled = sorted([*_grid(0.0, 21), 0.2])  # one setpoint sent twice: a 0 ms interval
    stats = arrival_stats([late, doubled], 0.0, 1.0, PERIOD)
    assert stats.worst_gap_ms == pytest.approx(300.0)
    assert stats.jitter_p50_ms == pytest.approx(0.0, abs=1e-6)
    assert 150.0 < stats.jitter_p99_ms <= 250.0  # the gap (250 ms late) and the double (50)
    assert stats.rate == pytest.approx((16 + 22) / 2)
    outside = [-5.0, *_grid(0.0, 21), 3.0]  # arrivals outside the window are not counted
    assert arrival_stats([outside], 0.0, 1.0, PERIOD).rate == pytest.approx(21.0)
    silent = arrival_stats([[], _grid(0.0, 21)], 0.0, 1.0, PERIOD)
    assert silent.worst_gap_ms == pytest.approx(1000.0)  # heard nothing: the whole window
    with pytest.raises(ValueError, match="t1 > t0"):
        arrival_stats([[]], 1.0, 1.0, PERIOD)


def _point(client: str, cpu: float, **kw: float) -> MavlinkPoint:
    base = MavlinkPoint(
        vehicles=10, seconds=8.0, setpoint_hz=20.0, telemetry_hz=50.0, connect_s=0.3,
        setpoint_rate=20.0, telemetry_rate=50.0, jitter_p50_ms=1.0, jitter_p99_ms=12.0,
        cpu_ms_per_vehicle=cpu, sim_cpu_ms_per_vehicle=6.0, worst_gap_ms=60.0, stress=8,
        load=9.5, heard_s=0.25, client=client,
    )  # fmt: skip
    return dataclasses.replace(base, **kw)


def test_the_side_by_side_table_pairs_the_clients_and_compares_cpu() -> None:
    points = [
        _point("btmission", 4.5),
        _point("mavsdk", 9.0, setpoint_rate=24.6, jitter_p99_ms=49.9, connect_s=1.5),
        _point("mavsdk", 3.0, vehicles=30),
        _point("btmission", 4.0, vehicles=30),
        _point("btmission", 4.0, vehicles=3),  # no peer at 3: no row
    ]
    rows = side_by_side(points)
    assert rows[2] == (
        "| 10 | 8 | 9.5 / 9.5 | 20.0 / 24.6 | 60 / 60 | 12.0 / 49.9 | 4.5 / 9.0 | "
        "0.30 / 1.50 | yes |"
    )
    assert rows[3].startswith("| 30 | 8 |") and rows[3].endswith(
        "| 4.0 / 3.0 | 0.30 / 0.30 | **no** |"
    )
    assert len(rows) == 4
    assert side_by_side([_point("btmission", 4.5)]) == []
    env = {"date": "d", "machine": "m", "cpus": "2", "python": "p", "btmission": "b"}
    page = markdown(points, env, INSTALL_NOTE)
    assert INSTALL_NOTE in page and "| MAVSDK-Python | 10 | 8 |" in page
    assert "Side by side" in page and rows[2] in page


def test_only_mavsdk_4_counts_as_the_peer(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.metadata as md

    for installed, want in (("4.1.0", "4.1.0"), ("3.10.2", None), ("10.0", "10.0")):
        monkeypatch.setattr(md, "version", lambda name, v=installed: v)
        assert mavsdk_version() == want

    def missing(name: str) -> str:
        raise md.PackageNotFoundError(name)

    monkeypatch.setattr(md, "version", missing)
    assert mavsdk_version() is None


def test_mavsim_stamps_each_setpoint_addressed_to_a_vehicle_when_it_arrived() -> None:
    gcs_port = free_port()
    specs = vehicles_in_a_row(1, Autopilot.PX4, base_port=gcs_port)
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", gcs_port))  # where the vehicle sends: the ground station
    sim = MavSim(MavSimConfig(specs, empty_world((20.0, 20.0, 10.0), 0.5)))
    try:
        ap = sim.autopilots["V1"]
        arrivals = sim.stamp_arrivals()["V1"]
        vehicle = ap.conn.port.getsockname()
        mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)

        def setpoint(target: int) -> bytes:
            msg = mavlink.MAVLink_set_position_target_local_ned_message(
                0, target, 1, mavlink.MAV_FRAME_LOCAL_NED, 0b0000_1111_1111_1000,
                1.0, 2.0, -3.0, 0, 0, 0, 0, 0, 0, 0, 0,
            )  # fmt: skip
            return bytes(msg.pack(mav))

        before = time.time()
        for target in (1, 1, 7, 1):  # sysid 7 is another vehicle's
            gcs.sendto(setpoint(target), vehicle)
        after = time.time()
        time.sleep(0.2)  # the simulator reads them late
        read_at = time.time()
        for _ in range(50):
            ap.receive()
            if len(arrivals) == 3:
                break
            time.sleep(0.01)
        assert len(arrivals) == 3 and sim.vehicle_state("V1")["setpoints"] == 3
        # stamped when they arrived (while they were sent), not when they were read
        assert all(before - 0.01 <= t <= after + 0.01 < read_at for t in arrivals)
    finally:
        sim.close()
        gcs.close()


@pytest.mark.serial
def test_without_mavsdk_the_bench_says_how_to_install_it_and_measures_btmission(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(bench, "mavsdk_version", lambda: None)  # as in an install without it
    result = CliRunner().invoke(
        cli, ["bench", "mavlink", "--vehicles", "1", "--seconds", "1", "--out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    assert result.output.startswith(INSTALL_NOTE)
    assert "pip install 'btmission[bench]'" in INSTALL_NOTE
    with (tmp_path / "mavlink.csv").open() as f:
        (row,) = list(csv.DictReader(f))
    assert row["client"] == "btmission" and row["vehicles"] == "1"
    assert float(row["setpoint_rate"]) > 0 and float(row["cpu_ms_per_vehicle"]) > 0
    page = (tmp_path / "mavlink.md").read_text()
    assert INSTALL_NOTE in page and "| btmission | 1 |" in page and "Side by side" not in page


@pytest.mark.slow
def test_btmission_and_mavsdk_drive_the_same_vehicles_side_by_side(tmp_path: Path) -> None:
    assert mavsdk_version() is not None, (
        "MAVSDK-Python 4 is missing: pip install -e '.[bench]' (make install does)"
    )
    result = CliRunner().invoke(
        cli, ["bench", "mavlink", "--vehicles", "2", "--seconds", "2", "--out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    assert INSTALL_NOTE not in result.output
    with (tmp_path / "mavlink.csv").open() as f:
        rows = {r["client"]: r for r in csv.DictReader(f)}
    assert rows.keys() == {"btmission", "mavsdk"}
    for row in rows.values():
        assert row["vehicles"] == "2"
        assert 12.0 < float(row["setpoint_rate"]) < 45.0  # 20 Hz renewed (MAVSDK re-sends too)
        assert 20.0 < float(row["telemetry_rate"]) < 100.0  # 50 Hz asked (a late mavsim catches up)
        assert float(row["worst_gap_ms"]) >= 0 and float(row["cpu_ms_per_vehicle"]) > 0
        assert 0.0 < float(row["heard_s"]) <= float(row["connect_s"])
    page = (tmp_path / "mavlink.md").read_text()
    assert "| MAVSDK-Python | 2 |" in page and "| btmission | 2 |" in page
    assert "Side by side" in page and "Peer: MAVSDK-Python 4." in page
