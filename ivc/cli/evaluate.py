"""``ivc evaluate LUT CHECKFILE``: corrected against true poses, in the layout of Himberg 2010's Table 24."""

from __future__ import annotations

import json

import click

from ivc import lut
from ivc import session as session_io
from ivc.app.inputs import RECORDING, SESSION, TABLE, expect_kind, refuse_corrected
from ivc.cli.options import POSITIVE, solver_option
from ivc.cli.tracker import tracker_option, with_tracker
from ivc.correct.evaluate import evaluate as evaluate_table
from ivc.correct.measured import corrector_for
from ivc.correct.solver import MAX_RESIDUAL
from ivc.fixtures.measurement import PoseInput, SignalInput, measurement_of
from ivc.table.grid import INTERPOLATIONS

_COLUMNS = ("p25", "p50", "p75", "p95", "p99", "max")


def _row(label: str, values: dict, unit: str) -> str:
    if not values:
        return f"  {label:<30}{'(no samples)':>54}"
    return f"  {label:<30}" + "".join(f"{values[k]:>9.2f}" for k in _COLUMNS) + f"  {unit}"


def render_table(report: dict) -> str:
    flagged = ", ".join(f"{n} {k}" for k, n in report["flagged"].items() if n) or "none"
    lines = [f"Check poses: {report['samples']}"
             + (" (reported poses only)" if report.get("input") == "reported poses" else "")
             + f"; corrected and trusted: {report['corrected']} (flagged: {flagged})",
             f"IVC errors against {report['frame']}"
             + (f"; declared cube pose off by {report['placement_error_mm']:.2f} mm at the check poses"
                if "placement_error_mm" in report else ""),
             "",
             f"  {'':<30}" + "".join(f"{h:>9}" for h in ("25%", "50%", "75%", "95%", "99%", "max")),
             _row("IVC position", report["ivc"]["position_mm"], "mm"),
             _row("IVC orientation", report["ivc"]["orientation_mrad"], "mrad")]
    if report["ivc"] is not report["ivc_raw"] and "placement_error_mm" in report:
        lines += [_row("IVC position, raw truth", report["ivc_raw"]["position_mm"], "mm"),
                  _row("IVC orientation, raw truth", report["ivc_raw"]["orientation_mrad"], "mrad")]
    if "ivc_aligned" in report:
        lines += [_row("IVC position, rigid fit", report["ivc_aligned"]["position_mm"], "mm"),
                  _row("IVC orientation, rigid fit", report["ivc_aligned"]["orientation_mrad"], "mrad")]
    if "predicted_precision" in report:
        lines.append(_row("predicted precision", report["predicted_precision"]["position_mm"], "mm"))
    source = "reported" if report.get("input") == "reported poses" else "dipole"
    lines += [_row(f"{source} position (uncorrected)", report["dipole"]["position_mm"], "mm"),
              _row(f"{source} orientation", report["dipole"]["orientation_mrad"], "mrad")]
    if "predicted_precision" in report:
        ratio = report["predicted_precision"]
        lines += ["", f"error / predicted precision: {ratio['error_over_predicted_median']:.2f} median, "
                      f"{ratio['error_over_predicted_p95']:.2f} p95 (errors that are the tracker's noise alone: "
                      "0.7-0.9 and 1.6-2.0; above: the map adds error the prediction does not hold)"]
    return "\n".join(lines)


@click.command()
@click.argument("lut_file", type=click.Path(dir_okay=False))
@click.argument("check_file", type=click.Path(dir_okay=False))
@click.option("--step", default="check", show_default=True, help="Step of CHECK_FILE holding the check poses.")
@click.option("--interpolation", type=click.Choice(INTERPOLATIONS), default="cubic", show_default=True,
              help="Between grid nodes: Catmull-Rom cubic, or trilinear (Himberg 2010's).")
@click.option("--max-residual", type=POSITIVE, default=None,
              help="Flag corrections whose rms(M − T S)/rms(S) exceeds this (default: a limit per pose, a multiple "
              "of the residual the table's cross-validated model error and the signal noise explain there; "
              f"{MAX_RESIDUAL:g} for a table that records neither).")
@solver_option("Check poses reported only: the tracker's own pose solver (default: the one the table was fitted "
               "for, else closed-form).")
@click.option("--json", "as_json", is_flag=True, help="Print the table as JSON.")
@click.option("--allow-corrected", is_flag=True, help="Evaluate the reported poses of a CHECK_FILE that is ivc's "
              "corrected output (refused otherwise: they would be corrected twice).")
@tracker_option
def evaluate(lut_file, check_file, step, interpolation, max_residual, solver, as_json, allow_corrected, tracker_file):
    """Correct the check poses of CHECK_FILE with LUT_FILE and compare with their truth (Himberg 2010's Table 24)."""
    expect_kind(lut_file, (TABLE,), "LUT_FILE")
    kind = expect_kind(check_file, (SESSION, RECORDING), "CHECK_FILE")
    if kind == RECORDING or session_io.is_recording_csv(check_file):
        raise click.UsageError(f"{check_file}: a recording CSV holds no true poses; evaluate a session .h5 with "
                               "/truth/check (a simulation or a precision rig), or correct the CSV with `ivc correct`")
    table = lut.read(lut_file)
    check = session_io.read(check_file)
    if tracker_file is not None and step in check.steps:
        check = with_tracker(check, tracker_file, [step])
    measurement = measurement_of(check.steps[step]) if step in check.steps else SignalInput()
    if isinstance(measurement, PoseInput):  # the reported poses are corrected: refuse ivc's corrected ones
        refuse_corrected(check_file, allow_corrected, "CHECK_FILE", kind)
        options = {"solver": solver}
    else:  # the tracker's noise, when the table's fit measured it, gives each pose's predicted precision
        options = {"max_residual": max_residual, "precision": table.signal_noise is not None}
    corrector = corrector_for(measurement, table, check.hemisphere, interpolation, **options)
    report = evaluate_table(corrector, check, step)
    click.echo(json.dumps(report, indent=2) if as_json else render_table(report))
