"""The golden runs: every shipped mission's event log and report, recorded before a refactoring.

A change that must not alter what any mission does (issue #35, the middle-floor renovation) is
checked against these: ``tests/system/test_golden.py`` runs each mission again, as a user would
(``btmission run MISSION``, in a fresh process), and compares the event log line by line and the
report text with the ones committed under ``tests/golden/``.

What is left out, because it is not the mission's behaviour:

- fields measured on the wall clock: ``wall_s`` (end), ``build_s`` (built), ``step_ms`` (round),
  ``time_ms`` (relocalized), and a ``leaf_error``'s ``traceback`` (line numbers move);
- where the files are: the header's ``world_ref`` paths (``base_dir``, ``map``, ``topomap``) are
  made relative to the repository;
- the report's ``log:`` line (the log's name holds the wall-clock date).

The MAVLink missions (``mine_inspection_px4``, ``mine_inspection_ardupilot``) fly against
``btmission mavsim`` in real time: their logs depend on the wall clock and the machine's load, so
they are not golden; ``tests/system/test_mavlink_run.py`` checks them (every task done once).

Record them again (only when a change is *meant* to alter behaviour, and say so in the commit)::

    .venv/bin/python -m tests.golden --update            # every mission
    .venv/bin/python -m tests.golden --update warehouse  # one
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
GOLDEN = ROOT / "tests" / "golden"

MISSIONS: tuple[str, ...] = (
    "compra_sar",
    "mine_haulage",
    "mine_inspection",
    "mine_relocalize",
    "pick_and_deliver",
    "seed000_field",
    "seed002_tunnel",
    "warehouse",
)
"""The shipped missions that run in the embedded simulator, each with its own controller."""

REAL_TIME = ("mine_inspection_px4", "mine_inspection_ardupilot")
"""Shipped missions on MAVLink vehicles: paced by the wall clock, so not golden (module doc)."""

WALL_FIELDS: dict[str, tuple[str, ...]] = {
    "end": ("wall_s",),
    "built": ("build_s",),
    "round": ("step_ms",),
    "relocalized": ("time_ms",),
    "leaf_error": ("traceback",),
    "internal_error": ("traceback",),
}


def normalise(line: str) -> str:
    """One event log line without its wall-clock fields and machine paths (module docstring)."""
    event: dict[str, Any] = json.loads(line)
    for key in WALL_FIELDS.get(event.get("ev", ""), ()):
        event.pop(key, None)
    if event.get("ev") == "header":
        ref = event.get("world_ref")
        if isinstance(ref, dict):
            for key, value in ref.items():  # base_dir, map, topomap: where this clone is
                if isinstance(value, str) and Path(value).is_absolute():
                    path = Path(value)
                    ref[key] = (
                        path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else value
                    )
    return json.dumps(event, separators=(",", ":"), sort_keys=True)


def report_text(stdout: str) -> str:
    """The report a run printed, without the ``log:`` line (its name has the wall-clock date)."""
    return "".join(
        line for line in stdout.splitlines(keepends=True) if not line.startswith("log: ")
    )


def run(mission: str) -> tuple[list[str], str]:
    """Run a shipped mission as a user would; returns its normalised log lines and its report."""
    with tempfile.TemporaryDirectory(prefix=f"golden-{mission}-") as tmp:
        proc = subprocess.run(
            [sys.executable, "-m", "btmission", "run", f"missions/{mission}.yaml",
             "--log", tmp, "--quiet", "--no-png"],
            cwd=ROOT, capture_output=True, text=True, timeout=900,
            env={**os.environ, "PYTHONHASHSEED": "0"},
        )  # fmt: skip
        if proc.returncode not in (0, 1):
            raise RuntimeError(
                f"{mission}: btmission run exited {proc.returncode}\n{proc.stderr[-3000:]}"
            )
        (log,) = Path(tmp).glob("*.jsonl")
        lines = [normalise(line) for line in log.read_text().splitlines() if line.strip()]
    return lines, report_text(proc.stdout)


def paths(mission: str) -> tuple[Path, Path]:
    """Where a mission's golden log (gzip'd normalised JSON Lines) and report are kept."""
    return GOLDEN / f"{mission}.events.jsonl.gz", GOLDEN / f"{mission}.report.txt"


def load(mission: str) -> tuple[list[str], str]:
    """A mission's golden log lines and report."""
    log, report = paths(mission)
    with gzip.open(log, "rt", encoding="utf-8") as f:
        lines = f.read().splitlines()
    return lines, report.read_text(encoding="utf-8")


def save(mission: str, lines: list[str], report: str) -> None:
    """Write a mission's golden files (gzip without a time stamp: same run, same bytes)."""
    GOLDEN.mkdir(parents=True, exist_ok=True)
    log, report_path = paths(mission)
    with open(log, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as f:
        f.write(("\n".join(lines) + "\n").encode("utf-8"))
    report_path.write_text(report, encoding="utf-8")


def first_difference(golden: list[str], now: list[str]) -> str:
    """Where two logs part, for a failure message: the first differing line and the counts."""
    for i, (a, b) in enumerate(zip(golden, now)):
        if a != b:
            differing = sum(x != y for x, y in zip(golden, now))
            return (
                f"line {i + 1} of {len(golden)} differs ({differing} lines differ in all; "
                f"{len(now)} lines now)\n  golden: {a[:400]}\n  now:    {b[:400]}"
            )
    if len(golden) != len(now):
        return f"the golden log has {len(golden)} lines, this run {len(now)} (the same up to there)"
    return "identical"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tests.golden",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("missions", nargs="*", help=f"default: all of {', '.join(MISSIONS)}")
    parser.add_argument("--update", action="store_true", help="record them (else: compare)")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.missions) - set(MISSIONS))
    if unknown:
        parser.error(f"not a golden mission: {', '.join(unknown)} (known: {', '.join(MISSIONS)})")
    failed = 0
    for mission in args.missions or MISSIONS:
        start = time.monotonic()
        lines, report = run(mission)
        took = time.monotonic() - start
        if args.update:
            save(mission, lines, report)
            print(f"{mission}: recorded {len(lines)} events ({took:.1f} s)", flush=True)
            continue
        golden_lines, golden_report = load(mission)
        verdict = first_difference(golden_lines, lines)
        same_report = golden_report == report
        failed += verdict != "identical" or not same_report
        print(f"{mission}: log {verdict}; report {'identical' if same_report else 'differs'}"
              f" ({took:.1f} s)", flush=True)  # fmt: skip
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
