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


@bench.command("control")
@click.option(
    "--only",
    default="nmpc,apf,dphr",
    show_default=True,
    help="Comma-separated parts to run: nmpc, apf, dphr.",
)
@click.option(
    "--steps",
    default=200,
    show_default=True,
    type=click.IntRange(1),
    help="Closed-loop NMPC steps per solver (20 Hz).",
)
@click.option(
    "--repeat",
    default=200,
    show_default=True,
    type=click.IntRange(1),
    help="Timed APF calls (DPHR runs a quarter as many).",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("benchmarks/results"),
    show_default=True,
    help="Directory for control.md and control.csv.",
)
def control_bench(only: str, steps: int, repeat: int, out: Path) -> None:
    """NMPC (fatrop vs ipopt), APF and DPHR timings. Targets: NMPC median <= 3 ms and p99 <= 15 ms,
    APF (30,000 points) <= 1 ms, DPHR (640x480) <= 10 ms.

    \b
    Example:
      btmission bench control --only apf,dphr --repeat 50 --out /tmp/results
    """
    from btmission.bench.control import PARTS, run_control_benchmark

    parts = [p.strip() for p in only.split(",") if p.strip()]
    unknown = [p for p in parts if p not in PARTS]
    if unknown or not parts:
        raise click.BadParameter(
            f"unknown part(s) '{only}' (choose from {', '.join(PARTS)})", param_hint="--only"
        )
    run_control_benchmark(parts, steps=steps, repeat=repeat, out_dir=out, echo=click.echo)
