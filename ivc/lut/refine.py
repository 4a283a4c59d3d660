"""Refinement beyond Himberg 2010: re-solve each wand frame as one rigid body against the current map.

Himberg 2010's map trusts sensor 0's pose in the cube alone and carries every other sensor
with it (eq. 97-98), so sensor 0's small orientation error grows along the wand. Once a
first map exists, every sensor's signal says something about the wand's pose: the
frame is re-solved as one rigid 6-DOF body, sensor 0 against dipole + cube field and
sensors 1.. against dipole + map, all residuals relative to each sensor's rms(S). New
samples ``G = T_n S_n − f_D(r_n)`` then give a new map; repeat while it pays
(:func:`refine_map`): each refinement must lower the cross-validation score by
``REFINE_MIN_GAIN``, it stops when the map changes by less than ``REFINE_TOLERANCE``, and
the map with the lowest score is the one kept.

Perturbing sensor 0's pose by ``δ`` and ``T_0 ← T_0 exp([ω]×)`` moves sensor n by
``δ − T_0 [b_n]× ω`` and turns it by ``T_n ← T_n exp([R_nᵀ ω]×)`` (``b_n``, ``R_n`` its
calibrated pose in the wand frame), which chains the single-sensor Jacobians.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ivc import dipole, rotations
from ivc.fixtures.interpolant import HarmonicField
from ivc.fixtures.wand import WandCalibration
from ivc.lut.fitter import Fitter, fit_table
from ivc.lut.samples import FieldSamples, leverage
from ivc.lut.support import mapped_nodes, node_support
from ivc.pose import levenberg_marquardt, signal_residual
from ivc.table.grid import Grid, GridField

CHUNK_FRAMES = 5_000
#: refinement stops when the map changes by less than this, pose-equivalent RMS over valid nodes (m)
REFINE_TOLERANCE = 5e-6
#: ... or when its cross-validation score improves by less than this fraction; the best-scoring map is kept
REFINE_MIN_GAIN = 0.01

Progress = Callable[[str, int], Callable[[int], None]]


@dataclass
class MapFit:
    """One fitted map: node ``values`` (nx, ny, nz, 3, 3), ``valid`` and ``support`` (nx, ny, nz), the
    ``samples`` it was fitted to and the fit ``report`` (with ``cv_rms_mm``)."""

    values: np.ndarray
    valid: np.ndarray
    support: np.ndarray
    samples: FieldSamples
    report: dict


def fit_map(fitter: Fitter, samples: FieldSamples, grid: Grid, min_support: int,
            progress: Callable[[int], None] | None = None) -> MapFit:
    """Fit ``samples`` on ``grid`` (:func:`ivc.lut.fitter.fit_table`) and mark the nodes with at least
    ``min_support`` samples around them and a fitted value."""
    values, report = fit_table(fitter, samples, grid, progress)
    support = node_support(grid, samples.positions)
    return MapFit(values, mapped_nodes(values, support, min_support), support, samples, report)


def map_change(grid: Grid, before: np.ndarray, after: np.ndarray, valid: np.ndarray) -> float:
    """Pose-equivalent RMS difference of two tables over the valid nodes where both are defined (m)."""
    valid = valid & np.all(np.isfinite(after.reshape(*grid.shape, 9)), axis=-1)
    change = leverage(grid.nodes()[valid]) * np.linalg.norm(after[valid] - before[valid], axis=(1, 2))
    return float(np.sqrt(np.mean(change**2)))


def refine_map(first: MapFit, mapping, model, S: np.ndarray, sweep_valid: np.ndarray, grid: Grid, fitter: Fitter,
               max_refinements: int, min_support: int,
               progress: Progress) -> tuple[MapFit, list[dict], str]:
    """Refine ``first`` (the map of the cube-solved sweep) by rigid re-solves of the wand frames.

    ``mapping``: the sweep's :class:`~ivc.fixtures.mapping.SweepMapping` (sensor 0's poses in the cube,
    the kept samples and their error estimates); ``model``: the
    :class:`~ivc.fixtures.mapping.FixtureModel` (wand calibration, cube field); ``S`` (F, W, 3, 3) and
    ``sweep_valid`` (F, W): the sweep's signals. Each refinement re-solves every frame against the
    current map, refits ``fitter`` to the new samples and scores it. Returns the map with the lowest
    cross-validation score, each refinement's record (``kept`` marks the chosen one) and why it stopped.
    """
    position0, rotation0 = mapping.positions[:, 0], mapping.rotations[:, 0]
    current, best, best_iteration = first, first, 0
    history, stopped = [], None
    for iteration in range(1, max_refinements + 1):
        table = GridField(grid, current.values, current.valid)
        r0, T0, ok = resolve_sweep(S, sweep_valid, model.wand, model.interpolant.value_and_jacobian, table,
                                   position0, rotation0, progress(f"refinement {iteration}: rigid wand solve", len(S)))
        positions, rots = model.wand.propagate(np.where(ok[:, None], r0, 0.0),
                                               np.where(ok[:, None, None], T0, np.eye(3)))
        frame, sensor = np.nonzero(mapping.keep & ok[:, None])
        fields = rots[frame, sensor] @ S[frame, sensor] - dipole.field(positions[frame, sensor])
        samples = FieldSamples(positions[frame, sensor], fields, mapping.error_estimate[frame, sensor], frame, sensor)
        refit = fit_map(fitter, samples, grid, min_support,
                        progress(f"refinement {iteration}: refit", fitter.progress_units(samples)))
        change = map_change(grid, current.values, refit.values, current.valid)
        moved = np.linalg.norm(r0[ok] - position0[ok], axis=1)
        cv = refit.report["cv_rms_mm"]
        history.append({"iteration": iteration, "frames_converged": int(ok.sum()),
                        "sensor0_moved_median_mm": float(1000 * np.median(moved)),
                        "map_change_mm": 1000 * change, "cv_rms_mm": cv})
        current = refit
        position0 = np.where(ok[:, None], r0, position0)
        rotation0 = np.where(ok[:, None, None], T0, rotation0)
        gained = cv < (1 - REFINE_MIN_GAIN) * best.report["cv_rms_mm"]
        if cv < best.report["cv_rms_mm"]:
            best, best_iteration = refit, iteration
        if change < REFINE_TOLERANCE:
            stopped = f"the map changed by less than {1e6 * REFINE_TOLERANCE:g} µm"
            break
        if not gained:
            stopped = f"the cross-validation score improved by less than {100 * REFINE_MIN_GAIN:g} %"
            break
    for step in history:
        step["kept"] = step["iteration"] == best_iteration
    return best, history, stopped or f"the limit of {max_refinements} refinements reached"


def skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], -2)


def _residuals(S, scale, valid, wand, cube_field, map_field, r0, T0):
    """Stacked residuals (F, W·9) and Jacobian (F, W·9, 6) of the rigid wand."""
    F, W = S.shape[:2]
    positions, rots = wand.propagate(r0, T0)
    M = dipole.field(positions)
    dM = dipole.field_jacobian(positions)
    g0, dg0 = cube_field(positions[:, 0])
    g, dg, mapped = map_field.evaluate(positions[:, 1:])
    valid = valid.copy()
    valid[:, 1:] &= mapped  # a sensor where the map says nothing does not pull the wand
    M[:, 0] += g0
    dM[:, 0] += dg0
    M[:, 1:] += g
    dM[:, 1:] += dg
    e, J = signal_residual(S.reshape(-1, 3, 3), M.reshape(-1, 3, 3), dM.reshape(-1, 3, 3, 3), rots.reshape(-1, 3, 3))
    e, J = e.reshape(F, W, 9), J.reshape(F, W, 9, 6)
    lever = -T0[:, None] @ skew(wand.positions)[None]  # (F, W, 3, 3): ∂r_n/∂ω
    J_w = J[..., :3] @ lever + J[..., 3:] @ np.swapaxes(wand.rotations, -1, -2)[None]
    J = np.concatenate([J[..., :3], J_w], axis=-1)
    w = (valid / scale)[..., None]
    return (e * w).reshape(F, -1), (J * w[..., None]).reshape(F, -1, 6)


def _compiled(S, valid, scale, wand, field: HarmonicField, map_field: GridField, r, T, max_iterations,
              step_tolerance) -> np.ndarray:
    """:func:`solve_rigid` in compiled code (``ivc.lut.refine_kernels``); r, T updated in place."""
    from ivc.fixtures.kernels import Cube
    from ivc.lut.refine_kernels import rigid_kernel
    from ivc.lut.rigid_kernels import Limits, Wand

    converged = np.empty(len(S), dtype=bool)
    m = map_field
    rigid_kernel(np.ascontiguousarray(S), np.ascontiguousarray(valid), np.ascontiguousarray(scale),
                 Wand(np.ascontiguousarray(wand.positions, dtype=float),
                      np.ascontiguousarray(wand.rotations, dtype=float)),
                 Cube(np.ascontiguousarray(field.centre, dtype=float), float(field.scale),
                      np.ascontiguousarray(field.coefficients, dtype=float)),
                 m.kernel_grid, Limits(int(max_iterations), float(step_tolerance)), r, T, converged)
    return converged


def solve_rigid(S: np.ndarray, valid: np.ndarray, wand: WandCalibration, cube_field: Callable, map_field: GridField,
                position0: np.ndarray, rotation0: np.ndarray, max_iterations: int = 30,
                step_tolerance: float = 1e-9, compiled: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt for the wand's pose (sensor 0's) in every frame, from a starting pose.

    ``S`` (F, W, 3, 3), ``valid`` (F, W); ``cube_field``: ``r -> (g, ∂g/∂r)``; ``map_field``: the current map.
    Returns sensor 0's position (F, 3), rotation (F, 3, 3) and per-frame convergence (F,).
    When ``cube_field`` is a :class:`~ivc.fixtures.interpolant.HarmonicField`'s ``value_and_jacobian``
    the frames are solved in compiled code (the same rules, one frame at a time) unless ``compiled``
    is False.
    """
    valid = valid & dipole.usable_signals(S)
    S = np.where(valid[..., None, None], S, 0.0)
    scale = np.sqrt(np.mean(S**2, axis=(-1, -2)))
    scale = np.where(valid, scale, 1.0)
    r, T = position0.copy(), rotation0.copy()
    field = getattr(cube_field, "__self__", None)
    if compiled and isinstance(field, HarmonicField) and isinstance(map_field, GridField):
        r, T = np.ascontiguousarray(r, dtype=float), np.ascontiguousarray(T, dtype=float)
        converged = _compiled(S, valid, scale, wand, field, map_field, r, T, max_iterations, step_tolerance)
        return r, T, converged
    F = len(S)
    active = np.all(np.isfinite(r), axis=1) & valid[:, 0]
    r[~active], T[~active] = np.nan, np.nan
    idx = np.flatnonzero(active)
    e, J = np.zeros((F, S.shape[1] * 9)), np.zeros((F, S.shape[1] * 9, 6))
    e[idx], J[idx] = _residuals(S[idx], scale[idx], valid[idx], wand, cube_field, map_field, r[idx], T[idx])

    def trial(idx, step):
        trial_r = r[idx] + step[:, :3]
        trial_T = T[idx] @ rotations.to_matrix(rotations.from_rotvec(step[:, 3:]))
        return (trial_r, trial_T), *_residuals(S[idx], scale[idx], valid[idx], wand, cube_field, map_field,
                                               trial_r, trial_T)

    converged, _ = levenberg_marquardt((r, T), e, J, active, trial, max_iterations, step_tolerance)
    return r, T, converged


def resolve_sweep(S: np.ndarray, valid: np.ndarray, wand: WandCalibration, cube_field: Callable, map_field: GridField,
                  position0: np.ndarray, rotation0: np.ndarray,
                  progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`solve_rigid` over a whole sweep in chunks (bounded memory), with progress."""
    r, T, ok = np.empty_like(position0), np.empty_like(rotation0), np.zeros(len(S), dtype=bool)
    for start in range(0, len(S), CHUNK_FRAMES):
        part = slice(start, start + CHUNK_FRAMES)
        r[part], T[part], ok[part] = solve_rigid(S[part], valid[part], wand, cube_field, map_field, position0[part],
                                                 rotation0[part])
        if progress is not None:
            progress(len(S[part]))
    return r, T, ok
