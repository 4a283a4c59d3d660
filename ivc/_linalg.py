"""Compiled small dense linear algebra shared by the numba kernels (correction, prediction filters).

Matrices are at most a few rows; ``n`` (and ``m``) give the size used, so callers can pass
larger scratch arrays. Every function is inlined into its caller.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(inline="always")
def cholesky(S, n, L):
    """Lower Cholesky factor of the symmetric n x n matrix S into L (L may be S: in place).

    Returns False when S is not positive definite (or holds NaN).
    """
    for i in range(n):
        for j in range(i + 1):
            acc = S[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if not acc > 0.0:
                    return False
                L[i, i] = np.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    return True


@numba.njit(inline="always")
def cholesky_logdet(L, n):
    """log det S from its Cholesky factor L."""
    det = 1.0
    for i in range(n):
        det *= L[i, i]
    return 2.0 * np.log(det)  # one log: det L stays far inside the float range for these small matrices


@numba.njit(inline="always")
def cholesky_solve(L, n, b, x):
    """Solve (L Lᵀ) x = b, L from :func:`cholesky`."""
    for i in range(n):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * x[k]
        x[i] = acc / L[i, i]
    for i in range(n - 1, -1, -1):
        acc = x[i]
        for k in range(i + 1, n):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]


@numba.njit(inline="always")
def cholesky_inverse(L, n, out):
    """out = S⁻¹ (n x n, symmetric) from the Cholesky factor L of S: one reciprocal per row, no solves."""
    # out's lower triangle first holds M = L⁻¹ (forward substitution on the columns of I)
    for j in range(n):
        out[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            acc = 0.0
            for k in range(j, i):
                acc -= L[i, k] * out[k, j]
            out[i, j] = acc / L[i, i]
    # S⁻¹ = Mᵀ M, built from the top row down so each M entry is read before it is overwritten
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(j, n):
                acc += out[k, i] * out[k, j]
            out[i, j] = acc
    for i in range(n):
        for j in range(i):
            out[i, j] = out[j, i]


@numba.njit(inline="always")
def congruence(A, P, n, T, out, ncols):
    """out = A P Aᵀ (n x n, symmetric by construction); T is n x n scratch.

    A's columns from ``ncols`` on must be those of I (pass n for a general A); they are not read,
    and the products skip them: the terms skipped are exact zeros, so the result is the same to the bit.
    """
    for a in range(n):
        for b in range(n):
            acc = 0.0
            for c in range(ncols):
                acc += A[a, c] * P[c, b]
            T[a, b] = acc + P[a, b] if a >= ncols else acc
    for a in range(n):
        for b in range(a + 1):
            acc = 0.0
            for c in range(ncols):
                acc += T[a, c] * A[b, c]
            out[a, b] = acc + T[a, b] if b >= ncols else acc
            out[b, a] = out[a, b]


@numba.njit(inline="always")
def joseph(IKH, Pp, K, R, n, m, T, P, ncols):
    """Joseph-form covariance update P = (I − KH) P⁻ (I − KH)ᵀ + K diag(R) Kᵀ; IKH = I − KH (n x n), K n x m.

    H's columns from ``ncols`` on are zero (pass n for a general H), so those of I − KH are I's.
    """
    congruence(IKH, Pp, n, T, P, ncols)
    for a in range(n):
        for b in range(a + 1):
            acc = P[a, b]
            for r in range(m):
                acc += K[a, r] * R[r] * K[b, r]
            P[a, b] = acc
            P[b, a] = acc
