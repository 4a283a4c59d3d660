"""``ivc fixtures SESSION``: the fixture calibration report; ``ivc fixtures print``: a printable cube or wand."""

from __future__ import annotations

import json

import click
from tqdm import tqdm

from ivc import session as session_io
from ivc.cli.options import POSITIVE, solver_option
from ivc.cli.progress import ON_TERMINAL
from ivc.cli.tracker import tracker_option, with_tracker
from ivc.fixtures import VERTEX_CHOICES
from ivc.fixtures.build_check import check_session
from ivc.fixtures.geometry import load_geometries
from ivc.fixtures.interpolant import INTERPOLANTS
from ivc.fixtures.mapping import Gates
from ivc.fixtures.measurement import PoseInput, measurement_of
from ivc.pose import METHODS


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


class _FixturesGroup(click.Group):
    """``ivc fixtures SESSION [OPTIONS]`` (the report, as before) beside ``ivc fixtures print ...``: an
    argument that is not a sub-command's name goes to ``report``."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in ctx.help_option_names:
            args = ["report", *args]
        elif not args:
            args = ["report"]
        return super().parse_args(ctx, args)


@click.group(cls=_FixturesGroup)
def fixtures():
    """The fixture calibration report of a session (`ivc fixtures SESSION`, the same as `ivc fixtures report
    SESSION`), or a printable cube or wand and its geometry file (`ivc fixtures print cube|wand -o PART.stl`)."""


@fixtures.command("report")
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
@solver_option("For a session of reported poses only: the tracker's own pose solver (docs/lut.md).",
               dest="tracker_solver", default="closed-form", show_default=True)
@click.option("--geometry", "geometry_files", multiple=True, type=click.Path(dir_okay=False),
              help="The printed cube's and/or wand's geometry file (repeat for both): check the calibrated "
                   "sensors against it; the cube's is the ideal cube of --vertices ideal (docs/printing.md).")
@tracker_option
def report(session_file, vertices, interpolant, method, max_residual, max_error_mm, compare_cubes, as_json,
           tracker_solver, geometry_files, tracker_file):
    """Calibrate the cube and wand of SESSION_FILE, solve the sweep, and report what a map would be built from.

    A session of reported poses only (no signals) goes through the pose path: the cube's field fitted
    through the tracker model, sensor 0 traced back into the cube by inverting it (docs/fixtures.md)."""
    geometries = load_geometries(geometry_files)
    data = with_tracker(session_io.read(session_file), tracker_file)
    checks = check_session(data, geometries)
    nominal = geometries["cube"].in_declared_frame()[0] if "cube" in geometries else None
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
        report = measurement.fixture_report(data, vertices, progress=bar.update, nominal=nominal)
    if geometry_files:
        report["build_checks"] = [check.to_dict() for check in checks]
    click.echo(json.dumps(report, indent=2) if as_json else "\n\n".join([render(report)]
                                                                         + [check.render() for check in checks]))


_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "in": 0.0254}


class Length(click.ParamType):
    """A positive length: ``50.8mm``, ``2in``, ``5.08cm``, ``0.0508m``, or a bare number of millimetres; metres."""

    name = "LENGTH"

    def convert(self, value, param, ctx):
        if isinstance(value, float):
            return value
        text = str(value).strip().lower()
        unit = next((u for u in sorted(_UNITS, key=len, reverse=True) if text.endswith(u)), None)
        try:
            number = float(text[: -len(unit)] if unit else text)
        except ValueError:
            self.fail(f"{value!r}: give a length such as 50.8mm, 2in or 5.08cm (a bare number is mm)", param, ctx)
        if not number > 0:
            self.fail(f"{value!r}: must be positive", param, ctx)
        return number * _UNITS[unit or "mm"]


LENGTH = Length()


@fixtures.command("print")
@click.argument("kind", type=click.Choice(["cube", "wand"]))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="The part: PART.stl or PART.3mf.")
@click.option("--sensor", default="liberty-rx2", show_default=True,
              help="Sensor model: liberty-rx2, liberty-micro, ndi-8mm, aurora-6dof, aurora-5dof, or "
                   "custom:LxW (a tube) / custom:LxWxH (a box), in mm.")
@click.option("--edge", type=LENGTH, default="50.8mm", show_default=True, help="Cube: distance between sensors.")
@click.option("--sensors", type=click.IntRange(2, 64), default=8, show_default=True, help="Wand: number of sensors.")
@click.option("--pitch", type=LENGTH, help="Wand: distance between sensors (default 25.4mm, or the smallest that "
              "fits the sensor).")
@click.option("--clearance", type=LENGTH, default="0.2mm", show_default=True,
              help="Gap round each sensor in its pocket (a printer's tolerance).")
@click.option("--wall", type=LENGTH, default="3mm", show_default=True, help="Wall round the pockets (>= 1.5mm).")
@click.option("--geometry", "geometry_path", type=click.Path(dir_okay=False),
              help="Geometry file to write (default: PART.json).")
@click.option("--preview", "preview_path", type=click.Path(dir_okay=False), help="PNG preview (default: PART.png).")
@click.option("--force", is_flag=True, help="Replace files that exist.")
def print_part(kind, output, sensor, edge, sensors, pitch, clearance, wall, geometry_path, preview_path, force):
    """Write a printable cube or wand (KIND), its geometry file and a PNG preview (docs/printing.md).

    Needs manifold3d: pip install 'ivc[print]'."""
    from ivc.fixtures.geometry import PartOptions
    from ivc.fixtures.printing import print_fixture

    part, paths = print_fixture(kind, output, sensor=sensor, edge=edge, sensors=sensors, pitch=pitch,
                                options=PartOptions(clearance=clearance, wall=wall), geometry_path=geometry_path,
                                preview_path=preview_path, force=force)
    g = part.geometry
    size = (f"edge {1000 * g.parameters['edge']:.2f} mm" if kind == "cube"
            else f"{g.n_sensors} sensors at {1000 * g.parameters['pitch']:.2f} mm")
    if kind == "wand" and pitch is None and abs(g.parameters["pitch"] - 0.0254) > 1e-9:
        click.echo(f"note: {g.sensor.name} does not fit at 25.4 mm; pitch {1000 * g.parameters['pitch']:.1f} mm "
                   "(the smallest with 1.5 mm walls)", err=True)
    low, high = 1000 * g.extent
    click.echo(f"{kind} for {g.sensor.name}, {size}: {high[0] - low[0]:.1f} x {high[1] - low[1]:.1f} x "
               f"{high[2] - low[2]:.1f} mm, {1e6 * part.assembled.volume:.1f} cm3 of plastic")
    click.echo(f"wrote {paths[0]} (print as laid out: no supports), {paths[1]} (geometry), {paths[2]} (preview)")
