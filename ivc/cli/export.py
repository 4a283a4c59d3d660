"""``ivc export LUT --format F -o OUT``: the look-up table for tracker firmware, 3D Slicer, ParaView and Vrui."""

from __future__ import annotations

from pathlib import Path

import click

from ivc import lut
from ivc.cli.paths import check_output
from ivc.export import FORMATS
from ivc.export import export as export_table
from ivc.units import LENGTH_UNITS

_HELP = "; ".join(f"{name}: {text}" for name, (_, _, text) in FORMATS.items())


@click.command()
@click.argument("lut_file", type=click.Path(dir_okay=False))
@click.option("--format", "fmt", type=click.Choice(list(FORMATS)), required=True, help=_HELP)
@click.option("-o", "--output", type=click.Path(dir_okay=False),
              help="File to write (default: LUT_FILE's name with the format's extension).")
@click.option("--unit", type=click.Choice(list(LENGTH_UNITS)), default="m", show_default=True,
              help="Length unit of the csv and vrui files (Vrui's calibrator works in the tracker's own unit).")
@click.option("--force", is_flag=True, help="Replace OUTPUT if it exists.")
def export(lut_file, fmt, output, unit, force):
    """Write LUT_FILE in another format; docs/export.md says what each holds and which direction it maps."""
    path = Path(output) if output else Path(lut_file).with_suffix(FORMATS[fmt][1])
    check_output(path, force, {"LUT_FILE": lut_file})
    table = lut.read(lut_file)
    written = export_table(table, fmt, path, unit=unit, overwrite=force)
    click.echo(f"wrote {written} ({fmt}; {table.grid.shape[0]}x{table.grid.shape[1]}x{table.grid.shape[2]} nodes, "
               f"{table.valid.sum()} mapped)")
