"""``btmission bench paper``: sections stored one by one, the page rebuilt from all of them."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
from click.testing import CliRunner

from btmission.bench import paper
from btmission.bench.paper import SectionResult, assemble, parse_only, pct, run_paper_benchmark
from tests.system.test_cli import run


def _fake_section(monkeypatch: pytest.MonkeyPatch, key: str, value: float) -> list[bool]:
    """Install ``btmission.bench.paper_<key>`` as a module that records each call's ``quick``."""
    calls: list[bool] = []

    def run_section(quick: bool, echo: Callable[[str], None]) -> SectionResult:
        calls.append(quick)
        echo("fake section running")
        return SectionResult(
            markdown=paper.table(["x", "paper", "btmission"], [["y", 1, value]]),
            data={"value": value},
        )

    module = ModuleType(f"btmission.bench.paper_{key}")
    module.KEY = key  # type: ignore[attr-defined]
    module.TITLE = f"Fake {key}"  # type: ignore[attr-defined]
    module.run = run_section  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setattr(paper, "available", lambda: ["seed002", "seed004"])
    return calls


def test_pct_is_the_signed_deviation_from_the_paper() -> None:
    assert pct(332.2, 311.0) == "+6.8 %"
    assert pct(15.9, 23.7) == "-32.9 %"
    assert pct(1.0, 0.0) == "n/a"


def test_only_names_sections_in_page_order_and_refuses_unknown_ones(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(paper, "available", lambda: ["seed000", "seed004"])
    assert parse_only("") == ["seed000", "seed004"]
    assert parse_only("seed004, seed000") == ["seed000", "seed004"]
    with pytest.raises(ValueError, match=r"unknown section.*seed9.*expected some of seed000"):
        parse_only("seed9")
    with pytest.raises(ValueError, match="seed002 not available"):
        parse_only("seed002")


def test_each_section_is_stored_and_a_rerun_of_one_keeps_the_other(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    calls2 = _fake_section(monkeypatch, "seed002", 1.5)
    calls4 = _fake_section(monkeypatch, "seed004", 2.5)
    out, doc = tmp_path / "results", tmp_path / "docs" / "fidelity.md"
    lines: list[str] = []
    run_paper_benchmark(["seed002", "seed004"], out_dir=out, doc=doc, echo=lines.append)
    assert calls2 == [False] and calls4 == [False]
    stored = json.loads((out / "paper" / "seed004.json").read_text())
    assert stored["data"] == {"value": 2.5} and stored["title"] == "Fake seed004"
    assert stored["env"]["cpus"] and "load average" in stored["env"]["load"]
    # re-run seed004 alone with another result: seed002's stored section stays on the page
    _fake_section(monkeypatch, "seed004", 9.5)
    run_paper_benchmark(["seed004"], out_dir=out, doc=doc, echo=lines.append)
    page = doc.read_text()
    assert page.startswith("# Fidelity to the papers\n")
    assert page.index("## Fake seed002") < page.index("## Fake seed004")
    assert "| y | 1 | 1.5 |" in page and "| y | 1 | 9.5 |" in page and "2.5 |" not in page
    # sections never run are named, with the command that runs them
    assert "## seed000\n\nNot run yet: `btmission bench paper --only seed000`." in page
    assert any("fake section running" in x for x in lines)


def test_a_quick_run_never_writes_over_the_page(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    calls = _fake_section(monkeypatch, "seed002", 1.0)
    doc = tmp_path / "fidelity.md"
    doc.write_text("the real page\n")
    run_paper_benchmark(["seed002"], quick=True, out_dir=tmp_path / "r", doc=doc, echo=print)
    assert calls == [True]
    assert doc.read_text() == "the real page\n"
    quick_page = (tmp_path / "r" / "fidelity.md").read_text()
    assert "**Quick run**" in quick_page
    assert "**Quick run**" in assemble(tmp_path / "r")


def test_the_command_refuses_an_unknown_section(runner: CliRunner, tmp_path: Path) -> None:
    code, _, err = run(runner, "bench", "paper", "--only", "seed1", "--out", str(tmp_path))
    assert code == 2
    assert "unknown section(s) seed1" in err
    assert not (tmp_path / "paper").exists()


def test_the_command_runs_a_section_into_out(
    monkeypatch: pytest.MonkeyPatch, runner: CliRunner, tmp_path: Path
) -> None:
    _fake_section(monkeypatch, "seed004", 3.0)
    monkeypatch.chdir(tmp_path)  # no ./docs here: the page goes beside the results
    code, out, _ = run(runner, "bench", "paper", "--only", "seed004", "--out", "res")
    assert code == 0, out
    assert "wrote res/fidelity.md" in out
    assert "| y | 1 | 3.0 |" in (tmp_path / "res" / "fidelity.md").read_text()
