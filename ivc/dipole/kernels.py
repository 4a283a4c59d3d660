"""Compiled per-sample kernels behind :mod:`ivc.dipole` (numba, parallel over samples).

Each kernel takes flat arrays (M samples) and writes into a preallocated output.
The public, shape-checking, documented functions live in ``field.py`` and ``pose.py``;
the pure-NumPy forms of the same equations are in the tests as a reference.
"""

from __future__ import annotations

import numba
import numpy as np

_OPTS = dict(parallel=True, cache=True, nogil=True)


@numba.njit(inline="always")
def field_entries(x, y, z):
    """The six distinct entries of f_D(r) = (3 r rᵀ/|r|² − I)/|r|³ (eq. 72)."""
    rho2 = x * x + y * y + z * z
    inv3 = 1.0 / (rho2 * np.sqrt(rho2))
    inv5 = 3.0 * inv3 / rho2
    return (inv5 * x * x - inv3, inv5 * y * y - inv3, inv5 * z * z - inv3, inv5 * x * y, inv5 * x * z, inv5 * y * z)


@numba.njit(inline="always")
def field_matrix(x, y, z, out):
    """f_D(r) (eq. 72) written into the (3, 3) array out."""
    f00, f11, f22, f01, f02, f12 = field_entries(x, y, z)
    out[0, 0] = f00
    out[1, 1] = f11
    out[2, 2] = f22
    out[0, 1] = out[1, 0] = f01
    out[0, 2] = out[2, 0] = f02
    out[1, 2] = out[2, 1] = f12


@numba.njit(**_OPTS)
def field_kernel(r, out):  # pragma: no cover - compiled
    for n in numba.prange(r.shape[0]):
        field_matrix(r[n, 0], r[n, 1], r[n, 2], out[n])


@numba.njit(**_OPTS)
def signal_kernel(r, T, out):  # pragma: no cover - compiled
    """out[n] = T[n]ᵀ f_D(r[n]) (eq. 73 with G = 0)."""
    for n in numba.prange(r.shape[0]):
        f00, f11, f22, f01, f02, f12 = field_entries(r[n, 0], r[n, 1], r[n, 2])
        for i in range(3):
            a = T[n, 0, i]
            b = T[n, 1, i]
            c = T[n, 2, i]
            out[n, i, 0] = a * f00 + b * f01 + c * f02
            out[n, i, 1] = a * f01 + b * f11 + c * f12
            out[n, i, 2] = a * f02 + b * f12 + c * f22


@numba.njit(inline="always")
def _matmul3(A, B, out):
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@numba.njit(inline="always")
def principal_eigenvector(B, work_a, work_b, v):
    """Unit eigenvector of the largest eigenvalue of a symmetric PSD 3x3 matrix.

    Power iteration by repeated squaring: after k squarings the other eigen-directions
    are suppressed by (λ2/λ1)^(2^k). In free space λ2/λ1 = 1/4, so 8 squarings leave
    nothing; 12 cover strongly distorted fields too.
    """
    tr = B[0, 0] + B[1, 1] + B[2, 2]
    for i in range(3):
        for j in range(3):
            work_a[i, j] = B[i, j] / tr
    for _ in range(12):
        _matmul3(work_a, work_a, work_b)
        t = work_b[0, 0] + work_b[1, 1] + work_b[2, 2]
        for i in range(3):
            for j in range(3):
                work_a[i, j] = work_b[i, j] / t
    best = 0
    best_norm = -1.0
    for j in range(3):
        nrm = work_a[0, j] ** 2 + work_a[1, j] ** 2 + work_a[2, j] ** 2
        if nrm > best_norm:
            best_norm = nrm
            best = j
    for i in range(3):
        v[i] = work_a[i, best]
    # two plain power steps with B itself polish the last bits
    for _ in range(2):
        w0 = B[0, 0] * v[0] + B[0, 1] * v[1] + B[0, 2] * v[2]
        w1 = B[1, 0] * v[0] + B[1, 1] * v[1] + B[1, 2] * v[2]
        w2 = B[2, 0] * v[0] + B[2, 1] * v[1] + B[2, 2] * v[2]
        nrm = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        v[0] = w0 / nrm
        v[1] = w1 / nrm
        v[2] = w2 / nrm


@numba.njit(inline="always")
def _det3(A):
    return (
        A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
        - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
        + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0])
    )


@numba.njit(inline="always")
def _inverse_transpose3(A, out):
    """out = A⁻ᵀ, by cofactors."""
    d = _det3(A)
    out[0, 0] = (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]) / d
    out[0, 1] = -(A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0]) / d
    out[0, 2] = (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]) / d
    out[1, 0] = -(A[0, 1] * A[2, 2] - A[0, 2] * A[2, 1]) / d
    out[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) / d
    out[1, 2] = -(A[0, 0] * A[2, 1] - A[0, 1] * A[2, 0]) / d
    out[2, 0] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) / d
    out[2, 1] = -(A[0, 0] * A[1, 2] - A[0, 2] * A[1, 0]) / d
    out[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) / d


@numba.njit(inline="always")
def _fro(A):
    s = 0.0
    for i in range(3):
        for j in range(3):
            s += A[i, j] * A[i, j]
    return np.sqrt(s)


@numba.njit
def rotation_polar_factor(K, X, work, out):
    """Rotation nearest to K (orthogonal Procrustes), written into out.

    Scaled Newton iteration for the polar factor, X <- (γX + X⁻ᵀ/γ)/2, which converges
    quadratically to U Vᵀ when det K > 0. When det K <= 0 the nearest *rotation* is
    U diag(1, 1, -1) Vᵀ, which Newton cannot reach: fall back to an SVD.
    """
    if not _det3(K) > 0.0:
        if not np.isfinite(_det3(K)):
            for i in range(3):
                for j in range(3):
                    out[i, j] = np.nan
            return
        U, _, Vt = np.linalg.svd(K)
        d = np.sign(_det3(U) * _det3(Vt))
        for i in range(3):
            U[i, 2] *= d
        _matmul3(U, Vt, out)
        return
    for i in range(3):
        for j in range(3):
            X[i, j] = K[i, j]
    for it in range(60):
        _inverse_transpose3(X, work)
        gamma = np.sqrt(_fro(work) / _fro(X)) if it < 10 else 1.0
        change = 0.0
        for i in range(3):
            for j in range(3):
                new = 0.5 * (gamma * X[i, j] + work[i, j] / gamma)
                change += (new - X[i, j]) ** 2
                X[i, j] = new
        if change < 1e-30:
            break
    for i in range(3):
        for j in range(3):
            out[i, j] = X[i, j]


@numba.njit(inline="always")
def closed_form_one(s, hemisphere, r_out, T_out, work_a, work_b, v, B, F, K):
    """Closed-form dipole pose (docs/math.md §3) of one signal matrix s, into r_out (3,) and T_out (3, 3).

    ``work_a``, ``work_b``, ``B``, ``F``, ``K`` are (3, 3) and ``v`` (3,) scratch arrays.
    """
    for i in range(3):
        for j in range(3):
            B[i, j] = s[0, i] * s[0, j] + s[1, i] * s[1, j] + s[2, i] * s[2, j]
    tr = B[0, 0] + B[1, 1] + B[2, 2]
    principal_eigenvector(B, work_a, work_b, v)
    sign = 1.0
    if v[0] * hemisphere[0] + v[1] * hemisphere[1] + v[2] * hemisphere[2] < 0.0:
        sign = -1.0
    rng = sign * (6.0 / tr) ** (1.0 / 6.0)  # eq. 75
    x = rng * v[0]
    y = rng * v[1]
    z = rng * v[2]
    r_out[0] = x
    r_out[1] = y
    r_out[2] = z
    # K = f_D(r) Sᵀ; the rotation maximising tr(Tᵀ K) minimises ‖S − Tᵀ f_D‖
    field_matrix(x, y, z, F)
    for i in range(3):
        for j in range(3):
            K[i, j] = F[i, 0] * s[j, 0] + F[i, 1] * s[j, 1] + F[i, 2] * s[j, 2]
    rotation_polar_factor(K, work_a, work_b, T_out)


@numba.njit(**_OPTS)
def closed_form_pose_kernel(S, hemisphere, r_out, T_out):  # pragma: no cover - compiled
    """Closed-form dipole pose (docs/math.md §3) of each S[n]."""
    for n in numba.prange(S.shape[0]):
        closed_form_one(S[n], hemisphere, r_out[n], T_out[n], np.empty((3, 3)), np.empty((3, 3)), np.empty(3),
                        np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)))


#: the names ivc.correct.kernels and ivc.correct.pose_kernels still import (until their own rework)
_rotation_polar_factor, _principal_eigenvector = rotation_polar_factor, principal_eigenvector
