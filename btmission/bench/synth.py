"""Synthesis benchmark: back-chaining and library checks on generated libraries.

``btmission bench synth`` (or ``python benchmarks/bench_synth.py``) generates capability libraries
of a given size in a few shapes, and times, for each one:

* **compile** — :func:`~btmission.spec.library.compile_library`: the already-validated
  :class:`~btmission.spec.library.LibrarySpec` → checked :class:`~btmission.spec.library.Library`
  (reference resolution and binding; YAML parsing and pydantic validation are *not* timed);
* **synth** — a fresh :class:`~btmission.synthesis.backchain.Synthesizer` back-chaining the shape's
  goal into the fully expanded tree, including the result's findings and node count;
* **check** — :func:`~btmission.synthesis.checks.check_library`: the whole-library check
  (declared goals, every achievable condition, every action's preconditions, unreachable actions).

Each time is the median of ``repeat`` runs measured with :func:`time.perf_counter` (garbage
collection left on, a collection before each run). The issue's target is *synthesis + checks of a
1,000-action library in under 100 ms*; the ``target`` column reports it for the size-1,000 rows.

Shapes (every generated library loads without errors and synthesises without diagnostics):

``chain``  (``n`` actions)
    Conditions ``c1(x) … cn(x)``; action ``a0(x)`` achieves ``c1(x)`` with no precondition and
    ``a{i}(x)`` achieves ``c{i+1}(x)`` given ``c{i}(x)``. The goal ``cn(x)`` back-chains into one
    long path: ``4n − 1`` nodes, depth ``2n`` — the worst case for deep expansion and for any
    recursion. Every condition and action takes the parameter ``x``, so binding is exercised at
    every step.
``fanin``  (width ``n``: ``n + ⌈n/4⌉ + 1`` actions)
    One action ``top(x)`` with ``n`` preconditions ``p1(x) … pn(x)``, each achieved by its own
    ``ach{i}(x)``; every fourth of those needs its own argument-less ``q{i}``, achieved by
    ``sub{i}``. Wide and shallow: the root sequence has ``n + 1`` children, depth 6.
``diamond``  (``n ≥ 4`` actions; opt-in, not part of the default run)
    ``n − 3`` middle actions ``m{i}(x)`` all need the same ``ready(x)`` (achieved by
    ``prepare(x)``, which needs ``powered``, achieved by ``power_on``); ``combine(x)`` needs every
    ``d{i}(x)``. The shared precondition is expanded once and its subtree shared (memoisation), so
    the *expanded* tree (``11(n − 3) + 4`` nodes) is much larger than the work done.
"""

from __future__ import annotations

import csv
import gc
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from btmission._version import __version__
from btmission.diagnostics import Diagnostic, errors
from btmission.spec.library import Library, LibrarySpec, compile_library
from btmission.synthesis.backchain import Synthesis, Synthesizer, parse_goals
from btmission.synthesis.checks import CheckReport, check_library
from btmission.synthesis.tree import depth

__all__ = [
    "CSV_HEADER",
    "DEFAULT_SHAPES",
    "QUIET_LOAD",
    "SHAPES",
    "TARGET_ACTIONS",
    "TARGET_MS",
    "Measurement",
    "chain_library",
    "describe_load",
    "diamond_library",
    "environment",
    "fanin_library",
    "header_lines",
    "host_speed_ms",
    "host_workload",
    "load_note",
    "measure",
    "run_synth_benchmark",
]

TARGET_ACTIONS = 1000
"""Library size the issue's target applies to."""
TARGET_MS = 100.0
"""Synthesis + checks of a ``TARGET_ACTIONS``-size library must take less than this."""

FANIN_SUB_EVERY = 4
"""In the fan-in shape, every this-many-th precondition has its own precondition."""


# --------------------------------------------------------------------------------------------
# Generators (pure: size → LibrarySpec, goal)
# --------------------------------------------------------------------------------------------
def _spec(
    name: str, description: str, goal: str, conditions: dict[str, Any], actions: dict[str, Any]
) -> LibrarySpec:
    return LibrarySpec.model_validate(
        {
            "library": name,
            "version": 1,
            "description": description,
            "goals": [goal],
            "conditions": conditions,
            "actions": actions,
        }
    )


def chain_library(n: int) -> LibrarySpec:
    """``n`` actions in a chain: ``a{i}(x)`` turns ``c{i}(x)`` into ``c{i+1}(x)``; goal ``c{n}(x)``.

    (``a0`` needs nothing; every condition and action takes the parameter ``x``.)
    """
    if n < 1:
        raise ValueError("a chain needs at least one action")
    conditions: dict[str, Any] = {f"c{i}": {"params": ["x"]} for i in range(1, n + 1)}
    actions: dict[str, Any] = {}
    for i in range(n):
        actions[f"a{i}"] = {
            "params": ["x"],
            "pre": [f"c{i}(x)"] if i else [],
            "post": [f"c{i + 1}(x)"],
        }
    return _spec(f"chain{n}", f"generated chain of {n} actions", f"c{n}(x)", conditions, actions)


def fanin_library(n: int) -> LibrarySpec:
    """``top(x)`` needs ``p1(x) … pn(x)``, each achieved by its own action; goal ``top(x)``.

    Every ``FANIN_SUB_EVERY``-th achiever ``ach{i}`` has one argument-less precondition ``q{i}``,
    achieved by ``sub{i}``, so the library has ``n + ⌈n/4⌉ + 1`` actions.
    """
    if n < 1:
        raise ValueError("a fan-in needs at least one precondition")
    conditions: dict[str, Any] = {"top": {"params": ["x"]}}
    actions: dict[str, Any] = {}
    for i in range(1, n + 1):
        conditions[f"p{i}"] = {"params": ["x"]}
        pre: list[str] = []
        if i % FANIN_SUB_EVERY == 1:
            conditions[f"q{i}"] = None
            actions[f"sub{i}"] = {"post": [f"q{i}"]}
            pre = [f"q{i}"]
        actions[f"ach{i}"] = {"params": ["x"], "pre": pre, "post": [f"p{i}(x)"]}
    actions["finish"] = {
        "params": ["x"],
        "pre": [f"p{i}(x)" for i in range(1, n + 1)],
        "post": ["top(x)"],
    }
    return _spec(f"fanin{n}", f"generated fan-in of width {n}", "top(x)", conditions, actions)


def diamond_library(n: int) -> LibrarySpec:
    """``n`` actions (at least 4): ``combine(x)`` needs ``n − 3`` conditions ``d{i}(x)`` whose
    achievers all need one shared ``ready(x)``; goal ``done(x)``."""
    k = max(1, n - 3)
    conditions: dict[str, Any] = {
        "done": {"params": ["x"]},
        "ready": {"params": ["x"]},
        "powered": None,
    }
    actions: dict[str, Any] = {
        "power_on": {"post": ["powered"]},
        "prepare": {"params": ["x"], "pre": ["powered"], "post": ["ready(x)"]},
    }
    for i in range(1, k + 1):
        conditions[f"d{i}"] = {"params": ["x"]}
        actions[f"m{i}"] = {"params": ["x"], "pre": ["ready(x)"], "post": [f"d{i}(x)"]}
    actions["combine"] = {
        "params": ["x"],
        "pre": [f"d{i}(x)" for i in range(1, k + 1)],
        "post": ["done(x)"],
    }
    description = f"generated diamond of {k} branches"
    return _spec(f"diamond{n}", description, "done(x)", conditions, actions)


SHAPES: dict[str, Callable[[int], LibrarySpec]] = {
    "chain": chain_library,
    "fanin": fanin_library,
    "diamond": diamond_library,
}
DEFAULT_SHAPES: tuple[str, ...] = ("chain", "fanin")


# --------------------------------------------------------------------------------------------
# Measurement
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Measurement:
    """Timings (median ms over ``repeat`` runs) and the result's shape for one library."""

    shape: str
    size: int
    actions: int
    conditions: int
    tree_nodes: int
    depth: int
    compile_ms: float
    synth_ms: float
    check_ms: float
    repeat: int
    errors: int

    @property
    def total_ms(self) -> float:
        """Synthesis + checks (the quantity the target is about)."""
        return self.synth_ms + self.check_ms

    @property
    def target_met(self) -> bool | None:
        """Whether synth+check < ``TARGET_MS``; None when the target does not apply to this size."""
        if self.size != TARGET_ACTIONS:
            return None
        return self.total_ms < TARGET_MS


@contextmanager
def own_heap() -> Iterator[None]:
    """Garbage collections inside the block scan only what was allocated inside it.

    Benchmarks collect garbage before each timed call, so that collecting earlier garbage does
    not land in a measurement. In a large process (the test suite, a notebook) each of those
    collections would scan every object the caller holds, and a quick benchmark would take
    many seconds: the caller's objects are collected once on entry and frozen
    (:func:`gc.freeze`) until the block ends. Measurements are unchanged: the benchmark's own
    garbage is collected as before. Used as a decorator on the ``run_*_benchmark`` functions.
    A caller that froze objects itself keeps them frozen (nothing is done then)."""
    if gc.get_freeze_count():
        yield
        return
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _median_ms(fn: Callable[[], object], repeat: int) -> tuple[float, object]:
    """Median wall time of ``repeat`` calls, in ms, and the last call's result."""
    times: list[float] = []
    result: object = None
    for _ in range(repeat):
        gc.collect()
        t0 = time.perf_counter()
        result = fn()
        times.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(times), result


def measure(
    spec: LibrarySpec, goal: str, repeat: int = 5, *, shape: str = "", size: int = 0
) -> Measurement:
    """Time compile, synthesis of ``goal`` and ``check_library`` on ``spec`` (median of ``repeat``).

    Every run starts from scratch (a new :class:`Library`, :class:`Synthesizer`), so the memo of one
    run never helps the next. Raises ``ValueError`` if the generated library does not compile
    cleanly, since timing a broken library would be meaningless.
    """
    if repeat < 1:
        raise ValueError("repeat must be at least 1")
    compile_ms, compiled = _median_ms(lambda: compile_library(spec), repeat)
    library, load_diags = _unpack(compiled)
    if errors(load_diags):
        first = errors(load_diags)[0].format()
        raise ValueError(f"generated library {spec.library} has errors: {first}")
    goals = parse_goals([goal], library)
    synth_ms, synthesis = _median_ms(lambda: Synthesizer(library).synthesize(goals), repeat)
    assert isinstance(synthesis, Synthesis)
    check_ms, report = _median_ms(lambda: check_library(library, load_diags), repeat)
    assert isinstance(report, CheckReport)
    return Measurement(
        shape=shape or spec.library,
        size=size,
        actions=len(library.actions),
        conditions=len(library.conditions),
        tree_nodes=synthesis.size,
        depth=depth(synthesis.tree),
        compile_ms=compile_ms,
        synth_ms=synth_ms,
        check_ms=check_ms,
        repeat=repeat,
        errors=len(errors(synthesis.diagnostics)) + len(errors(report.diagnostics)),
    )


def _unpack(compiled: object) -> tuple[Library, list[Diagnostic]]:
    assert isinstance(compiled, tuple) and len(compiled) == 2
    library, diags = compiled
    assert isinstance(library, Library)
    return library, list(diags)


# --------------------------------------------------------------------------------------------
# Reporting
# --------------------------------------------------------------------------------------------
CSV_HEADER: tuple[str, ...] = (
    "shape",
    "size",
    "actions",
    "conditions",
    "tree_nodes",
    "depth",
    "compile_ms",
    "synth_ms",
    "check_ms",
    "synth_check_ms",
    "target_met",
    "repeat",
)
_MD_HEADER = (
    "shape",
    "size",
    "actions",
    "tree nodes",
    "depth",
    "compile ms",
    "synth ms",
    "check ms",
    "synth+check ms",
    f"target (<{TARGET_MS:g} ms)",
)
_RIGHT = frozenset(_MD_HEADER[1:-1])  # numeric columns, right-aligned


def _target_text(m: Measurement) -> str:
    met = m.target_met
    return "—" if met is None else ("yes" if met else "**no**")


def _md_row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _md_cells(m: Measurement) -> list[str]:
    return [
        m.shape,
        f"{m.size:,}",
        f"{m.actions:,}",
        f"{m.tree_nodes:,}",
        f"{m.depth:,}",
        f"{m.compile_ms:.2f}",
        f"{m.synth_ms:.2f}",
        f"{m.check_ms:.2f}",
        f"{m.total_ms:.2f}",
        _target_text(m),
    ]


def _md_table_head() -> list[str]:
    return [
        _md_row(list(_MD_HEADER)),
        _md_row(["---:" if h in _RIGHT else "---" for h in _MD_HEADER]),
    ]


def _csv_row(m: Measurement) -> list[str]:
    met = m.target_met
    return [
        m.shape,
        str(m.size),
        str(m.actions),
        str(m.conditions),
        str(m.tree_nodes),
        str(m.depth),
        f"{m.compile_ms:.3f}",
        f"{m.synth_ms:.3f}",
        f"{m.check_ms:.3f}",
        f"{m.total_ms:.3f}",
        "" if met is None else str(met).lower(),
        str(m.repeat),
    ]


QUIET_LOAD = 0.5
"""Other work (runnable tasks in the 1-minute load average, the benchmark itself subtracted) below
which a header calls the machine quiet: less than half a core busy with anything else."""


def _load1() -> float | None:
    """The 1-minute load average now, or None where the OS does not report one."""
    try:
        return os.getloadavg()[0]
    except (OSError, AttributeError):
        return None


def _cpu_s() -> float:
    """CPU seconds used by this process and by the child processes it has waited for (a
    benchmark that runs ``btmission run`` in a subprocess counts that run as its own work)."""
    t = os.times()
    return time.process_time() + t.children_user + t.children_system


HOST_SPEED_ROUNDS = 300_000
"""Rounds of :func:`host_workload` that :func:`host_speed_ms` times (~0.3 s on the 2-vCPU
development machine when it is quick)."""


def host_workload(rounds: int = HOST_SPEED_ROUNDS) -> int:
    """A fixed pure-Python workload: float and integer arithmetic, dict updates, list appends and
    sorts, ``rounds`` times; returns a checksum (the same for a ``rounds`` on every run).

    Pure and deterministic (no I/O, no randomness, no clock): the same bytecode does the same
    work every time, so its wall time measures only how fast the host runs Python right now.
    The mix is the kind of work a mission's Python side does (loops over small dicts and
    lists, float updates), not a numeric kernel."""
    table: dict[int, float] = {}
    batch: list[int] = []
    acc = 0
    x = 0.5
    for i in range(rounds):
        x = x * 0.999 + 1.0 / (i + 1)
        k = (i * 40503) % 1021
        table[k] = table.get(k, 0.0) + x
        batch.append(k ^ i)
        if len(batch) == 64:
            batch.sort()
            acc = (acc + batch[32] * 31 + len(table)) % 1_000_003
            batch.clear()
    return acc + int(sum(table.values()))


def host_speed_ms(rounds: int = HOST_SPEED_ROUNDS) -> float:
    """The host speed reference: wall time of :func:`host_workload` (``rounds``), in ms.

    A shared host's speed drifts: other virtual machines take its cores for minutes at a time,
    and the load average (which counts only this machine's own processes) does not show it.
    Timed just before a measurement, this fixed workload shows a busy minute: when a
    benchmark's number drops and the reference's time rose with it, the host was slow. Its
    small working set does not see everything, though: a machine whose memory is slower (a
    different virtual machine: the fleet benchmark at half speed) can read the same, so a change
    of code is judged side by side, in the same minutes. Lower is faster; compare it only
    between runs on the same machine and Python."""
    t0 = time.perf_counter()
    host_workload(rounds)
    return (time.perf_counter() - t0) * 1000.0


def environment() -> dict[str, str]:
    """Where and when the numbers are measured; call it when the benchmark starts.

    Besides date, machine, CPUs and versions it records the 1-minute load average and the
    process's CPU and wall clocks at the start, which :func:`load_note` compares with the end.
    """
    machine = " ".join(x for x in (platform.processor(), platform.machine()) if x) or "unknown"
    load = _load1()
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{machine} ({platform.system()} {platform.release()})",
        "cpus": str(os.cpu_count() or "unknown"),
        "python": f"{platform.python_implementation()} {sys.version.split()[0]}",
        "btmission": __version__,
        "load_start": "" if load is None else repr(load),
        "cpu_s_start": repr(_cpu_s()),
        "wall_s_start": repr(time.perf_counter()),
    }


def describe_load(start: float, end: float, own_cpus: float) -> str:
    """How busy the machine was, from the 1-minute load average at the start and end of a run.

    ``own_cpus`` is the benchmark's own average CPU use (process CPU time ÷ wall time): at the end
    the load average counts the benchmark itself, so other work ≈ end − own; at the start (before
    any of our work) it is all other work. The larger of the two is compared with
    :data:`QUIET_LOAD`. The 1-minute average lags (it decays over about a minute), so this is an
    estimate, which the note says by giving the raw numbers.
    """
    other = max(start, end - own_cpus, 0.0)
    verdict = (
        f"quiet (< {QUIET_LOAD:g})"
        if other < QUIET_LOAD
        else "busy: other jobs shared the machine, expect noise"
    )
    return (
        f"1-min load average {start:.2f} at start, {end:.2f} at end; the benchmark itself used "
        f"{own_cpus:.2f} CPU on average, so other work ≈ {other:.2f}: {verdict}"
    )


def load_note(env: dict[str, str]) -> str:
    """:func:`describe_load` for a run that began with ``env = environment()`` and ends now."""
    end = _load1()
    if not env.get("load_start") or end is None:
        return "load average not available on this OS: quiet or shared is unknown"
    wall = time.perf_counter() - float(env["wall_s_start"])
    own = (_cpu_s() - float(env["cpu_s_start"])) / wall if wall > 0 else 0.0
    return describe_load(float(env["load_start"]), end, own)


def earlier_runs(path: Path) -> list[str]:
    """The body of a previous results page ``path`` (its own earlier runs included), to keep below
    the new one under "Earlier runs" (issue 19: every benchmark keeps its previous numbers)."""
    if not path.exists():
        return []
    text = path.read_text(encoding="utf-8")
    body = text.split("\n", 1)[1] if text.startswith("# ") else text
    marker = "## Earlier runs"
    head, _, older = body.partition(marker)
    lines = ["## Earlier runs", "", "### Run before this one", "", head.strip()]
    if older.strip():
        lines += ["", older.strip()]
    return [*lines, ""]


def write_page(path: Path, text: str) -> None:
    """Write the results page ``path``, the previous page's runs kept below the new one under
    "Earlier runs" (:func:`earlier_runs`)."""
    earlier = earlier_runs(path)
    body = "\n".join([text.rstrip("\n"), "", *earlier]) if earlier else text
    path.write_text(body, encoding="utf-8")


def header_lines(env: dict[str, str]) -> list[str]:
    """The lines every results file starts with (under its title): date, machine, measured
    load, Python and btmission versions. Call it when the run has finished (it reads the load)."""
    return [
        f"- date: {env['date']}",
        f"- machine: {env['machine']}, {env['cpus']} CPU(s)",
        f"- load: {load_note(env)}",
        f"- Python: {env['python']}",
        f"- btmission: {env['btmission']}",
    ]


def _markdown(results: Sequence[Measurement], repeat: int, env: dict[str, str]) -> str:
    lines = [
        "# Synthesis benchmark",
        "",
        *header_lines(env),
        "",
        f"Timed (median of {repeat} run(s), ms): *compile* = validated spec → checked library; "
        "*synth* = back-chaining the goal into the fully expanded tree; *check* = the "
        "whole-library `check_library`. Target: synth+check of a 1,000-size library < "
        f"{TARGET_MS:g} ms. Shapes: `chain` = n actions in one chain (depth 2n); `fanin` = one "
        "action with n preconditions (n + ⌈n/4⌉ + 1 actions); see `btmission/bench/synth.py`.",
        "",
        *_md_table_head(),
        *(_md_row(_md_cells(m)) for m in results),
        "",
        "Regenerate with `btmission bench synth` or `python benchmarks/bench_synth.py`.",
        "",
    ]
    return "\n".join(lines)


@own_heap()
def run_synth_benchmark(
    sizes: Iterable[int],
    repeat: int = 5,
    out_dir: Path | str = Path("benchmarks/results"),
    echo: Callable[[str], object] = print,
    *,
    shapes: Sequence[str] = DEFAULT_SHAPES,
) -> list[Measurement]:
    """Measure every shape × size, echoing a Markdown table as it goes; write ``synth.md``/``.csv``.

    Returns the measurements. ``shapes`` picks from :data:`SHAPES` (default: chain and fan-in).
    """
    sizes = list(sizes)
    if not sizes or any(n < 1 for n in sizes):
        raise ValueError(f"sizes must be positive integers, got {sizes}")
    unknown = [s for s in shapes if s not in SHAPES]
    if unknown:
        raise ValueError(f"unknown shape(s) {', '.join(unknown)} (known: {', '.join(SHAPES)})")
    out = Path(out_dir)
    env = environment()
    echo(
        f"synthesis benchmark: shapes {', '.join(shapes)}, sizes {', '.join(map(str, sizes))}, "
        f"median of {repeat} run(s); {env['machine']}, {env['cpus']} CPU(s), {env['python']}"
    )
    echo("")
    for line in _md_table_head():
        echo(line)
    results: list[Measurement] = []
    cases = [(shape, n) for shape in shapes for n in sizes]
    for k, (shape, n) in enumerate(cases, 1):
        if n >= 1000:  # the big cases take a few seconds: say what is going on
            echo(f"  … [{k}/{len(cases)}] {shape} n={n:,}: generating and timing ×{repeat}")
        spec = SHAPES[shape](n)
        goal = spec.goals[0]
        m = measure(spec, goal, repeat, shape=shape, size=n)
        if m.errors:
            echo(f"  warning: {shape} n={n} produced {m.errors} error diagnostic(s)")
        results.append(m)
        echo(_md_row(_md_cells(m)))

    out.mkdir(parents=True, exist_ok=True)
    md_path = out / "synth.md"
    csv_path = out / "synth.csv"
    write_page(md_path, _markdown(results, repeat, env))
    with csv_path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_HEADER)
        writer.writerows(_csv_row(m) for m in results)
    echo("")
    for m in results:
        if m.target_met is not None:
            verdict = "met" if m.target_met else "NOT met"
            echo(
                f"target ({m.shape}, {m.size:,}): synth+check {m.total_ms:.1f} ms "
                f"< {TARGET_MS:g} ms — {verdict}"
            )
    echo(f"wrote {md_path} and {csv_path}")
    return results
