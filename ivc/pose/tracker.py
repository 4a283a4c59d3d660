"""Sensor pose in free space with a calibrated tracker model (docs/tracker.md).

The start is the closed-form dipole pose (docs/conventions.md) of the gain-corrected
signal ``B⁻ᵀ S A⁻¹``, exact for concentric coils without noise; Levenberg-Marquardt on
the full model (coil offsets included) then minimises ``‖S − S_model(r, T)‖_F`` over
position and a rotation increment ``T ← T exp([ω]×)``, every frame of the batch
stepping together (:func:`ivc.pose.solver.levenberg_marquardt`). The ideal tracker
gives the closed-form pose itself, bit for bit. A tracker's output correction, if it
has one, is applied last.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ivc import rotations
from ivc.dipole import closed_form_pose, hemisphere_vector
from ivc.dipole.tracker import Tracker
from ivc.errors import InputError
from ivc.pose.solver import PoseSolution, levenberg_marquardt

__all__ = ["tracker_pose"]


def _directions(hemisphere: str | ArrayLike, frames: int) -> np.ndarray:
    if isinstance(hemisphere, str):
        return np.broadcast_to(hemisphere_vector(hemisphere), (frames, 3))
    h = np.asarray(hemisphere, dtype=float)
    if h.shape not in ((3,), (frames, 3)):
        raise InputError(f"hemisphere must be a name like '+x', a vector (3,) or vectors (F, 3); got {h.shape}")
    return np.broadcast_to(h, (frames, 3))


def tracker_pose(S: ArrayLike, tracker: Tracker | None = None, hemisphere: str | ArrayLike = "+x", *,
                 max_iterations: int = 50, step_tolerance: float = 1e-10, correct: bool = True) -> PoseSolution:
    """Poses of free-space signal matrices ``S`` (F, 3, 3) under ``tracker`` (None: ideal).

    ``hemisphere``: a declared side (``"+x"``, ...), or a direction (3,) or one per frame
    (F, 3); the position is taken on its side. Returns a :class:`ivc.pose.solver.PoseSolution`
    (position metres, source frame; ``residual`` is rms(S − S_model) / rms(S)). Frames with
    non-finite signals come back NaN, not converged. ``correct``: apply the tracker's output
    correction (:meth:`ivc.dipole.tracker.Tracker.correct_pose`), if it has one.
    """
    S = np.asarray(S, dtype=float)
    if S.ndim != 3 or S.shape[1:] != (3, 3):
        raise InputError(f"S must have shape (F, 3, 3), got {S.shape}")
    F = len(S)
    h = _directions(hemisphere, F)
    tracker = Tracker.ideal() if tracker is None else tracker
    finite = np.all(np.isfinite(S.reshape(F, -1)), axis=1)
    S = np.where(finite[:, None, None], S, np.eye(3))  # placeholders, never reported
    r, T = closed_form_pose(tracker.corrected(S), "+x")
    flip = np.einsum("fi,fi->f", r, h) < 0
    r[flip] = -r[flip]
    zeros = np.zeros(F)
    if tracker.is_ideal:
        r[~finite], T[~finite] = np.nan, np.nan
        return PoseSolution(r, T, finite.copy(), np.zeros(F, dtype=int), zeros, zeros.copy(), zeros.copy())

    def residual(idx, r_, T_):
        Sm, dS = tracker.pose_jacobian(r_, T_)
        return (S[idx] - Sm).reshape(len(idx), 9), -dS.reshape(len(idx), 9, 6)

    every = np.arange(F)
    e, J = residual(every, r, T)

    def trial(idx, step):
        r_t = r[idx] + step[:, :3]
        T_t = T[idx] @ rotations.to_matrix(rotations.from_rotvec(step[:, 3:]))
        return (r_t, T_t), *residual(idx, r_t, T_t)

    converged, iterations = levenberg_marquardt((r, T), e, J, finite, trial, max_iterations, step_tolerance)
    rms_s = np.sqrt(np.mean(S**2, axis=(1, 2)))
    rel = np.sqrt(np.mean(e**2, axis=1)) / rms_s
    sigma2 = np.sum(e**2, axis=1) / 3.0
    with np.errstate(invalid="ignore"):
        cov = np.linalg.pinv(np.einsum("fki,fkj->fij", J, J)) * sigma2[:, None, None]
        diag = np.einsum("fii->fi", cov)
        pos_sigma, ang_sigma = np.sqrt(diag[:, :3].sum(axis=1)), np.sqrt(diag[:, 3:].sum(axis=1))
    if correct:
        r, T = tracker.correct_pose(r, T)
    r[~finite], T[~finite] = np.nan, np.nan
    return PoseSolution(r, T, converged & finite, iterations, rel, pos_sigma, ang_sigma)
