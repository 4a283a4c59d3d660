"""The numbers behind ``ivc report``: field slices, coverage, sweep and check-pose errors.

Lengths are metres in the arrays and millimetres in the summaries; angles radians in the
arrays, milliradians in the summaries. Positions are in the frame of the *declared* cube
pose, the frame the table lives in (docs/math.md §5). Truth, where a session has it, is used
for evaluation only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ivc import dipole
from ivc.correct.evaluate import CheckErrors, check_errors, summarise
from ivc.correct.measured import corrector_for
from ivc.errors import InputError
from ivc.fixtures.cube import CUBE_BITS, NOMINAL_EDGE, declared_pose, placed_vertices
from ivc.fixtures.interpolant import INTERPOLANTS
from ivc.fixtures.mapping import FixtureModel, Gates, SweepMapping, map_sweep
from ivc.fixtures.measurement import PoseInput, measurement_of
from ivc.fixtures.report import SweepErrors, sweep_errors
from ivc.lut.coverage import box_coverage, box_points
from ivc.lut.joint import JointOptions, extension_part, extension_samples
from ivc.lut.options import FitOptions
from ivc.lut.support import MIN_SUPPORT
from ivc.session import Session, extension_steps, working_volume
from ivc.table.grid import GridField
from ivc.table.lookup import LookupTable
from ivc.truth import declared_frame_map, percentiles

#: horizontal slices drawn at most
MAX_SLICES = 6
#: interpolated points per grid cell along x and y in the field slices
OVERSAMPLE = 6
#: a mapped cell holding fewer wand samples than this is "thin" (by default)
THIN_SAMPLES = MIN_SUPPORT

Progress = Callable[[str, int], Callable[[int], None]]


def no_progress(description: str, total: int) -> Callable[[int], None]:
    return lambda n: None


@dataclass
class Slices:
    """Horizontal planes through the table at the mid-heights of its cell layers.

    ``z`` (L,) metres; ``x_edges`` (nx,), ``y_edges`` (ny,): the grid's node coordinates,
    which bound its cells; ``x``, ``y``: the fine sample coordinates of ``percent``
    (L, len(y), len(x)): |G| as % of the measured signal |f_D + G| (Frobenius norms,
    orientation-free), NaN outside the mapped volume. ``counts`` (L, nx-1, ny-1): kept
    wand samples per cell; ``mapped`` (L, nx-1, ny-1): cells whose eight nodes are valid
    (both the layers of :class:`ReportData`'s whole-grid arrays).
    """

    z: np.ndarray
    x_edges: np.ndarray
    y_edges: np.ndarray
    x: np.ndarray
    y: np.ndarray
    percent: np.ndarray
    counts: np.ndarray
    mapped: np.ndarray


@dataclass
class SweepView:
    """The sweep as solved for the report (first pass, before the fit's refinement)."""

    mapping: SweepMapping
    recorded: int  # sweep frames in the session
    stride: int  # every stride-th frame was solved
    errors: SweepErrors | None
    distance: np.ndarray  # (F, W) metres from the cube centre, solved positions
    gates: Gates


@dataclass
class SweepRegion:
    """Where one sweep's kept wand samples lie: the part of the volume that sweep maps.

    ``positions`` (N, 3) m, the table's frame; ``frames_recorded`` in the session, ``frames_solved``
    of them (every ``stride``-th), ``frames_kept``: solved frames that gave at least one sample."""

    name: str
    positions: np.ndarray
    frames_recorded: int
    frames_solved: int
    frames_kept: int
    stride: int


@dataclass
class CheckView:
    errors: CheckErrors
    distance: np.ndarray | None  # (F, N) metres from the cube centre, true positions (declared frame)
    source: str  # where the check poses came from


@dataclass
class ReportData:
    """What the report draws. Without the mapping steps (a check recording, say) ``model``,
    ``sweep`` and ``cell_counts`` are None and ``mapping_missing`` lists what the session lacks;
    the cube is then the ideal one at the declared pose, or None without a declared pose."""

    table: LookupTable
    model: FixtureModel | None
    slices: Slices
    sweep: SweepView | None
    check: CheckView | None
    check_missing: str | None  # why there is no check evaluation
    thin: int
    cube_vertices: np.ndarray | None  # (8, 3) m, declared frame: calibrated, else the ideal cube
    cell_counts: np.ndarray | None  # (nx-1, ny-1, nz-1) kept wand samples per grid cell
    mapped_cells: np.ndarray  # (nx-1, ny-1, nz-1) cells whose eight nodes are valid
    mapping_missing: tuple[str, ...] = ()
    box: dict | None = None  # the declared working volume's coverage (ivc.lut.coverage.box_coverage), if declared
    regions: list[SweepRegion] | None = None  # per sweep (the cube's first, then each extension sweep), with a sweep
    volume: tuple[np.ndarray, np.ndarray] | None = None  # the declared working volume (centre, size) m

    @property
    def cube_centre(self) -> np.ndarray | None:
        return None if self.cube_vertices is None else self.cube_vertices.mean(axis=0)

    @property
    def cube_half_diagonal(self) -> float | None:
        """The cube's centre-to-vertex distance (m)."""
        if self.cube_vertices is None:
            return None
        return float(np.linalg.norm(self.cube_vertices - self.cube_centre, axis=1).mean())


def percent_of_measured(field_values: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """100·|G| / |f_D + G| at each position (Frobenius norms of the 3x3 fields)."""
    measured = np.linalg.norm(dipole.field(positions) + field_values, axis=(-2, -1))
    return 100.0 * np.linalg.norm(field_values, axis=(-2, -1)) / measured


def cell_counts(table: LookupTable, positions: np.ndarray) -> np.ndarray:
    """Samples per grid cell (nx − 1, ny − 1, nz − 1) of ``positions`` (N, 3) m, source frame."""
    g = table.grid
    edges = [g.origin[a] + g.spacing * np.arange(g.shape[a]) for a in range(3)]
    counts, _ = np.histogramdd(positions, bins=edges)
    return counts.astype(np.int64)


def mapped_layers(mapped_cells: np.ndarray, keep: int | None = None) -> np.ndarray:
    """Up to MAX_SLICES cell layers (z) spread over those holding any mapped cell, with
    layer ``keep`` (the cube's) among them when it holds any."""
    filled = np.flatnonzero(mapped_cells.any(axis=(0, 1)))
    if len(filled) == 0:
        filled = np.arange(mapped_cells.shape[2])
    picks = filled[np.unique(np.round(np.linspace(0, len(filled) - 1, min(MAX_SLICES, len(filled)))).astype(int))]
    if keep is not None and keep in filled and keep not in picks:
        picks[np.argmin(np.abs(picks - keep))] = keep
    return np.sort(picks)


def slices(table: LookupTable, field: GridField, cell_counts: np.ndarray | None,
           cube_centre: np.ndarray | None = None) -> Slices:
    """The field and coverage slices (see :class:`Slices`) of the table's interpolated ``field`` and
    its per-cell sample counts (zero without them), one slice through ``cube_centre`` (m) if that
    layer is mapped."""
    if cell_counts is None:
        cell_counts = np.zeros(field.valid_cells.shape, dtype=np.int64)
    g = table.grid
    x_edges, y_edges, z_edges = (g.origin[a] + g.spacing * np.arange(g.shape[a]) for a in range(3))
    keep = None if cube_centre is None else int(np.floor((cube_centre[2] - g.origin[2]) / g.spacing))
    layers = mapped_layers(field.valid_cells, keep)
    z = z_edges[layers] + g.spacing / 2
    step = g.spacing / OVERSAMPLE
    x = np.arange(x_edges[0] + step / 2, x_edges[-1], step)
    y = np.arange(y_edges[0] + step / 2, y_edges[-1], step)
    points = np.stack(np.broadcast_arrays(x[None, None, :], y[None, :, None], z[:, None, None]), axis=-1)
    values, _, mapped = field.evaluate(points)
    percent = np.where(mapped, percent_of_measured(values, points), np.nan)
    return Slices(z, x_edges, y_edges, x, y, percent, np.moveaxis(cell_counts[:, :, layers], 2, 0),
                  np.moveaxis(field.valid_cells[:, :, layers], 2, 0))


def solve_sweep(session: Session, model: FixtureModel, table: LookupTable, cube_centre: np.ndarray,
                max_frames: int | None = None, progress: Progress = no_progress) -> SweepView:
    """Solve the sweep in the cube with the gates and the frames the table was fitted with: at most
    ``max_frames`` (default: the table's own setting, else ``ivc fit``'s default), every k-th beyond."""
    parameters = table.provenance.get("parameters", {})
    if max_frames is None:
        max_frames = int(parameters.get("max_frames") or FitOptions.max_frames)
    if max_frames < 1:
        raise InputError(f"max_frames = {max_frames}: solve at least one sweep frame")
    gates = Gates(max_residual=float(parameters.get("max_residual", Gates.max_residual)),
                  max_error=float(parameters.get("max_error", Gates.max_error)))
    recorded = session.steps["wand_sweep"].n_frames
    stride = max(1, -(-recorded // max_frames))
    if stride > 1:
        session = session.select_frames("wand_sweep", slice(None, None, stride))
    frames = session.steps["wand_sweep"].n_frames
    mapping = map_sweep(session, model, gates, progress=progress("solving the sweep in the cube", frames))
    distance = np.linalg.norm(mapping.positions - cube_centre, axis=-1)
    return SweepView(mapping, recorded, stride, sweep_errors(session, mapping), distance, gates)


def sweep_regions(session: Session, model: FixtureModel, table: LookupTable, field: GridField, sweep: SweepView,
                  progress: Progress = no_progress) -> list[SweepRegion]:
    """Where each sweep's samples lie: the cube sweep's kept samples as solved in the cube (``sweep``), then each
    extension sweep solved as a rigid wand against the table's ``field``, from its sensors the table maps, with
    the gates and the decimation the table was fitted with (its provenance and fit record; the joint fit's
    defaults otherwise). The joint fit solved its last round against the map before; against the final map
    about as many frames pass."""
    parameters = table.provenance.get("parameters", {})
    fitted = table.fit.get("extension_sweeps", {})
    defaults = JointOptions()
    options = JointOptions(max_residual=float(parameters.get("max_residual", defaults.max_residual)),
                           max_error=float(parameters.get("max_error", defaults.max_error)))
    mapping = sweep.mapping
    regions = [SweepRegion("wand_sweep", mapping.positions[mapping.keep], sweep.recorded, len(mapping.inside),
                           int(mapping.keep.any(axis=1).sum()), sweep.stride)]
    for name in extension_steps(session.steps):
        part, stride = extension_part(session, name, model.wand, options.max_extension_frames,
                                      fitted.get(name, {}).get("stride"))
        update = progress(f"solving {name} against the table", 1)
        samples, _, _ = extension_samples(part.signal_matrices(), part.valid_mask, model.wand, field,
                                          session.hemisphere, options, 0)
        update(1)
        regions.append(SweepRegion(name, samples.positions, session.steps[name].n_frames, part.n_frames,
                                   int(np.unique(samples.frame).size), stride))
    return regions


def region_cells(table: LookupTable, positions: np.ndarray) -> np.ndarray:
    """The grid cells (nx − 1, ny − 1, nz − 1) holding at least one of ``positions`` (N, 3) m."""
    return cell_counts(table, positions) > 0


def region_summary(data: ReportData) -> list[dict]:
    """Per sweep: frames, samples, the mapped litres its samples reach, those only it reaches, and (with a
    declared working volume) the share of the box it reaches, probed on the coverage lattice."""
    table, mapped = data.table, data.mapped_cells
    cell_litres = 1000 * table.grid.spacing ** 3
    reached = [region_cells(table, r.positions) & mapped for r in data.regions]
    total = np.sum(reached, axis=0)
    inside = None
    if data.volume is not None:
        g = table.grid
        index = np.floor((box_points(*data.volume) - g.origin) / g.spacing).astype(np.int64)
        inside = np.all((index >= 0) & (index < np.array(g.shape) - 1), axis=1)
        index = index[inside]
    rows = []
    for region, cells in zip(data.regions, reached, strict=True):
        row = {"name": region.name, "frames_recorded": region.frames_recorded, "frames_solved": region.frames_solved,
               "stride": region.stride, "frames_kept": region.frames_kept, "samples": int(len(region.positions)),
               "mapped_litres_reached": round(float(cells.sum() * cell_litres), 2),
               "mapped_litres_reached_by_it_alone": round(float((cells & (total == 1)).sum() * cell_litres), 2)}
        if inside is not None:
            hit = np.zeros(len(inside), dtype=bool)
            hit[inside] = cells[tuple(index.T)]
            row["box_share_reached"] = round(float(hit.mean()), 4)
        rows.append(row)
    return rows


def check_view(table: LookupTable, session: Session, check: Session | None, step: str,
               cube_centre: np.ndarray | None, source: str,
               progress: Progress = no_progress) -> tuple[CheckView | None, str | None]:
    """Correct the check poses and judge them against truth; or why that cannot be done."""
    check = session if check is None else check
    if step not in check.steps:
        return None, f"{source} has no {step!r} step (record one with `ivc collect {step}`)"
    if step not in check.truth:
        return None, (f"{source} has no /truth/{step}: errors need true poses (a simulation or a precision rig)")
    # the table's frame is the session's declared cube frame: judge the check poses in it
    found = declared_frame_map(session) if "cube_survey" in session.truth else None
    frame_map = None if found is None else found[:2]
    # signals through the signal path; reported poses alone through the pose path, with the table's tracker solver
    corrector = corrector_for(measurement_of(check.steps[step]), table, check.hemisphere)
    errors = check_errors(corrector, check, step, frame_map,
                          progress("correcting the check poses", check.steps[step].n_frames))
    distance = None if cube_centre is None else np.linalg.norm(errors.true_position - cube_centre, axis=-1)
    return CheckView(errors, distance, source), None


def declared_cube(session: Session) -> np.ndarray | None:
    """The ideal cube's vertices (8, 3) m at the pose declared in ``cube_survey`` (eq. 87 with the
    nominal edge), for a session without the cube's calibration; None without a declared pose."""
    survey = session.steps.get("cube_survey")
    declared = None if survey is None else declared_pose(survey)
    return None if declared is None else placed_vertices(NOMINAL_EDGE * CUBE_BITS, declared)


def lacks_sentence(lacks: tuple[str, ...]) -> str:
    """``("no a step", "no b step")`` as "the session has no a step and no b step"."""
    listed = ", ".join(lacks[:-1]) + (" and " if len(lacks) > 1 else "") + lacks[-1]
    return f"the session has {listed}"


#: what a session of reported poses only lacks for the cube, sweep and coverage sections
POSE_ONLY = "no signals (reported poses only: `ivc fixtures` reports its cube and sweep through the pose path)"


def gather(session: Session, table: LookupTable, check: Session | None = None, step: str = "check",
           thin: int = THIN_SAMPLES, max_frames: int | None = None, check_source: str = "the session",
           progress: Progress = no_progress) -> ReportData:
    """Everything the report draws. ``check``: a separate check recording (default: ``session``'s own).

    A session without the mapping steps (a check recording, say) gives the table's field and the
    check poses only; ``mapping_missing`` says what it lacks. So does a session of reported poses only
    (:data:`POSE_ONLY`): its check poses are corrected through the pose path, and its cube and sweep are
    not solved again from signals rebuilt from the poses.
    """
    if thin < 1:
        raise InputError(f"thin = {thin}: the thin-cell threshold is a number of samples, at least 1")
    field = table.field()
    lacks = tuple(lack.short for lack in session.lacks_for_fit())
    if not lacks and isinstance(measurement_of(session), PoseInput):
        lacks = (POSE_ONLY,)  # the cube, sweep and coverage sections are the signal path's: not rebuilt from poses
    if lacks:
        model = sweep = counts = regions = None
        vertices = declared_cube(session)
    else:
        fixtures = table.provenance.get("fixtures", {})
        interpolant = next((name for name, kind in INTERPOLANTS.items()
                            if kind.__name__ == fixtures.get("interpolant")), "harmonic")
        model = FixtureModel.from_session(session, fixtures.get("vertices", "averaged"), interpolant)
        vertices = model.placement.positions
        sweep = solve_sweep(session, model, table, vertices.mean(axis=0), max_frames, progress)
        regions = sweep_regions(session, model, table, field, sweep, progress)
        counts = cell_counts(table, np.concatenate([r.positions for r in regions]))
    centre = None if vertices is None else vertices.mean(axis=0)
    view, missing = check_view(table, session, check, step, centre, check_source, progress)
    volume = working_volume(session.attrs)
    box = None if volume is None else box_coverage(field, *volume)
    return ReportData(table, model, slices(table, field, counts, centre), sweep, view, missing, thin, vertices,
                      counts, field.valid_cells, lacks, box, regions, volume)


def figures_missing(data: ReportData) -> dict[str, str]:
    """The figures that cannot be drawn from ``data``, each with the reason."""
    out = {}
    if data.check is None:
        out["error_histograms"] = data.check_missing
    if data.sweep is None:
        lacks = lacks_sentence(data.mapping_missing)
        for name in ("lambda_vs_error", "cube_residuals", "coverage", "sweep_regions"):
            out[name] = lacks
        if data.check is None:
            out["error_vs_distance"] = f"{lacks}, and {data.check_missing}"
        elif data.check.distance is None:
            out["error_vs_distance"] = f"{lacks}: no cube to measure distances from"
    return out


def cube_errors(model: FixtureModel) -> tuple[np.ndarray, np.ndarray]:
    """Each cube sensor's calibrated position (fixture frame) minus the ideal cube's vertex
    (Himberg 2010's Table 20) and minus the optimised cube's (eq. 108, Table 21), (8, 3) mm each."""
    relative = model.cube.relative_positions
    return 1000 * (relative - NOMINAL_EDGE * CUBE_BITS), 1000 * model.cube.fit.residuals


def _rounded(values: dict) -> dict:
    return {k: round(v, 4) for k, v in values.items()}


def summary(data: ReportData) -> dict:
    """The report's numbers, JSON-ready (mm, mrad, %). Sections the session cannot give (the
    cube's calibration, coverage, the sweep) hold ``missing``: what it lacks."""
    table, model, sweep = data.table, data.model, data.sweep
    g = table.grid
    nodes = g.nodes()[table.valid]
    node_percent = percent_of_measured(table.values[table.valid], nodes)
    cells = data.mapped_cells
    out = {
        "table": {
            "origin_mm": (1000 * g.origin).round(3).tolist(), "spacing_mm": round(1000 * g.spacing, 3),
            "shape": list(g.shape), "valid_nodes": int(table.valid.sum()), "nodes": int(table.valid.size),
            "mapped_cells": int(cells.sum()), "cells": int(cells.size),
            "method": table.fit.get("method"), "degree": table.fit.get("degree"),
            "cv_rms_mm": table.fit.get("cv_rms_mm"), "hemisphere": table.hemisphere,
        },
        "secondary_field": {
            "percent_of_measured_at_valid_nodes": _rounded(percentiles(node_percent)),
            "slice_heights_mm": (1000 * data.slices.z).round(2).tolist(),
        },
    }
    if "rounds" in table.fit:  # a whole-volume map (ivc.lut.joint): its rounds and error against distance
        out["volume"] = {key: table.fit[key] for key in ("rounds", "extension_sweeps", "never_touched_mapped_region",
                                                        "mapped_litres", "error_by_distance", "stopped")
                         if key in table.fit}
    if data.box is not None:  # the session declares the working volume: how much of it the table maps
        out["box"] = {**data.box, "fraction": round(data.box["fraction"], 4),
                      "mapped_litres": round(data.box["mapped_litres"], 2),
                      "faces": {name: round(share, 4) for name, share in data.box["faces"].items()}}
    lacks = {"missing": list(data.mapping_missing)}
    if model is None:
        out["cube"] = dict(lacks)
        if data.cube_vertices is not None:
            out["cube"].update(centre_mm=(1000 * data.cube_centre).round(3).tolist(),
                               vertices="the ideal cube at the declared pose")
        out["coverage"], out["sweep"] = dict(lacks), dict(lacks)
    else:
        mapping, counts = sweep.mapping, data.cell_counts
        minus_ideal, minus_optimised = cube_errors(model)
        out["cube"] = {
            "fitted_edge_mm": round(1000 * model.cube.fit.edge, 4),
            "nominal_edge_mm": 1000 * NOMINAL_EDGE,
            "minus_ideal_mm": minus_ideal.round(4).tolist(),
            "minus_optimised_mm": minus_optimised.round(4).tolist(),
            "centre_mm": (1000 * data.cube_centre).round(3).tolist(),
            "vertices": "calibrated",
        }
        out["coverage"] = {
            "thin_threshold_samples": data.thin,
            "samples_kept": int(sum(len(r.positions) for r in data.regions)),  # every sweep's
            "samples_per_mapped_cell": _rounded(percentiles(counts[cells])),
            "thin_mapped_cells": int(np.sum(cells & (counts < data.thin))),
            "empty_mapped_cells": int(np.sum(cells & (counts == 0))),
            "sampled_cells_outside_mapped_volume": int(np.sum(~cells & (counts > 0))),
        }
        out["sweep_regions"] = region_summary(data)
        out["sweep"] = {
            "frames_solved": int(len(mapping.inside)), "frames_recorded": sweep.recorded, "stride": sweep.stride,
            "gate_residual": sweep.gates.max_residual, "gate_error_mm": 1000 * sweep.gates.max_error,
            "residual_relative": percentiles(mapping.sensor0.residual[mapping.sensor0.converged]),
            "samples": {"total": int(mapping.keep.size), "kept": mapping.kept, "dropped": mapping.dropped},
            "estimated_error_mm": _rounded(percentiles(mapping.error_estimate[mapping.keep], 1000)),
        }
        if sweep.errors is not None:
            ok0 = mapping.sensor0.converged & mapping.inside
            out["sweep"]["sensor0_position_mm"] = _rounded(percentiles(sweep.errors.position[ok0, 0], 1000))
            out["sweep"]["sensor0_orientation_mrad"] = _rounded(percentiles(sweep.errors.angle[ok0, 0], 1000))
            out["sweep"]["kept_samples_position_mm"] = _rounded(percentiles(sweep.errors.position[mapping.keep],
                                                                            1000))
    if data.check is None:
        out["check"] = {"missing": data.check_missing}
    else:
        out["check"] = {"source": data.check.source, **summarise(data.check.errors)}
        if data.check.distance is not None:
            out["check"]["distance_from_cube_mm"] = percentiles(data.check.distance[data.check.errors.valid], 1000)
    return out
