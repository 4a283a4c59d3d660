"""``ivc fixtures SESSION``: the fixture calibration report."""

from __future__ import annotations

import json

import click
from tqdm import tqdm

from ivc import session as session_io
from ivc.cli.options import POSITIVE
from ivc.cli.progress import ON_TERMINAL
from ivc.cli.tracker import tracker_option, with_tracker
from ivc.fixtures import VERTEX_CHOICES
from ivc.fixtures.interpolant import INTERPOLANTS
from ivc.fixtures.mapping import Gates
from ivc.fixtures.measurement import PoseInput, measurement_of
from ivc.pose import METHODS
from ivc.pose.tracker_solver import SOLVERS


def _row(label: str, values: dict, unit: str) -> str:
    if not values:
        return f"  {label:<34} (no samples)"
    cells = "".join(f"{values[k]:>9.3f}" for k in ("p25", "p50", "p75", "p95", "p99", "max"))
    return f"  {label:<34}{cells}  {unit}"


def render(report: dict) -> str:
    cube, wand, sweep, samples = report["cube"], report["wand"], report["sweep"], report["samples"]
    lines = [
        f"Interpolation cube (vertices: {cube['vertices']}, {cube['interpolant']} interpolant); "
        f"fitted perfect cube edge {cube['fitted_edge_mm']:.2f} mm",
        "  sensor   residual x      y      z    |r| mm   frames   G at vertex (% primary) +- s.e.",
    ]
    pose_only = report.get("input") == "reported poses"
    if pose_only:
        lines[0] = (f"Interpolation cube (vertices: {cube['vertices']}; from reported poses, {cube['interpolant']}, "
                    f"{report['tracker_solver']} tracker); fitted perfect cube edge {cube['fitted_edge_mm']:.2f} mm")
        lines[1] = ("  sensor   pose residual x y z (mm)    |r| mm   orient. mrad   frames   G at vertex (% primary)")
    for n in range(8):
        rx, ry, rz = cube["residuals_mm"][n]
        if pose_only:
            lines.append(f"  {n:>6} {rx:>10.3f} {ry:>6.3f} {rz:>6.3f} {cube['residual_norm_mm'][n]:>10.3f} "
                         f"{cube['orientation_residual_mrad'][n]:>12.3f} {cube['frames_averaged'][n]:>8}   "
                         f"{cube['vertex_field_percent_of_primary'][n]:>8.2f}")
            continue
        lines.append(f"  {n:>6} {rx:>10.3f} {ry:>6.3f} {rz:>6.3f} {cube['residual_norm_mm'][n]:>8.3f} "
                     f"{cube['frames_averaged'][n]:>8}   {cube['vertex_field_percent_of_primary'][n]:>8.2f} "
                     f"+- {cube['vertex_field_standard_error_percent'][n]:.4f}")
    lines.append("")
    lines.append(f"Mapping wand: {wand['sensors']} sensors, lever arms (mm) "
                 + ", ".join(f"{a:.1f}" for a in wand["lever_arms_mm"]))
    lines.append("")
    residual = sweep["residual_relative"]
    lines.append(f"Sweep: {sweep['frames']} frames ({sweep['method']} solve); sensor 0 valid "
                 f"{100 * sweep['sensor0_valid_fraction']:.2f}%, converged {100 * sweep['converged_fraction']:.3f}%, "
                 f"inside the cube {100 * sweep['inside_fraction']:.2f}%, median {sweep['iterations_median']:.0f} "
                 "iterations")
    if residual:
        lines.append(f"  rms(Λ)/rms(S): median {residual['p50']:.2e}, 99% {residual['p99']:.2e}, "
                     f"max {residual['max']:.2e}")
    miss = sweep.get("inversion_miss_um")
    if miss:
        lines.append(f"  sensor 0's reported position reproduced to: median {miss['p50']:.2e} um, "
                     f"max {miss['max']:.2e} um")
    lines.append(f"Samples: {samples['kept']} of {samples['total']} kept"
                 + "".join(f"; {count} dropped: {reason}" for reason, count in samples["dropped"].items() if count))
    truth = report.get("truth")
    if truth:
        lines += ["", f"Against truth ({truth['frame']}; declared cube pose off by "
                      f"{truth['placement_error_mm']:.2f} mm, {truth['placement_error_mrad']:.2f} mrad):",
                  f"  {'':<34}{'25%':>9}{'50%':>9}{'75%':>9}{'95%':>9}{'99%':>9}{'max':>9}",
                  _row("sensor 0 position", truth["sensor0_position_mm"], "mm"),
                  _row("sensor 0 orientation", truth["sensor0_orientation_mrad"], "mrad"),
                  _row("sensor 0 position, raw vs truth", truth["sensor0_position_raw_mm"], "mm")]
        for n, values in enumerate(truth["sensors_position_mm"]):
            lines.append(_row(f"wand sensor {n} position", values, "mm"))
    choices = report.get("cube_choices")
    if choices:
        lines += ["", "Cube vertex choice (Himberg 2010's Table 22), farthest wand sensor position error, mm:"]
        for choice, values in choices.items():
            far = values["farthest_sensor_position_mm"]
            lines.append(f"  {choice:<10} median {far['p50']:.3f}  95% {far['p95']:.3f}  max {far['max']:.3f}")
    return "\n".join(lines)


@click.command()
@click.argument("session_file", type=click.Path(dir_okay=False))
@click.option("--vertices", type=click.Choice(VERTEX_CHOICES), default="averaged", show_default=True,
              help="Cube vertex positions: the sensors' averaged ones, the optimised perfect cube, or the ideal cube.")
@click.option("--interpolant", type=click.Choice(list(INTERPOLANTS)), default="harmonic", show_default=True,
              help="Field inside the cube: harmonic (curl/div-free, follows curvature) or trilinear (Himberg 2010's).")
@click.option("--method", type=click.Choice(METHODS), default="joint", show_default=True,
              help="Pose solve in the cube: joint 6-DOF, or Himberg 2010's two-stage (eq. 92 then 93).")
@click.option("--max-residual", type=POSITIVE, default=Gates.max_residual, show_default=True,
              help="Gate: largest rms(Λ)/rms(S) of sensor 0's solve.")
@click.option("--max-error-mm", type=POSITIVE, default=1000 * Gates.max_error, show_default=True,
              help="Gate: largest estimated sample error (eq. 101), mm.")
@click.option("--compare-cubes", type=click.IntRange(0), default=0,
              help="Also compare the cube vertex choices on this many frames.")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
@click.option("--tracker", "tracker_solver", type=click.Choice(SOLVERS),
              default="closed-form", show_default=True,
              help="For a session of reported poses only: the tracker's own pose solver (docs/lut.md).")
@tracker_option
def fixtures(session_file, vertices, interpolant, method, max_residual, max_error_mm, compare_cubes, as_json,
             tracker_solver, tracker_file):
    """Calibrate the cube and wand of SESSION_FILE, solve the sweep, and report what a map would be built from.

    A session of reported poses only (no signals) goes through the pose path: the cube's field fitted
    through the tracker model, sensor 0 traced back into the cube by inverting it (docs/fixtures.md)."""
    data = with_tracker(session_io.read(session_file), tracker_file)
    frames = data.steps["wand_sweep"].n_frames if "wand_sweep" in data.steps else 0
    gates = Gates(max_residual=max_residual, max_error=max_error_mm / 1000)
    measurement = measurement_of(data, solver=tracker_solver, gates=gates, method=method, interpolant=interpolant,
                                 compare_cubes=compare_cubes)
    if isinstance(measurement, PoseInput):
        ignored = [name for name, value, default in (("--interpolant", interpolant, "harmonic"),
                                                     ("--method", method, "joint"),
                                                     ("--compare-cubes", compare_cubes, 0))
                   if value != default]
        if ignored:
            raise click.UsageError(f"{', '.join(ignored)} apply to signals; {session_file} holds reported poses only")
    with tqdm(total=frames, desc="solving the sweep", unit="frame", leave=False,
              disable=True if as_json else ON_TERMINAL) as bar:
        report = measurement.fixture_report(data, vertices, progress=bar.update)
    click.echo(json.dumps(report, indent=2) if as_json else render(report))
