"""docs/auction.md: every ``$ btmission ...`` example runs (exit 0 unless marked) and the Python
example works. (``-o PATH`` outputs go to a temporary directory.)"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.cli.main import cli

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "auction.md"


def blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", PAGE.read_text(encoding="utf-8"), re.S)


def commands() -> list[str]:
    return [line[2:] for b in blocks("console") for line in b.splitlines() if line.startswith("$ ")]


def test_the_page_has_examples() -> None:
    assert len(commands()) >= 5 and len(blocks("python")) == 1


@pytest.mark.parametrize("line", commands())
def test_console_example_runs(line: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(ROOT)
    expect = 0
    m = re.search(r"#\s*exit (\d)\s*$", line)
    if m:
        expect = int(m.group(1))
    args = shlex.split(line, comments=True)
    assert args[0] == "btmission"
    args = args[1:]
    for i, a in enumerate(args[:-1]):
        if a in ("-o", "--out"):
            args[i + 1] = str(tmp_path / Path(args[i + 1]).name)
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == expect, r.output + r.stderr
    assert "Traceback" not in r.output + r.stderr


def test_python_example_runs(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(ROOT)
    exec(compile(blocks("python")[0], str(PAGE), "exec"), {})
    out = capsys.readouterr().out
    assert "'R3': 'T1'" in out and "outbid" in out
