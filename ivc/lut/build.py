"""From a session to a look-up table: map the sweep, fit the secondary field on a grid, refine (``ivc fit``).

Stages: the fixtures are calibrated and the sweep solved through the cube
(:mod:`ivc.fixtures.mapping`); the gated samples are fitted on the grid by the chosen
method; then, optionally, the wand frames are re-solved as rigid bodies against the map
and the map refitted until it stops changing or stops gaining (:mod:`ivc.lut.refine`):
each refinement must lower the cross-validation score by ``ivc.lut.refine.REFINE_MIN_GAIN``, and the map
with the lowest score is the one kept.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from ivc import dipole
from ivc.files import file_digest  # noqa: F401 (public here before ivc.files)
from ivc.fixtures.mapping import DROP_REASONS, Gates
from ivc.fixtures.measurement import PoseInput, SignalInput, measurement_of
from ivc.lut.fit_steps import ADVICE, check_enough, decimated, provenance
from ivc.lut.joint import fit_joint_lut
from ivc.lut.options import (  # noqa: F401 (public here before ivc.lut.options)
    METHODS,
    MIN_KEPT_FRACTION,
    MIN_SAMPLES,
    FitOptions,
    Progress,
    check_grid_memory,
    grid_memory,
)
from ivc.lut.refine import fit_map, refine_map
from ivc.lut.reported_build import fit_pose_lut
from ivc.lut.reported_joint import fit_pose_joint_lut
from ivc.lut.samples import FieldSamples
from ivc.lut.signal_noise import measure_signal_noise
from ivc.session import Session, SessionError, extension_steps
from ivc.table.grid import Grid
from ivc.table.lookup import LookupTable


def _noop(desc: str, total: int) -> Callable[[int], None]:
    return lambda n: None


def _check_data_grid(session: Session, spacing: float) -> None:
    """Refuse, before the sweep is solved, a grid around the data too large for memory: the extent is
    taken from the sweep's dipole poses (its reported poses, else the closed form of its signals)."""
    sweep = session.steps["wand_sweep"]
    valid = sweep.valid_mask
    if not valid.any():
        return  # the gates will say so
    if sweep.position is not None:
        points = sweep.position[valid]
    else:
        points = dipole.closed_form_pose(sweep.signal_matrices()[valid])[0]
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) == 0:
        return
    extent = points.max(axis=0) - points.min(axis=0)
    check_grid_memory(tuple(int(n) for n in np.ceil(extent / spacing) + 3))  # + 1 node and a cell each side


def fit_lut(session: Session, options: FitOptions | None = None, source: str | Path | None = None,
            progress: Progress | None = None, tracker: str = "closed-form") -> LookupTable:
    """Build the look-up table of ``session`` (which must hold the fixture steps and the sweep).

    ``source``: the session's file, recorded (with its SHA-256) in the table's provenance.
    ``progress(description, total)`` returns an update callback per stage. The path is the session's
    measurement's (:func:`ivc.fixtures.measurement.measurement_of`, :data:`FIT_PATHS`): a session whose cube
    survey and sweep hold reported poses only is fitted from them through the model of the tracker's solver
    ``tracker`` (:func:`ivc.lut.reported_build.fit_pose_lut`; with extension sweeps
    :func:`ivc.lut.reported_joint.fit_pose_joint_lut`); one with signals by the chosen fitter, or, with
    extension sweeps, over the whole working volume by the joint solve (:func:`ivc.lut.joint.fit_joint_lut`).
    """
    measurement = measurement_of(session, solver=tracker) if not session.missing_for_fit() else SignalInput()
    return FIT_PATHS[type(measurement)](session, measurement, options or FitOptions(), source, progress or _noop)


def _fit_signals(session: Session, measurement: SignalInput, options: FitOptions, source: str | Path | None,
                 progress: Progress) -> LookupTable:
    """The signal path: the sweep mapped through the cube, fitted, refined (or the joint solve, with extension
    sweeps)."""
    if extension_steps(session.steps):  # the whole working volume: the joint solve (ivc.lut.joint)
        return _with_signal_noise(fit_joint_lut(session, options, source, progress), session)
    missing = session.missing_for_fit()
    if missing:
        raise SessionError("cannot fit a map; the session is missing:\n  " + "\n  ".join(missing))
    if options.origin is None:
        _check_data_grid(session, options.spacing)
    measurement = replace(measurement, gates=Gates(max_residual=options.max_residual, max_error=options.max_error))
    model = measurement.fixture_model(session)
    session, recorded, stride = decimated(session, options.max_frames)
    sweep = session.steps["wand_sweep"]
    mapping = measurement.map_sweep(session, model, progress("solving the sweep in the cube", sweep.n_frames))
    check_enough(mapping.kept, mapping.keep.size, mapping.dropped, DROP_REASONS, ADVICE, recorded, stride)
    samples = FieldSamples.from_mapping(mapping)
    if options.origin is not None:
        grid = Grid(np.asarray(options.origin, float), options.spacing, tuple(options.shape))
    else:
        grid = Grid.around(samples.positions, options.spacing)
    outside = int(np.sum(~grid.contains(samples.positions)))
    fitter = options.fitter.clone()
    result = fit_map(fitter, samples, grid, options.min_support,
                     progress(fitter.progress_label, fitter.progress_units(samples)))
    history, stopped = [], None
    if options.refine:
        result, history, stopped = refine_map(result, mapping, model, sweep.signal_matrices(), sweep.valid_mask, grid,
                                              fitter, options.max_refinements, options.min_support, progress)
    values, valid, support, samples, report = (result.values, result.valid, result.support, result.samples,
                                               result.report)
    fit = {
        "method": fitter.name, **report,
        "frames": {"recorded": recorded, "used": sweep.n_frames, "stride": stride},
        "samples": {"total": int(mapping.keep.size), "kept": mapping.kept, "used": len(samples),
                    "outside_grid": outside, "dropped": mapping.dropped},
        "refinement": history,
        "refinement_stopped": stopped,
        "grid_from": "user" if options.origin is not None else "data (one-cell margin)",
        "min_support": options.min_support,
        "valid_nodes": int(valid.sum()),
    }
    fixtures = {"vertices": model.vertices, "interpolant": type(model.interpolant).__name__}
    return _with_signal_noise(LookupTable(grid, values, valid, support, session.hemisphere, fit,
                                          provenance(options.describe(), source, fixtures)), session)


def _fit_reported(session: Session, measurement: PoseInput, options: FitOptions, source: str | Path | None,
                  progress: Progress) -> LookupTable:
    """The reported-pose path (:func:`ivc.lut.reported_build.fit_pose_lut`, or with extension sweeps the whole
    working volume, :func:`ivc.lut.reported_joint.fit_pose_joint_lut`); both measure the noise themselves."""
    if extension_steps(session.steps):
        return fit_pose_joint_lut(session, options, source, progress, solver=measurement.solver)
    return fit_pose_lut(session, options, source, progress, solver=measurement.solver)


#: the fit path of each kind of measurement (:mod:`ivc.fixtures.measurement`): ``(session, measurement, options,
#: source, progress) -> LookupTable``; a new kind of input registers its path here
FIT_PATHS = {SignalInput: _fit_signals, PoseInput: _fit_reported}


def _with_signal_noise(table: LookupTable, session: Session) -> LookupTable:
    """``table`` with the tracker's signal noise measured from ``session``'s static steps in its fit report
    (``fit["signal_noise"]``, None when unmeasurable), from which ``ivc correct`` predicts each pose's precision."""
    noise = measure_signal_noise(session)
    table.fit["signal_noise"] = noise.as_dict() if noise is not None else None
    return table
