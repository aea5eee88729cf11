"""``btmission auction`` and ``btmission bench auction`` through CliRunner: outputs and exit codes
(0 ok, 2 bad input, never a traceback)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from tests.system.test_cli import MINE, PICK, run


@pytest.mark.parametrize("args", [["auction"], ["bench", "auction"]])
def test_help(runner: CliRunner, args: list[str]) -> None:
    code, out, _ = run(runner, *args, "--help")
    assert code == 0 and "Examples:" in out and "btmission " in out


def test_auction_round_on_the_mine_mission(runner: CliRunner) -> None:
    code, out, _ = run(runner, "auction", MINE)
    assert code == 0
    lines = out.splitlines()
    assert lines[0].startswith("mine_inspection at t = 0 s: 6 task(s) announced, 3 agent(s)")
    assert {line.split()[0]: line.split()[1] for line in lines[1:4]} == {
        "R1": "T4",
        "R2": "T2",
        "R3": "T1",
    }
    assert "  T3 unassigned: outbid: its 3 bidder(s) won other tasks" in lines
    assert "  not yet arrived: T7" in lines
    code, out, _ = run(runner, "auction", MINE, "--at", "120", "--bids")
    assert "T7 unassigned" in out and "not yet arrived" not in out
    assert out.splitlines()[-4].split() == ["T1", "T2", "T3", "T4", "T5", "T6", "T7"]
    assert out.splitlines()[-1].split()[:2] == ["R3", "54.65"]


def test_auction_json_and_solver_override(runner: CliRunner) -> None:
    outs = {}
    for solver in ("assignment", "ilp-scip"):
        code, out, _ = run(runner, "auction", PICK, "--at", "3", "--solver", solver, "--json")
        assert code == 0
        outs[solver] = json.loads(out)
    a, b = outs["assignment"], outs["ilp-scip"]
    assert (a["solver"], b["solver"]) == ("dense", "ilp-scip")
    assert a["assignments"] == b["assignments"]
    assert a["assignments"]["G1"]["task"] == "I1"  # the inspection is nearer than the pick
    assert a["announced"] == ["P1", "I1"] and a["unassigned"]["P1"].startswith("outbid")


def test_auction_bad_inputs(runner: CliRunner, tmp_path: Path) -> None:
    code, _, err = run(runner, "auction", str(tmp_path / "missing.yaml"))
    assert code == 2 and "missing.yaml" in err
    code, _, err = run(runner, "auction", MINE, "--at", "-1")
    assert code == 2 and "--at" in err
    bad = tmp_path / "named.yaml"
    text = Path(MINE).read_text()
    t1 = re.search(r"\{id: T1, type: inspect, location: (\[[^\]]*\])", text)
    assert t1 is not None
    bad.write_text(text.replace(t1.group(1), "bay3", 1), encoding="utf-8")
    code, _, err = run(runner, "auction", str(bad))
    assert code == 2
    line = next(i for i, t in enumerate(text.splitlines(), 1) if "{id: T1," in t)
    assert f"named.yaml:{line}:" in err and "tasks[0].location" in err  # caught on loading
    assert "expected [x, y, z] (a place name like 'bay3' needs a world.topomap)" in err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--agents", "x"], "expected comma-separated integers, got 'x'"),
        (["--tasks", "0"], "expected positive integers"),
        (["-p", "1.5"], "'1.5' is not a fraction in (0, 1]"),
        (["-p", ","], "expected at least one value"),
        (["--scale", "10by20"], "'10by20' is not AGENTSxTASKS"),
        (["--crossover", "5x"], "'5x' is not AGENTSxTASKS"),
        (["--repeat", "0"], "--repeat"),
    ],
)
def test_bench_auction_bad_options(runner: CliRunner, args: list[str], message: str) -> None:
    code, _, err = run(runner, "bench", "auction", *args)
    assert code == 2 and message in err


def test_bench_auction_tiny_run(runner: CliRunner, tmp_path: Path) -> None:
    code, out, _ = run(
        runner, "bench", "auction", "--agents", "4", "--tasks", "10", "-p", "50%,1",
        "--repeat", "1", "--rounds", "2", "--scale", "", "--crossover", "", "-o", str(tmp_path),
    )  # fmt: skip
    assert code == 0
    assert "| fig4 | 4 | 10 | 50% |" in out and "| fig5 | 4 | 10 | 100% |" in out
    assert {p.name for p in tmp_path.iterdir()} == {"auction.md", "auction.csv", "auction.png"}


def test_auction_fig7_what_ifs(runner: CliRunner) -> None:
    """Seed 003 Fig. 7 from the command line: before the pick the inspection steals G1, after
    the pick (committed, k_bt = 0) it does not."""
    code, out, _ = run(
        runner, "auction", PICK, "--at", "3", "--holding", "G1=P1", "--agent-at", "G1=3,1.5,0"
    )
    assert code == 0
    assert "  G1  I1  cost 1.80" in out and "  P1: G1 → — (G1 reassigned to I1)" in out
    code, out, _ = run(
        runner, "auction", PICK, "--at", "40", "--committed", "G1=P1", "--agent-at", "G1=9,2,0"
    )
    assert code == 0
    assert "  G1  P1  cost 0.00" in out
    assert "  I2 unassigned: no bids: declined by G1 (committed to P1)" in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--at", "5", "--committed", "G1=I1"], "task type 'inspect' has no commit_after"),
        (["--holding", "X=P1"], "no agent 'X' (agents: G1)"),
        (["--holding", "G1=Q"], "no task 'Q' in the mission"),
        (["--holding", "G1"], "expected AGENT=VALUE"),
        (["--holding", "G1=I2"], "task 'I2' arrives at 40 s, after --at 0"),
        (["--at", "5", "--holding", "G1=I1", "--committed", "G1=P1"], "an agent holds one task"),
        (["--at", "5", "--holding", "G1=P1", "--holding", "G1=I1"], "an agent holds one task"),
        (["--agent-at", "G1=1,2"], "expected AGENT=X,Y,Z"),
    ],
)
def test_auction_what_if_bad_options(runner: CliRunner, args: list[str], message: str) -> None:
    code, _, err = run(runner, "auction", PICK, *args)
    assert code == 2 and message in err
