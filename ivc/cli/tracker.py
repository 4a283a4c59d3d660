"""``ivc tracker calibrate`` and ``ivc tracker check``: the tracker's own coil model (docs/tracker.md)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from ivc.app.inputs import RIG, expect_kind
from ivc.cli.paths import check_output
from ivc.cli.progress import ON_TERMINAL
from ivc.collect.ilemt import folder_sign_fixes, parse_sign_fix, read_ilemt, stack
from ivc.collect.rig_csv import read_rig_csv
from ivc.dipole.tracker import load_tracker, save_tracker
from ivc.pose.calibrate import calibrate as fit_tracker
from ivc.pose.tracker_check import beyond_calibration, check_tracker, fixtures_of
from ivc.session import Session


def _load(paths, carrier: str, compensate: bool, sign_fixes=()):
    """Points of ILEMT .dat files and rig CSVs (docs/tracker.md), stacked, and each point's file index.

    ``sign_fixes`` (``--sign-fix``) come first; a folder's options file adds its own after them.
    """
    parts = []
    for p in paths:
        kind = expect_kind(p, (RIG,), "the recording")  # a session, table or recording CSV is refused by name
        if kind == RIG or str(p).lower().endswith(".csv"):
            parts.append(read_rig_csv(p))
        else:
            fixes = tuple(sign_fixes) + folder_sign_fixes(Path(p).parent)
            S, J_so, J_st, _ = stack([read_ilemt(p, carrier=carrier, compensate=compensate, sign_fixes=fixes)])
            parts.append((S, J_so, J_st))
    for p, part in zip(paths, parts, strict=True):
        _unit_warning(p, part[2])
    S, J_so, J_st = (np.concatenate([part[k] for part in parts]) for k in range(3))
    index = np.concatenate([np.full(len(part[0]), k) for k, part in enumerate(parts)])
    return index, S, J_so, J_st


#: a rig's stage that moves the sensor at all moves it more than this (m); less is a length in another unit
MIN_STAGE_TRAVEL_M = 1e-3


def _unit_warning(path, J_st: np.ndarray) -> None:
    """Warn when a recording's stage positions move, but by less than a millimetre in all: metres in a file that
    reads millimetres (ILEMT's .dat, a rig CSV's x_mm columns), which the calibration cannot fit (its coil model
    comes out singular or its points a few mm from the source)."""
    travel = float(np.max(np.ptp(J_st[:, :3, 3], axis=0), initial=0.0))
    if 0.0 < travel < MIN_STAGE_TRAVEL_M:
        click.echo(f"WARNING: {Path(path).name}: its stage positions span {1e3 * travel:.3g} mm in all, where a "
                   "calibration rig moves the sensor by centimetres: are they in metres where the file reads "
                   "millimetres (an ILEMT .dat gives stage X Y Z in mm; a rig CSV names its unit x_mm or x)?",
                   err=True)


def _sign_findings(paths, index, S, J_so, J_st) -> list[dict]:
    """What :func:`ivc.pose.coil_signs.find_sign_flips` says of the recordings (JSON-ready)."""
    from ivc.pose.coil_signs import find_sign_flips

    if len(paths) < 2:
        return []
    return [{"recording": Path(paths[f.group]).name, "source_signs": [int(v) for v in f.signs],
             "reference": Path(paths[0]).name, "joint_residue_percent": 100 * f.joint,
             "flipped_residue_percent": 100 * f.flipped, "reference_residue_percent": 100 * f.reference}
            for f in find_sign_flips(S, J_so, J_st, index)]


def _sign_warning(findings: list[dict]) -> str:
    lines = []
    for f in findings:
        signs = ",".join(str(v) for v in f["source_signs"])
        stem = Path(f["recording"]).stem
        lines.append(f"WARNING: {f['recording']}: its source coil signs disagree with {f['reference']}'s: its residue "
                     f"in a joint fit is {f['joint_residue_percent']:.2f} %, {f['flipped_residue_percent']:.2f} % with "
                     f"source signs {signs}. If its phase reference was wrong, read it with "
                     f"--sign-fix '{stem}={signs}' (or a [[sign_fix]] in the folder's ivc-ilemt.toml).")
    return "\n".join(lines)


def render(title: str, report: dict) -> str:
    lines = [f"{title}: {report['points']} points; residue ‖C − C_pred‖_F / ‖C‖₂ "
             f"rms {report['residue_rms_percent']:.3f} %, max {report['residue_max_percent']:.3f} %"]
    for row in report["residue_by_range"]:
        lo, hi = row["range_mm"]
        lines.append(f"  range {lo:6.1f}-{hi:6.1f} mm  {row['points']:5d} points  residue rms "
                     f"{row['residue_rms_percent']:.3f} %")
    for key, label in (("pose", "pose error"), ("pose_uncorrected", "pose error without output correction")):
        if key in report:
            p = report[key]
            lines.append(f"  {label}: position rms {p['position_rms_mm']:.3f} mm (max {p['position_max_mm']:.3f}), "
                         f"orientation rms {p['angle_rms_deg']:.3f} deg (max {p['angle_max_deg']:.3f}); "
                         f"converged {100 * p['converged_fraction']:.1f} % (gate {p['residual_gate_percent']:.2f} %)")
    p = report.get("pose")
    if p and p["failed"]:
        where = ", ".join(f"{row['failed']}/{row['points']} at {row['range_mm'][0]:.0f}-{row['range_mm'][1]:.0f} mm"
                          for row in p["failed_by_range"])
        angles = ", ".join(f"{row['failed']}/{row['points']} at {row['angle_deg'][0]:.0f}-{row['angle_deg'][1]:.0f} "
                           "deg" for row in p["failed_by_off_axis_angle"])
        lines.append(f"  WARNING: {p['failed']} poses failed the model's residual gate (left out of the output "
                     f"correction): by range {where}; by off-axis angle {angles}")
    if p and p["converged_wrong"]:
        lines.append(f"  WARNING: {p['converged_wrong']} converged poses are more than 10 mm or 5 deg off the chain's")
    return "\n".join(lines)


@click.group()
def tracker() -> None:
    """Calibrate and check the tracker's own source and sensor model (gains, cross-talk, coil offsets).

    A research or custom tracker's signals are off the ideal dipole model by percent;
    the tracker file written here says how (docs/tracker.md).
    """


_carrier = click.option("--carrier", type=click.Choice(["high", "low"]), default="high", show_default=True,
                        help="Which ILEMT carrier's couplings to use.")
_compensation = click.option("--no-stage-compensation", is_flag=True,
                             help="Use the commanded stage poses as they are (without the stage's measured errors).")
_sign_fix = click.option("--sign-fix", "sign_fixes", multiple=True, metavar="PATTERN=sx,sy,sz[/tx,ty,tz]",
                         help="Negate coils of ILEMT files whose name matches PATTERN (a regular expression): signs "
                              "per source coil, optionally '/' and per sensor coil (repeatable; none by default; "
                              "a folder's ivc-ilemt.toml adds its own).")


@tracker.command()
@click.argument("recordings", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Tracker file to write (JSON).")
@click.option("--one-centre", is_flag=True, help="All coils at one centre each (no per-coil position offsets).")
@click.option("--bias", is_flag=True, help="Also fit a constant added signal (electronic pick-up).")
@click.option("--no-output-correction", is_flag=True,
              help="Do not fit the affine output correction of solved poses.")
@click.option("--source-motions", type=click.Choice(["exact", "free"]), default="exact", show_default=True,
              help="With several source fixturings: their nominal turns are exact, or each gets a fitted error.")
@click.option("--test", "tests", multiple=True, type=click.Path(exists=True, dir_okay=False),
              help="A held-out recording to score with the fitted model and fixtures (repeatable).")
@_carrier
@_compensation
@_sign_fix
@click.option("--no-sign-check", is_flag=True,
              help="Skip comparing the recordings' coil signs (a few one-centre fits per recording).")
@click.option("--force", is_flag=True, help="Replace OUTPUT if it exists.")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def calibrate(recordings, output, one_centre, bias, no_output_correction, source_motions, tests, carrier,
              no_stage_compensation, sign_fixes, no_sign_check, force, as_json):
    """Fit the tracker model to RECORDINGS and write it to OUTPUT.

    RECORDINGS are ILEMT .dat files, or rig CSVs of (known motion, signal) rows for any
    precision rig (docs/tracker.md).

    The unknown source, stage and sensor fixture transforms are fitted with the magnetics
    and stored in the tracker file, so that `ivc tracker check` can score other recordings
    made on the same rig.
    """
    output_path = check_output(output, force, {f"the recording {p}": p for p in (*recordings, *tests)})
    compensate = not no_stage_compensation
    fixes = tuple(parse_sign_fix(text) for text in sign_fixes)
    index, S, J_so, J_st = _load(recordings, carrier, compensate, fixes)
    findings = [] if no_sign_check else _sign_findings(recordings, index, S, J_so, J_st)
    start = time.perf_counter()
    with tqdm(desc="calibrating", unit="iteration", leave=False, disable=True if as_json else ON_TERMINAL) as bar:
        result = fit_tracker(S, J_so, J_st, offsets=not one_centre, bias=bias,
                             output_correction=not no_output_correction, source_motions=source_motions,
                             progress=lambda iteration, cost: bar.update(1))
    seconds = time.perf_counter() - start
    report = {"calibration": check_tracker(result.tracker, result.fixtures, S, J_so, J_st),
              "seconds": seconds, "iterations": result.iterations, "converged": result.converged,
              "sign_findings": findings}
    if tests:
        _, S_t, J_so_t, J_st_t = _load(tests, carrier, compensate, fixes)
        report["test"] = check_tracker(result.tracker, result.fixtures, S_t, J_so_t, J_st_t)
    result.tracker.calibration = {
        "model": "one centre" if one_centre else "per-coil offsets",
        "bias": bias,
        "source_motions": source_motions,
        "output_correction": not no_output_correction,
        "carrier": carrier,
        "stage_compensation": compensate,
        "sign_fixes": [list(fix) for fix in fixes],
        "recordings": [Path(p).name for p in recordings],
        "test_recordings": [Path(p).name for p in tests],
        "fixtures": result.fixtures.to_dict(),
        "parameter_sigma": result.parameter_sigma,
        "report": report,
    }
    save_tracker(result.tracker, output_path)
    if as_json:
        click.echo(json.dumps(report, indent=2))
        return
    click.echo(f"Fitted {'one-centre' if one_centre else 'per-coil-offset'} tracker model in {seconds:.1f} s "
               f"({result.iterations} iterations{'' if result.converged else ', NOT converged'}); wrote {output_path}")
    click.echo(render("Calibration points", report["calibration"]))
    if tests:
        click.echo(render("Held-out points", report["test"]))
    if findings:
        click.echo(_sign_warning(findings), err=True)


@tracker.command()
@click.argument("tracker_file", type=click.Path(exists=True, dir_okay=False))
@click.argument("recordings", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@_carrier
@_compensation
@_sign_fix
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def check(tracker_file, recordings, carrier, no_stage_compensation, sign_fixes, as_json):
    """Score TRACKER_FILE on RECORDINGS made on the rig it was calibrated on: residue and pose error."""
    model = load_tracker(tracker_file)
    fixtures = fixtures_of(model)
    fixes = tuple(parse_sign_fix(text) for text in sign_fixes)
    _, S, J_so, J_st = _load(recordings, carrier, not no_stage_compensation, fixes)
    report = check_tracker(model, fixtures, S, J_so, J_st)
    warning = beyond_calibration(model, report)
    if warning:
        report["warning"] = warning
    click.echo(json.dumps(report, indent=2) if as_json else render("Points", report))
    if warning:
        click.echo(f"WARNING: {warning}", err=True)


def tracker_option(command: Callable) -> Callable:
    """``--tracker-model FILE``: the device's coil model, applied to the signals a command reads (docs/tracker.md)."""
    return click.option("--tracker-model", "tracker_file", type=click.Path(exists=True, dir_okay=False),
                        help="The tracker's coil model (from `ivc tracker calibrate`): signals are brought to "
                             "ideal-dipole units before anything else.")(command)


def with_tracker(data: Session, tracker_file: str | None, steps: list[str] | None = None) -> Session:
    """``data`` (a Session) with ``tracker_file``'s model applied to its steps (all, or ``steps``); None: as is."""
    from ivc.collect.tracker_units import apply_tracker_file

    return apply_tracker_file(data, tracker_file, steps)
