"""The documentation stays true: its examples run, and its links lead somewhere.

Every ``$ btmission ...`` line inside a ```` ```console ```` block of ``docs/*.md`` is run through
click's ``CliRunner`` from the repository root, and must exit with status 0, or with the status
its trailing ``# exit N`` comment documents. Commands never touch the repository: ``-o``/``--output``
and ``--out`` paths are redirected into ``tmp_path``, and ``library new`` (and commands on the
plugin it scaffolds) run inside ``tmp_path``. svg/png commands are skipped without Graphviz.

Every ```` ```python ```` block is a complete program and is executed (from the repository root,
in a fresh namespace); excerpts that cannot run on their own are fenced ```` ```py ```` instead.

Only the exit status is checked, not the output shown in the docs, so that wording changes in
messages do not break this test; re-run the examples when you change them.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.cli.main import cli
from btmission.export import graphviz_available

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(DOCS.glob("*.md"))

_EXIT = re.compile(r"\s+#\s*exit\s+(\d+)\s*$")
_FENCE = re.compile(r"^\s*(```+|~~~+)\s*([\w+-]*)")
_OUTPUT_OPTIONS = ("-o", "--output", "--out", "--log", "--png")
_SCAFFOLD_DIR = re.compile(r"^btmission-([a-z0-9-]+)(/|$)")


@dataclass(frozen=True)
class Example:
    """One documented command: where it is, its arguments and its documented exit status."""

    page: str
    line: int
    args: tuple[str, ...]
    exit_code: int

    @property
    def id(self) -> str:
        return f"{self.page}:{self.line}"


def console_lines(page: Path) -> list[tuple[int, str]]:
    """``(line number, text)`` of every line inside a ```console block of ``page``."""
    out: list[tuple[int, str]] = []
    fence: str | None = None
    is_console = False
    for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), start=1):
        m = _FENCE.match(line)
        if m and fence is None:
            fence, is_console = m.group(1), m.group(2) == "console"
            continue
        if m and fence is not None and line.strip() == fence:
            fence, is_console = None, False
            continue
        if is_console:
            out.append((number, line))
    return out


def collect_examples() -> list[Example]:
    examples: list[Example] = []
    for page in PAGES:
        for number, line in console_lines(page):
            if not line.startswith("$ "):
                continue
            command = line[2:]
            exit_code = 0
            m = _EXIT.search(command)
            if m:
                exit_code = int(m.group(1))
                command = command[: m.start()]
            args = shlex.split(command, comments=True)
            examples.append(
                Example(page.relative_to(ROOT).as_posix(), number, tuple(args), exit_code)
            )
    return examples


EXAMPLES = collect_examples()


def test_docs_have_examples() -> None:
    assert len(EXAMPLES) >= 40, [e.id for e in EXAMPLES]


@pytest.mark.parametrize("example", EXAMPLES, ids=[e.id for e in EXAMPLES])
def test_console_lines_are_btmission_commands(example: Example) -> None:
    """``console`` blocks hold only btmission commands; other commands go in ``sh`` blocks."""
    assert example.args[:1] == ("btmission",), f"{example.id}: {shlex.join(example.args)}"


def _rewrite_outputs(args: list[str], tmp_path: Path) -> list[str]:
    """Send every output file or directory into ``tmp_path`` (keeping its base name)."""
    out: list[str] = []
    i = 0
    while i < len(args):
        arg = args[i]
        if arg in _OUTPUT_OPTIONS and i + 1 < len(args):
            out += [arg, str(tmp_path / Path(args[i + 1]).name)]
            i += 2
            continue
        assert not arg.startswith(("--output=", "--out=", "--log=", "--png=")), (
            "write '-o PATH' in the docs"
        )
        assert not (arg.startswith("-o") and len(arg) > 2), "write '-o PATH' in the docs"
        out.append(arg)
        i += 1
    if out[:2] == ["bench", "synth"] and "--out" not in out:
        out += ["--out", str(tmp_path / "results")]  # never rewrite benchmarks/results
    return out


def _needs_graphviz(args: list[str]) -> bool:
    for i, arg in enumerate(args[:-1]):
        if arg in ("-f", "--format") and args[i + 1] in ("svg", "png"):
            return True
        if arg in ("-o", "--output") and args[i + 1].lower().endswith((".svg", ".png")):
            return True
    return False


@pytest.mark.parametrize("example", EXAMPLES, ids=[e.id for e in EXAMPLES])
def test_documented_command_runs(
    example: Example, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    args = list(example.args[1:])  # drop the leading "btmission"
    if _needs_graphviz(args) and not graphviz_available():
        pytest.skip("graphviz 'dot' is not installed")
    runner = CliRunner()
    scaffolded = [m.group(1) for m in map(_SCAFFOLD_DIR.match, args) if m]
    if args[:2] == ["library", "new"] or scaffolded:
        # Scaffolding writes into the current directory: do it in tmp_path, and create the
        # plugin first when the command works on the files `library new` makes.
        monkeypatch.chdir(tmp_path)
        for name in scaffolded:
            made = runner.invoke(cli, ["library", "new", name.replace("-", "_")])
            assert made.exit_code == 0, made.output
    else:
        monkeypatch.chdir(ROOT)
    args = _rewrite_outputs(args, tmp_path)

    result = runner.invoke(cli, args)

    shown = f"{example.id}: btmission {shlex.join(args)}\n{result.output}"
    assert "Traceback" not in result.output, shown
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise AssertionError(shown) from result.exception
    assert result.exit_code == example.exit_code, shown


# ------------------------------------------------------------------------------------ links
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_CODE_SPAN = re.compile(r"`[^`]*`")


def _prose(page: Path) -> str:
    """``page`` without fenced code blocks and code spans (links there are not links)."""
    lines: list[str] = []
    fence: str | None = None
    for line in page.read_text(encoding="utf-8").splitlines():
        m = _FENCE.match(line)
        if m and fence is None:
            fence = m.group(1)
            continue
        if fence is not None:
            if line.strip() == fence:
                fence = None
            continue
        lines.append(_CODE_SPAN.sub("", line))
    return "\n".join(lines)


def _heading_anchors(page: Path) -> set[str]:
    """GitHub-style anchors of the headings of ``page`` (code-span text kept, as GitHub does)."""
    anchors: set[str] = set()
    fence: str | None = None
    for line in page.read_text(encoding="utf-8").splitlines():
        m = _FENCE.match(line)
        if m and fence is None:
            fence = m.group(1)
            continue
        if fence is not None:
            if line.strip() == fence:
                fence = None
            continue
        h = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if h:
            anchors.add(re.sub(r"[^\w\- ]", "", h.group(1).lower()).replace(" ", "-"))
    return anchors


def _links(page: Path) -> list[str]:
    return [m.group(1) for m in _LINK.finditer(_prose(page))]


LINKED_PAGES = [*PAGES, ROOT / "README.md"]


PYTHON_BLOCKS = [
    pytest.param(block, id=f"{page.name}[{i}]")
    for page in PAGES
    for i, block in enumerate(
        re.findall(r"```python\n(.*?)```", page.read_text(encoding="utf-8"), re.S)
    )
]


@pytest.mark.parametrize("block", PYTHON_BLOCKS)
def test_python_examples_run(block: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(ROOT)
    exec(compile(block, "<docs example>", "exec"), {"__name__": "__docs_example__"})


@pytest.mark.parametrize(
    "page", LINKED_PAGES, ids=[p.relative_to(ROOT).as_posix() for p in LINKED_PAGES]
)
def test_relative_links_resolve(page: Path) -> None:
    broken = []
    for target in _links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        dest = (page.parent / path_part).resolve() if path_part else page
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _heading_anchors(dest):
            broken.append(f"{target}: no heading with anchor #{anchor}")
    assert broken == [], f"{page.relative_to(ROOT)}: {broken}"


def test_every_page_is_linked_from_the_index() -> None:
    index = DOCS / "index.md"
    linked = {(index.parent / t.partition("#")[0]).resolve() for t in _links(index)}
    missing = [p.name for p in PAGES if p != index and p.resolve() not in linked]
    assert missing == []


def test_readme_documentation_links_exist() -> None:
    """The pages README.md promises are there."""
    for name in ("quickstart", "library-format", "mission-format", "synthesis", "plugins", "cli"):
        assert (DOCS / f"{name}.md").is_file(), name
    assert (DOCS / "benchmarks.md").is_file()
