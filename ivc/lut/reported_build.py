"""A look-up table from reported poses alone (``ivc fit`` on a session without signals).

Stages (docs/lut.md, "Pose-only trackers"): the cube's field is fitted through the tracker model
from the survey's vertex poses and wand sensor 0 solved in it (:mod:`ivc.fixtures.reported_mapping`);
the wand's other sensors give (true pose, reported pose) pairs over the room; a harmonic
secondary field ``G`` is fitted so that the tracker model of ``f_D + G`` reproduces the reported
poses (:mod:`ivc.pose.reported_fit`); and ``G`` is tabulated on the grid. The table is the same kind of
table as the signal path's (the secondary field), so it corrects signals and poses alike.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ivc.errors import InputError
from ivc.fixtures.measurement import PoseInput
from ivc.fixtures.reported_mapping import DROP_REASONS
from ivc.lut import harmonics
from ivc.lut.fit_harmonic import HarmonicFit, HarmonicModel
from ivc.lut.fit_steps import ADVICE, check_enough, decimated, provenance
from ivc.lut.map_error import BLOCK_SECONDS, shared_residual
from ivc.lut.options import FitOptions
from ivc.lut.reported_bundle import self_calibrate
from ivc.lut.signal_noise import measure_signal_noise
from ivc.lut.support import mapped_nodes, node_support
from ivc.pose.precision import reported_noise
from ivc.pose.reported_fit import ORIENTATION_LENGTH, PosePairs, fit_through_tracker, pose_residuals
from ivc.pose.tracker_solver import check_solver, distortion
from ivc.session import Session, SessionError, extension_steps
from ivc.table.grid import Grid, GridField
from ivc.table.lookup import LookupTable

#: the largest harmonic degree tried (cross-validated below it)
MAX_DEGREE = 10
#: the samples disagree with the map when their median reported-position residual is more than this many times
#: the tracker's noise there (measured: 1.9 on the default scene, 2.5 on the severe one, 19 on the strong one)
DISAGREEMENT = 5.0
#: pairs the first fit, the self-calibration's start, uses at most
START_PAIRS = 8_000
#: pairs used by the fit at most (every k-th kept pair): the Gauss-Newton passes cost per pair
MAX_PAIRS = 40_000

Progress = Callable[[str, int], Callable[[int], None]]

#: what to redo when most samples fail a gate: the signal path's advice, but for sensor 0's inversion
_ADVICE = {**{reason: ADVICE[reason] for reason in DROP_REASONS},
           "not converged": "sensor 0's reported poses could not be traced back into the cube: check the declared "
                            "cube pose and redo cube_survey"}


def _noop(desc: str, total: int) -> Callable[[int], None]:
    return lambda n: None


def fit_pose_lut(session: Session, options: FitOptions | None = None, source: str | Path | None = None,
                 progress: Progress | None = None, solver: str = "closed-form",
                 max_pairs: int = MAX_PAIRS) -> LookupTable:
    """Build the look-up table of a pose-only ``session`` (fixture steps and sweep as reported poses).

    ``solver``: the tracker's own pose solver (``ivc.pose.tracker_solver.SOLVERS``), recorded in the
    table so that corrections invert the same model. ``options``: as :func:`ivc.lut.fit_lut` (the
    fitter must be a :class:`~ivc.lut.fit_harmonic.HarmonicFit`, whose ``degree`` (None: cross-validated
    up to MAX_DEGREE) and number of folds apply; ``refine``: fit the field and the sweep's wand poses together
    first, :func:`ivc.lut.reported_bundle.self_calibrate`, rather than rest sensor 0 on the cube's field). The map
    covers the wand's reach around the cube; with extension sweeps :func:`ivc.lut.reported_joint.fit_pose_joint_lut`
    maps more.
    """
    return cube_map(session, options, source, progress, solver, max_pairs)[0]


def cube_map(session: Session, options: FitOptions | None = None, source: str | Path | None = None,
             progress: Progress | None = None, solver: str = "closed-form", max_pairs: int = MAX_PAIRS
             ) -> tuple[LookupTable, PosePairs, np.ndarray]:
    """:func:`fit_pose_lut`, also returning the sweep's kept pairs and each one's time (s) on the sweep's clock."""
    check_solver(solver)
    options = options or FitOptions()
    progress = progress or _noop
    harmonic_fit = options.fitter
    if not isinstance(harmonic_fit, HarmonicFit):
        raise InputError("a pose-only session is fitted with the harmonic method only (through the tracker model)")
    missing = session.missing_for_fit()
    if missing:
        raise SessionError("cannot fit a map; the session is missing:\n  " + "\n  ".join(missing))
    measurement = PoseInput(solver)
    model = measurement.fixture_model(session)
    session, recorded, stride = decimated(session, options.max_frames)
    sweep = session.steps["wand_sweep"]
    mapping = measurement.map_sweep(session, model, progress("tracing sensor 0 into the cube", sweep.n_frames))
    total = int(mapping.keep.size)
    check_enough(mapping.kept, total, mapping.dropped, DROP_REASONS, _ADVICE, recorded, stride)
    pairs = mapping.pairs
    thin = max(1, -(-len(pairs) // max_pairs))
    used = pairs.subset(slice(None, None, thin)) if thin > 1 else pairs
    centre = 0.5 * (used.position.min(axis=0) + used.position.max(axis=0))
    scale = float(np.max(np.linalg.norm(used.position - centre, axis=1)))
    top = MAX_DEGREE if harmonic_fit.degree is None else int(harmonic_fit.degree)
    if not 1 <= top <= 12:
        raise InputError(f"harmonic degree {top}: use 1 to 12")
    counts = {d: harmonics.count(d) for d in range(1, top + 1)}

    def basis(r: np.ndarray) -> np.ndarray:  # (n, K, 3): a view of the compiled (n, 3, K) rows
        return np.swapaxes(harmonics.gradient_rows((r - centre) / scale, top), 1, 2)

    calibration = first = None
    if options.refine:  # the room's field and the wand's poses together: sensor 0 no longer rests on the cube alone
        start = used.subset(slice(None, None, max(1, -(-len(used) // START_PAIRS))))
        progress("self-calibrating the wand's poses and the field", 0)
        first, _ = fit_through_tracker(start, basis, {top: counts[top]}, solver, session.hemisphere, top, 1)
        mapping, first, calibration = self_calibrate(session, model, mapping, basis, first, solver)
        pairs = mapping.pairs
        thin = max(1, -(-len(pairs) // max_pairs))
        used = pairs.subset(slice(None, None, thin)) if thin > 1 else pairs
    coefficients, report = fit_through_tracker(used, basis, counts, solver, session.hemisphere,
                                               harmonic_fit.degree, harmonic_fit.cv.k,
                                               progress=progress("fitting through the tracker model", 0), start=first)
    K = harmonics.count(report["degree"])
    harmonic = HarmonicModel(centre, scale, report["degree"], coefficients[:K])
    if options.origin is not None:
        grid = Grid(np.asarray(options.origin, float), options.spacing, tuple(options.shape))
    else:
        grid = Grid.around(pairs.position, options.spacing)
    values = harmonic(grid.nodes())
    support = node_support(grid, pairs.position)
    valid = mapped_nodes(values, support, options.min_support)
    noise = measure_signal_noise(session)
    map_error = table_error(pairs, GridField(grid, values, valid), sweep.time[pairs.frame], solver,
                            session.hemisphere, None if noise is None else noise.sigma)
    dropped = dict(mapping.dropped)
    fit = {
        "method": "harmonic", **report, "input": "reported poses", "tracker_solver": solver,
        "frames": {"recorded": recorded, "used": sweep.n_frames, "stride": stride},
        "samples": {"total": total, "kept": mapping.kept, "used": len(used),
                    "outside_grid": int(np.sum(~grid.contains(pairs.position))), "dropped": dropped},
        "cube": {k: model.report[k] for k in ("degree", "vertex_position_rms_mm", "vertex_orientation_rms_mrad")},
        "refinement": [],
        "self_calibration": calibration,
        "grid_from": "user" if options.origin is not None else "data (one-cell margin)",
        "min_support": options.min_support,
        "valid_nodes": int(valid.sum()),
        "map_error": map_error,
        "signal_noise": None if noise is None else noise.as_dict(),
    }
    ignored = extension_steps(session.steps)
    if ignored:  # the pose-only map covers the cube's reach only: say so rather than drop them without a word
        fit["extension_sweeps_ignored"] = ignored
    fixtures = {"vertices": model.vertices, "interpolant": "HarmonicField (through the tracker model)"}
    parameters = {**options.describe(), "tracker_solver": solver, "max_pairs": max_pairs}
    table = LookupTable(grid, values, valid, support, session.hemisphere, fit, provenance(parameters, source, fixtures))
    return table, pairs, sweep.time[pairs.frame]


def table_error(pairs: PosePairs, field: GridField, time: np.ndarray, solver: str, hemisphere: str,
                sigma: float | None = None) -> dict:
    """The map's own error at the sweep's kept ``pairs`` (all of them, not only those the fit used), as
    corrections use it (``field``: the table's interpolated field): the reported position's (mm) and
    orientation's (mrad) RMS error. Pairs outside the mapped volume are left out.

    Two parts, the larger counts: the residual that revisits of one place share
    (:func:`ivc.lut.map_error.shared_residual`; ``time`` (N,) s of each pair), and, when the samples disagree
    with the map by more than :data:`DISAGREEMENT` times the tracker's noise at the median (``sigma``: its
    white noise per signal entry; :func:`ivc.pose.precision.reported_noise` at each reported pose), the RMS
    residual beyond that many times the noise: the samples themselves are off (sensor 0's tracing in the
    cube), in a way no revisit shares, the map averaged them, and how far off it is ivc cannot tell better
    than the samples' own spread."""
    g, _, inside = field.evaluate(pairs.position)
    pairs = pairs.subset(inside)
    position, turn = distortion(pairs.position, g[inside].reshape(-1, 3, 3), solver=solver, hemisphere=hemisphere)
    residual = pose_residuals(pairs, position, turn)
    residual[:, 3:] /= ORIENTATION_LENGTH
    shared = [shared_residual(pairs.position, part, time[inside], field.grid) for part in
              (residual[:, :3], residual[:, 3:])]
    out = {"shared_position_mm": 1000 * shared[0], "shared_orientation_mrad": 1000 * shared[1],
           "block_seconds": BLOCK_SECONDS}
    error = list(shared)
    if sigma is not None and len(pairs):
        length = np.linalg.norm(residual[:, :3], axis=1)
        noise = reported_noise(pairs.reported_position, pairs.reported_rotation, sigma)
        ratio = float(np.median(length / noise))
        excess = turn_excess = 0.0
        if ratio > DISAGREEMENT:  # RMS beyond the noise allowed: the tail counts, a flag is a promise
            typical = float(np.sqrt(np.mean(length**2)))
            excess = float(np.sqrt(max(typical**2 - DISAGREEMENT**2 * float(np.mean(noise**2)), 0.0)))
            turn_excess = excess / typical * float(np.sqrt(np.mean(np.sum(residual[:, 3:] ** 2, axis=1))))
        error = [max(shared[0], excess), max(shared[1], turn_excess)]
        out.update(disagreement=ratio, excess_position_mm=1000 * excess)
    out.update(position_mm=1000 * error[0], orientation_mrad=1000 * error[1])
    return out
