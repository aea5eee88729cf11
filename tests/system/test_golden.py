"""Every shipped simulator mission does what it did when its golden run was recorded (issue #35).

Each mission runs as a user runs it (``btmission run``, a fresh process); its event log, less the
wall-clock fields, and its report must equal the ones in ``tests/golden/`` line for line
(:mod:`tests.golden` says what is left out and how to record them again).
"""

from __future__ import annotations

import json

import pytest

from tests import golden


@pytest.mark.slow
@pytest.mark.parametrize("mission", golden.MISSIONS)
def test_shipped_mission_matches_its_golden_run(mission: str) -> None:
    want_lines, want_report = golden.load(mission)
    lines, report = golden.run(mission)
    assert report == want_report
    verdict = golden.first_difference(want_lines, lines)
    assert verdict == "identical", f"{mission}: {verdict}"


def test_golden_files_cover_every_shipped_simulator_mission() -> None:
    """A mission added to missions/ gets a golden run, or is named as real-time (not golden)."""
    shipped = {p.stem for p in (golden.ROOT / "missions").glob("*.yaml")}
    assert shipped == set(golden.MISSIONS) | set(golden.REAL_TIME)
    for mission in golden.MISSIONS:
        lines, report = golden.load(mission)
        assert lines[0].startswith('{"agents"') and '"ev":"header"' in lines[0]
        assert '"ev":"end"' in lines[-1]
        assert f"Mission {mission}" in report
        assert not any(str(golden.ROOT) in line for line in lines[:2])  # no clone's own paths


def test_normalise_drops_wall_clock_fields_and_machine_paths() -> None:
    base = golden.ROOT / "missions"
    header = golden.normalise(
        json.dumps({"t": 0.0, "ev": "header", "world_ref": {"base_dir": str(base), "map": None}})
    )
    assert '"base_dir":"missions"' in header
    mapped = golden.normalise(
        json.dumps({"ev": "header", "world_ref": {"map": str(base / "data" / "m.npz")}})
    )
    assert '"map":"missions/data/m.npz"' in mapped
    end = golden.normalise('{"t":3.5,"ev":"end","reason":"completed","wall_s":0.81,"steps":70}')
    assert end == '{"ev":"end","reason":"completed","steps":70,"t":3.5}'
    rnd = golden.normalise('{"t":1.0,"ev":"round","round":3,"step_ms":0.4}')
    assert rnd == '{"ev":"round","round":3,"t":1.0}'
    assert golden.first_difference(["a", "b"], ["a", "c"]).startswith("line 2 of 2 differs")
    assert golden.first_difference(["a"], ["a", "b"]).startswith("the golden log has 1 lines")
