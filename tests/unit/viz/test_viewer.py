"""The viewer without a browser: what it feeds the page, the scene it encodes, its server on
loopback (bound address, routes, the stream to its end, a port in use), the static export and
the `view` command's bad input. The page itself is tested in a real browser in
test_viewer_browser.py."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import urllib.request
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from btmission.cli.main import cli
from btmission.runtime.events import Event, read_events
from btmission.runtime.observers import QueuedObserver
from btmission.runtime.session import RunSession
from btmission.runtime.treestatus import blackboard_value
from btmission.viz.feed import LiveFeed, replay_records, thin_poses, view_record
from btmission.viz.scene import build_scene, pack_commands, unpack_commands
from btmission.viz.server import ViewerError, ViewerServer, log_source
from btmission.world.voxel import OCCUPIED, VoxelMap

ROOT = Path(__file__).resolve().parents[3]
MINE = ROOT / "missions" / "mine_inspection.yaml"


def _unpack(data: bytes) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import umsgpack
    return umsgpack.unpackb(data)


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=10) as r:
        data: bytes = r.read()
        return data


def _stream(url: str) -> Iterator[tuple[str, dict[str, Any]]]:
    """(event name, data) of a Server-Sent Events stream until it ends."""
    with urllib.request.urlopen(url, timeout=10) as r:
        name = "message"
        for raw in r:
            line = raw.decode().rstrip("\n")
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: "):
                yield name, json.loads(line[6:])
                name = "message"


# ---------------------------------------------------------------------------- records
def test_view_record_keeps_what_the_page_draws() -> None:
    pose = Event(1.0, "pose", {"agent": "R1", "p": [1, 2, 3], "v": [0, 0, 0], "yaw": 0.5,
                               "mode": "OFFBOARD", "odometer_m": 12.0, "clearance_m": 1.0})  # fmt: skip
    assert view_record(pose) == {"t": 1.0, "ev": "pose", "agent": "R1", "p": [1, 2, 3],
                                 "yaw": 0.5, "mode": "OFFBOARD"}  # fmt: skip
    quiet_round = Event(2.0, "round", {"round": 3, "announced": 2, "bids": 4})
    assert view_record(quiet_round) is None
    changed = Event(2.0, "round", {"round": 4, "assignments": {"R1": "T1"}, "bids": 4})
    assert view_record(changed) == {"t": 2.0, "ev": "round", "round": 4,
                                    "assignments": {"R1": "T1"}}  # fmt: skip
    err = Event(3.0, "leaf_error", {"leaf": "scan", "traceback": "long...", "message": "boom"})
    assert "traceback" not in view_record(err)  # type: ignore[operator]
    assert view_record(Event(3.0, "objects_of_my_library", {})) is None


def test_thin_poses_keeps_first_last_and_every_other_kind() -> None:
    recs = [{"t": i * 0.1, "ev": "pose", "agent": a} for i in range(100) for a in ("A", "B")]
    recs.insert(50, {"t": 2.5, "ev": "task", "task": "T1"})
    out = thin_poses(recs, 1.0)
    assert {"t": 2.5, "ev": "task", "task": "T1"} in out
    for a in ("A", "B"):
        ts = [r["t"] for r in out if r["ev"] == "pose" and r["agent"] == a]
        assert ts[0] == 0.0 and ts[-1] == pytest.approx(9.9)
        gaps = np.diff(ts[:-1])
        assert (gaps >= 1.0 - 1e-9).all() and len(ts) == 11


def test_replay_records_stay_within_the_pose_budget(mine_log: Path) -> None:
    events = read_events(mine_log).events
    full = replay_records(events)
    poses = sum(1 for r in full if r["ev"] == "pose")
    assert poses == sum(1 for e in events if e.kind == "pose")  # under budget: all of them
    small = replay_records(events, pose_budget=30)
    assert sum(1 for r in small if r["ev"] == "pose") <= 30 + 3  # (each agent's last kept)
    assert [r for r in small if r["ev"] != "pose"] == [r for r in full if r["ev"] != "pose"]


def test_live_feed_reads_by_cursor_and_thins_its_pose_history() -> None:
    feed = LiveFeed(pose_history_s=0.5)
    feed.on_event(Event(0.0, "pose", {"agent": "R1", "p": [0, 0, 0]}))  # from snapshots only
    assert len(feed) == 0
    for i in range(20):  # 10 Hz for 2 s
        feed.add_poses([{"t": i * 0.1, "ev": "pose", "agent": "R1", "p": [i, 0, 0]}])
    feed.on_event(Event(2.0, "task", {"task": "T1", "state": "done", "agent": "R1"}))
    records, cursor, latest, seen = feed.read(0)
    kept = [r["t"] for r in records if r["ev"] == "pose"]
    assert kept == pytest.approx([0.0, 0.5, 1.0, 1.5])
    assert latest == [{"t": pytest.approx(1.9), "ev": "pose", "agent": "R1", "p": [19, 0, 0]}]
    assert records[-1]["ev"] == "task" and cursor == len(records)
    again = feed.read(cursor, seen)
    assert again[0] == [] and again[2] == []  # nothing new: no latest poses either
    assert not feed.complete(cursor)
    feed.on_event(Event(3.0, "end", {"reason": "completed"}))
    assert not feed.complete(cursor) and feed.complete(cursor + 1)


def test_no_task_event_is_lost_behind_a_slow_reader() -> None:
    """A feed behind a full queue: poses make room, every task event arrives in order."""
    feed = LiveFeed()
    with QueuedObserver(feed, maxsize=5) as queued:
        for i in range(2000):
            queued.on_event(Event(i * 0.01, "pose", {"agent": f"R{i % 3}", "p": [i, 0, 0]}))
            if i % 10 == 0:
                queued.on_event(Event(i * 0.01, "task", {"task": f"T{i}", "state": "open",
                                                         "agent": None, "reason": ""}))  # fmt: skip
        queued.flush()
    records, _, _, _ = feed.read(0)
    assert [r["task"] for r in records if r["ev"] == "task"] == [
        f"T{i}" for i in range(0, 2000, 10)
    ]


def test_tree_events_carry_the_blackboard_keys_that_changed(mine_log: Path) -> None:
    trees = [e for e in read_events(mine_log).events if e.kind == "tree" and e.get("agent") == "R1"]
    first = trees[0]
    assert first.get("nodes") and first.get("blackboard", {}).get("start") == [4, 5, 0]
    assigned = [e for e in trees if "task" in (e.get("blackboard") or {})]
    assert assigned, "the task's id is written on the blackboard when a task is assigned"
    task = assigned[0].get("blackboard")
    assert isinstance(task["location"], list) and len(task["location"]) == 3
    for e in trees[1:]:  # later events only carry what changed
        assert "start" not in (e.get("blackboard") or {})
        assert e.typed().blackboard == e.get("blackboard")  # type: ignore[attr-defined]


def test_blackboard_values_are_shown_short_and_json_safe() -> None:
    assert blackboard_value((1.0, 2.123456, 3)) == [1.0, 2.1235, 3]
    assert blackboard_value(np.array([1.0, 2.0])) == [1.0, 2.0]
    assert blackboard_value(float("inf")) == "inf"
    assert len(blackboard_value("x" * 500)) == 80
    assert blackboard_value(np.zeros(100)).startswith("array(")
    text = blackboard_value(object())
    assert isinstance(text, str) and text.startswith("<object")
    json.dumps([blackboard_value(v) for v in ((1, 2), {"a": 1}, None, True, np.float32(2.5))])
    assert (
        blackboard_value(frozenset({("P2", 1), ("P1", 2)})) == "frozenset({('P1', 2), ('P2', 1)})"
    )
    assert blackboard_value({"b", "a"}) == "{'a', 'b'}" and blackboard_value(set()) == "set()"


def test_a_set_on_the_blackboard_is_logged_the_same_in_every_process() -> None:
    """Sets iterate in their items' hash order, which changes with PYTHONHASHSEED: the log must
    not (the same seed gives the same log)."""
    code = (
        "from btmission.runtime.treestatus import blackboard_value as b;"
        "print(b(frozenset(f'P{i}' for i in range(12))), repr(frozenset(f'P{i}' for i in range(12))))"
    )
    outs = [
        subprocess.run(
            [sys.executable, "-c", code],
            env={**os.environ, "PYTHONHASHSEED": seed},
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split(" frozenset(")
        for seed in ("1", "2", "3")
    ]
    assert len({o[0] for o in outs}) == 1  # ours: the same text in every process
    assert len({o[1] for o in outs}) > 1  # (while the plain repr differs: the test can fail)


# ---------------------------------------------------------------------------- the scene
def test_scene_encodes_the_mine_the_risk_layer_and_the_look() -> None:
    state = np.zeros((20, 12, 6), dtype=np.uint8)
    state[:, :, 0] = OCCUPIED  # a floor
    state[8:12, 4:8, 1:4] = OCCUPIED  # a pillar
    vmap = VoxelMap(state, 0.5, (10.0, 20.0, 0.0))
    scene = build_scene(vmap)
    cmds = [_unpack(c) for c in unpack_commands(scene.packed())]
    assert unpack_commands(pack_commands(scene.commands)) == scene.commands
    by_path = {(c["type"], c["path"]): c for c in cmds}
    mine = by_path[("set_object", "/mine")]["object"]
    assert mine["materials"][0]["vertexColors"] and mine["materials"][0]["side"] == 0
    assert by_path[("set_property", "/risk")]["value"] is False  # the risk layer: on demand
    risk = by_path[("set_object", "/risk")]["object"]
    assert risk["object"]["type"] == "Points" and risk["materials"][0]["opacity"] < 1
    assert scene.info["bounds"] == [[10.0, 20.0, 0.0], [20.0, 26.0, 3.0]]
    assert scene.info["triangles"] > 0 and scene.info["risk_points"] > 0


# ---------------------------------------------------------------------------- the server
def test_server_binds_loopback_and_serves_a_replay_to_its_end(mine_log: Path) -> None:
    source, notes = log_source(mine_log)
    assert notes == []
    with ViewerServer(source, port=0) as server:
        host, port = server.address
        assert host == "127.0.0.1" and port > 0  # the bound address, not the printed one
        assert server.url == f"http://127.0.0.1:{port}/"
        page = _get(server.url).decode()
        assert "static/meshcat.js" in page and '"title": "mine_inspection"' in page
        assert b"MeshCat" in _get(server.url + "static/meshcat.js")[:200_000]
        info = json.loads(_get(server.url + "api/info"))
        assert info["mode"] == "replay" and [a["id"] for a in info["agents"]] == ["R1", "R2", "R3"]
        assert info["scene"]["bounds"] == [[0.0, 0.0, -1.0], [200.0, 120.0, 11.0]]
        commands = unpack_commands(_get(server.url + "api/scene"))
        assert _unpack(commands[0])["path"] == "/mine"
        got: list[dict[str, Any]] = []
        names = []
        for name, data in _stream(server.url + "api/stream?cursor=0"):
            names.append(name)
            got.extend(data.get("records", []))
        assert names[-1] == "complete"
        want = replay_records(read_events(mine_log).events)
        assert got == json.loads(json.dumps(want))
        # a page that reconnects mid-way asks from its cursor and gets the rest only
        rest = [r for n, d in _stream(server.url + f"api/stream?cursor={len(want) - 5}")
                for r in d.get("records", [])]  # fmt: skip
        assert rest == got[-5:]
        scan = json.loads(_get(server.url + "api/scan?x=4&y=5&z=1&yaw=0"))
        pts = np.array(scan["points"]).reshape(-1, 3)
        assert len(pts) > 1000 and (np.linalg.norm(pts - [4, 5, 1], axis=1) <= 60.5).all()
        with pytest.raises(urllib.error.HTTPError) as bad:
            _get(server.url + "api/scan?x=nan&y=5&z=1")
        assert bad.value.code == 422
        bad.value.close()
        with pytest.raises(urllib.error.HTTPError) as missing:
            _get(server.url + "static/secret.py")
        assert missing.value.code == 404
        missing.value.close()
    with pytest.raises(OSError):  # closed: the port is free, nothing answers
        _get(f"http://127.0.0.1:{port}/api/info")


def test_a_port_in_use_is_refused_clearly() -> None:
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    port = holder.getsockname()[1]
    try:
        server = ViewerServer(None, port=port)
        with pytest.raises(ViewerError, match=f"port {port} on 127.0.0.1 in use"):
            server.bind()
        moved = ViewerServer(None, port=port, port_tries=3)  # the default port: the next free
        assert moved.bind()[1] != port
        moved.close()
    finally:
        holder.close()


# ---------------------------------------------------------------------------- the commands
def test_view_html_writes_one_self_contained_file(mine_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "run.html"
    r = CliRunner().invoke(cli, ["view", str(mine_log), "--html", str(out)])
    assert r.exit_code == 0, r.output
    assert f"wrote {out}" in r.output
    html = out.read_text()
    assert "static/" not in html.replace("static/viewer.css", "")  # nothing to fetch ...
    assert "MeshCat.Viewer" in html and '"embedded":true' in html
    start = html.index("window.BTM_CONFIG = ") + len("window.BTM_CONFIG = ")
    config = json.loads(html[start : html.index(";</script>", start)])
    assert len(config["records"]) == len(replay_records(read_events(mine_log).events))
    assert "</script" not in json.dumps(config["records"])


def test_view_refuses_what_is_not_a_log(tmp_path: Path) -> None:
    bad = tmp_path / "notes.jsonl"
    bad.write_text('{"hello": 1}\n')
    r = CliRunner().invoke(cli, ["view", str(bad), "--html", str(tmp_path / "x.html")])
    assert r.exit_code == 2 and "not a btmission event log" in r.output
    assert "Traceback" not in r.output and not (tmp_path / "x.html").exists()
    r = CliRunner().invoke(cli, ["view", str(tmp_path / "missing.jsonl")])
    assert r.exit_code == 2 and "no such log file" in r.output


def test_run_view_on_a_port_in_use_stops_before_anything_runs(tmp_path: Path) -> None:
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    port = holder.getsockname()[1]
    try:
        r = CliRunner().invoke(
            cli, ["run", str(MINE), "--view", "--port", str(port), "--log", str(tmp_path)]
        )
    finally:
        holder.close()
    assert r.exit_code == 2 and f"port {port} on 127.0.0.1 in use" in r.output
    assert list(tmp_path.iterdir()) == []  # no log: nothing ran


@pytest.mark.parametrize(
    "sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)]
)
def test_view_server_closes_cleanly_on_ctrl_c_and_sigterm(mine_log: Path, sig: int) -> None:
    """`btmission view LOG` serves until Ctrl-C or SIGTERM, then closes the server and exits 0
    (a real process: the signal goes to it, by its PID)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "btmission", "view", str(mine_log), "--port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        assert line.startswith("viewer: http://127.0.0.1:"), line
        url = line.split()[1]
        assert json.loads(_get(url + "api/info"))["mission"] == "mine_inspection"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0 and "viewer closed" in err and "Traceback" not in err
    with pytest.raises(OSError):
        _get(url + "api/info")


def test_the_run_queues_only_what_the_page_draws() -> None:
    from btmission.runtime.events import Recorder
    from btmission.viz.live import ViewerKinds

    rec = Recorder()
    kinds = ViewerKinds(rec)
    kinds.on_event(Event(0.1, "pose", {"agent": "R1", "p": [0, 0, 0]}))
    kinds.on_event(Event(0.1, "round", {"round": 1, "bids": 3}))
    kinds.on_event(Event(0.2, "round", {"round": 2, "assignments": {"R1": "T1"}}))
    kinds.on_event(Event(0.2, "task", {"task": "T1", "state": "assigned", "agent": "R1"}))
    kinds.on_event(Event(0.3, "my_library_kind", {}))
    assert [(e.kind, e.t) for e in rec.events] == [("round", 0.2), ("task", 0.2)]


def test_run_view_serves_while_the_run_goes_and_closes_with_it(tmp_path: Path) -> None:
    """`run --view` without a terminal: the URL is printed, the run and its report are as
    without it, and the server is gone when the command returns (no linger)."""
    mission = ROOT / "missions" / "warehouse.yaml"
    args = ["run", str(mission), "--controller", "track", "--quiet", "--no-png", "--until", "15"]
    plain = CliRunner().invoke(cli, [*args, "--log", str(tmp_path / "plain")])
    r = CliRunner().invoke(
        cli, [*args, "--view", "--port", "0", "--speed", "0", "--log", str(tmp_path / "view")]
    )
    assert r.exit_code == plain.exit_code, r.output
    line = next(x for x in r.stderr.splitlines() if x.startswith("viewer: "))
    url = line.split()[1]
    assert url.startswith("http://127.0.0.1:")
    assert r.stdout == plain.stdout  # the same report
    with pytest.raises(OSError):
        _get(url + "api/info")


def test_the_live_viewer_watches_any_provider(tmp_path: Path) -> None:
    """The viewer reads only events and snapshots: the `fake` provider's kinematic vehicles
    show up the same (poses sampled from the snapshots, task events, tree events)."""
    from btmission.viz.live import LiveViewer

    viewer = LiveViewer(port=0)
    with RunSession(
        ROOT / "docs" / "examples" / "fake_fleet.yaml", log_dir=None, observers=[viewer.observer]
    ) as session:
        run = session.start()
        url = viewer.attach(session, run)
        result = session.run()
    viewer.finish()
    try:
        records = [r for _, d in _stream(url + "api/stream?cursor=0") for r in d.get("records", [])]
    finally:
        viewer.close()
    assert result is not None and result.reason == "completed"
    kinds = {r["ev"] for r in records}
    assert {"task", "tree", "agent_task", "end"} <= kinds
    poses = {r["agent"] for r in records if r["ev"] == "pose"}
    assert poses == {"R1", "R2"}
    done = [r["task"] for r in records if r["ev"] == "task" and r["state"] == "done"]
    assert sorted(done) == ["T1", "T2"]


def test_a_viewer_off_loopback_is_announced_with_a_warning(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from btmission.cli.view_cmds import announce_server

    announce_server("http://127.0.0.1:8470/", "127.0.0.1")
    assert capsys.readouterr().err == "viewer: http://127.0.0.1:8470/\n"
    announce_server("http://0.0.0.0:8470/", "0.0.0.0")  # (nothing is bound here)
    err = capsys.readouterr().err
    assert err.startswith("warning: the viewer listens on 0.0.0.0: anyone who can reach")


def test_view_latest_and_the_viewer_options_need_their_command(
    mine_log: Path, tmp_path: Path
) -> None:
    runs = tmp_path / "runs"
    runs.mkdir()
    (runs / "old.jsonl").write_text(mine_log.read_text())
    out = tmp_path / "latest.html"
    r = CliRunner().invoke(cli, ["view", "--latest", str(runs), "--html", str(out)])
    assert r.exit_code == 0 and out.stat().st_size > 1_000_000, r.output
    r = CliRunner().invoke(cli, ["view"])
    assert r.exit_code == 2 and "give a LOG file, or --latest DIR" in r.output
    r = CliRunner().invoke(cli, ["view", "--latest", str(tmp_path / "none")])
    assert r.exit_code == 2 and "no such directory" in r.output
    r = CliRunner().invoke(cli, ["run", str(MINE), "--port", "0", "--log", str(tmp_path / "x")])
    assert (
        r.exit_code == 2 and "--host, --port and --tls-* are the viewer's: add --view" in r.output
    )
    assert not (tmp_path / "x").exists()


def test_view_on_a_port_in_use_is_refused_clearly(mine_log: Path) -> None:
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    port = holder.getsockname()[1]
    try:
        r = CliRunner().invoke(cli, ["view", str(mine_log), "--port", str(port)])
    finally:
        holder.close()
    assert r.exit_code == 2 and f"port {port} on 127.0.0.1 in use" in r.output
    assert "Traceback" not in r.output
