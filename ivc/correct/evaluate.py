"""How good is a table? Corrected poses of a check recording against its truth (seed Table 24).

The table and its corrections live in the frame of the *declared* cube pose (MATH.md §5):
every sample was placed through it. When the check file also holds the cube survey's
truth (a simulated session, or a precision rig), the true poses are moved into that frame
and IVC is judged there, which is the accuracy the method itself delivers; the error
against raw truth, which adds the cube-placement error, is reported beside it. The
uncorrected dipole solution lives in the source frame and is compared with raw truth.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ivc import rotations
from ivc.correct.solver import FLAG_NAMES, Corrector
from ivc.dipole import closed_form_pose
from ivc.fixtures.report import declared_frame_map, percentiles
from ivc.lut.table import LookupTable
from ivc.session import Session, SessionError


def _errors(position, rotation, true_position, true_rotation):
    return (1000 * np.linalg.norm(position - true_position, axis=-1),
            1000 * rotations.angle_between_matrices(rotation, true_rotation))


def evaluate(table: LookupTable | Corrector, check: Session, step: str = "check",
             frame_map: tuple | None = None, progress: Callable[[int], None] | None = None) -> dict:
    """Percentiles (25/50/75/95/99/max) of position (mm) and orientation (mrad) errors, IVC and dipole.

    ``frame_map``: ``(D_R, D_t)`` taking true source-frame poses into the declared frame; by
    default from ``check``'s own cube survey and its truth, if it has them.
    """
    if step not in check.steps:
        raise SessionError(f"the check file has no {step!r} step: record one with `ivc collect {step}`")
    if step not in check.truth:
        raise SessionError(f"the check file has no /truth/{step}: evaluation needs true poses (a simulation or a "
                           "precision rig)")
    corrector = table if isinstance(table, Corrector) else Corrector(table, check.hemisphere)
    data, truth = check.steps[step], check.truth[step]
    S = data.signal_matrices()
    valid = data.valid_mask
    out = corrector.batch(S, valid)
    if progress is not None:
        progress(S.shape[0])
    true_p, true_T = truth.position, rotations.to_matrix(truth.quaternion)
    if frame_map is None:
        found = declared_frame_map(check) if "cube_survey" in check.truth else None
        frame_map = None if found is None else found[:2]
    ok = out.flags == 0
    T_ivc = rotations.to_matrix(np.where(ok[..., None], out.quaternion, rotations.IDENTITY))
    raw_p, raw_a = _errors(out.position, T_ivc, true_p, true_T)
    r_dip, T_dip = closed_form_pose(S, check.hemisphere)
    dip_p, dip_a = _errors(r_dip, T_dip, true_p, true_T)
    report = {
        "samples": int(valid.size),
        "corrected": int(ok.sum()),
        "flagged": {name: int(np.sum((out.flags & bit) != 0)) for bit, name in FLAG_NAMES.items()},
        "ivc_raw": {"position_mm": percentiles(raw_p[ok]), "orientation_mrad": percentiles(raw_a[ok])},
        "dipole": {"position_mm": percentiles(dip_p[valid]), "orientation_mrad": percentiles(dip_a[valid])},
        "frame": "raw truth (source frame)",
    }
    if frame_map is not None:
        D_R, D_t = frame_map
        p, a = _errors(out.position, T_ivc, true_p @ D_R.T + D_t, D_R @ true_T)
        report["ivc"] = {"position_mm": percentiles(p[ok]), "orientation_mrad": percentiles(a[ok])}
        report["frame"] = "declared cube frame (true poses moved by the declared-pose error)"
        report["placement_error_mm"] = float(1000 * np.linalg.norm(D_t + (D_R - np.eye(3)) @ np.mean(
            true_p[valid], axis=0)))
    else:
        report["ivc"] = report["ivc_raw"]
    report["iterations_median"] = float(np.median(out.iterations[valid])) if valid.any() else 0.0
    return report
