"""``btmission bench``: the project's benchmarks (results as Markdown + CSV tables)."""

from __future__ import annotations

from pathlib import Path

import click


@click.group()
def bench() -> None:
    """Run benchmarks; each prints a table and writes it under --out (default benchmarks/results)."""


@bench.command("synth")
@click.option(
    "--sizes",
    default="10,100,1000,5000",
    show_default=True,
    help="Comma-separated library sizes (chain: actions; fan-in: width, i.e. preconditions of the top action).",
)
@click.option(
    "--repeat",
    default=5,
    show_default=True,
    type=click.IntRange(1),
    help="Timed repetitions per case (the median is reported).",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("benchmarks/results"),
    show_default=True,
    help="Directory for synth.md and synth.csv.",
)
def synth_bench(sizes: str, repeat: int, out: Path) -> None:
    """Synthesis + checks on generated libraries (chains and wide fan-in). Target: 1,000 actions < 100 ms."""
    from btmission.bench.synth import run_synth_benchmark

    try:
        ns = [int(s) for s in sizes.split(",") if s.strip()]
    except ValueError:
        raise click.BadParameter(
            f"expected comma-separated integers, got '{sizes}'", param_hint="--sizes"
        ) from None
    run_synth_benchmark(ns, repeat=repeat, out_dir=out, echo=click.echo)


@bench.command("dispatch")
@click.option(
    "--vehicles",
    default="2,4,6,8,10",
    show_default=True,
    help="Fleet sizes (even), comma-separated.",
)
@click.option(
    "--runs", default=5, show_default=True, type=click.IntRange(1),
    help="Random instances per fleet size and map (the paper: 1,000).",
)  # fmt: skip
@click.option(
    "--tau", default=0.3, show_default=True, type=click.FloatRange(min=0, min_open=True),
    help="GA budget per vehicle in s (0.3: 3 s at 10 vehicles, a tenth of the paper's).",
)  # fmt: skip
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed.")
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("benchmarks/results"),
    show_default=True,
    help="Directory for dispatch.md and dispatch.csv.",
)
def dispatch_bench(vehicles: str, runs: int, tau: float, seed: int, out: Path) -> None:
    """Static GA batch vs push and swap on the NPR/SPR maps, and fitness evaluations per second.

    Targets: Σ ≥ 98.6 % and r ≤ 1.02 at 10 vehicles with 3 s in total.

    \b
    Example:
      btmission bench dispatch --vehicles 2,10 --runs 3
    """
    from btmission.bench.dispatch import run_dispatch_benchmark
    from btmission.cli.dispatch_cmds import int_list, progress_bar

    sizes = int_list(vehicles, "--vehicles")
    with progress_bar(2 * len(sizes) * runs, "NPR + SPR: GA + push and swap") as advance:
        run_dispatch_benchmark(
            sizes, runs, tau, seed, out, echo=click.echo, on_run=lambda *_: advance(1)
        )


@bench.command("dispatch-dynamic")
@click.option("--vehicles", default="2,3,4,5", show_default=True, help="Fleet sizes.")
@click.option("--runs", default=5, show_default=True, type=click.IntRange(1), help="Runs per size.")
@click.option(
    "--hours", default=4.0, show_default=True, type=click.FloatRange(min=0, min_open=True),
    help="Simulated hours per run.",
)  # fmt: skip
@click.option(
    "--budget", default=0.5, show_default=True, type=click.FloatRange(min=0, min_open=True),
    help="GA wall-clock budget per optimisation (s).",
)  # fmt: skip
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed.")
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("benchmarks/results"),
    show_default=True,
    help="Directory for dispatch_dynamic.md and .csv.",
)
def dispatch_dynamic_bench(
    vehicles: str, runs: int, hours: float, budget: float, seed: int, out: Path
) -> None:
    """Dynamic planning on the Fig. 1 mine: Table 6 (C, i_t, i_p) for 2-5 trucks.

    The full run (5 × 4 h per size) takes about 20 min here.

    \b
    Example:
      btmission bench dispatch-dynamic --vehicles 2,3 --runs 1 --hours 0.5
    """
    from btmission.bench.dispatch import run_dynamic_benchmark
    from btmission.cli.dispatch_cmds import int_list, progress_bar

    sizes = int_list(vehicles, "--vehicles")
    with progress_bar(len(sizes) * runs, "mine: dynamic runs") as advance:
        run_dynamic_benchmark(
            sizes, runs, hours, budget, seed, out, echo=click.echo, on_run=lambda _: advance(1)
        )
