"""``btmission bench paper``: the four seed papers' reported results reproduced side by side.

Each paper has a *section* module (``btmission.bench.paper_seed000`` …) that runs btmission's
version of the paper's experiment and returns a :class:`SectionResult`: its Markdown (the paper's
numbers and btmission's in one table, the command that produced them, why they differ) and the
raw numbers. :func:`run_paper_benchmark` runs the selected sections, stores each one's result as
``<out>/paper/<key>.json`` and ``.md``, and rebuilds ``docs/fidelity.md`` from every stored section,
so one section can be re-run without re-running the others.

A section module exposes::

    KEY: str                    # "seed000"; the file name and the --only name
    TITLE: str                  # "Seed 000 field test (Tables II and III)"
    def run(quick: bool, echo: Callable[[str], None]) -> SectionResult: ...

``quick`` is for tests and smoke runs: a shorter experiment with the same shape (fewer seeds,
runs or hours); its page says it is quick and is never written over docs/fidelity.md.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

from btmission.bench.synth import environment, load_note

SECTIONS: tuple[str, ...] = ("seed000", "seed002", "seed003", "seed004")
"""Section keys in page order; each is the module ``btmission.bench.paper_<key>``."""

DOC_TITLE = "# Fidelity to the papers"

INTRO = """\
How close btmission's runs come to the numbers the four seed papers report, experiment by
experiment: the paper's value and btmission's side by side, the command that produced btmission's,
and why each difference is there. The papers ran on their authors' hardware (real drones in a real
mine, a C# implementation on a desktop PC); btmission runs them in its simulator on the machine
named under each section, so numbers such as solver times are compared for their order, not their
digits.

This page is generated: `btmission bench paper` re-runs every section ({minutes} on a
2-core machine) and rewrites it; `btmission bench paper --only seed004` re-runs one section and
keeps the others' stored results (`benchmarks/results/paper/*.json`).
"""


@dataclass
class SectionResult:
    """One section's outcome: Markdown under its ``## TITLE`` and the numbers behind it."""

    markdown: str
    data: dict[str, Any] = field(default_factory=dict)
    quick: bool = False
    env: dict[str, str] = field(default_factory=dict)
    """Filled by the runner: date, machine, load (see :func:`btmission.bench.synth.environment`)."""
    wall_s: float = 0.0


def pct(ours: float, paper: float) -> str:
    """Signed deviation of ``ours`` from ``paper`` in per cent, e.g. ``+6.8 %``."""
    if paper == 0:
        return "n/a"
    return f"{(ours - paper) / abs(paper) * 100:+.1f} %"


def table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A Markdown table; cells are written with ``str``; numeric-looking columns are not aligned
    specially (the page is read rendered)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def section_module(key: str) -> ModuleType:
    """The module of section ``key`` (raises ``KeyError`` for an unknown key)."""
    if key not in SECTIONS:
        raise KeyError(key)
    return importlib.import_module(f"btmission.bench.paper_{key}")


def available() -> list[str]:
    """The sections whose module this installation has, in page order."""
    return [k for k in SECTIONS if importlib.util.find_spec(f"btmission.bench.paper_{k}")]


def parse_only(only: str) -> list[str]:
    """``--only`` → section keys in page order (all available ones when empty); ``ValueError``
    names an unknown or unavailable one."""
    if not only.strip():
        return available()
    wanted = [k.strip() for k in only.split(",") if k.strip()]
    unknown = [k for k in wanted if k not in SECTIONS]
    if unknown:
        raise ValueError(
            f"unknown section(s) {', '.join(unknown)}; expected some of {', '.join(SECTIONS)}"
        )
    missing = [k for k in wanted if k not in available()]
    if missing:
        raise ValueError(f"section(s) {', '.join(missing)} not available in this version")
    return [k for k in SECTIONS if k in wanted]


def _store(out: Path, key: str, title: str, result: SectionResult) -> None:
    folder = out / "paper"
    folder.mkdir(parents=True, exist_ok=True)
    record = {"key": key, "title": title, **asdict(result)}
    (folder / f"{key}.json").write_text(json.dumps(record, indent=1, default=str) + "\n")
    (folder / f"{key}.md").write_text(section_markdown(title, result) + "\n", encoding="utf-8")


def section_markdown(title: str, result: SectionResult) -> str:
    """A section as it appears on the page: title, what was run where, then its own Markdown."""
    env = result.env
    where = (
        f"*Measured {env.get('date', '?')} on {env.get('machine', '?')}, "
        f"{env.get('cpus', '?')} CPU(s), in {result.wall_s / 60:.1f} min; "
        f"{env.get('load', 'load unknown')}.*"
    )
    quick = (
        "\n\n**Quick run** (`--quick`: fewer runs than the paper's protocol; not the page's "
        "numbers)."
        if result.quick
        else ""
    )
    return f"## {title}\n\n{where}{quick}\n\n{result.markdown.strip()}"


def assemble(out: Path) -> str:
    """The whole page from every stored section (a missing one is named as not yet run)."""
    parts = [DOC_TITLE, ""]
    total_s = 0.0
    bodies = []
    for key in SECTIONS:
        path = out / "paper" / f"{key}.json"
        if not path.exists():
            bodies.append(f"## {key}\n\nNot run yet: `btmission bench paper --only {key}`.")
            continue
        record = json.loads(path.read_text())
        total_s += float(record.get("wall_s", 0.0))
        result = SectionResult(
            markdown=record["markdown"],
            data=record.get("data", {}),
            quick=bool(record.get("quick", False)),
            env=record.get("env", {}),
            wall_s=float(record.get("wall_s", 0.0)),
        )
        bodies.append(section_markdown(record["title"], result))
    minutes = max(1, round(total_s / 60))
    parts.append(INTRO.format(minutes=f"about {minutes} minute{'s' if minutes > 1 else ''}"))
    for body in bodies:
        parts += [body, ""]
    return "\n".join(parts).rstrip() + "\n"


def run_paper_benchmark(
    keys: Sequence[str],
    *,
    quick: bool = False,
    out_dir: Path = Path("benchmarks/results"),
    doc: Path | None = Path("docs/fidelity.md"),
    echo: Callable[[str], None] = print,
) -> dict[str, SectionResult]:
    """Run the sections ``keys``, store each, rebuild the page ``doc`` (not for quick runs into
    the default results folder: a quick page goes beside the results as ``fidelity.md``)."""
    results: dict[str, SectionResult] = {}
    for key in keys:
        module = section_module(key)
        echo(f"== {key}: {module.TITLE}")
        env = environment()
        t0 = time.perf_counter()
        result: SectionResult = module.run(quick, echo)
        result.wall_s = time.perf_counter() - t0
        result.quick = quick
        result.env = {
            "date": env["date"],
            "machine": env["machine"],
            "cpus": env["cpus"],
            "load": load_note(env),
        }
        _store(out_dir, key, module.TITLE, result)
        echo(f"   {key} done in {result.wall_s / 60:.1f} min")
        results[key] = result
    page = assemble(out_dir)
    target = doc if (doc is not None and not quick) else out_dir / "fidelity.md"
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(page, encoding="utf-8")
    echo(f"wrote {target} and {out_dir / 'paper'}/<section>.json")
    return results
