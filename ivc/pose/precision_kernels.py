"""Compiled Cramér-Rao covariance of single-frame poses: the kernels behind :mod:`ivc.pose.precision`.

:func:`crb_covariance_one` is the per-pose step, the covariance ``(JᵀJ)⁻¹`` (for unit noise) of the pose
``(r, ω)`` that a signal ``S = Tᵀ M(r)`` fixes, with ``J`` the 9 x 6 Jacobian of ``Tᵀ M(r)`` in the
position (m, source frame) and the rotation increment ``T ← T exp([ω]×)`` (rad, sensor frame), the same
``J`` as :func:`ivc.pose.solver.signal_residual` (up to its sign). :func:`precision_kernel` applies it to
corrected poses with the table's secondary field; the pose-only correction (``ivc.correct.reported_kernels``)
applies it at the reported pose in free space and carries the covariance through the inverse map.
The NumPy form is :func:`ivc.pose.precision.pose_covariance` (tests/test_trust.py compares them).
"""

from __future__ import annotations

import numba
import numpy as np

from ivc.dipole.kernels import dipole_jacobian, field_matrix
from ivc.linalg import cholesky, cholesky_inverse

#: an information matrix worse conditioned than this fixes no pose: its covariance is infinite
MAX_CONDITION = 1e14


@numba.njit(cache=True, error_model="numpy")
def crb_covariance_one(T, M, dM, J, out):
    """``out`` (6, 6) = ``(JᵀJ)⁻¹`` for the pose (position, rotation increment) a signal ``Tᵀ M`` fixes, with
    M (3, 3) the field at the pose and dM (3, 3, 3) its derivative ∂M_aj/∂r_k; J (9, 6) is work space.
    Returns False (and ``out`` infinite) where the information matrix is singular or not finite."""
    P = out[:3, :3]  # Tᵀ M; out is free until the information matrix is inverted into it
    for i in range(3):
        for j in range(3):
            s = 0.0
            for a in range(3):
                s += T[a, i] * M[a, j]
            P[i, j] = s
            for k in range(3):  # ∂P_ij/∂r_k = Σ_a T_ai ∂M_aj/∂r_k
                s = 0.0
                for a in range(3):
                    s += T[a, i] * dM[a, j, k]
                J[3 * i + j, k] = s
    # P = Tᵀ M, ∂P/∂ω_a = −[e_a]× P: signal_residual's columns with its sign flipped (e = S − P)
    for j in range(3):
        J[0 * 3 + j, 3], J[1 * 3 + j, 3], J[2 * 3 + j, 3] = 0.0, P[2, j], -P[1, j]
        J[0 * 3 + j, 4], J[1 * 3 + j, 4], J[2 * 3 + j, 4] = -P[2, j], 0.0, P[0, j]
        J[0 * 3 + j, 5], J[1 * 3 + j, 5], J[2 * 3 + j, 5] = P[1, j], -P[0, j], 0.0
    # the information matrix JᵀJ into out's lower triangle; its Cholesky factor and from it the inverse into J's
    # first six rows (J is no longer needed), then back into out
    finite = True
    size = 0.0
    for a in range(6):
        for b in range(a + 1):
            s = 0.0
            for m in range(9):
                s += J[m, a] * J[m, b]
            out[a, b] = s
            size += s * s if a == b else 2.0 * s * s
            finite = finite and np.isfinite(s)
    inverse = J[:6, :]
    if finite and cholesky(out, 6, inverse):
        cholesky_inverse(inverse, 6)
        # the condition number in the Frobenius norm (an upper bound of the 2-norm's, without an SVD)
        inverse_size = 0.0
        for a in range(6):
            for b in range(6):
                inverse_size += inverse[a, b] * inverse[a, b]
        if np.isfinite(inverse_size) and np.sqrt(size * inverse_size) < MAX_CONDITION:
            for a in range(6):
                for b in range(6):
                    out[a, b] = inverse[a, b]
            return True
    for a in range(6):
        for b in range(6):
            out[a, b] = np.inf
    return False


@numba.njit(cache=True, error_model="numpy")
def traces(covariance):
    """``(sqrt(tr C_rr), sqrt(tr C_ωω))`` of a (6, 6) pose covariance: RMS position and orientation errors."""
    return (np.sqrt(covariance[0, 0] + covariance[1, 1] + covariance[2, 2]),
            np.sqrt(covariance[3, 3] + covariance[4, 4] + covariance[5, 5]))


@numba.njit(cache=True, error_model="numpy")
def _precision_one(r, T, G, dG, sigma, M, dM, J, covariance):
    """(RMS position m, RMS orientation rad) of the pose (r (3,), T (3, 3)) whose signal carries the secondary
    field G (3, 3), ∂G/∂r (3, 3, 3) and white noise ``sigma``; M, dM, J and covariance are work space."""
    if not (np.isfinite(r[0]) and np.isfinite(r[1]) and np.isfinite(r[2])):
        return np.nan, np.nan
    field_matrix(r[0], r[1], r[2], M)
    dipole_jacobian(r, dM)
    for i in range(3):
        for j in range(3):
            M[i, j] += G[i, j]
            for k in range(3):
                dM[i, j, k] += dG[i, j, k]
    crb_covariance_one(T, M, dM, J, covariance)
    p, a = traces(covariance)
    return sigma * p, sigma * a


@numba.njit(parallel=True, cache=True, nogil=True)
def precision_kernel(r, T, G, dG, sigma, position_out, orientation_out):  # pragma: no cover - compiled
    """RMS position (m) and orientation (rad) precision of poses (r (n, 3), T (n, 3, 3)) whose signals carry the
    secondary field G (n, 3, 3), ∂G/∂r (n, 3, 3, 3) and white noise ``sigma`` per entry; NaN where r is not
    finite, inf where the signal fixes no pose."""
    for n in numba.prange(r.shape[0]):
        position_out[n], orientation_out[n] = _precision_one(r[n], T[n], G[n], dG[n], sigma, np.empty((3, 3)),
                                                             np.empty((3, 3, 3)), np.empty((9, 6)), np.empty((6, 6)))


@numba.njit(cache=True, nogil=True)
def precision_serial(r, T, G, dG, sigma, position_out, orientation_out):  # pragma: no cover - compiled
    """:func:`precision_kernel` without threads: a live frame's few poses."""
    M, dM, J, covariance = np.empty((3, 3)), np.empty((3, 3, 3)), np.empty((9, 6)), np.empty((6, 6))
    for n in range(r.shape[0]):
        position_out[n], orientation_out[n] = _precision_one(r[n], T[n], G[n], dG[n], sigma, M, dM, J, covariance)
