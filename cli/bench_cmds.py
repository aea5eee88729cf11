"""``btmission bench``: the project's benchmarks (results as Markdown + CSV tables)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import click

from btmission.bench.synth import DEFAULT_SHAPES, SHAPES
from btmission.cli.common import (
    SEED,
    BadInput,
    ChecksFailed,
    FiniteFloat,
    int_option,
    output_file_option,
    output_target,
    positive_float_option,
)
from btmission.cli.dispatch_cmds import HOURS
from btmission.cli.map_cmds import mine_resolution_option, size_option
from btmission.limits import MAX_AGENTS, MAX_TASKS, Budget

F = TypeVar("F", bound=Callable[..., Any])


def out_option(what: str, *short: str) -> Callable[[F], F]:
    """The ``--out`` directory option every benchmark shares (results land in ``what``)."""
    return click.option(
        "--out",
        *short,
        type=click.Path(file_okay=False, path_type=Path),
        default=Path("benchmarks/results"),
        callback=output_target("dir"),
        show_default=True,
        help=f"Directory for {what}.",
    )


def list_option(name: str, default: str, help: str) -> Callable[[F], F]:
    """A comma-separated list given as text (parsed by the command), default shown."""
    return click.option(name, default=default, show_default=True, help=help)


def seed_option(help: str) -> Callable[[F], F]:
    """``--seed`` (an integer, default 0)."""
    return click.option("--seed", type=SEED, default=0, show_default=True, help=help)


def script_main(name: str, script: str, argv: Sequence[str] | None = None) -> int:
    """Run ``btmission bench NAME`` as the script ``benchmarks/bench_NAME.py``.

    The same options, output and exit statuses as the command; the only difference is where
    results go by default: ``results/`` next to ``script`` (not relative to the current directory).
    Returns 0 when it ran; bad options exit (``SystemExit``) with click's status, as argparse would.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    if not any(a in ("-o", "--out") or a.startswith("--out=") for a in args):
        args += ["--out", str(Path(script).resolve().parent / "results")]
    try:
        bench.commands[name].main(args, prog_name=Path(script).name)
    except SystemExit as exc:
        if exc.code not in (0, None):
            raise
    return 0


@click.group()
def bench() -> None:
    """Run benchmarks; each prints a table and writes it under --out (default benchmarks/results)."""


@bench.command("synth")
@list_option(
    "--sizes",
    default="10,100,1000,5000",
    help="Comma-separated library sizes (chain: actions; fan-in: width, i.e. preconditions of the top action).",
)
@int_option("--repeat", default=5, help="Timed repetitions per case (the median is reported).")
@list_option(
    "--shapes",
    default=",".join(DEFAULT_SHAPES),
    help=f"Comma-separated shapes: {', '.join(SHAPES)}.",
)
@out_option("synth.md and synth.csv")
def synth_bench(sizes: str, repeat: int, shapes: str, out: Path) -> None:
    """Synthesis + checks on generated libraries (chains and wide fan-in). Target: 1,000 actions < 100 ms."""
    from btmission.bench.synth import run_synth_benchmark

    ns = _int_list(sizes, "--sizes")
    names = _names(shapes, list(SHAPES), "--shapes", "shape")
    run_synth_benchmark(ns, repeat=repeat, out_dir=out, echo=click.echo, shapes=names)


@bench.command("control")
@list_option(
    "--only",
    default="nmpc,apf,dphr",
    help="Comma-separated parts to run: nmpc, apf, dphr.",
)
@int_option("--steps", default=200, help="Closed-loop NMPC steps per solver (20 Hz).")
@int_option("--repeat", default=200, help="Timed APF calls (DPHR runs a quarter as many).")
@out_option("control.md and control.csv")
def control_bench(only: str, steps: int, repeat: int, out: Path) -> None:
    """NMPC (fatrop vs ipopt), APF and DPHR timings. Targets: NMPC median <= 3 ms and p99 <= 15 ms,
    APF (30,000 points) <= 1 ms, DPHR (640x480) <= 10 ms.

    \b
    Example:
      btmission bench control --only apf,dphr --repeat 50 --out /tmp/results
    """
    from btmission.bench.control import PARTS, run_control_benchmark

    parts = _names(only, PARTS, "--only", "part")
    run_control_benchmark(parts, steps=steps, repeat=repeat, out_dir=out, echo=click.echo)


@bench.command("startup")
@int_option(
    "--repeat", default=10, max=1000, help="Timed runs of each command (the median is reported)."
)
@out_option("startup.md and startup.csv")
def startup_bench(repeat: int, out: Path) -> None:
    """Start-up time of the command line: --version, --help and validate on the mine mission,
    beside the interpreter alone. Targets: --help <= 0.15 s, validate <= 0.5 s (median).

    \b
    Example:
      btmission bench startup --repeat 3 --out /tmp/results
    """
    from btmission.bench.startup import run_startup_benchmark

    run_startup_benchmark(repeat=repeat, out_dir=out, echo=click.echo)


@bench.command("fleet")
@list_option("--sizes", default="3,10,30,100", help="Comma-separated fleet sizes (drones) to fly.")
@list_option("--controllers", default="track", help="Comma-separated controllers (track, nmpc).")
@positive_float_option(
    "--warmup", default=10.0, help="Simulated seconds flown before the timed window."
)
@positive_float_option("--duration", default=60.0, help="Simulated seconds of the timed window.")
@int_option(
    "--repeat",
    default=1,
    help="Times each fleet size is built and flown (a fresh run each time): the table reports "
    "the median run's speed-up, with the min and max; fleet.csv has every run.",
)
@out_option("fleet.md, fleet.csv and fleet.png")
def fleet_bench(
    sizes: str, controllers: str, warmup: float, duration: float, repeat: int, out: Path
) -> None:
    """Simulator speed against fleet size: 3, 10, 30 and 100 drones in the seed 000 mine (7
    inspections per 3 drones), the whole system in one process. Targets (tracking controller):
    3 drones >= 100x, 30 drones >= 25x real time, on the median of --repeat runs. Each run is
    preceded by a host speed reference (a fixed Python workload, in ms: higher = the shared
    host was slower then).

    \b
    Examples:
      btmission bench fleet --sizes 3,10 --warmup 2 --duration 5 --out /tmp/results
      btmission bench fleet --sizes 30 --repeat 5 --out /tmp/results   # median of 5
    """
    from btmission.bench.fleet import run_fleet_benchmark

    ctrls = [c.strip() for c in controllers.split(",") if c.strip()]
    bad = [c for c in ctrls if c not in ("track", "nmpc")]
    if bad or not ctrls:
        raise click.BadParameter(
            f"unknown controller(s) {', '.join(bad) or '(none given)'}: track or nmpc",
            param_hint="--controllers",
        )
    fleet: list[int] = []
    for item in (s.strip() for s in sizes.split(",") if s.strip()):
        if not item.isdigit() or not 1 <= int(item) <= MAX_FLEET:
            raise click.BadParameter(
                f"expected a number of drones from 1 to {MAX_FLEET}, got '{item}'",
                param_hint="--sizes",
            )
        fleet.append(int(item))
    if not fleet:
        raise click.BadParameter("give at least one fleet size", param_hint="--sizes")
    run_fleet_benchmark(fleet, ctrls, warmup, duration, out, click.echo, repeat)


MAX_FLEET = 150
"""The most drones ``bench fleet`` flies: the seed 000 mine has room for ~600 starts and tasks
at 7 tasks per 3 drones."""


@bench.command("paper")
@click.option(
    "--only",
    default="",
    help="Comma-separated sections to re-run (seed000, seed002, seed003, seed004); the others' "
    "stored results are kept. [default: all]",
)
@click.option(
    "--quick",
    is_flag=True,
    help="Short runs of the same experiments (a smoke test); the page goes to OUT/fidelity.md, "
    "never over docs/fidelity.md.",
)
@output_file_option(
    "--doc",
    help="The page to rewrite. [default: docs/fidelity.md if ./docs exists, else OUT/fidelity.md]",
)
@out_option("paper/<section>.json and .md (each section's stored result)")
def paper_bench(only: str, quick: bool, doc: Path | None, out: Path) -> None:
    """The four seed papers' reported results reproduced side by side (docs/fidelity.md).

    Each section runs btmission's version of one paper's experiment (seed 000's field test,
    seed 002's COMPRA flights, seed 003's NMPC safety distances, seed 004's dispatch tables),
    stores its result under OUT/paper/ and the page is rebuilt from every stored section, so
    one section can be re-run alone. A full run takes tens of minutes on a 2-core machine.

    \b
    Examples:
      btmission bench paper                    # every section; rewrites docs/fidelity.md
      btmission bench paper --only seed000     # one section, the others kept
      btmission bench paper --quick --out /tmp/paper
    """
    from btmission.bench.paper import parse_only, run_paper_benchmark

    try:
        keys = parse_only(only)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--only") from None
    if doc is None:
        doc = Path("docs/fidelity.md") if Path("docs").is_dir() else out / "fidelity.md"
    run_paper_benchmark(keys, quick=quick, out_dir=out, doc=doc, echo=click.echo)


def _names(text: str, known: Sequence[str], name: str, what: str) -> list[str]:
    """The comma-separated ``text`` as a list of names, each one of ``known``."""
    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names or any(n not in known for n in names):
        raise click.BadParameter(
            f"unknown {what}(s) '{text}' (choose from {', '.join(known)})", param_hint=name
        )
    return names


def _int_list(text: str, name: str) -> tuple[int, ...]:
    try:
        values = tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        raise click.BadParameter(
            f"expected comma-separated integers, got '{text}'", param_hint=name
        ) from None
    if not values or min(values) < 1:
        raise click.BadParameter(f"expected positive integers, got '{text}'", param_hint=name)
    return values


def _fraction_list(text: str, name: str) -> tuple[float, ...]:
    out: list[float] = []
    for s in (s.strip() for s in text.split(",")):
        if not s:
            continue
        try:
            v = float(s[:-1]) / 100 if s.endswith("%") else float(s)
        except ValueError:
            v = -1.0
        if not 0 < v <= 1:
            raise click.BadParameter(
                f"'{s}' is not a fraction in (0, 1] (e.g. 0.3 or 30%)", param_hint=name
            )
        out.append(v)
    if not out:
        raise click.BadParameter("expected at least one value", param_hint=name)
    return tuple(out)


def _within_budget(values: Sequence[int], budget: Budget, what: str, name: str) -> None:
    """Refuse a count over the mission budget for ``what`` (agents or tasks) before building."""
    for v in values:
        if v > budget.limit:
            raise click.BadParameter(budget.exceeded(f"the number of {what}", v), param_hint=name)


def _size_list(text: str, name: str) -> tuple[tuple[int, int], ...]:
    sizes: list[tuple[int, int]] = []
    for s in (s.strip().lower() for s in text.split(",")):
        if not s:
            continue
        parts = s.split("x")
        try:
            na, nt = (int(p) for p in parts) if len(parts) == 2 else (0, 0)
        except ValueError:
            na = nt = 0
        if na < 1 or nt < 1:
            raise click.BadParameter(
                f"'{s}' is not AGENTSxTASKS (e.g. 1000x10000)", param_hint=name
            )
        _within_budget([na], MAX_AGENTS, "agents", name)
        _within_budget([nt], MAX_TASKS, "tasks", name)
        sizes.append((na, nt))
    return tuple(sizes)


@bench.command("auction")
@click.option(
    "--agents",
    help="Agent counts for Fig. 4 (the largest is Fig. 5's fixed count). [default: 10,20,30,40,50]",
)
@click.option(
    "--tasks",
    help="Task counts for Fig. 5 (the largest is Fig. 4's fixed count). [default: 50,100,200,300,400]",
)
@click.option(
    "--participation",
    "-p",
    help="Fractions of the tasks each agent bids on. [default: 0.3,0.6,0.9]",
)
@click.option(
    "--repeat",
    type=click.IntRange(1),
    help="Timed runs of the assignment solver per point (median). [default: 5]",
)
@click.option(
    "--rounds", type=click.IntRange(1), help="Coordinator rounds timed at 50x400. [default: 300]"
)
@click.option(
    "--scale",
    help="AGENTSxTASKS sizes for the assignment solver alone ('' for none). [default: 1000x10000]",
)
@click.option(
    "--crossover",
    help="AGENTSxTASKS sizes for dense vs sparse solvers ('' for none). "
    "[default: 200x2000,1000x10000]",
)
@click.option(
    "--no-scip", is_flag=True, help="Skip the paper's ILP on SCIP (assignment solver only)."
)
@click.option(
    "--scip-max-bids",
    type=click.IntRange(1),
    default=20_000,
    show_default=True,
    help="Skip SCIP on instances with more bid variables than this.",
)
@click.option(
    "--quick", is_flag=True, help="A short run (~20 s): fewer points, repeats and rounds."
)
@seed_option("Instance seed.")
@out_option("auction.md, auction.csv (and auction.png)", "-o")
@output_file_option("--png", help="Where to write the plot. [default: OUT/auction.png]")
def auction_bench(
    agents: str | None,
    tasks: str | None,
    participation: str | None,
    repeat: int | None,
    rounds: int | None,
    scale: str | None,
    crossover: str | None,
    no_scip: bool,
    scip_max_bids: int,
    quick: bool,
    seed: int,
    out: Path,
    png: Path | None,
) -> None:
    """Task allocation: seed 003 Fig. 4 (time vs agents) and Fig. 5 (time vs tasks).

    For each participation (30/60/90 % of the tasks bid on by each agent), times the default
    exact assignment solver and the paper's ILP on OR-Tools + SCIP side by side and checks they
    reach the same optimum; then a whole coordinator round at 50 x 400, the assignment solver at
    1,000 x 10,000 and dense vs sparse solvers. Writes a table (Markdown + CSV) and a plot.
    Targets: ≥ 1,000x faster than SCIP at 50 x 400 (p = 0.9), rounds ≥ 200 Hz, 1,000 x 10,000
    in ≤ 50 ms.

    \b
    Examples:
      btmission bench auction                      # full run, a few minutes
      btmission bench auction --quick              # ~20 s
      btmission bench auction --agents 50 --tasks 400 -p 0.9 --scale '' --crossover '' -o /tmp/r
    """
    from btmission.bench.auction import BenchConfig, run_auction_benchmark

    overrides: dict[str, object] = {
        "scip": not no_scip,
        "scip_max_bids": scip_max_bids,
        "seed": seed,
    }
    if agents is not None:
        overrides["agents"] = counts = _int_list(agents, "--agents")
        _within_budget(counts, MAX_AGENTS, "agents", "--agents")
    if tasks is not None:
        overrides["tasks"] = counts = _int_list(tasks, "--tasks")
        _within_budget(counts, MAX_TASKS, "tasks", "--tasks")
    if participation is not None:
        overrides["participation"] = _fraction_list(participation, "--participation")
    if repeat is not None:
        overrides["repeat"] = repeat
        overrides["scale_repeat"] = repeat
    if rounds is not None:
        overrides["rounds"] = rounds
    if scale is not None:
        overrides["scale"] = _size_list(scale, "--scale")
    if crossover is not None:
        overrides["crossover"] = _size_list(crossover, "--crossover")
    cfg = BenchConfig.quick(**overrides) if quick else BenchConfig(**overrides)  # type: ignore[arg-type]
    run_auction_benchmark(cfg, out_dir=out, png=png, echo=click.echo)


@bench.command("planner")
@size_option((200.0, 120.0, 10.0))
@mine_resolution_option
@int_option("--repeat", default=5, help="Timed repetitions (median reported).")
@int_option("--queries", default=20, help="Random start/goal pairs for single queries.")
@click.option("--no-peers", is_flag=True, help="Skip skimage and networkx (scipy always runs).")
@out_option("planner.md and planner.csv")
def planner_bench(
    size: tuple[float, float, float],
    resolution: float,
    repeat: int,
    queries: int,
    no_peers: bool,
    out: Path,
) -> None:
    """D*+ planner on a generated mine vs scipy / skimage / networkx (one-to-all, queries, replan).

    \b
    Example:
      btmission bench planner                      # the 200 × 120 × 10 m mine, ~1.9 M voxels
      btmission bench planner --size 80 50 8 --repeat 3 --queries 5 --out /tmp/r
    """
    from btmission.bench.planner import run_planner_benchmark
    from btmission.world.voxel import MapError

    try:
        run_planner_benchmark(
            size, resolution, repeat, queries, out_dir=out, echo=click.echo, peers=not no_peers
        )
    except MapError as exc:
        raise BadInput(f"--size: {exc}") from None


@bench.command("dispatch")
@list_option(
    "--vehicles",
    default="2,4,6,8,10",
    help="Fleet sizes (even), comma-separated.",
)
@int_option("--runs", default=5, help="Random instances per fleet size and map (the paper: 1,000).")
@positive_float_option(
    "--tau",
    default=0.3,
    help="GA budget per vehicle in s (0.3: 3 s at 10 vehicles, a tenth of the paper's).",
)
@seed_option("Random seed.")
@out_option("dispatch.md and dispatch.csv")
def dispatch_bench(vehicles: str, runs: int, tau: float, seed: int, out: Path) -> None:
    """Static GA batch vs push and swap on the NPR/SPR maps, and fitness evaluations per second.

    Targets: Σ ≥ 98.6 % and r ≤ 1.02 at 10 vehicles with 3 s in total.

    \b
    Example:
      btmission bench dispatch --vehicles 2,10 --runs 3
    """
    from btmission.bench.dispatch import run_dispatch_benchmark
    from btmission.cli.dispatch_cmds import check_static_sizes, int_list, progress_bar
    from btmission.dispatch.maps import static_map

    sizes = int_list(vehicles, "--vehicles")
    check_static_sizes(sizes, static_map("npr"), static_map("spr"))
    with progress_bar(2 * len(sizes) * runs, "NPR + SPR: GA + push and swap") as advance:
        run_dispatch_benchmark(
            sizes, runs, tau, seed, out, echo=click.echo, on_run=lambda *_: advance(1)
        )


@bench.command("dispatch-dynamic")
@list_option("--vehicles", default="2,3,4,5", help="Fleet sizes.")
@int_option("--runs", default=5, help="Runs per size.")
@click.option("--hours", type=HOURS, default=4.0, show_default=True,
              help="Simulated hours per run.")  # fmt: skip
@positive_float_option("--budget", default=0.5, help="GA wall-clock budget per optimisation (s).")
@click.option("--map", "map_name", type=click.Choice(["mine_table6", "mine"]),
              default="mine_table6", show_default=True,
              help="The Fig. 1 mine scaled to Table 6's trip length, or as drawn.")  # fmt: skip
@positive_float_option("--tau", default=3.0,
                       help="Simulated time charged per optimisation and vehicle (s).")  # fmt: skip
@seed_option("Random seed.")
@out_option("dispatch_dynamic.md and .csv")
def dispatch_dynamic_bench(
    vehicles: str,
    runs: int,
    hours: float,
    budget: float,
    map_name: str,
    tau: float,
    seed: int,
    out: Path,
) -> None:
    """Dynamic planning on the Fig. 1 mine: Table 6 (C, i_t, i_p) for 2-5 trucks.

    The full run (5 × 4 h per size) takes about 12 min here.

    \b
    Example:
      btmission bench dispatch-dynamic --vehicles 2,3 --runs 1 --hours 0.5
    """
    from btmission.bench.dispatch import run_dynamic_benchmark
    from btmission.cli.dispatch_cmds import int_list, progress_bar

    sizes = int_list(vehicles, "--vehicles")
    with progress_bar(len(sizes) * runs, "mine: dynamic runs") as advance:
        run_dynamic_benchmark(
            sizes, runs, hours, budget, seed, out, echo=click.echo, on_run=lambda _: advance(1),
            map_name=map_name, tau_s=tau,
        )  # fmt: skip


@bench.command("sim")
@list_option(
    "--controllers",
    default="track,nmpc",
    help="Comma-separated controllers to run the mine mission with (track, nmpc).",
)
@list_option(
    "--scale",
    default="50x400",
    help="Comma-separated AGENTSxTASKS scaling points ('' for none).",
)
@click.option(
    "-p",
    "--participation",
    default=0.3,
    show_default=True,
    type=FiniteFloat(0, 1, min_open=True),
    help="Participation of the scaling runs (seed 003 Fig. 4: 0.3, 0.6, 0.9).",
)
@positive_float_option("--duration", default=30.0, help="Simulated seconds of each scaling run.")
@out_option("sim.md and sim.csv")
def sim_bench(
    controllers: str, scale: str, participation: float, duration: float, out: Path
) -> None:
    """Simulator speed: mine_inspection vs real time per controller (targets: track >= 100x,
    nmpc >= 20x) and the seed 003 scaling point (round rate, bid time, wall time).

    The NMPC row also gives the CPU time of the solver calls and the ceiling it sets on this
    machine: simulated time / (solver CPU time / CPUs), the speed-up the solves alone allow.

    \b
    Example (quick):
      btmission bench sim --controllers track --scale 10x40 --duration 5 --out /tmp/results
    """
    from btmission.bench.sim import run_sim_benchmark

    ctrls = [c.strip() for c in controllers.split(",") if c.strip()]
    bad = [c for c in ctrls if c not in ("track", "nmpc")]
    if bad:
        raise click.BadParameter(
            f"unknown controller(s) {', '.join(bad)}", param_hint="--controllers"
        )
    points: list[tuple[int, int, float]] = []
    for item in (s.strip() for s in scale.split(",") if s.strip()):
        a, sep, t = item.partition("x")
        if not sep or not a.isdigit() or not t.isdigit() or int(a) < 1 or int(t) < 1:
            raise click.BadParameter(f"expected AGENTSxTASKS, got '{item}'", param_hint="--scale")
        _within_budget([int(a)], MAX_AGENTS, "agents", "--scale")
        _within_budget([int(t)], MAX_TASKS, "tasks", "--scale")
        points.append((int(a), int(t), participation))
    run_sim_benchmark(ctrls, points, duration, out, click.echo)


@bench.command("transport")
@list_option("--sizes", default="10x40,50x400", help="Comma-separated AGENTSxTASKS sizes.")
@click.option(
    "--rounds",
    type=click.IntRange(1),
    help="Timed rounds per transport and size. [default: 300; --quick: 60]",
)
@click.option(
    "--warmup",
    type=click.IntRange(0),
    help="Untimed rounds first. [default: 10; --quick: 5]",
)
@click.option(
    "-p",
    "--participation",
    default=0.9,
    show_default=True,
    type=FiniteFloat(0, 1, min_open=True),
    help="Fraction of the tasks each agent bids on.",
)
@list_option(
    "--layouts",
    default="1:each,2:shared",
    help="The agents' sides over Zenoh, a row each: PROCESSES:each|shared (a Zenoh session per "
    "agent, or one per process); 'thread' for a thread of this process.",
)
@click.option("--shm", is_flag=True, help="Let Zenoh use shared memory between the processes.")
@positive_float_option("--timeout", default=20.0, help="Bound of every wait, in seconds.")
@click.option("--quick", is_flag=True, help="A short run (~1 min): 60 rounds, 5 warm-up.")
@seed_option("Instance seed.")
@out_option("transport.md and transport.csv", "-o")
def transport_bench(
    sizes: str,
    rounds: int | None,
    warmup: int | None,
    participation: float,
    layouts: str,
    shm: bool,
    timeout: float,
    quick: bool,
    seed: int,
    out: Path,
) -> None:
    """Auction rounds over Zenoh on loopback vs the in-process bus (issue #17). Each round:
    announce, bids from every agent, solve, assign, every agent confirms. Reports round rate,
    p50/p99 latency, CPU per round and message sizes. Target: >= 50 Hz at 50x400 over Zenoh.
    Needs the net extra (eclipse-zenoh).

    \b
    Examples:
      btmission bench transport                    # 10x40 and 50x400, a few minutes
      btmission bench transport --quick --sizes 10x40 --layouts 1:each --out /tmp/results
    """
    from btmission.bench.transport import BenchError, Layout, TransportBenchConfig
    from btmission.transport.zenoh_session import NEEDS_NET, zenoh_available

    points = _size_list(sizes, "--sizes")
    if not points:
        raise click.BadParameter("expected at least one AGENTSxTASKS size", param_hint="--sizes")
    try:
        lays = tuple(Layout.parse(t) for t in layouts.split(",") if t.strip())
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--layouts") from None
    if not lays:
        raise click.BadParameter("expected at least one layout", param_hint="--layouts")
    if not zenoh_available():
        raise BadInput(NEEDS_NET)
    overrides: dict[str, Any] = {
        "sizes": points,
        "participation": participation,
        "layouts": lays,
        "shared_memory": shm,
        "timeout_s": timeout,
        "seed": seed,
    }
    if rounds is not None:
        overrides["rounds"] = rounds
    if warmup is not None:
        overrides["warmup"] = warmup
    cfg = TransportBenchConfig.quick(**overrides) if quick else TransportBenchConfig(**overrides)
    from btmission.bench.transport import run_transport_benchmark

    try:
        run_transport_benchmark(cfg, out_dir=out, echo=click.echo)
    except BenchError as exc:
        raise ChecksFailed(f"the transport benchmark failed: {exc}") from None


@bench.command("reloc")
@list_option(
    "--seeds",
    default="7,11",
    help="Comma-separated mine seeds (the poses are split evenly over them).",
)
@size_option((200.0, 120.0, 12.0))
@mine_resolution_option
@int_option("--poses", default=200, help="Random poses in all, each localised by every method.")
@int_option(
    "--robustness",
    default=50,
    min=0,
    help="Poses per mine for the dust, occlusion and other-mine rows (0: skip them).",
)
@click.option("--no-peers", is_flag=True, help="Only ours (no descriptor-only or plain-ICP rows).")
@click.option("--quick", is_flag=True, help="A short run (~30 s): one 120 × 80 m mine, 40 poses.")
@out_option("reloc.md and reloc.csv")
def reloc_bench(
    seeds: str,
    size: tuple[float, float, float],
    resolution: float,
    poses: int,
    robustness: int,
    no_peers: bool,
    quick: bool,
    out: Path,
) -> None:
    """Global relocalization from one scan with no initial guess, on generated ~200 m mines, side
    by side with the descriptor guess alone and plain ICP (from that guess and from the identity).
    Target: ≥ 95 % within 0.3 m and 3°, median < 200 ms.

    \b
    Examples:
      btmission bench reloc                          # 2 mines, 200 poses: a few minutes
      btmission bench reloc --quick --out /tmp/r     # ~30 s
    """
    from btmission.bench.reloc import run_reloc_benchmark
    from btmission.world.voxel import MapError

    seed_list = _int_list(seeds, "--seeds")
    if quick:
        seed_list, size, poses, robustness = (seed_list[0],), (120.0, 80.0, 12.0), 40, 10
    try:
        run_reloc_benchmark(
            seed_list,
            poses,
            size,
            resolution,
            robustness,
            out_dir=out,
            echo=click.echo,
            peers=not no_peers,
        )
    except MapError as exc:
        raise BadInput(f"--size: {exc}") from None


@bench.command("mavlink")
@list_option("--vehicles", default="10,30", help="Comma-separated fleet sizes (1-100).")
@positive_float_option("--seconds", default=10.0, help="Measured wall seconds per fleet size.")
@positive_float_option("--setpoint-hz", default=20.0, help="Setpoints per vehicle per second.")
@positive_float_option(
    "--telemetry-hz", default=50.0, help="Telemetry messages asked of each vehicle per second."
)
@click.option(
    "--stress",
    type=click.IntRange(0, 64),
    default=0,
    show_default=True,
    help="CPU-burning processes to run meanwhile (started and ended by the benchmark).",
)
@click.option(
    "--peer/--no-peer",
    default=True,
    show_default=True,
    help="Also measure MAVSDK-Python 4 doing the same work (when installed: "
    "pip install 'btmission[bench]').",
)
@out_option("mavlink.md and mavlink.csv")
def mavlink_bench(
    vehicles: str, seconds: float, setpoint_hz: float, telemetry_hz: float, stress: int,
    peer: bool, out: Path,
) -> None:  # fmt: skip
    """Many MAVLink vehicles from one ground station process, btmission beside MAVSDK-Python 4:
    N simulated PX4 vehicles (their own process) driven by one client process, each library in
    turn; setpoint rate, interval jitter p50/p99 and worst gap where the setpoints arrive,
    telemetry rate, CPU per vehicle, connect time (goal: 30 vehicles at 20 Hz setpoints and
    50 Hz telemetry with p99 jitter < 10 ms; with --stress, ≥ 97.5 % of the rate, no gap over
    200 ms, p99 ≤ 50 ms and no more CPU than MAVSDK-Python). Without MAVSDK-Python it says how
    to install it and measures btmission alone.

    \b
    Examples:
      btmission bench mavlink --vehicles 3 --seconds 2 --out /tmp/results
      btmission bench mavlink --vehicles 3,10,30 --stress 8 --out /tmp/results
    """
    from btmission.bench.mavlink import run_mavlink_benchmark

    counts = _int_list(vehicles, "--vehicles")
    if any(not 1 <= n <= 100 for n in counts):
        raise click.BadParameter("fleet sizes must be 1-100", param_hint="--vehicles")
    if not 2.0 < setpoint_hz <= 200.0:
        raise click.BadParameter(
            "must be > 2 (PX4's minimum) and <= 200", param_hint="--setpoint-hz"
        )
    if telemetry_hz > 200.0:
        raise click.BadParameter("must be <= 200", param_hint="--telemetry-hz")
    run_mavlink_benchmark(counts, seconds, setpoint_hz, telemetry_hz, out, click.echo, stress, peer)


@bench.command("viewer")
@int_option("--agents", default=30, max=MAX_AGENTS.limit, help="Robots in the mission.")
@click.option(
    "--tasks",
    type=click.IntRange(1, MAX_TASKS.limit),
    help="Inspection tasks, all open from the start. [default: twice --agents]",
)
@positive_float_option("--duration", default=20.0, help="Simulated seconds of each run.")
@int_option("--repeats", default=8, help="Runs of each variant (alternating; medians reported).")
@int_option("--clients", default=1, max=32, help="Readers of the stream in the viewer runs.")
@click.option(
    "--slow-pause",
    type=FiniteFloat(0, 10),
    default=0.5,
    show_default=True,
    help="The slow reader's pause after each message (s; 0: no slow-reader runs).",
)
@int_option(
    "--slow-buffer",
    default=0,
    min=0,
    help="The slow reader's socket receive buffer in bytes (0: the OS's).",
)
@click.option(
    "--controller",
    type=click.Choice(["track", "nmpc"]),
    default="track",
    show_default=True,
    help="Path following of the robots.",
)
@seed_option("Mission and simulator seed (the same in every run).")
@out_option("viewer.md and viewer.csv")
def viewer_bench(
    agents: int,
    tasks: int | None,
    duration: float,
    repeats: int,
    clients: int,
    slow_pause: float,
    slow_buffer: int,
    controller: str,
    seed: int,
    out: Path,
) -> None:
    """What the live viewer costs the simulator: the same mission with and without
    `run --view`'s viewer, in alternating runs as fast as they go. Target: at most 10 % slower
    with 30 agents and 10 Hz poses, and no task event dropped.

    The mission is `bench sim`'s scaling floor (ground robots, inspection tasks). Viewer runs
    serve the viewer on 127.0.0.1 (a free port) with --clients readers of its event stream
    over loopback HTTP; a third variant has one reader that pauses --slow-pause s after each
    message. Each viewer run checks that only superseded poses and routes were dropped and that
    the readers received every other record of the run's log. The viewer threads' CPU time
    is reported too: on a shared machine it is steadier than the speed.

    \b
    Examples:
      btmission bench viewer                       # 30 agents, 8 × 3 runs of 20 s: ~4 min
      btmission bench viewer --agents 5 --duration 10 --repeats 1 --out /tmp/r
    """
    import shlex

    from btmission.bench.viewer import ViewerBenchError, ViewerConfig, run_viewer_benchmark
    from btmission.cli.view_cmds import require_viz

    require_viz()
    cfg = ViewerConfig(
        agents=agents,
        tasks=tasks if tasks is not None else min(2 * agents, MAX_TASKS.limit),
        duration_s=duration,
        repeats=repeats,
        clients=clients,
        slow=slow_pause > 0,
        slow_pause_s=slow_pause,
        slow_buffer=slow_buffer,
        controller=controller,
        seed=seed,
        warmup_s=min(5.0, duration),
    )
    command = shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])
    try:
        run_viewer_benchmark(cfg, out, click.echo, command)
    except ViewerBenchError as exc:
        raise click.ClickException(str(exc)) from None


@bench.command("console")
@click.option(
    "--mission",
    default="missions/mine_inspection.yaml",
    show_default=True,
    help="The mission file to run, or 'floor': `bench viewer`'s floor of 30 ground robots "
    "and 60 tasks.",
)
@click.option(
    "--controller",
    type=click.Choice(["track", "nmpc"]),
    default="track",
    show_default=True,
    help="Path following of the robots.",
)
@positive_float_option("--seconds", default=80.0, help="Simulated seconds of each run.")
@int_option("--pairs", default=5, max=100, help="Repeats of the variants (alternating; medians).")
@click.option(
    "--flood",
    type=click.Choice(["both", "valid", "refused", "none"]),
    default="both",
    show_default=True,
    help="Flood variants: with valid adds (new tasks), with adds the console refuses (422), "
    "both, or none (viewer only and idle console).",
)
@click.option(
    "--refused",
    type=click.Choice(["rock", "outside"]),
    default="rock",
    show_default=True,
    help="Where the refused flood's adds go: into rock next to the valid ones (the console "
    "names the nearest free voxel), or outside the map.",
)
@int_option("--burst", default=1000, max=100_000, help="Requests in a burst of the flood.")
@int_option(
    "--burst-adds",
    default=200,
    min=0,
    max=100_000,
    help="Of them, POST /api/tasks (the rest GET /api/status).",
)
@int_option("--threads", default=16, max=128, help="The flood's client threads (connections).")
@positive_float_option(
    "--every", default=2.0, help="Wall seconds from a burst's start to the next's."
)
@seed_option("Mission and simulator seed (the same in every run).")
@out_option("console.md and console.csv")
def console_bench(
    mission: str,
    controller: str,
    seconds: float,
    pairs: int,
    flood: str,
    refused: str,
    burst: int,
    burst_adds: int,
    threads: int,
    every: float,
    seed: int,
    out: Path,
) -> None:
    """What the operator console costs a running mission: the same mission served with the
    viewer only (`run --view`), with the console idle (`run --console` and one page polling
    its status every second), and under a flood of requests from another process (bursts of
    --burst requests, --burst-adds of them task adds, from --threads threads), in alternating
    runs as fast as they go.

    Every run has one reader of the event stream in a process of its own. The flood's adds are
    copies of the mission's first task (valid: each a new task for the auction) or the same
    moved into rock, which the console refuses (422: the server's own cost). Each run checks
    that every add answered 201 is in the run's log, that nothing was answered 5xx, and that
    the stream reader received every record. Progress goes to stderr, the summary to stdout.

    \b
    Examples:
      btmission bench console                  # mine_inspection, 5 × 4 runs of 80 s: ~4 min
      btmission bench console --seconds 20 --pairs 1 --burst 200 --burst-adds 40 --out /tmp/r
    """
    import shlex

    from btmission.bench.console import ConsoleBenchError, ConsoleConfig, run_console_benchmark
    from btmission.cli.view_cmds import require_viz
    from btmission.diagnostics import SpecError

    require_viz()
    if burst_adds > burst:
        raise click.BadParameter("cannot be more than --burst", param_hint="--burst-adds")
    floods = {"both": ("flood", "refused"), "valid": ("flood",), "refused": ("refused",)}
    path = Path(mission)
    if mission != "floor" and not path.exists() and not path.is_absolute():
        here = Path(__file__).resolve().parent.parent / path  # the repository's missions/
        mission = str(here) if here.exists() else mission
    cfg = ConsoleConfig(
        mission=None if mission == "floor" else mission,
        duration_s=seconds,
        pairs=pairs,
        variants=("viewer", "idle", *floods.get(flood, ())),
        controller=controller,
        seed=seed,
        burst=burst,
        adds=burst_adds,
        threads=threads,
        every_s=every,
        refused=refused,
        warmup_s=min(30.0, seconds),
    )
    prog = Path(sys.argv[0]).name
    command = shlex.join(["btmission" if prog == "__main__.py" else prog, *sys.argv[1:]])
    try:
        run_console_benchmark(
            cfg, out, click.echo, lambda line: click.echo(line, err=True), command
        )
    except SpecError as exc:
        raise BadInput(f"--mission: {exc}") from None
    except ConsoleBenchError as exc:
        raise click.ClickException(str(exc)) from None
