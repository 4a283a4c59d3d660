"""``ivc export LUT --format F -o OUT``: the look-up table for tracker firmware, 3D Slicer, ParaView and Vrui."""

from __future__ import annotations

from pathlib import Path

import click

from ivc import lut
from ivc.cli.paths import check_output
from ivc.export import FORMATS, REPORTED_GRID_FORMATS, csv_sidecar, resolve_unit
from ivc.export import export as export_table
from ivc.units import LENGTH_UNITS

_HELP = "; ".join(f"{name}: {text}" for name, (_, _, text) in FORMATS.items())


@click.command()
@click.argument("lut_file", type=click.Path(dir_okay=False))
@click.option("--format", "fmt", type=click.Choice(list(FORMATS)), required=True, help=_HELP)
@click.option("-o", "--output", type=click.Path(dir_okay=False),
              help="File to write (default: LUT_FILE's name with the format's extension).")
@click.option("--unit", type=click.Choice(list(LENGTH_UNITS)),
              help="Length unit of the file: npz, csv, vti (default m); hdf5 is in m and slicer, slicer-itk, itk in "
              "mm only; vrui needs it: the tracker driver's unit (in for Vrui's Polhemus drivers).")
@click.option("--spacing", type=click.FloatRange(min=0.5, max=1000.0),
              help=f"Node spacing in mm of the grid over the reported region ({', '.join(REPORTED_GRID_FORMATS)}; "
              "default: the table's spacing / 8 for slicer-itk and itk, / 4 for vrui).")
@click.option("--force", is_flag=True, help="Replace OUTPUT if it exists.")
def export(lut_file, fmt, output, unit, spacing, force):
    """Write LUT_FILE in another format; docs/export.md says what each holds and which direction it maps."""
    if not Path(lut_file).name:  # '' or '/': no name to derive the default output from
        raise click.BadParameter(f"{lut_file!r} is not a file name: give the look-up table's .h5 file",
                                 param_hint="LUT_FILE")
    path = Path(output) if output else Path(lut_file).with_suffix(FORMATS[fmt][1])
    if fmt == "slicer-itk" and not output:
        path = Path(lut_file).with_name(Path(lut_file).stem + "_slicer.h5")  # LUT_FILE is .h5 itself
    elif fmt == "itk" and not output:
        path = Path(lut_file).with_name(Path(lut_file).stem + "_itk.h5")
    unit = resolve_unit(fmt, unit)
    if spacing is not None and fmt not in REPORTED_GRID_FORMATS:
        raise click.UsageError(f"--spacing applies to {', '.join(REPORTED_GRID_FORMATS)} only")
    check_output(path, force, {"LUT_FILE": lut_file})
    if fmt == "csv":
        check_output(csv_sidecar(path), force, {"LUT_FILE": lut_file}, "the CSV's JSON sidecar")
    table = lut.read(lut_file)
    written = export_table(table, fmt, path, unit=unit, overwrite=force,
                           spacing=None if spacing is None else spacing / 1000.0)
    also = f" and its grid and units in {csv_sidecar(written)}" if fmt == "csv" else ""
    if fmt in REPORTED_GRID_FORMATS:
        click.echo(f"wrote {written} ({fmt}, {unit}; a grid over the reported region, docs/export.md)")
    else:
        click.echo(f"wrote {written}{also} ({fmt}, {unit}; {table.grid.shape[0]}x{table.grid.shape[1]}x"
                   f"{table.grid.shape[2]} nodes, {table.valid.sum()} mapped)")
