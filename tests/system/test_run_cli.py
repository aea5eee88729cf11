"""``btmission run`` and ``btmission report`` through click's CliRunner."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.cli.main import cli

ROOT = Path(__file__).resolve().parents[2]
PICK = ROOT / "missions" / "pick_and_deliver.yaml"


def test_run_prints_the_report_and_writes_log_and_pngs(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(cli, ["run", str(PICK), "--log", str(tmp_path), "--controller", "track"])
    assert result.exit_code == 0, result.output
    assert "Tasks (seed 000 Table III)" in result.output
    assert "Mission (seed 000 Table II)" in result.output
    assert "Tasks done              3 of 3" in result.output
    logs = list(tmp_path.glob("pick_and_deliver-*-seed0.jsonl"))
    assert len(logs) == 1
    stem = logs[0].stem
    assert (tmp_path / f"{stem}-timeline.png").is_file()
    assert (tmp_path / f"{stem}-topview.png").is_file()
    again = runner.invoke(cli, ["report", str(logs[0]), "--json"])
    assert again.exit_code == 0, again.output
    summary = json.loads(again.output)["summary"]
    assert summary["tasks_done"] == 3 and summary["end"] == "completed"


def test_run_until_stops_early_with_exit_1(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(
        cli, ["run", str(PICK), "--log", str(tmp_path), "--until", "5", "--quiet", "--no-png"]
    )
    assert result.exit_code == 1, result.output
    assert "ended: until" in result.output
    assert not list(tmp_path.glob("*.png"))


def _mission(tmp_path: Path, old: str, new: str) -> Path:
    text = PICK.read_text().replace(old, new)
    assert text != PICK.read_text()
    path = tmp_path / "m.yaml"
    path.write_text(text)
    return path


def test_bad_missions_exit_2_before_anything_runs(runner: CliRunner, tmp_path: Path) -> None:
    cases = {
        "unknown key": ("coordination: {auction_rate_hz: 9}", "coordination: {auction_rate: 9}"),
        "in rock / outside": ("location: [4, 3, 0]", "location: [40, 3, 0]"),
        "unknown setting": ("coordination:", "runtime: {settings: {wings: 2}}\ncoordination:"),
        "bad controller": ("coordination:", "runtime: {controller: pid}\ncoordination:"),
    }
    for name, (old, new) in cases.items():
        logs = tmp_path / name.replace(" ", "_").replace("/", "")
        m = _mission(tmp_path, old, new)
        result = runner.invoke(cli, ["run", str(m), "--log", str(logs)])
        assert result.exit_code == 2, (name, result.output)
        assert "nothing was run" in result.output and "Traceback" not in result.output
        assert not any(logs.glob("*.jsonl")), name


def test_report_of_a_bad_or_missing_log_exits_2(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(cli, ["report", str(tmp_path / "none.jsonl")])
    assert result.exit_code == 2 and "no such log file" in result.output
    junk = tmp_path / "junk.jsonl"
    junk.write_text("hello\n")
    result = runner.invoke(cli, ["report", str(junk)])
    assert result.exit_code == 2 and "not a btmission event log" in result.output


def test_report_pngs_go_to_the_given_directory(runner: CliRunner, tmp_path: Path) -> None:
    log = ROOT / "docs" / "examples" / "pick_and_deliver.jsonl"
    result = runner.invoke(cli, ["report", str(log), "--png", str(tmp_path / "plots")])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == [
        "pick_and_deliver-timeline.png",
        "pick_and_deliver-topview.png",
    ]


def test_help_has_examples(runner: CliRunner) -> None:
    for cmd in ("run", "report"):
        result = runner.invoke(cli, [cmd, "--help"])
        assert result.exit_code == 0 and "Example" in result.output


NOISE = "runtime: {sim: {velocity_noise: 0.05, pose_noise_m: 0.002, heading_noise_rad: 0.01}}\n"


def _poses(log_dir: Path) -> list[tuple[float, str, list[float], float]]:
    (log,) = log_dir.glob("*.jsonl")
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    return [(e["t"], e["agent"], e["p"], e["odometer_m"]) for e in lines if e["ev"] == "pose"]


def test_run_with_noise_is_the_same_run_for_a_seed_and_another_for_another(
    runner: CliRunner, tmp_path: Path
) -> None:
    """runtime.sim's noise (velocity tracking and pose estimate) is drawn from the run's seed:
    ``--seed 1`` twice gives the same log, ``--seed 2`` another one."""
    m = _mission(tmp_path, "coordination:", NOISE + "coordination:")
    poses = {}
    for name, seed in (("a", "1"), ("b", "1"), ("c", "2")):
        args = ["--seed", seed, "--log", str(tmp_path / name), "--until", "20", "--quiet"]
        result = runner.invoke(cli, ["run", str(m), *args, "--no-png", "--controller", "track"])
        assert result.exit_code == 1 and "ended: until" in result.output, result.output
        poses[name] = _poses(tmp_path / name)
    assert len(poses["a"]) > 30 and poses["a"] == poses["b"]
    assert [p[:2] for p in poses["a"]] == [p[:2] for p in poses["c"]]  # same cadence ...
    moved = max(abs(a[3] - c[3]) for a, c in zip(poses["a"], poses["c"]))
    assert moved > 0.01  # ... but another drive (odometers from the simulator's truth)


def test_bad_noise_settings_exit_2_with_where_and_why(runner: CliRunner, tmp_path: Path) -> None:
    bad = (
        "runtime: {sim: {velocity_noise: 0.8, velocity_noise_tau_s: 0, pose_noise_m: -0.01,"
        " heading_noise_rad: .inf}}\n"
    )
    m = _mission(tmp_path, "coordination:", bad + "coordination:")
    result = runner.invoke(cli, ["run", str(m), "--log", str(tmp_path / "logs")])
    assert result.exit_code == 2, result.output
    out = result.output
    assert (
        "m.yaml:24:33: runtime.sim.velocity_noise: Input should be less than or equal to 0.5 "
        "(got 0.8)"
    ) in out
    assert "runtime.sim.velocity_noise_tau_s: Input should be greater than 0 (got 0)" in out
    assert "runtime.sim.pose_noise_m: Input should be greater than or equal to 0 (got -0.01)" in out
    assert "runtime.sim.heading_noise_rad: expected a finite number (got inf)" in out
    assert "nothing was run" in out and not (tmp_path / "logs").exists()


def test_the_terminal_shows_a_vehicle_link_lost_and_back_and_a_takeover(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A field engineer watching ``btmission run`` sees at once what only the log had: a
    vehicle's link lost and back (with how long), its autopilot taking it over, and a flapping
    link is not allowed to flood the terminal."""
    from btmission.cli.run_cmds import _StderrNotes
    from btmission.runtime.events import Event

    notes = _StderrNotes()
    lines = [
        '{"t":25.0178,"ev":"vehicle_link","agent":"R1","up":false}',
        '{"t":35.2176,"ev":"vehicle_link","agent":"R1","up":true,"mode":"HOLD"}',
        '{"t":35.4191,"ev":"taken_over","agent":"R1","mode":"LAND","failsafe":true,'
        '"final":true,"task":"T1"}',
        '{"t":36.0,"ev":"taken_over","agent":"R2","mode":"MANUAL","failsafe":false,"final":false}',
        '{"t":36.5,"ev":"pose","agent":"R2","p":[0,0,0],"v":[0,0,0],"yaw":0,"mode":"HOLD",'
        '"armed":true,"flying":true,"odometer_m":null,"clearance_m":null}',
    ]
    for line in lines:
        notes.on_event(Event.from_json(line))
    assert capsys.readouterr().err.splitlines() == [
        "warning: R1: vehicle link lost at t=25.0 s (its autopilot is not heard): its tree "
        "waits for it",
        "R1: vehicle link back at t=35.2 s after 10.2 s in HOLD",
        "warning: R1: its autopilot's failsafe switched the vehicle to LAND at t=35.4 s: it "
        "stands down and T1 goes back to the pool (the console's include brings it back)",
        "warning: R2: its autopilot or pilot switched the vehicle to MANUAL at t=36.0 s: its "
        "tree flies on (takeover_is_final: false)",
    ]
    for i in range(30):  # a flapping link: 10 lines (the 9 before + this one), then the log only
        notes.on_event(Event.from_json(f'{{"t":{40 + i},"ev":"vehicle_link","agent":"R1",'
                                       f'"up":{"true" if i % 2 else "false"}}}'))  # fmt: skip
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 8 and err[-1].endswith("(further link changes of R1 only in the log)")


def test_run_prints_when_an_agent_loses_and_regains_its_coordinator(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Issue #37: the agent says when it stops hearing its coordinator and when it hears it
    again (it keeps its task within its lease meanwhile); its lease running out is a warning."""
    from btmission.cli.run_cmds import _StderrNotes
    from btmission.runtime.events import Event

    notes = _StderrNotes()
    for line in (
        '{"t":4.0,"ev":"coordinator_link","agent":"R1","up":false,"silent_s":1.1}',
        '{"t":8.0,"ev":"coordinator_link","agent":"R1","up":true,"silent_s":5.1}',
    ):
        notes.on_event(Event.from_json(line))
    assert capsys.readouterr().err.splitlines() == [
        "warning: R1: coordinator lost at t=4.0 s (not heard for 1.1 s): it keeps its task "
        "within its lease",
        "R1: coordinator regained at t=8.0 s after 5.1 s",
    ]
