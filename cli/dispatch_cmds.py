"""``btmission dispatch``: GA fleet dispatch on topological mine maps (seed 004)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from btmission.cli.common import (
    FINITE,
    NON_NEGATIVE,
    POSITIVE,
    SEED,
    BadInput,
    FiniteFloat,
    handle_spec_errors,
    output_target,
    write_output,
)

if TYPE_CHECKING:
    from btmission.dispatch.topomap import TopoMap

HOURS = FiniteFloat(min=0, min_open=True, max=1000)
"""Simulated hours of a dynamic-dispatch run: about 0.5 s of computing each at 2 trucks, and
the run shows no progress until it ends; 1000 h (six weeks) is far beyond the paper's 4 h."""

MAP_HELP = "A built-in map (static_npr, static_spr, mine) or a map YAML file."


def resolve_map(ref: str) -> Any:
    """A built-in map by name, else a map file (SpecError → exit 2 via handle_spec_errors)."""
    from btmission.dispatch.maps import BUILTIN_MAPS
    from btmission.spec.topomap import load_topomap

    if ref in BUILTIN_MAPS:
        return BUILTIN_MAPS[ref]()
    if not Path(ref).exists():
        raise BadInput(
            f"no map '{ref}': not a built-in map ({', '.join(BUILTIN_MAPS)}) nor an existing file"
        )
    return load_topomap(ref)


def int_list(text: str, option: str) -> list[int]:
    try:
        values = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise BadInput(f"{option}: expected comma-separated integers, got '{text}'") from None
    if not values or min(values) < 1:
        raise BadInput(f"{option}: expected positive integers, got '{text}'")
    return values


def check_static_sizes(sizes: Sequence[int], *tmaps: TopoMap) -> None:
    """Every fleet size can make a static-batch instance on every map, else :class:`BadInput`
    (before any optimisation runs)."""
    import numpy as np

    from btmission.dispatch.static import random_instance

    for tmap in tmaps:
        for size in sizes:
            try:
                random_instance(tmap, size, np.random.default_rng(0))
            except ValueError as exc:
                raise BadInput(f"--vehicles: {exc} (map {tmap.name})") from None


@contextlib.contextmanager
def progress_bar(total: int, label: str) -> Iterator[Callable[[int], None]]:
    """A rich progress bar on stderr; yields ``advance(n)``."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=Console(stderr=True),
        transient=True,
    ) as prog:
        task = prog.add_task(label, total=total)

        def advance(n: int = 1) -> None:
            prog.advance(task, n)

        yield advance


@click.group()
def dispatch() -> None:
    """GA fleet dispatch for haul trucks on topological mine maps (seed 004).

    \b
    Examples:
      btmission dispatch map mine -o mine.png
      btmission dispatch static --map static_npr --vehicles 2,4 --runs 3 --budget 0.5
      btmission dispatch dynamic --map mine --vehicles 2 --hours 0.5 --budget 0.1
      btmission dispatch plan --map mine --vehicle L1n:O --vehicle O:L2s -o plan.png
    """


@dispatch.command("map")
@click.argument("map_ref", metavar="MAP")
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, path_type=Path),
    callback=output_target("file"), help="Write the map: .yaml (the map file format) or .png (a drawing). Default: YAML to stdout.",
)  # fmt: skip
@handle_spec_errors
def map_cmd(map_ref: str, output: Path | None) -> None:
    """Check a map and print it as a map file, or draw it.

    MAP is a built-in map (static_npr, static_spr, mine) or a YAML map file, which is checked
    (known nodes, times > 0, connected, loop-free).

    \b
    Example:
      btmission dispatch map mine -o mine.png
    """
    from btmission.dispatch.topomap import NodeKind
    from btmission.spec.topomap import dump_topomap

    tmap = resolve_map(map_ref)
    click.echo(
        f"map '{tmap.name}': {tmap.n} nodes ({len(tmap.terminals)} terminals, "
        f"{len(tmap.nodes_of(NodeKind.PAUSE))} pause, {len(tmap.nodes_of(NodeKind.TRANSIT))} "
        f"transit), {len(tmap.segments)} segments, loop-free",
        err=True,
    )
    if output is not None and output.suffix.lower() == ".png":
        from btmission.dispatch.plot import map_png

        try:
            write_output(map_png(tmap), output)
        except ValueError as exc:
            raise BadInput(str(exc)) from None
        return
    if output is not None and output.suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"cannot tell the format from '{output.name}': use .yaml or .png")
    write_output(dump_topomap(tmap), output)


def _ga_params(budget: float | None, generations: int | None, tau: float = 3.0) -> Any:
    from btmission.dispatch.ga import GAParams

    try:
        return GAParams(tau_s=tau, budget_s=budget, max_generations=generations)
    except ValueError as exc:
        raise BadInput(str(exc)) from None


budget_option = click.option(
    "--budget", type=FINITE, default=None,
    help="GA time budget per optimisation in s (default: 3 s per vehicle, as in the paper).",
)  # fmt: skip
generations_option = click.option(
    "--generations", type=click.IntRange(1), default=None,
    help="Also stop each optimisation after this many generations (reproducible runs).",
)  # fmt: skip
seed_option = click.option("--seed", type=SEED, default=0, show_default=True, help="Random seed.")
delta_option = click.option(
    "--delta", type=NON_NEGATIVE, default=2.0, show_default=True,
    help="Grazing-collision window δ in s.",
)  # fmt: skip


@dispatch.command("static")
@click.option("--map", "map_ref", required=True, help=MAP_HELP)
@click.option(
    "--vehicles", default="10", show_default=True, help="Fleet sizes, e.g. 2,4,6,8,10 (even)."
)
@click.option(
    "--runs", type=click.IntRange(1), default=5, show_default=True, help="Instances per size."
)
@budget_option
@generations_option
@seed_option
@delta_option
@click.option("--gantt", type=click.Path(dir_okay=False, path_type=Path), default=None,
              callback=output_target("file"),
              help="Write a Fig. 3-style PNG of the GA plan of one more instance of the last size.")  # fmt: skip
@handle_spec_errors
def static_cmd(
    map_ref: str, vehicles: str, runs: int, budget: float | None, generations: int | None,
    seed: int, delta: float, gantt: Path | None,
) -> None:  # fmt: skip
    """Static planning batch (§6.1): GA and push and swap side by side (Tables 2, 3, 5).

    For each fleet size L, RUNS random instances: L/2 vehicles start at left terminals and L/2 at
    right terminals, each going to its partner's start. Prints Σ (success %), mean ξ (mission
    items), mean r (ξ / ξ0), mean Δ (fleet mission duration; push and swap: its serial plan) and
    σ (std of ξ) for both methods. The map needs terminals in groups 'left' and 'right'.

    \b
    Example:
      btmission dispatch static --map static_npr --vehicles 2,10 --runs 5 --budget 3
    """
    from btmission.bench.dispatch import static_table
    from btmission.dispatch.static import run_static_batch

    tmap = resolve_map(map_ref)
    sizes = int_list(vehicles, "--vehicles")
    check_static_sizes(sizes, tmap)
    params = _ga_params(budget, generations)
    try:
        with progress_bar(len(sizes) * runs, f"{tmap.name}: GA + push and swap") as advance:
            batch = run_static_batch(
                tmap, sizes, runs, params, seed, delta, on_run=lambda *_: advance(1)
            )
    except ValueError as exc:
        raise BadInput(str(exc)) from None
    d = f"{budget:g} s" if budget is not None else "3 s × L"
    click.echo(
        f"map {tmap.name}, {runs} run(s) per size, GA budget {d}, seed {seed}, δ = {delta:g} s"
    )
    for line in static_table([batch]):
        click.echo(line)
    if batch.eval_seconds:
        click.echo(f"GA: {batch.evaluations / batch.eval_seconds:,.0f} evaluations/s")
    if gantt is not None:
        import numpy as np

        from btmission.dispatch.plot import gantt_png
        from btmission.dispatch.static import plan_static, random_instance

        rng = np.random.default_rng(seed)
        inst = random_instance(tmap, sizes[-1], rng)
        run = plan_static(tmap, inst, params, np.random.default_rng(seed), delta)
        ev = run.result.evaluation
        title = f"{tmap.name}: {sizes[-1]} vehicles, " + (
            f"ξ = {ev.items}, Δ = {ev.duration:.0f} s" if ev.feasible else "no feasible plan"
        )
        write_output(gantt_png(tmap, run.result.best, title), gantt)


@dispatch.command("dynamic")
@click.option("--map", "map_ref", default="mine", show_default=True, help=MAP_HELP)
@click.option("--vehicles", default="2,3,4,5", show_default=True, help="Fleet sizes, e.g. 2,3,4,5.")
@click.option("--hours", type=HOURS, default=4.0, show_default=True,
              help="Simulated duration of each run.")  # fmt: skip
@click.option("--runs", type=click.IntRange(1), default=1, show_default=True, help="Runs per size.")
@click.option("--budget", type=POSITIVE, default=0.5, show_default=True,
              help="GA wall-clock budget per optimisation in s.")  # fmt: skip
@click.option("--opt-time", type=POSITIVE, default=3.0, show_default=True,
              help="Simulated time one optimisation takes (causality: plans apply after it).")  # fmt: skip
@click.option("--settle/--no-settle", default=True, show_default=True,
              help="Shorten the adopted plans' idle stops (see docs/dispatch.md).")  # fmt: skip
@generations_option
@seed_option
@delta_option
@click.option("--gantt", type=click.Path(dir_okay=False, path_type=Path), default=None,
              callback=output_target("file"),
              help="Write the executed plan of the first run (first hour) as a PNG.")  # fmt: skip
@handle_spec_errors
def dynamic_cmd(
    map_ref: str, vehicles: str, hours: float, runs: int, budget: float, opt_time: float,
    settle: bool, generations: int | None, seed: int, delta: float, gantt: Path | None,
) -> None:  # fmt: skip
    """Dynamic planning (§5, §6.2): re-plan after every loading/offloading; Table 6 metrics.

    Loading takes 2-5 min, offloading 30-60 s (random). Prints C (terminal-to-terminal
    traversals per vehicle), i_t (idle fraction at terminals) and i_p (fraction at pause nodes),
    as mean ± std over the runs. The map needs exactly one prioritised terminal.

    \b
    Example:
      btmission dispatch dynamic --vehicles 2,3 --hours 1 --budget 0.2
    """
    from btmission.bench.dispatch import dynamic_table
    from btmission.dispatch.dynamic import DynamicConfig, DynamicResult, run_dynamic

    tmap = resolve_map(map_ref)
    sizes = int_list(vehicles, "--vehicles")
    params = _ga_params(budget, generations)
    T = hours * 3600.0
    results: dict[int, list[DynamicResult]] = {}
    try:
        cfgs = [
            DynamicConfig(
                L, T, opt_time_s=opt_time, ga=params, delta=delta, seed=seed + k, settle=settle
            )
            for L in sizes
            for k in range(runs)
        ]
        with progress_bar(int(len(cfgs) * T), f"{tmap.name}: simulated s") as advance:
            for cfg in cfgs:
                done = [0.0]

                def tick(t: float, done: list[float] = done) -> None:
                    if t - done[0] >= 60:
                        advance(int(t - done[0]))
                        done[0] = float(int(t))

                results.setdefault(cfg.vehicles, []).append(run_dynamic(tmap, cfg, tick))
                advance(int(T - done[0]))
    except ValueError as exc:
        raise BadInput(str(exc)) from None
    click.echo(
        f"map {tmap.name}, {hours:g} h, {runs} run(s) per size, GA budget {budget:g} s, "
        f"optimisation time {opt_time:g} s (simulated), seed {seed}"
        + ("" if settle else ", plans not settled")
    )
    for line in dynamic_table(results):
        click.echo(line)
    if gantt is not None:
        from btmission.dispatch.dynamic import executed_tracks
        from btmission.dispatch.plot import gantt_png

        first = results[sizes[0]][0]
        tracks = _clip(tmap, executed_tracks(first), min(T, 3600.0))
        title = f"{tmap.name}: executed plan, {sizes[0]} vehicles, first {min(hours, 1.0):g} h"
        write_output(gantt_png(tmap, tracks, title), gantt)


def _clip(tmap: Any, tracks: Any, t_end: float) -> Any:
    """Tracks cut after the first node reached after ``t_end`` (for readable Gantt charts)."""
    from dataclasses import replace

    from btmission.dispatch.evaluate import timeline

    out = []
    for m in tracks:
        arr, _ = timeline(tmap, [int(x) for x in m.nodes], list(m.waits), m.t0)
        keep = next((i for i, a in enumerate(arr) if a > t_end), len(arr) - 1) + 1
        waits = m.waits[:keep].copy()
        waits[-1] = 0.0
        out.append(replace(m, nodes=m.nodes[:keep], waits=waits))
    return tuple(out)


@dispatch.command("plan")
@click.option("--map", "map_ref", required=True, help=MAP_HELP)
@click.option("--vehicle", "vehicles", multiple=True, required=True, metavar="START:END",
              help="A vehicle's start and end node (repeatable).")  # fmt: skip
@budget_option
@generations_option
@seed_option
@delta_option
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              callback=output_target("file"),
              help="Write the plan as a Fig. 3-style Gantt PNG.")  # fmt: skip
@handle_spec_errors
def plan_cmd(
    map_ref: str, vehicles: tuple[str, ...], budget: float | None, generations: int | None,
    seed: int, delta: float, output: Path | None,
) -> None:  # fmt: skip
    """Plan one static fleet mission with the GA and print each vehicle's mission.

    A vehicle whose end node is a prioritised terminal gets a prioritised mission (Π0, no stops
    after the start). Exit status 1 when no feasible plan is found within the budget.

    \b
    Example:
      btmission dispatch plan --map mine --vehicle L1n:O --vehicle O:L2s -o plan.png
    """
    import numpy as np

    from btmission.cli.common import ChecksFailed
    from btmission.dispatch.missions import describe
    from btmission.dispatch.static import StaticInstance, plan_static

    tmap = resolve_map(map_ref)
    starts, ends = [], []
    for v in vehicles:
        a, sep, b = v.partition(":")
        if not sep:
            raise BadInput(f"--vehicle: expected START:END, got '{v}'")
        for name in (a, b):
            if name not in tmap.index:
                raise BadInput(f"--vehicle {v}: no node '{name}' in map '{tmap.name}'")
        starts.append(tmap.id(a))
        ends.append(tmap.id(b))
    if len(set(starts)) < len(starts) or len(set(ends)) < len(ends):
        raise BadInput("--vehicle: start nodes must differ, and so must end nodes")
    params = _ga_params(budget, generations)
    run = plan_static(
        tmap, StaticInstance(tuple(starts), tuple(ends)), params, np.random.default_rng(seed), delta
    )
    res = run.result
    ev = res.evaluation
    for k, m in enumerate(res.best):
        tag = " (prioritized)" if m.prioritized else ""
        click.echo(f"v{k + 1}{tag}: {describe(tmap, m)}")
    click.echo(
        f"{'feasible' if ev.feasible else 'INFEASIBLE'}: ξ = {ev.items} (ξ_min = {run.xi_min}), "
        f"Δ = {ev.duration:.1f} s, collisions = {ev.collisions}; {res.generations} generations in "
        f"{res.elapsed_s:.2f} s"
    )
    if output is not None:
        from btmission.dispatch.plot import gantt_png

        write_output(gantt_png(tmap, res.best, f"{tmap.name}: {len(starts)} vehicles"), output)
    if not ev.feasible:
        raise ChecksFailed("no feasible fleet mission found; try a larger --budget")
