"""``ivc report SESSION LUT [CHECKFILE] -o DIR``: figures and one self-contained HTML page."""

from __future__ import annotations

from pathlib import Path

import click

from ivc import lut
from ivc import session as session_io
from ivc.cli.paths import refuse_inputs_as_outputs
from ivc.cli.progress import StageBars
from ivc.files import file_digest
from ivc.report import REPORT_FILES, build_report
from ivc.report.compute import THIN_SAMPLES


@click.command()
@click.argument("session_file", type=click.Path(dir_okay=False))
@click.argument("lut_file", type=click.Path(dir_okay=False))
@click.argument("check_file", type=click.Path(dir_okay=False), required=False)
@click.option("-o", "--output", "directory", type=click.Path(file_okay=False), required=True,
              help="Directory for report.html, report.json and the PNG figures (made if missing).")
@click.option("--step", default="check", show_default=True,
              help="Step holding the check poses (of CHECK_FILE, else of SESSION_FILE).")
@click.option("--thin", type=click.IntRange(1), default=THIN_SAMPLES, show_default=True,
              help="A mapped cell with fewer kept wand samples than this is marked thin.")
@click.option("--max-frames", type=click.IntRange(1),
              help="Solve at most this many sweep frames, every k-th beyond (default: "
              "as the table was fitted).")
@click.option("--force", is_flag=True, help="Replace an earlier report in the directory.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def report(session_file, lut_file, check_file, directory, step, thin, max_frames, force, quiet):
    """Report on LUT_FILE fitted from SESSION_FILE: field, coverage, cube, Λ, and accuracy on check poses.

    The check poses (with their truth) come from CHECK_FILE, or from SESSION_FILE's own
    check step. Figures that need truth say so on the page when there is none. A
    SESSION_FILE without the mapping steps (a check recording) gives the field and the
    accuracy sections only.
    """
    if max_frames is not None and max_frames < 1:
        raise click.BadParameter("must be at least 1", param_hint="--max-frames")
    inputs = {"SESSION_FILE": session_file, "LUT_FILE": lut_file, "CHECK_FILE": check_file}
    refuse_inputs_as_outputs({"--output": directory}, inputs)
    refuse_inputs_as_outputs({f"--output's {name}": Path(directory) / name for name in REPORT_FILES}, inputs)
    table = lut.read(lut_file)
    data = session_io.read(session_file)
    check = session_io.read(check_file) if check_file else None
    names = {"session": str(session_file), "lut": str(lut_file), "session_sha256": file_digest(session_file)}
    if check_file:
        names["check"] = str(check_file)
    with StageBars(disable=quiet) as bars:
        result = build_report(data, table, directory, check=check, step=step, thin=thin, max_frames=max_frames,
                              overwrite=force, names=names, progress=bars)
    for reason in result.numbers["warnings"]:
        click.echo(f"note: {reason}", err=True)
    by_reason: dict[str, list[str]] = {}
    for name, reason in result.missing.items():
        by_reason.setdefault(reason, []).append(name)
    for reason, figure_names in by_reason.items():
        click.echo(f"not drawn: {', '.join(figure_names)}: {reason}", err=True)
    box = result.numbers.get("box")
    if box is not None:
        click.echo(f"working volume: {100 * box['fraction']:.1f} % of the declared {box['box_litres']:.0f} litres "
                   f"mapped ({box['mapped_litres']:.1f} litres)")
    regions = result.numbers.get("sweep_regions") or []
    if len(regions) > 1:  # extension sweeps: the region each one maps
        for row in regions:
            share = (f", {100 * row['box_share_reached']:.1f} % of the working volume"
                     if "box_share_reached" in row else "")
            click.echo(f"  {row['name']}: {row['frames_kept']:,} of {row['frames_solved']:,} solved frames kept, "
                       f"{row['mapped_litres_reached']:.1f} mapped litres reached "
                       f"({row['mapped_litres_reached_by_it_alone']:.1f} by it alone){share}")
    figures = sum(1 for f in result.files if f.suffix == ".png")
    click.echo(f"wrote {result.html} ({figures} figures embedded) and report.json in {Path(directory)}")
