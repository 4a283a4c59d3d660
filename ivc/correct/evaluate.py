"""How good is a table? Corrected poses of a check recording against its truth (Himberg 2010's Table 24).

The table and its corrections live in the frame of the *declared* cube pose (docs/math.md §5):
every sample was placed through it. When the check file also holds the cube survey's
truth (a simulated session, or a precision rig), the true poses are moved into that frame
and IVC is judged there, which is the accuracy the method itself delivers; the error
against raw truth, which adds the cube-placement error, is reported beside it. The
uncorrected dipole solution lives in the source frame and is compared with raw truth. A check
step of reported poses only is corrected through the pose path, and the tracker's own reported
poses are the uncorrected figure. Beside both frames, the errors left after the best rigid
alignment of the corrected positions to truth: what a registration removes (the declared cube
pose's error is such a rigid offset).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ivc import rotations
from ivc.correct.measured import CORRECTORS, corrector_for
from ivc.correct.reported import PoseCorrector
from ivc.correct.solver import FLAG_NAMES, Corrector
from ivc.fixtures.measurement import measurement_of
from ivc.session import Session, SessionError
from ivc.table.lookup import LookupTable
from ivc.truth import DECLARED_FRAME, RAW_FRAME, declared_frame_map, percentiles, pose_errors


@dataclass
class CheckErrors:
    """Per-sample errors of one check recording, (F, N) each: IVC (``ok`` samples only are
    meaningful) and the uncorrected dipole solution (``valid`` samples), in mm and mrad.

    ``ivc_*`` are judged in the declared cube frame when ``frame_map`` is known (else equal to
    ``ivc_raw_*``, against raw truth). ``true_position`` (F, N, 3) metres is in the frame the
    IVC errors were judged in. ``precision_mm`` (F, N): each corrected pose's predicted RMS position error
    when the corrector predicted it (``Corrector(precision=True)``), else None.
    """

    valid: np.ndarray
    ok: np.ndarray
    flags: np.ndarray
    iterations: np.ndarray
    ivc_position_mm: np.ndarray
    ivc_orientation_mrad: np.ndarray
    ivc_raw_position_mm: np.ndarray
    ivc_raw_orientation_mrad: np.ndarray
    dipole_position_mm: np.ndarray
    dipole_orientation_mrad: np.ndarray
    true_position: np.ndarray
    frame_map: tuple | None
    placement_error_mm: float | None
    aligned_position_mm: np.ndarray | None = None
    aligned_orientation_mrad: np.ndarray | None = None
    input: str = "signals"
    precision_mm: np.ndarray | None = None


#: refits of the rigid alignment without its outliers, and what counts as one (times the median error)
ALIGNMENT_TRIMS = 2
ALIGNMENT_OUTLIER = 5.0


def rigid_alignment(points: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` minimising ``Σ |R p + t − q|²`` over point pairs (N, 3) (Kabsch / Umeyama without scale)."""
    p_mean, q_mean = points.mean(axis=0), targets.mean(axis=0)
    U, _, Vt = np.linalg.svd((targets - q_mean).T @ (points - p_mean))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return R, q_mean - R @ p_mean


def aligned_errors(position, rotation, true_position, true_rotation, ok):
    """Errors (mm, mrad) of the ``ok`` samples after the best rigid alignment of their positions to truth
    (what a registration to a patient or a virtual world removes; the orientations turned by the same R).
    The alignment is refitted without the samples more than ALIGNMENT_OUTLIER times the median error
    off (they are still reported). NaN elsewhere, and everywhere when fewer than 3 samples are ok."""
    p_mm = np.full(ok.shape, np.nan)
    a_mrad = np.full(ok.shape, np.nan)
    if ok.sum() < 3:
        return p_mm, a_mrad
    used = np.ones(int(ok.sum()), dtype=bool)
    for _ in range(ALIGNMENT_TRIMS + 1):  # a few gross errors (a wrong fold branch) must not tilt the fit
        R, t = rigid_alignment(position[ok][used], true_position[ok][used])
        miss = np.linalg.norm(position[ok] @ R.T + t - true_position[ok], axis=1)
        used = miss <= max(ALIGNMENT_OUTLIER * float(np.median(miss)), 1e-6)
    p_mm[ok], a_mrad[ok] = pose_errors(position[ok] @ R.T + t, R @ rotation[ok], true_position[ok], true_rotation[ok])
    return p_mm, a_mrad


def check_errors(table: LookupTable | Corrector | PoseCorrector, check: Session, step: str = "check",
                 frame_map: tuple | None = None, progress: Callable[[int], None] | None = None) -> CheckErrors:
    """Correct ``check``'s ``step`` and compare every sample with its truth (see :class:`CheckErrors`).

    ``frame_map``: ``(D_R, D_t)`` taking true source-frame poses into the declared frame; by
    default from ``check``'s own cube survey and its truth, if it has them.
    """
    if step not in check.steps:
        raise SessionError(f"the check file has no {step!r} step: record one with `ivc collect {step}`")
    if step not in check.truth:
        raise SessionError(f"the check file has no /truth/{step}: evaluation needs true poses (a simulation or a "
                           "precision rig)")
    data, truth = check.steps[step], check.truth[step]
    valid = data.valid_mask
    measurement = measurement_of(data)  # signals, or reported poses only (the tracker's own as the uncorrected)
    if isinstance(table, CORRECTORS[type(measurement)]):
        corrector = table
    elif isinstance(table, PoseCorrector):
        raise SessionError(f"the {step!r} step holds signals: evaluate it with a signal Corrector")
    elif isinstance(table, Corrector):  # a signal corrector's table, for reported poses, with its noise
        corrector = corrector_for(measurement, table.field, table.hemisphere, signal_noise=table.gate.sigma)
    else:
        corrector = corrector_for(measurement, table, check.hemisphere)
    out = corrector.batch(*measurement.data(data), valid)
    r_dip, T_dip = measurement.uncorrected(data, check.hemisphere)
    if progress is not None:
        progress(data.n_frames)
    true_p, true_T = truth.position, rotations.to_matrix(truth.quaternion)
    if frame_map is None:
        found = declared_frame_map(check) if "cube_survey" in check.truth else None
        frame_map = None if found is None else found[:2]
    ok = out.flags == 0
    T_ivc = rotations.to_matrix(np.where(ok[..., None], out.quaternion, rotations.IDENTITY))
    raw_p, raw_a = pose_errors(out.position, T_ivc, true_p, true_T)
    dip_p, dip_a = pose_errors(r_dip, T_dip, true_p, true_T)
    aligned_p, aligned_a = aligned_errors(out.position, T_ivc, true_p, true_T, ok)
    p, a, placement, judged = raw_p, raw_a, None, true_p
    if frame_map is not None:
        D_R, D_t = frame_map
        judged = true_p @ D_R.T + D_t
        p, a = pose_errors(out.position, T_ivc, judged, D_R @ true_T)
        placement = float(1000 * np.linalg.norm(D_t + (D_R - np.eye(3)) @ np.mean(true_p[valid], axis=0)))
    return CheckErrors(valid, ok, out.flags, out.iterations, p, a, raw_p, raw_a, dip_p, dip_a, judged, frame_map,
                       placement, aligned_p, aligned_a, measurement.kind,
                       None if out.precision is None else 1000 * out.precision)


def summarise(e: CheckErrors) -> dict:
    """Percentiles (25/50/75/95/99/max) of position (mm) and orientation (mrad) errors, IVC and dipole,
    with the flag counts: the layout of Himberg 2010's Table 24 (``ivc evaluate``)."""
    ok, valid = e.ok, e.valid
    report = {
        "samples": int(valid.size),
        "corrected": int(ok.sum()),
        "flagged": {name: int(np.sum((e.flags & bit) != 0)) for bit, name in FLAG_NAMES.items()},
        "ivc_raw": {"position_mm": percentiles(e.ivc_raw_position_mm[ok]),
                    "orientation_mrad": percentiles(e.ivc_raw_orientation_mrad[ok])},
        "dipole": {"position_mm": percentiles(e.dipole_position_mm[valid]),
                   "orientation_mrad": percentiles(e.dipole_orientation_mrad[valid])},
        "frame": RAW_FRAME,
    }
    if e.frame_map is not None:
        report["ivc"] = {"position_mm": percentiles(e.ivc_position_mm[ok]),
                         "orientation_mrad": percentiles(e.ivc_orientation_mrad[ok])}
        report["frame"] = DECLARED_FRAME
        report["placement_error_mm"] = e.placement_error_mm
    else:
        report["ivc"] = report["ivc_raw"]
    if e.aligned_position_mm is not None and ok.any():
        report["ivc_aligned"] = {"position_mm": percentiles(e.aligned_position_mm[ok]),
                                 "orientation_mrad": percentiles(e.aligned_orientation_mrad[ok])}
    if e.precision_mm is not None and ok.any():
        # errors that are the tracker's noise alone give a median ratio of 0.67-0.89 (a 3-D Gaussian error's
        # median length over its RMS, from all variance on one axis to isotropic); map error raises it
        ratio = e.ivc_position_mm[ok] / e.precision_mm[ok]
        report["predicted_precision"] = {"position_mm": percentiles(e.precision_mm[ok]),
                                         "error_over_predicted_median": float(np.median(ratio)),
                                         "error_over_predicted_p95": float(np.percentile(ratio, 95))}
    report["input"] = e.input
    report["iterations_median"] = float(np.median(e.iterations[valid])) if valid.any() else 0.0
    return report


def evaluate(table: LookupTable | Corrector, check: Session, step: str = "check",
             frame_map: tuple | None = None, progress: Callable[[int], None] | None = None) -> dict:
    """:func:`summarise` of :func:`check_errors`: how good the table is on ``check``'s ``step``.

    ``frame_map``: ``(D_R, D_t)`` taking true source-frame poses into the declared frame; by
    default from ``check``'s own cube survey and its truth, if it has them.
    """
    return summarise(check_errors(table, check, step, frame_map, progress))
