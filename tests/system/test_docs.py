"""The documentation stays true: its examples run, show what they print, and its links resolve.

Console examples
----------------
Every ``$ btmission ...`` line inside a ```` ```console ```` block of ``docs/*.md`` is run through
click's ``CliRunner`` from the repository root. It must exit with status 0, or with the status its
trailing comment documents (``# exit 2``). Commands never touch the repository: ``-o``/``--output``,
``--out``, ``--log``, ``--png`` and ``--html`` paths are redirected into ``tmp_path`` (a ``bench`` command shown
without ``--out`` gets one there: its default is ``benchmarks/results``), and ``library new`` (and
commands on the plugin it scaffolds) run inside ``tmp_path``. svg/png commands are skipped without
Graphviz.

**Output.** The lines after a ``$`` line, up to the next ``$`` line or the end of the block, are the
output the page shows for that command, and the command must print exactly that. The comparison is
against what a terminal shows: stdout and stderr together, in the order they were written
(``Result.output`` of click's ``CliRunner``, which mixes the two since click 8.2, and by default
before), with the program called ``btmission`` in usage lines. A command followed directly by another ``$`` line (or
by the end of the block) shows no output, and its output is not compared — use that for lists of
commands whose output the page shows elsewhere or not at all.

Before comparing, both sides are normalised line by line so that what legitimately changes from run
to run does not count (see :func:`normalise`):

- trailing whitespace, and blank lines at the end of the output;
- the ``tmp_path`` the test redirects outputs into is written back as the path the page gave
  (``wrote fig8.svg``), and the repository root and ``tmp_path`` prefixes of any other absolute
  path are dropped;
- durations (``12.4 s``, ``0.26 ms``, ``3 min``, ``1.5 h``), rates (``775 Hz``), speed-ups
  (``65× real time``) become ``<time>``, ``<rate>``, ``<speed>``;
- timestamps in file names (``mission-20261124-031500-seed0.jsonl``) and ISO dates and times
  (``2026-11-24T03:15:00Z``) become ``<stamp>`` and ``<date>``.

**Abbreviating.** A line that is exactly ``...`` matches any run of lines (none included); ``...``
inside a line matches any text within that line (as doctest's ELLIPSIS), compared both with the
normalised line and with the line as printed (so ``time ... ms`` works). Use it for long output
(show the first line or two, then ``...``) and for numbers that vary without a unit (benchmark
tables, the machine's description).

**Opting out.** A block whose output is truly not reproducible (it depends on the machine or on
wall-clock timing beyond the rules above, and ``...`` would leave nothing worth showing) is marked
by the HTML comment ``<!-- output not compared: REASON -->`` on the line just before its opening
fence; the reason is required and shows in the page's source. Its commands still run and their
exit status is still checked. This should be rare: prefer ``...``.

**Slow commands.** A command whose trailing comment contains ``slow`` (``# slow``, or
``# exit 1, slow``) is marked ``@pytest.mark.slow``: it runs under ``make test-all`` only, so that
the fast selection stays fast. Mark a command slow when it takes more than a few seconds.

When the output differs, the failure names ``page:line``, the command as run, the block as the page
shows it, the real output (paths written back as on the page, ready to paste) and a unified diff of
the two after normalisation. After a deliberate change of a message, ``BTMISSION_UPDATE_DOCS=1
pytest tests/system/test_docs.py`` writes the real output into every failing block that has no ``...``
(the test still fails, saying so); review the result with ``git diff docs/``.

Python examples
---------------
Every ```` ```python ```` block is a complete program and is executed (from the repository root,
in a fresh namespace); excerpts that cannot run on their own are fenced ```` ```py ```` instead.
"""

from __future__ import annotations

import difflib
import os
import re
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner

from btmission.cli.main import cli
from btmission.export import graphviz_available

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
PAGES = sorted(DOCS.glob("*.md"))

_COMMENT = re.compile(r"\s+#\s*([^'\"#]*)$")
_EXIT = re.compile(r"\bexit\s+(\d+)\b")
_SLOW = re.compile(r"\bslow\b")
_FENCE = re.compile(r"^\s*(```+|~~~+)\s*([\w+-]*)")
_NO_COMPARE = re.compile(r"^<!--\s*output not compared:\s*(\S.*?)\s*-->$")
_OUTPUT_OPTIONS = ("-o", "--output", "--out", "--log", "--png", "--html")
_SCAFFOLD_DIR = re.compile(r"^btmission-([a-z0-9-]+)(/|$)")
ELLIPSIS = "..."


@dataclass(frozen=True)
class Example:
    """One documented command: where it is, its arguments, exit status and shown output.

    ``output`` is ``None`` when the page shows no output for the command (not compared) or the
    block opted out of the comparison.
    """

    page: str
    line: int
    args: tuple[str, ...]
    exit_code: int
    output: tuple[str, ...] | None = None
    slow: bool = False
    source: str = ""  # the ``$ ...`` line as the page writes it

    @property
    def id(self) -> str:
        return f"{self.page}:{self.line}"


@dataclass(frozen=True)
class ConsoleBlock:
    """The lines (with their numbers) of one ```console block; ``compared`` unless opted out."""

    lines: tuple[tuple[int, str], ...]
    compared: bool


def console_blocks(page: Path) -> list[ConsoleBlock]:
    """Every ```console block of ``page``."""
    blocks: list[ConsoleBlock] = []
    fence: str | None = None
    is_console = compared = False
    current: list[tuple[int, str]] = []
    previous = ""
    for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), start=1):
        m = _FENCE.match(line)
        if m and fence is None:
            fence, is_console = m.group(1), m.group(2) == "console"
            compared = not _NO_COMPARE.match(previous.strip())
            current = []
        elif m and fence is not None and line.strip() == fence:
            if is_console:
                blocks.append(ConsoleBlock(tuple(current), compared))
            fence, is_console = None, False
        elif is_console:
            current.append((number, line))
        if line.strip():
            previous = line
    return blocks


def console_lines(page: Path) -> list[tuple[int, str]]:
    """``(line number, text)`` of every line inside a ```console block of ``page``."""
    return [item for block in console_blocks(page) for item in block.lines]


def _example(page: str, number: int, command: str, shown: list[str] | None) -> Example:
    source = f"$ {command}"
    exit_code, slow = 0, False
    m = _COMMENT.search(command)
    if m:
        comment = m.group(1)
        code = _EXIT.search(comment)
        exit_code = int(code.group(1)) if code else 0
        slow = bool(_SLOW.search(comment))
        command = command[: m.start()]
    args = shlex.split(command, comments=True)
    output = tuple(shown) if shown else None
    return Example(page, number, tuple(args), exit_code, output, slow, source)


def collect_examples() -> list[Example]:
    examples: list[Example] = []
    for page in PAGES:
        name = page.relative_to(ROOT).as_posix()
        for block in console_blocks(page):
            pending: tuple[int, str] | None = None
            shown: list[str] = []
            for number, line in [*block.lines, (0, "$ ")]:  # a sentinel ends the last command
                if not line.startswith("$ "):
                    shown.append(line)
                    continue
                if pending is not None:
                    examples.append(_example(name, *pending, shown if block.compared else None))
                pending, shown = (number, line[2:]), []
    return examples


EXAMPLES = collect_examples()


def _params(examples: list[Example]) -> list[object]:
    return [pytest.param(e, id=e.id, marks=[pytest.mark.slow] if e.slow else []) for e in examples]


def test_docs_have_examples() -> None:
    assert len(EXAMPLES) >= 40, [e.id for e in EXAMPLES]
    compared = [e for e in EXAMPLES if e.output is not None]
    assert len(compared) >= 40, [e.id for e in compared]


@pytest.mark.parametrize("example", EXAMPLES, ids=[e.id for e in EXAMPLES])
def test_console_lines_are_btmission_commands(example: Example) -> None:
    """``console`` blocks hold only btmission commands; other commands go in ``sh`` blocks."""
    assert example.args[:1] == ("btmission",), f"{example.id}: {shlex.join(example.args)}"


# ------------------------------------------------------------------------- output comparison
_NUMBER = r"(?<![\w.,])[-+]?\d(?:[\d,]*\d)?(?:\.\d+)?"
_NORMALISE: tuple[tuple[re.Pattern[str], str], ...] = (
    (re.compile(r"\b\d{8}-\d{6}\b"), "<stamp>"),
    (
        re.compile(
            r"\b\d{4}-\d{2}-\d{2}(?:[T ]\d{2}:\d{2}(?::\d{2}(?:\.\d+)?)?)?(?:Z|[+-]\d{2}:?\d{2}|\s?UTC)?\b"
        ),
        "<date>",
    ),
    (re.compile(_NUMBER + r"\s?(?:×|x(?= real time))"), "<speed>"),
    (re.compile(_NUMBER + r"\s?(?:ms|µs|us|ns|s|sec|min|h)(?![\w(])"), "<time>"),
    (re.compile(_NUMBER + r"\s?(?:[kMG]?Hz)\b"), "<rate>"),
)


def normalise(line: str, paths: dict[str, str] | None = None) -> str:
    """``line`` without what legitimately varies between runs (see the module docstring).

    ``paths`` maps the paths the test wrote to (in ``tmp_path``) back to those on the page.
    """
    for real, shown in (paths or {}).items():
        line = line.replace(real, shown)
    line = line.replace(f"{ROOT}/", "")
    for pattern, replacement in _NORMALISE:
        line = pattern.sub(replacement, line)
    return line.rstrip()


def _trim(lines: list[str]) -> list[str]:
    while lines and not lines[-1].strip():
        lines = lines[:-1]
    return lines


Line = tuple[str, str]
"""A line as ``(normalised, as printed)``: a shown line matches a printed one if either matches."""


def _matches(expected: str, actual: str) -> bool:
    if ELLIPSIS not in expected:
        return expected == actual
    pattern = ".*".join(re.escape(part) for part in expected.split(ELLIPSIS))
    return re.fullmatch(pattern, actual) is not None


def _line_matches(expected: Line, actual: Line) -> bool:
    # normalised first; as printed for '...' standing for a normalised part ("time ... ms")
    return _matches(expected[0], actual[0]) or _matches(expected[1], actual[1])


def output_matches(expected: list[Line], actual: list[Line]) -> bool:
    """Whether ``actual`` is what ``expected`` shows, ``...`` lines matching any run of lines."""
    n, m = len(expected), len(actual)
    # ok[i][j]: expected[i:] matches actual[j:]
    ok = [[False] * (m + 1) for _ in range(n + 1)]
    ok[n][m] = True
    for i in range(n - 1, -1, -1):
        for j in range(m, -1, -1):
            if expected[i][1].strip() == ELLIPSIS:
                ok[i][j] = ok[i + 1][j] or (j < m and ok[i][j + 1])
            else:
                ok[i][j] = j < m and _line_matches(expected[i], actual[j]) and ok[i + 1][j + 1]
    return ok[0][0]


def output_mismatch(example: Example, command: str, output: str, paths: dict[str, str]) -> str:
    """A failure message naming what differs and how to fix it, or ``""`` when it matches."""
    assert example.output is not None
    expected = _trim([normalise(line) for line in example.output])
    shown = _trim([line.rstrip() for line in output.splitlines()])
    for real, doc in paths.items():
        shown = [line.replace(real, doc) for line in shown]
    actual = [normalise(line) for line in shown]
    raw = _trim([line.rstrip() for line in example.output])
    if output_matches(list(zip(expected, raw)), list(zip(actual, shown))):
        return ""
    first = example.line + 1
    diff = difflib.unified_diff(
        expected, actual, f"{example.page} (as shown)", "real output", lineterm="", n=2
    )
    return "\n".join(
        [
            f"{example.id}: the output shown in the page (lines {first}-"
            f"{first + len(example.output) - 1}) is not what the command prints.",
            f"  ran: btmission {command}",
            "  update the page with the real output below, or abbreviate varying parts with '...'",
            "  (see tests/system/test_docs.py's docstring for what is normalised).",
            "--- shown in the page:",
            *example.output,
            "--- real output:",
            *shown,
            "--- diff (after normalisation):",
            *diff,
        ]
    )


@pytest.mark.parametrize(
    ("printed", "shown"),
    [
        (
            "done in 12.4 s of wall time (65× real time)",
            "done in <time> of wall time (<speed> real time)",
        ),
        ("median 0.26 ms, 775 Hz, 3 min", "median <time>, <rate>, <time>"),
        (
            "wrote runs/mission-20261124-031500-seed0.jsonl",
            "wrote runs/mission-<stamp>-seed0.jsonl",
        ),
        ("started 2026-11-24T03:15:00Z", "started <date>"),
        (f"{ROOT}/missions/a.yaml: OK   ", "missions/a.yaml: OK"),
        (
            "3 task(s), 5 actions, cost 1.80, 2 CPU(s), sizes 10,x",
            "3 task(s), 5 actions, cost 1.80, 2 CPU(s), sizes 10,x",
        ),
    ],
)
def test_normalise(printed: str, shown: str) -> None:
    assert normalise(printed) == shown


def _lines(text: str) -> list[Line]:
    return [(normalise(line), line) for line in text.splitlines()]


@pytest.mark.parametrize(
    ("shown", "printed", "matches"),
    [
        ("a\nb", "a\nb", True),
        ("a\nb", "a\nc", False),
        ("a\nb", "a\nb\nc", False),  # nothing may be left over
        ("a\n...\nd", "a\nb\nc\nd", True),
        ("a\n...\nd", "a\nd", True),  # '...' matches no line too
        ("a\n...\nd", "a\nb\nc", False),
        ("...\nz", "a\nz", True),
        ("time ... ms (x ...)", "time 12 ms (x 3, y 4)", True),  # inside a line
        ("time ... ms", "space 12 ms", False),
        ("took 3 s", "took 4.5 s", True),  # normalised
    ],
)
def test_output_matching(shown: str, printed: str, matches: bool) -> None:
    assert output_matches(_lines(shown), _lines(printed)) is matches


def test_mismatch_message_says_where_and_what() -> None:
    example = Example("docs/x.md", 7, ("btmission", "validate"), 0, ("old line", "same"))
    message = output_mismatch(example, "validate m.yaml", "new line\nsame\n", {})
    assert message.startswith("docs/x.md:7: the output shown in the page (lines 8-9)")
    assert "ran: btmission validate m.yaml" in message
    assert "--- shown in the page:\nold line\nsame\n--- real output:\nnew line\nsame" in message
    assert "-old line\n+new line" in message
    assert output_mismatch(example, "validate", "old line\nsame\n\n", {}) == ""


def test_examples_are_collected_with_their_output(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    page = tmp_path / "p.md"
    page.write_text(
        "```console\n$ btmission a  # exit 2\nout a\n$ btmission b  # slow\n$ btmission c\n```\n"
        "<!-- output not compared: timings -->\n```console\n$ btmission d\nvaries\n```\n",
        encoding="utf-8",
    )
    monkeypatch.setattr(sys.modules[__name__], "PAGES", [page])
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    got = [(e.line, e.args[1], e.exit_code, e.output, e.slow) for e in collect_examples()]
    assert got == [
        (2, "a", 2, ("out a",), False),
        (4, "b", 0, None, True),
        (5, "c", 0, None, False),
        (9, "d", 0, None, False),
    ]


UPDATE_ENV = "BTMISSION_UPDATE_DOCS"


def update_page(example: Example, output: str, paths: dict[str, str]) -> bool:
    """Replace the output ``example``'s page shows by ``output``; ``False`` when it cannot.

    Only for ``BTMISSION_UPDATE_DOCS=1`` runs. A block abbreviated with ``...`` is left alone (the
    abbreviation is the author's choice), and so is one whose text is not found exactly once.
    """
    assert example.output is not None
    if any(ELLIPSIS in line for line in example.output):
        return False
    for real, doc in paths.items():
        output = output.replace(real, doc)
    page = ROOT / example.page
    text = page.read_text(encoding="utf-8")
    old = "\n".join([example.source, *example.output]) + "\n"
    shown = _trim([line.rstrip() for line in output.splitlines()])
    gap = len(example.output) - len(_trim(list(example.output)))  # blank lines kept as they were
    new = "\n".join([example.source, *shown, *[""] * gap]) + "\n"
    if text.count(old) != 1:
        return False
    page.write_text(text.replace(old, new), encoding="utf-8")
    return True


def test_update_page_writes_the_real_output_unless_abbreviated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    page = tmp_path / "p.md"
    page.write_text("```console\n$ btmission a\nold\n\n$ btmission b\nx\n...\n```\n", "utf-8")
    a = Example("p.md", 2, ("btmission", "a"), 0, ("old", ""), source="$ btmission a")
    assert update_page(a, f"wrote {tmp_path}/f.svg\nnew\n", {f"{tmp_path}/": ""})
    assert page.read_text("utf-8") == (
        "```console\n$ btmission a\nwrote f.svg\nnew\n\n$ btmission b\nx\n...\n```\n"
    )
    b = Example("p.md", 5, ("btmission", "b"), 0, ("x", "..."), source="$ btmission b")
    assert not update_page(b, "y\n", {})  # the author's abbreviation is kept


def _rewrite_outputs(args: list[str], tmp_path: Path) -> tuple[list[str], dict[str, str]]:
    """Send every output file or directory into ``tmp_path`` (keeping its base name).

    Returns the arguments to run and a map from each path written to back to the page's path.
    """
    out: list[str] = []
    paths: dict[str, str] = {}
    i = 0
    while i < len(args):
        arg = args[i]
        if arg in _OUTPUT_OPTIONS and i + 1 < len(args):
            target = str(tmp_path / Path(args[i + 1]).name)
            out += [arg, target]
            paths[target] = args[i + 1]
            i += 2
            continue
        assert not arg.startswith(("--output=", "--out=", "--log=", "--png=", "--html=")), (
            "write '-o PATH' in the docs"
        )
        assert not (arg.startswith("-o") and len(arg) > 2), "write '-o PATH' in the docs"
        out.append(arg)
        i += 1
    if (  # a benchmark run the page shows without --out: never rewrite benchmarks/results
        out[:1] == ["bench"]
        and len(out) > 1
        and not out[1].startswith("-")
        and "--help" not in out
        and not {"-o", "--out"} & set(out)
    ):
        target = str(tmp_path / "results")
        out += ["--out", target]
        paths[target] = "benchmarks/results"
    # longest first, so that a path is not cut by a shorter one it starts with; then any other
    # file the command put in tmp_path (the scaffold, relative outputs) loses the prefix
    paths = dict(sorted(paths.items(), key=lambda item: -len(item[0])))
    paths[f"{tmp_path}/"] = ""
    return out, paths


def _needs_graphviz(args: list[str]) -> bool:
    for i, arg in enumerate(args[:-1]):
        if arg in ("-f", "--format") and args[i + 1] in ("svg", "png"):
            return True
        if arg in ("-o", "--output") and args[i + 1].lower().endswith((".svg", ".png")):
            return True
    return False


@pytest.mark.parametrize("example", _params(EXAMPLES))
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
    args, paths = _rewrite_outputs(args, tmp_path)

    result = runner.invoke(cli, args, prog_name="btmission")

    shown = f"{example.id}: btmission {shlex.join(args)}\n{result.output}"
    assert "Traceback" not in result.output, shown
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise AssertionError(shown) from result.exception
    assert result.exit_code == example.exit_code, shown
    if example.output is not None:
        mismatch = output_mismatch(example, shlex.join(args), result.output, paths)
        if mismatch and os.environ.get(UPDATE_ENV) and update_page(example, result.output, paths):
            mismatch += f"\n--- {UPDATE_ENV} is set: {example.page} now shows the real output."
        if mismatch:
            pytest.fail(mismatch, pytrace=False)


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
    # an example that flies a mission on mavsim is paced by the wall clock: run alone (serial)
    pytest.param(
        block, id=f"{page.name}[{i}]", marks=pytest.mark.serial if "mavsim" in block else ()
    )
    for page in PAGES
    for i, block in enumerate(
        re.findall(r"```python\n(.*?)```", page.read_text(encoding="utf-8"), re.S)
    )
]


@pytest.mark.parametrize("block", PYTHON_BLOCKS)
def test_python_examples_run(block: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(ROOT)
    # dont_inherit: the block runs as the file a reader copies it into would, without this
    # module's `from __future__ import annotations` (under which a dataclass defined in exec'd
    # code cannot be built: dataclasses look its string annotations up in sys.modules)
    code = compile(block, "<docs example>", "exec", dont_inherit=True)
    exec(code, {"__name__": "__docs_example__"})


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
