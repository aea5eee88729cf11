"""``btmission bench``: the project's benchmarks (results as Markdown + CSV tables)."""

from __future__ import annotations

from pathlib import Path

import click

from btmission.cli.map_cmds import mine_resolution_option, size_option


@click.group()
def bench() -> None:
    """Run benchmarks; each prints a table and writes it under --out (default benchmarks/results)."""


@bench.command("synth")
@click.option(
    "--sizes",
    default="10,100,1000,5000",
    show_default=True,
    help="Comma-separated numbers of actions per generated library.",
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


@bench.command("planner")
@size_option((200.0, 120.0, 10.0))
@mine_resolution_option
@click.option(
    "--repeat",
    default=5,
    show_default=True,
    type=click.IntRange(1),
    help="Timed repetitions (median reported).",
)
@click.option(
    "--queries",
    default=20,
    show_default=True,
    type=click.IntRange(1),
    help="Random start/goal pairs for single queries.",
)
@click.option("--no-peers", is_flag=True, help="Skip skimage and networkx (scipy always runs).")
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("benchmarks/results"),
    show_default=True,
    help="Directory for planner.md and planner.csv.",
)
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

    run_planner_benchmark(
        size, resolution, repeat, queries, out_dir=out, echo=click.echo, peers=not no_peers
    )
