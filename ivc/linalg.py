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
def factored_update(L, PHt, nu, xp, Pp, n, m, U, w, x, P):
    """Kalman update with the optimal gain through the Cholesky factor L of S = H P⁻ Hᵀ + R (m x m).

    With U = P⁻Hᵀ L⁻ᵀ (n x m) and w = L⁻¹ ν: K = U L⁻¹, x = x⁻ + U w and
    P = P⁻ − K S Kᵀ = P⁻ − U Uᵀ, symmetric by construction, for a quarter of the Joseph form's
    products. Returns νᵀ S⁻¹ ν = wᵀ w, or −1 (x and P untouched) when a posterior variance
    is not positive (the subtraction lost it to rounding). x and P may be xp and Pp, and w may be
    nu (the forward substitution reads each ν entry before it writes the same entry of w).
    """
    maha = 0.0
    for r in range(m):
        acc = nu[r]
        for c in range(r):
            acc -= L[r, c] * w[c]
        w[r] = acc / L[r, r]
        maha += w[r] * w[r]
    for a in range(n):
        for r in range(m):
            acc = PHt[a, r]
            for c in range(r):
                acc -= L[r, c] * U[a, c]
            U[a, r] = acc / L[r, r]
        acc = Pp[a, a]
        for r in range(m):
            acc -= U[a, r] * U[a, r]
        if not acc > 0.0:
            return -1.0
    for a in range(n):
        acc = xp[a]
        for r in range(m):
            acc += U[a, r] * w[r]
        x[a] = acc
    for a in range(n):
        for b in range(a + 1):
            acc = Pp[a, b]
            for r in range(m):
                acc -= U[a, r] * U[b, r]
            P[a, b] = acc
            P[b, a] = acc
    return maha


@numba.njit(inline="always")
def congruence(A, P, n, T, out):
    """out = A P Aᵀ (n x n, symmetric by construction); T is n x n scratch."""
    for a in range(n):
        for b in range(n):
            acc = 0.0
            for c in range(n):
                acc += A[a, c] * P[c, b]
            T[a, b] = acc
    for a in range(n):
        for b in range(a + 1):
            acc = 0.0
            for c in range(n):
                acc += T[a, c] * A[b, c]
            out[a, b] = acc
            out[b, a] = acc
