"""``btmission control``: run the reactive-navigation examples and plot them."""

from __future__ import annotations

import io
from pathlib import Path

import click

from btmission.cli.common import BadInput, output_target, write_output

FIGURE_NAMES = ("nmpc", "apf", "dphr", "unicycle", "compra")
IMAGE_FORMATS = ("png", "svg", "pdf")


@click.group()
def control() -> None:
    """Reactive navigation: NMPC, APF, DPHR and COMPRA exploration (seed 002, seed 003).

    The algorithms live in btmission.control (see docs/control.md); these commands run their
    small examples. Timings: btmission bench control.

    \b
    Example:
      btmission control plot compra -o compra.png
    """


@control.command("plot")
@click.argument("name", type=click.Choice(FIGURE_NAMES))
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    callback=output_target("file"),
    help="Image file to write (.png, .svg or .pdf).",
)
def plot(name: str, output: Path) -> None:
    """Run a small closed-loop example and plot it.

    \b
    nmpc      MAV NMPC flies to a set-point (inputs, bounds, rate limits)
    apf       NMPC + APF down a corridor, carrot pulled into a wall, with dust
    dphr      depth image of a bending tunnel, deepest cluster, yaw rate
    unicycle  two ground robots pass head-on (set-exclusion NMPC)
    compra    explore a bending tunnel, return along breadcrumbs, land

    \b
    Example:
      btmission control plot apf -o apf.png
    """
    suffix = output.suffix.lower().lstrip(".")
    if suffix not in IMAGE_FORMATS:
        raise BadInput(
            f"{output}: unknown image type '.{suffix}' (use one of "
            f"{', '.join('.' + f for f in IMAGE_FORMATS)})"
        )
    from btmission.control.plots import FIGURES

    click.echo(f"running the {name} example…", err=True)
    fig = FIGURES[name]()
    buf = io.BytesIO()
    fig.savefig(buf, format=suffix, dpi=110)
    write_output(buf.getvalue(), output)  # says "wrote …"
