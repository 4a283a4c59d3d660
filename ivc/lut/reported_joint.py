"""Map a whole working volume from reported poses alone: extension sweeps carried by the wand.

The pose-only counterpart of :mod:`ivc.lut.joint` (docs/lut.md, "Extension sweeps from reported poses"):

1. the cube sweep's pairs map the wand's reach around the cube (:func:`ivc.lut.reported_build.cube_map`);
2. every frame of every extension sweep is corrected sensor by sensor with the current table, the default
   trust test included (the ambiguity test above all: next to metal a pose far outside the map can be
   reported where a mapped pose would be). Each trusted sensor's pose, carried back through the wand's
   calibration, says where sensor 0 is; where at least ``min_sensors`` of them, and more than half of the
   trusted ones, agree (:data:`AGREEMENT`), the wand's pose is their mean, and every sensor of the frame
   gives a pair: its true pose carried from the wand's, and the pose the tracker reported;
3. a pair fixes six of the nine entries of the secondary field at its true position: the field sample
   there is the current model's field moved by the least change (minimum norm) that makes the tracker
   model reproduce the reported pose (:func:`field_samples`);
4. equivalent sources (:mod:`ivc.lut.fit_sources`, as the signal path's joint solve) are fitted to the
   samples; steps 3-4 are repeated (:data:`PROJECTIONS`) so that the three unseen entries of each sample
   follow the fitted model rather than the previous one; the model is tabulated, and steps 2-4 repeat
   with the new table until the mapped volume stops growing.

A fixed point of steps 3-4 is a model whose tracker model reproduces every pair, as the cube map's
fit through the tracker (:mod:`ivc.pose.reported_fit`) is, at the cost of one linear fit per pass instead
of a Gauss-Newton fit over nine unknowns per dipole, which the hundreds of dipoles a cockpit needs
make too large.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.linalg.blas import dsyrk

from ivc import dipole, rotations
from ivc.correct.reported import PoseCorrector
from ivc.errors import InputError
from ivc.fixtures.measurement import PoseInput
from ivc.fixtures.wand import AGREEMENT, WandCalibration
from ivc.lut.fit_sources import (
    SourceModel,
    default_sources,
    design_rows,
    even_subset,
    normal_equations,
    solve_normal_equations,
)
from ivc.lut.fit_steps import provenance
from ivc.lut.joint import FRAME_OFFSET, JointOptions, extension_part, mapped_litres, tabulate
from ivc.lut.options import FitOptions
from ivc.lut.reported_build import MAX_PAIRS, cube_map, table_error
from ivc.lut.samples import FieldSamples
from ivc.pose.reported_fit import PosePairs
from ivc.pose.tracker_solver import left_difference, reported_pose_jacobian
from ivc.session import Session, SessionError, extension_steps
from ivc.table.grid import GridField
from ivc.table.lookup import LookupTable

#: Newton steps of a field sample's projection, and the reported pose it must then reproduce to (m, rad)
NEWTON_STEPS, REPRODUCED = 12, (1e-6, 1e-5)
#: projections and sources fits per round (step 3-4 of the module docstring)
PROJECTIONS = 2
#: the coupled fit's conjugate-gradient iterations at most, and the relative residual it stops at
CG_ITERATIONS, CG_TOLERANCE = 60, 1e-5
#: a cube-sweep pair's sample error (m) for the fit's weights: about the cube map's own error
ANCHOR_ERROR = 5e-5
#: extension sweeps' pairs are timed this far apart (s) so that the map error's blocks never mix sweeps
SWEEP_TIME_OFFSET = 1e6

Progress = Callable[[str, int], Callable[[int], None]]


def _noop(desc: str, total: int) -> Callable[[int], None]:
    return lambda n: None


def field_samples(pairs: PosePairs, prior: np.ndarray, solver: str, hemisphere: str
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Secondary fields ``G`` (n, 3, 3) at the pairs' true positions that the tracker model (``solver``) turns
    into their reported poses, each the least change (Frobenius norm of the field) from ``prior`` (n, 3, 3)
    that does; whether each reproduces its reported pose to :data:`REPRODUCED` (n,); and the orthogonal
    projector (n, 9, 9) onto the entries of the field (row by row) the reported pose sees there,
    ``Jᵀ (J Jᵀ)⁻¹ J`` with ``J = ∂(φ, ω)/∂G`` (rank 6: three combinations of the nine entries leave the
    reported pose unchanged).

    Newton steps on the six equations ``φ(f_D + G) = v``, ``C(f_D + G) = Q Tᵀ`` in the nine unknowns, each
    step the minimum-norm solution ``δ = Jᵀ (J Jᵀ)⁻¹ e`` of the linearised equations, capped at half the
    field's norm so that a far start does not overshoot."""
    r = pairs.position
    M = dipole.field(r) + np.asarray(prior, float)
    observed = pairs.observed_turn
    n = len(r)
    ok = np.zeros(n, dtype=bool)
    for _ in range(NEWTON_STEPS):
        position, turn, J = reported_pose_jacobian(M, solver, hemisphere)
        e = np.concatenate([pairs.reported_position - position, left_difference(observed, turn)], axis=1)
        finite = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(J.reshape(n, -1)), axis=1)
        ok = finite & (np.linalg.norm(e[:, :3], axis=1) <= REPRODUCED[0]) & \
            (np.linalg.norm(e[:, 3:], axis=1) <= REPRODUCED[1])
        active = finite & ~ok
        if not active.any():
            break
        Ja, ea = J[active], e[active]
        JJ = Ja @ np.swapaxes(Ja, -1, -2)
        try:
            step = (np.swapaxes(Ja, -1, -2) @ np.linalg.solve(JJ, ea[..., None]))[..., 0].reshape(-1, 3, 3)
        except np.linalg.LinAlgError:
            step = (np.linalg.pinv(Ja) @ ea[..., None])[..., 0].reshape(-1, 3, 3)
        size = np.linalg.norm(step, axis=(1, 2))
        cap = 0.5 * np.linalg.norm(M[active], axis=(1, 2))
        step *= np.minimum(1.0, cap / np.maximum(size, 1e-300))[:, None, None]
        M[active] += step
    _, _, J = reported_pose_jacobian(M, solver, hemisphere)
    J = np.where(ok[:, None, None], J, 0.0)
    JJ = J @ np.swapaxes(J, -1, -2) + np.where(ok, 0.0, 1.0)[:, None, None] * np.eye(6)
    projector = np.swapaxes(J, -1, -2) @ np.linalg.solve(JJ, J)
    return M - dipole.field(r), ok, projector


def wand_from_sensors(position: np.ndarray, quaternion: np.ndarray, trusted: np.ndarray, precision: np.ndarray,
                      orientation_precision: np.ndarray, wand: WandCalibration, min_sensors: int = 2):
    """The wand's pose in every frame from its trusted corrected sensors, where enough of them agree.

    ``position`` (F, W, 3) m, ``quaternion`` (F, W, 4): the corrected sensors; ``trusted`` (F, W); their
    predicted ``precision`` (F, W) m and ``orientation_precision`` (F, W) rad. Each trusted sensor implies
    sensor 0's pose, ``T_0 = T_n R_nᵀ``, ``r_0 = r_n − T_0 b_n``; the largest set that agrees with one of
    them to :data:`AGREEMENT` is kept when it has at least ``min_sensors`` and more than half the trusted
    sensors. Returns sensor 0's position (F, 3) and rotation (F, 3, 3) (their mean: the rotation the polar
    projection of the mean matrix), the frames kept (F,), and sensor 0's position and angle standard errors
    (F,) m, rad (the members' predicted precision over √k)."""
    position0, rotation0, kept, members = wand.consensus(position, quaternion, trusted, AGREEMENT, min_sensors)
    k = members.sum(axis=1)
    weight = members / np.maximum(k, 1)[:, None]
    with np.errstate(invalid="ignore"):
        sigma = np.sqrt(np.einsum("fn,fn->f", weight, np.where(members, precision, 0.0) ** 2) / np.maximum(k, 1))
        angle = np.sqrt(np.einsum("fn,fn->f", weight, np.where(members, orientation_precision, 0.0) ** 2)
                        / np.maximum(k, 1))
    return position0, rotation0, kept, sigma, angle


def extension_pairs(corrector: PoseCorrector, session: Session, name: str, wand: WandCalibration,
                    options: JointOptions, number: int) -> tuple[PosePairs, np.ndarray, np.ndarray, int]:
    """One extension sweep against ``corrector``'s table: pairs of every valid sensor of the frames whose wand
    pose its trusted sensors agree on (:func:`wand_from_sensors`), gated by their estimated error
    ``options.max_error``. Returns the pairs (frames offset by ``number`` · FRAME_OFFSET), each one's estimated
    error (m) and time (s, offset by ``number`` · SWEEP_TIME_OFFSET), and the frames used."""
    step, _ = extension_part(session, name, wand, options.max_extension_frames)
    valid = step.valid_mask
    out = corrector.batch(step.position, step.quaternion, valid)
    trusted = (out.flags == 0) & valid
    r0, T0, kept, sigma, angle = wand_from_sensors(out.position, out.quaternion, trusted, out.precision,
                                                   out.orientation_precision, wand, options.min_sensors)
    positions, rots = wand.propagate(np.where(kept[:, None], r0, 0.0), np.where(kept[:, None, None], T0, np.eye(3)))
    error = wand.error_estimate(np.where(kept, sigma, np.inf), np.where(kept, angle, 0.0))
    use = kept[:, None] & valid & (error <= options.max_error)
    frame, sensor = np.nonzero(use)
    pairs = PosePairs(positions[frame, sensor], rots[frame, sensor], step.position[frame, sensor],
                      rotations.to_matrix(step.quaternion[frame, sensor]), frame + number * FRAME_OFFSET, sensor)
    return pairs, error[frame, sensor], step.time[frame] + number * SWEEP_TIME_OFFSET, int(kept.sum())


def _joined(parts: list[PosePairs]) -> PosePairs:
    return PosePairs(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                       ("position", "rotation", "reported_position", "reported_rotation", "frame", "sensor")))


def _normal_operator(X: np.ndarray, weight: np.ndarray, projector: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``Σ_n w_n X_nᵀ P_n X_n c`` (3K, 3): the normal operator of the fit in the entries each sample's reported pose
    sees (``X`` (n, 3, 3K) the design rows, :func:`ivc.lut.fit_sources.design_rows`; ``P_n`` the projectors)."""
    G = (X @ c).reshape(-1, 9, 1)
    seen = (projector @ G)[..., 0].reshape(-1, 3, 3) * weight[:, None, None]
    return np.einsum("mia,mij->aj", X, seen, optimize=True)


def coupled_solve(samples: FieldSamples, projector: np.ndarray, sources: np.ndarray, damping: float,
                  error_floor: float, start: np.ndarray | None = None) -> tuple[np.ndarray, int, float]:
    """Moments (3K, 3) of ``sources`` that fit each sample's field in the entries its reported pose sees
    (``projector`` (n, 9, 9), :func:`field_samples`): ``min Σ_n w_n |P_n (X_n c − g_n)|² + damping · Σ d_k c_k²``
    with the separable fit's weights and damping (``d`` the diagonal of its Gram matrix, as
    :func:`ivc.lut.fit_sources.damped_solve`). Preconditioned conjugate gradients, the preconditioner the
    separable fit's damped normal equations (every entry seen): the separable fit repeated on re-projected
    samples is the same iteration without the conjugate directions, and needs hundreds of passes where the
    entries a pose does not see change slowly across space. ``start``: moments to start from (default: the
    separable fit's). Returns the moments, the iterations and the final relative residual."""
    weight = samples.weights(error_floor)
    X = design_rows(samples.positions, sources)  # (n, 3, 3K): held for every iteration
    root = np.sqrt(weight)[:, None]
    flat = (X * root[:, :, None]).reshape(-1, X.shape[2])
    gram = dsyrk(1.0, flat.T, trans=0)
    gram += np.triu(gram, 1).T
    del flat
    diag = damping * np.maximum(np.diag(gram), 1e-300)
    gram[np.diag_indices_from(gram)] += diag
    factor = cho_factor(gram, lower=False, overwrite_a=True, check_finite=False)
    seen = (projector @ samples.fields.reshape(-1, 9, 1))[..., 0].reshape(-1, 3, 3)
    rhs = np.einsum("mia,mij->aj", X, seen * weight[:, None, None], optimize=True)
    if start is None:
        start = cho_solve(factor, np.einsum("mia,mij->aj", X, samples.fields * weight[:, None, None], optimize=True),
                          check_finite=False)
    c = start.copy()
    residual = rhs - _normal_operator(X, weight, projector, c) - diag[:, None] * c
    z = cho_solve(factor, residual, check_finite=False)
    direction = z.copy()
    rz = float(np.sum(residual * z))
    norm0 = float(np.linalg.norm(rhs))
    relative = float(np.linalg.norm(residual)) / norm0
    iterations = 0
    while iterations < CG_ITERATIONS and relative > CG_TOLERANCE:
        Ad = _normal_operator(X, weight, projector, direction) + diag[:, None] * direction
        alpha = rz / float(np.sum(direction * Ad))
        c += alpha * direction
        residual -= alpha * Ad
        z = cho_solve(factor, residual, check_finite=False)
        rz, previous = float(np.sum(residual * z)), rz
        direction = z + (rz / previous) * direction
        relative = float(np.linalg.norm(residual)) / norm0
        iterations += 1
    return c, iterations, relative


def _fit(pairs: PosePairs, error: np.ndarray, prior: np.ndarray, solver: str, hemisphere: str,
         options: JointOptions, dampings, progress: Progress):
    """Steps 3-4 of the module docstring on at most ``options.max_samples`` of the pairs (spread evenly,
    :func:`ivc.lut.fit_sources.even_subset`): project, fit, :data:`PROJECTIONS` times (the fit in the entries
    each pair's reported pose sees, :func:`coupled_solve`; its damping chosen by the separable fit's
    cross-validation on the last projection's samples when ``dampings`` offers a choice; the largest before).
    Returns the model, its
    report and the share of the pairs fitted that their samples reproduce."""
    chosen = (even_subset(pairs.position, options.max_samples, options.even_cell) if options.even_cell
              else np.arange(0, len(pairs), max(1, -(-len(pairs) // options.max_samples))))
    pairs, error, prior = pairs.subset(chosen), error[chosen], prior[chosen]
    sources = default_sources(pairs.position, options.source_standoff, options.source_spacing)
    model, report, share, moments = None, {"damping": max(dampings)}, 0.0, None
    for projection in range(PROJECTIONS):
        if model is not None:
            prior = model(pairs.position)
        G, ok, projector = field_samples(pairs, prior, solver, hemisphere)
        share = float(ok.mean()) if len(ok) else 0.0
        samples = FieldSamples(pairs.position[ok], G[ok], error[ok], pairs.frame[ok], pairs.sensor[ok])
        if len(samples) < 2_000:
            raise SessionError(f"only {len(samples)} pose pairs could be turned into field samples: check the "
                               "cube survey and the wand calibration (`ivc fixtures`)")
        projector = projector[ok]
        if len(dampings) > 1 and projection == PROJECTIONS - 1:  # the last samples: their unseen entries the model's
            normal = normal_equations(samples, sources, error_floor=options.error_floor, max_samples=len(samples),
                                      progress=progress("choosing the sources' damping", len(samples)))
            _, report = solve_normal_equations(normal, dampings)
        damping = report["damping"]
        moments, iterations, relative = coupled_solve(samples, projector, sources, damping, options.error_floor,
                                                      moments)
        model = SourceModel(sources, moments.reshape(len(sources), 3, 3))
        report = {**report, "sources": len(sources), "damping": damping,
                  "coupled_iterations": iterations, "coupled_relative_residual": relative}
    return model, report, share


def _prior(field: GridField | None, model, r: np.ndarray) -> np.ndarray:
    """The current map's field at r (n, 3): the sources model where there is one, else the table's field inside
    its grid and zero beyond it."""
    if model is not None:
        return model(r)
    g, _, _ = field.evaluate(r)
    return np.where(field.grid.contains(r)[:, None, None], g, 0.0)


def fit_pose_joint_lut(session: Session, options: FitOptions | None = None, source: str | Path | None = None,
                       progress: Progress | None = None, solver: str = "closed-form",
                       joint: JointOptions | None = None) -> LookupTable:
    """The whole-volume table of a pose-only ``session`` with extension sweeps (module docstring).

    ``options``: as :func:`ivc.lut.reported_build.fit_pose_lut` for the cube map (its grid spacing and support
    also the whole map's); ``joint``: the rounds, gates and sources (:class:`ivc.lut.joint.JointOptions`; its
    ``spacing``, ``min_support`` and ``max_frames`` are taken from ``options``)."""
    options = options or FitOptions()
    progress = progress or _noop
    names = extension_steps(session.steps)
    if not names:
        raise SessionError("the session has no extension sweeps (extension_sweep_1, ...): the pose-only map "
                           "covers the region around the cube alone")
    joint = replace(joint or JointOptions(), spacing=options.spacing, min_support=options.min_support,
                    max_frames=options.max_frames)
    # the cube map as traced, not self-calibrated: with the self-calibrated one the cockpit's corrections were better
    # (median 0.064 -> 0.044 mm) but its map error shrank below the extension sweeps' own error, and 4.3 % of its
    # trusted poses were off by more than 5x their predicted precision (≤ 0.1 % with the traced map; docs/trust.md)
    cube, anchor, anchor_time = cube_map(session, replace(options, refine=False), source, progress, solver, MAX_PAIRS)
    wand = PoseInput(solver).fixture_model(session).wand
    for name in names:
        if session.steps[name].position is None:
            raise InputError(f"/steps/{name}: no reported poses (a pose-only map needs them in every sweep)")
    anchor_error = np.full(len(anchor), ANCHOR_ERROR)
    table = cube
    field, model = cube.field(), None
    history = [{"iteration": 0, "samples": len(anchor), "mapped_litres": mapped_litres(cube.grid, cube.valid),
                "map_change_mm": None, "frames_solved": {name: 0 for name in names}}]
    dampings, stopped, report, share = joint.dampings, None, {}, 1.0
    pairs, times = anchor, anchor_time
    for iteration in range(1, joint.max_iterations + 1):
        corrector = PoseCorrector(table, solver=solver)
        parts, errors, clock, solved = [anchor], [anchor_error], [anchor_time], {}
        for number, name in enumerate(names, start=1):
            found, error, time, frames = extension_pairs(corrector, session, name, wand, joint, number)
            parts.append(found), errors.append(error), clock.append(time)
            solved[name] = frames
        pairs, error, times = _joined(parts), np.concatenate(errors), np.concatenate(clock)
        prior = _prior(field, model, pairs.position)
        model, report, share = _fit(pairs, error, prior, solver, session.hemisphere, joint, dampings, progress)
        before = mapped_litres(table.grid, table.valid)
        grid, values, valid, support = tabulate(model, pairs.position, joint.spacing, joint.min_support,
                                                joint.table_subdivision)
        table = LookupTable(grid, values, valid, support, session.hemisphere,
                            {"input": "reported poses", "tracker_solver": solver,
                             "signal_noise": cube.fit.get("signal_noise")})
        field = table.field()
        litres = mapped_litres(grid, valid)
        history.append({"iteration": iteration, "samples": len(pairs), "mapped_litres": litres,
                        "map_change_mm": None, "frames_solved": solved})
        if litres < (1 + joint.stall_growth) * before:
            stopped = f"the mapped volume grew by less than {100 * joint.stall_growth:g} % (it has stopped growing)"
            break
    stopped = stopped or f"max_iterations {joint.max_iterations} reached"
    noise = cube.fit.get("signal_noise")
    map_error = table_error(pairs, field, times, solver, session.hemisphere, None if noise is None else noise["sigma"])
    never = [name for name in names if all(step["frames_solved"].get(name, 0) == 0 for step in history)]
    fit = {"method": "equivalent sources, joint", **report, "input": "reported poses", "tracker_solver": solver,
           "rounds": history, "stopped": stopped, "never_touched_mapped_region": never,
           "mapped_litres": mapped_litres(table.grid, table.valid), "pairs_reproduced": share,
           "frames": cube.fit["frames"],
           "samples": {"total": len(pairs), "kept": len(pairs), "used": len(pairs), "anchor": len(anchor),
                       "outside_grid": 0, "dropped": {}},
           "cube": cube.fit["cube"], "cube_map": {k: cube.fit.get(k) for k in ("degree", "cv_rms_mm", "map_error")},
           "self_calibration": cube.fit.get("self_calibration"),
           "refinement": [], "grid_from": "data (one-cell margin)", "min_support": joint.min_support,
           "valid_nodes": int(table.valid.sum()), "map_error": map_error, "signal_noise": noise}
    parameters = {**options.describe(), "tracker_solver": solver, "max_pairs": MAX_PAIRS,
                  "max_extension_frames": joint.max_extension_frames, "min_sensors": joint.min_sensors}
    return LookupTable(table.grid, table.values, table.valid, table.support, session.hemisphere, fit,
                       provenance(parameters, source, cube.provenance.get("fixtures")))

