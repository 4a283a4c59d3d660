"""``ivc fit SESSION -o LUT``: the room's secondary-field look-up table."""

from __future__ import annotations

import json
import time

import click
import numpy as np

from ivc import lut
from ivc import session as session_io
from ivc.cli.options import POSITIVE, solver_option
from ivc.cli.paths import check_output
from ivc.cli.progress import StageBars
from ivc.cli.tracker import tracker_option, with_tracker
from ivc.lut.options import FitOptions


def parse_grid(value: str | None) -> dict:
    """``--grid``: ``SPACING`` or ``X0,Y0,Z0:NX,NY,NZ:SPACING`` (millimetres; origin = minimum corner)."""
    if value is None:
        return {}
    try:
        parts = value.split(":")
        if len(parts) == 1:
            return {"spacing": float(parts[0]) / 1000}
        if len(parts) == 3:
            origin = tuple(float(v) / 1000 for v in parts[0].split(","))
            shape = tuple(int(v) for v in parts[1].split(","))
            if len(origin) == 3 and len(shape) == 3 and min(shape) >= 2:
                return {"origin": origin, "shape": shape, "spacing": float(parts[2]) / 1000}
    except ValueError:
        pass
    raise click.BadParameter("use SPACING or X0,Y0,Z0:NX,NY,NZ:SPACING, in millimetres (e.g. 38.1 or "
                             "300,-200,-200:12,12,12:38.1)", param_hint="--grid")


def _cv_text(report, scored: str) -> str:
    """The cross-validation score in words, or that there was none: nothing to choose (a single damping given) or
    nothing to hold out (data within one block of frames)."""
    if report.cv_rms_mm is None:
        return "no cross-validation score (the model was given, or the data too few to hold any out)"
    return f"{report.cv_folds}-fold cross-validation RMS {report.cv_rms_mm:.4f} mm ({scored})"


def render_fit(table: lut.LookupTable, seconds: float | None = None) -> str:
    report, grid = table.report, table.grid
    samples, frames = report.samples, report.frames
    lines = [f"Sweep: {frames.used} of {frames.recorded} frames used (every {frames.stride}); "
             f"{samples.kept} of {samples.total} wand samples kept"]
    for reason, count in samples.dropped.items():
        if count:
            lines.append(f"  dropped {count:>8}: {reason}")
    reported = report.reported_poses
    if reported is not None:
        lines.append(f"From reported poses alone (tracker solver {reported.tracker_solver}): cube field degree "
                     f"{reported.cube_degree}, vertex residual {reported.vertex_position_rms_mm:.4f} mm / "
                     f"{reported.vertex_orientation_rms_mrad:.4f} mrad RMS")
        scored = "pose-equivalent, the pairs' field samples" if report.rounds else "reported-pose residual"
        lines.append(f"Fit: {report.method} through the tracker model, {report.model_text()}; "
                     f"{_cv_text(report, scored)}")
    else:
        lines.append(f"Fit: {report.method}, {report.model_text()}; {_cv_text(report, 'pose-equivalent')}")
    calibration = table.fit.get("self_calibration")
    if calibration:
        rms = calibration["rms_mm_by_iteration"]
        lines.append(f"  self-calibration: the wand's poses and the field fitted together on {calibration['frames']} "
                     f"frames ({len(rms) - 1} steps, residual {rms[0]:.3f} -> {rms[-1]:.3f} mm RMS); sensor 0 moved "
                     f"{calibration['sensor0_moved_mm'].get('p50', float('nan')):.3f} mm (median) from its pose "
                     "traced through the cube")
    if report.outliers_downweighted:
        lines.append(f"  {report.outliers_downweighted} samples down-weighted as outliers (Huber)")
    if table.fit.get("model_choice"):  # the adaptive fit says which model the cross-validation chose, and why
        lines.append(f"  model: {table.fit['model_choice']}")
    if table.fit.get("residual_structure"):
        lines.append(f"  residual structure: {table.fit['residual_structure']['advice']}")
    for step in report.refinement:
        lines.append(f"  refinement {step.iteration}: {step.frames_converged} frames re-solved as rigid "
                     f"wands, sensor 0 moved {step.sensor0_moved_median_mm:.4f} mm (median), map changed "
                     f"{step.map_change_mm:.4f} mm, CV {step.cv_rms_mm:.4f} mm")
    for step in report.rounds:
        change = "" if step.map_change_mm is None else f", map changed {step.map_change_mm:.4f} mm"
        solved = ", ".join(f"{name} {n}" for name, n in step.frames_solved.items())
        lines.append(f"  round {step.iteration}: {step.samples} samples, {step.mapped_litres:.1f} litres "
                     f"mapped{change}; frames solved: {solved}")
    if report.extension_sweeps_ignored:
        lines.append(f"  warning: {', '.join(report.extension_sweeps_ignored)} not used: a map from reported poses "
                     "alone covers the wand's reach around the cube (extension sweeps are mapped from signals only); "
                     "poses beyond it are flagged as outside the mapped volume, and a pose truly beyond it can be "
                     "reported, and trusted, where a mapped pose would be (docs/trust.md)")
    for name in report.never_touched_mapped_region:
        lines.append(f"  warning: {name} never touched the mapped region (no frame had two sensors in it): "
                     "record it again, starting with the wand's tip near the cube")
    for row in report.error_by_distance:
        lines.append(f"  estimated error {row['from_mm']:.0f}-{row['to_mm']:.0f} mm from the cube: "
                     f"{row['error_p50_mm']:.3f} mm median, {row['error_p95_mm']:.3f} mm p95 "
                     f"({row['samples']} samples)")
    if report.refinement:
        kept = report.kept_refinement
        lines.append(f"  refinement stopped: {report.refinement_stopped or 'done'}; kept "
                     + (f"refinement {kept}" if kept else "the first fit") + " (lowest CV)")
    extent = (grid.origin, grid.origin + grid.spacing * (np.array(grid.shape) - 1))
    lines.append(f"Grid: {grid.shape[0]} x {grid.shape[1]} x {grid.shape[2]} nodes at {1000 * grid.spacing:.1f} mm "
                 f"from ({', '.join(f'{1000 * v:.1f}' for v in extent[0])}) to "
                 f"({', '.join(f'{1000 * v:.1f}' for v in extent[1])}) mm; {report.valid_nodes} nodes mapped "
                 f"(support >= {report.min_support} samples), "
                 f"{int((table.field().valid_cells).sum()) * (1000 * grid.spacing) ** 3 / 1e6:.1f} litres mapped")
    noise = report.signal_noise
    if noise:
        source = " from the reported poses" if noise.get("source") == "reported poses" else ""
        lines.append(f"Signal noise: {noise['sigma']:.3g} per entry, measured{source} on {', '.join(noise['steps'])} "
                     f"({noise['pairs']} frame pairs; per-sensor spread {noise['spread']:.2f}x): `ivc correct` "
                     "predicts each pose's precision from it and flags those over 0.8 mm RMS (docs/trust.md)")
    error = report.map_error
    if error:
        lines.append(f"Map error: {error['position_mm']:.4f} mm / {error['orientation_mrad']:.4f} mrad RMS in the "
                     "reported pose; added to each pose's predicted precision")
        if error.get("excess_position_mm"):
            cause = ("the wand's poses are off even after the self-calibration (check the wand calibration, "
                     "and that the sweep covers the room)" if calibration else
                     "sensor 0's poses traced through the cube's 8 vertex poses are off in this room (fit with "
                     "--refine, the default, to self-calibrate them)")
            lines.append(
                f"  warning: the sweep's samples disagree with the map {error['disagreement']:.1f} times more than "
                f"the tracker's noise explains (median): {cause}, and how far off the corrections are ivc cannot "
                "tell better than the "
                f"samples' spread about the map, {error['excess_position_mm']:.2f} mm RMS. Poses predicted worse "
                "than the precision limit are flagged (16). Record the session with signals if the tracker gives "
                "them, or survey the cube at a second placement (docs/trust.md)")
    if seconds is not None:
        lines.append(f"Done in {seconds:.1f} s")
    return "\n".join(lines)


@click.command()
@click.argument("session_file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Look-up table file to write.")
@click.option("--method", type=click.Choice(lut.METHODS), default="harmonic", show_default=True,
              help="harmonic: curl/div-free solid-harmonic fit; poly: Himberg 2010's local polynomial regression; "
              "adaptive: cross-validation chooses the expansion or expansion + equivalent dipoles (strong rooms).")
@click.option("--grid", "grid_spec", help="SPACING, or X0,Y0,Z0:NX,NY,NZ:SPACING, in mm (default: 38.1 mm around "
              "the data with a one-cell margin).")
@click.option("--degree", type=click.IntRange(1, 40),
              help="harmonic: fixed degree (default: cross-validated); poly: degree (2); adaptive: the "
              "expansion's degree beside the dipoles (8).")
@click.option("--refine/--no-refine", default=FitOptions.refine, show_default=True,
              help="Re-solve the wand frames as rigid bodies against the map and refit while the cross-validation "
              "score improves (docs/lut.md, Refinement); from reported poses alone, fit the field and the wand's "
              "poses together first (docs/lut.md, Pose-only trackers, step 5).")
@click.option("--max-refinements", type=click.IntRange(0, 100), default=FitOptions.max_refinements, show_default=True)
@click.option("--max-frames", type=click.IntRange(1), default=FitOptions.max_frames, show_default=True,
              help="Decimate the sweep to at most this many frames.")
@click.option("--min-support", type=click.IntRange(1), default=FitOptions.min_support, show_default=True,
              help="Samples needed around a node for it to count as mapped.")
@click.option("--max-residual", type=POSITIVE, default=FitOptions.max_residual, show_default=True,
              help="Gate: largest rms(Λ)/rms(S) of sensor 0's solve in the cube.")
@click.option("--max-error-mm", type=POSITIVE, default=1000 * FitOptions.max_error, show_default=True,
              help="Gate: largest estimated sample error (eq. 101), mm.")
@solver_option("A session of reported poses only (no signals): the tracker's own pose solver, whose model the map "
               "is fitted through.", dest="tracker", default="closed-form", show_default=True)
@click.option("--force", is_flag=True, help="Replace OUTPUT if it exists.")
@click.option("--json", "as_json", is_flag=True, help="Print the fit report as JSON.")
@tracker_option
def fit(session_file, output, method, grid_spec, degree, refine, max_refinements, max_frames, min_support,
        max_residual, max_error_mm, tracker, force, as_json, tracker_file):
    """Fit the secondary-field look-up table of SESSION_FILE and write it to OUTPUT."""
    check_output(output, force, {"SESSION_FILE": session_file})
    if degree is not None and method == "sources":
        raise click.UsageError("--degree is for the harmonic and poly fits; equivalent sources choose their "
                               "damping by cross-validation")
    fitter = lut.make_fitter(method, **({} if degree is None else {"degree": degree}))
    options = FitOptions(fitter=fitter, refine=refine, max_refinements=max_refinements,
                         max_frames=max_frames, min_support=min_support, max_residual=max_residual,
                         max_error=max_error_mm / 1000, **parse_grid(grid_spec))
    data = with_tracker(session_io.read(session_file), tracker_file)
    start = time.perf_counter()
    with StageBars("sample", disable=as_json) as bars:
        table = lut.fit_lut(data, options, source=session_file, progress=bars, tracker=tracker)
    lut.write(table, output, overwrite=force)
    seconds = time.perf_counter() - start
    report = table.report
    click.echo(json.dumps(report.to_dict(), indent=2) if as_json else render_fit(table, seconds) + f"\nwrote {output}")
