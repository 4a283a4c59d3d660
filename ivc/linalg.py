"""The compiled small-matrix and quaternion primitives every numba kernel of ivc uses (one set).

Dense n x n algebra (Cholesky, its solve and inverse, the Kalman update of the filters), 3 x 3 algebra
(product, determinant, inverse transpose, the principal eigenvector of a symmetric matrix, the
nearest rotation), rotations (the right increment ``T exp([w]×)``, the canonical quaternion of a
matrix) and quaternions (scalar-first Hamilton, as ``ivc.rotations``: products, normalisation,
the matrices of ``q ⊗ (0, ω)``). Matrices are at most a few rows; ``n`` (and ``m``) give the size
used, so callers can pass larger scratch arrays. Most are inlined into their caller
(``inline="always"``); the few larger ones (eigenvector, polar factor) are compiled once and called.
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
def cholesky_inverse(L, n):
    """S⁻¹ in place of S's Cholesky factor L (n x n, from :func:`cholesky`; its upper triangle is overwritten
    too): L⁻¹ by forward substitution column by column, then S⁻¹ = L⁻ᵀ L⁻¹, symmetric, without scratch."""
    for j in range(n):  # the lower triangle becomes L⁻¹
        L[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            acc = 0.0
            for k in range(j, i):
                acc -= L[i, k] * L[k, j]
            L[i, j] = acc / L[i, i]
    for i in range(n):  # (L⁻ᵀ L⁻¹)_ij, i <= j, = Σ_{k >= j} (L⁻¹)_ki (L⁻¹)_kj: into the upper triangle, which is free
        for j in range(i, n):
            acc = 0.0
            for k in range(j, n):
                acc += L[k, i] * L[k, j]
            if i == j:
                diagonal = acc
            else:
                L[i, j] = acc
        L[i, i] = diagonal
    for i in range(n):
        for j in range(i + 1, n):
            L[j, i] = L[i, j]


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


@numba.njit(inline="always")
def solve_spd6(A, b, x):
    """x = A⁻¹ b for a symmetric positive definite 6x6 A (Cholesky, in place on A). False if not PD."""
    if not cholesky(A, 6, A):
        return False
    cholesky_solve(A, 6, b, x)
    return True


@numba.njit(inline="always")
def copy_pose(r, T, r_out, T_out):
    """r_out (3,) = r and T_out (3, 3) = T, entry by entry: an array assigned to a slice (``r_out[:] = r``) makes
    numba compile the message of its shape check (string formatting: seconds on a cold cache, docs/kernels.md)."""
    for a in range(3):
        r_out[a] = r[a]
        for b in range(3):
            T_out[a, b] = T[a, b]


@numba.njit(inline="always")
def matmul3(A, B, out):
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@numba.njit(inline="always")
def det3(A):
    return (
        A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
        - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
        + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0])
    )


@numba.njit(inline="always")
def inverse_transpose3(A, out):
    """out = A⁻ᵀ, by cofactors."""
    d = det3(A)
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
def frobenius3(A):
    s = 0.0
    for i in range(3):
        for j in range(3):
            s += A[i, j] * A[i, j]
    return np.sqrt(s)


@numba.njit(cache=True)
def relative_residual(S, M, T):
    """rms(M − T S) / rms(S) of a pose (T (3, 3)) against the model M (3, 3) of the signal S (3, 3); NaN for a
    signal of zeros or denormals (no pose)."""
    lam = 0.0
    s2 = 0.0
    for i in range(3):
        for j in range(3):
            p = T[i, 0] * S[0, j] + T[i, 1] * S[1, j] + T[i, 2] * S[2, j]
            lam += (M[i, j] - p) ** 2
            s2 += S[i, j] ** 2
    return np.sqrt(lam / s2) if s2 > 0.0 else np.nan


@numba.njit(inline="always")
def finite3(v, A):
    """Whether every entry of v (3,) and A (3, 3) is finite (a sample a kernel can solve)."""
    finite = np.isfinite(v[0]) and np.isfinite(v[1]) and np.isfinite(v[2])
    for i in range(3):
        for j in range(3):
            finite = finite and np.isfinite(A[i, j])
    return finite


@numba.njit(cache=True, error_model="numpy")  # not inlined: compiled once; inf/NaN as in a parallel kernel
def principal_eigenvector(B, v):
    """Unit eigenvector v (3,) of the largest eigenvalue of a symmetric PSD 3x3 matrix B (its upper triangle
    is read for the squarings).

    Power iteration by repeated squaring: after k squarings the other eigen-directions
    are suppressed by (λ2/λ1)^(2^k). In free space λ2/λ1 = 1/4, so 8 squarings leave
    nothing; 12 cover strongly distorted fields too. The squared matrix stays exactly symmetric
    (its (i, j) and (j, i) entries are the same products summed in the same order), so its six
    distinct entries are held in registers and each is computed once: the same numbers as the full
    3 x 3 product, in half the time.
    """
    tr = B[0, 0] + B[1, 1] + B[2, 2]
    a00, a01, a02 = B[0, 0] / tr, B[0, 1] / tr, B[0, 2] / tr
    a11, a12, a22 = B[1, 1] / tr, B[1, 2] / tr, B[2, 2] / tr
    p00, p01, p02, p11, p12, p22 = np.nan, np.nan, np.nan, np.nan, np.nan, np.nan  # the matrix two squarings back
    for k in range(12):
        b00 = a00 * a00 + a01 * a01 + a02 * a02
        b01 = a00 * a01 + a01 * a11 + a02 * a12
        b02 = a00 * a02 + a01 * a12 + a02 * a22
        b11 = a01 * a01 + a11 * a11 + a12 * a12
        b12 = a01 * a02 + a11 * a12 + a12 * a22
        b22 = a02 * a02 + a12 * a12 + a22 * a22
        t = b00 + b11 + b22
        b00, b01, b02, b11, b12, b22 = b00 / t, b01 / t, b02 / t, b11 / t, b12 / t, b22 / t
        # once converged, the rounding makes the squarings repeat with period 1 or 2: the rest is known
        if b00 == a00 and b01 == a01 and b02 == a02 and b11 == a11 and b12 == a12 and b22 == a22:
            break
        if b00 == p00 and b01 == p01 and b02 == p02 and b11 == p11 and b12 == p12 and b22 == p22:
            if (11 - k) % 2 == 1:  # an odd number of squarings left: they end on the other matrix of the cycle
                b00, b01, b02, b11, b12, b22 = a00, a01, a02, a11, a12, a22
            a00, a01, a02, a11, a12, a22 = b00, b01, b02, b11, b12, b22
            break
        p00, p01, p02, p11, p12, p22 = a00, a01, a02, a11, a12, a22
        a00, a01, a02, a11, a12, a22 = b00, b01, b02, b11, b12, b22
    # the column of largest norm (the first of equal ones)
    v[0], v[1], v[2] = a00, a01, a02
    best_norm = a00 ** 2 + a01 ** 2 + a02 ** 2
    nrm = a01 ** 2 + a11 ** 2 + a12 ** 2
    if nrm > best_norm:
        best_norm = nrm
        v[0], v[1], v[2] = a01, a11, a12
    if a02 ** 2 + a12 ** 2 + a22 ** 2 > best_norm:
        v[0], v[1], v[2] = a02, a12, a22
    # two plain power steps with B itself polish the last bits
    for _ in range(2):
        w0 = B[0, 0] * v[0] + B[0, 1] * v[1] + B[0, 2] * v[2]
        w1 = B[1, 0] * v[0] + B[1, 1] * v[1] + B[1, 2] * v[2]
        w2 = B[2, 0] * v[0] + B[2, 1] * v[1] + B[2, 2] * v[2]
        nrm = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        v[0] = w0 / nrm
        v[1] = w1 / nrm
        v[2] = w2 / nrm


@numba.njit(cache=True, error_model="numpy")  # a zero determinant or norm mid-iteration: NaN below, not an exception
def rotation_polar_factor(K, X, work, out):
    """Rotation nearest to K (orthogonal Procrustes), written into out.

    Scaled Newton iteration for the polar factor, X <- (γX + X⁻ᵀ/γ)/2, which converges
    quadratically to U Vᵀ when det K > 0. When det K <= 0 the nearest *rotation* is
    U diag(1, 1, -1) Vᵀ, which Newton cannot reach: fall back to an SVD.
    """
    if not det3(K) > 0.0:
        if not np.isfinite(det3(K)):
            for i in range(3):
                for j in range(3):
                    out[i, j] = np.nan
            return
        U, _, Vt = np.linalg.svd(K)
        d = np.sign(det3(U) * det3(Vt))
        for i in range(3):
            U[i, 2] *= d
        matmul3(U, Vt, out)
        return
    for i in range(3):
        for j in range(3):
            X[i, j] = K[i, j]
    for it in range(60):
        inverse_transpose3(X, work)
        gamma = np.sqrt(frobenius3(work) / frobenius3(X)) if it < 10 else 1.0
        if not (gamma > 0.0 and np.isfinite(gamma)):  # K at the edge of double precision (huge or denormal)
            for i in range(3):
                for j in range(3):
                    out[i, j] = np.nan
            return
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


@numba.njit(cache=True)
def rotate_increment(T, w, out):
    """out = T exp([w]×) (Rodrigues: exp([w]×) = I + a [w]× + b [w]×²)."""
    angle2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    if angle2 < 1e-24:
        a, b = 1.0, 0.5
    else:
        angle = np.sqrt(angle2)
        a, b = np.sin(angle) / angle, (1.0 - np.cos(angle)) / angle2
    x, y, z = w[0], w[1], w[2]
    r00 = 1.0 - b * (y * y + z * z)
    r11 = 1.0 - b * (x * x + z * z)
    r22 = 1.0 - b * (x * x + y * y)
    r01 = -a * z + b * x * y
    r10 = a * z + b * x * y
    r02 = a * y + b * x * z
    r20 = -a * y + b * x * z
    r12 = -a * x + b * y * z
    r21 = a * x + b * y * z
    for i in range(3):
        t0, t1, t2 = T[i, 0], T[i, 1], T[i, 2]
        out[i, 0] = t0 * r00 + t1 * r10 + t2 * r20
        out[i, 1] = t0 * r01 + t1 * r11 + t2 * r21
        out[i, 2] = t0 * r02 + t1 * r12 + t2 * r22


@numba.njit(inline="always")
def quaternion_of(T, q):
    """Canonical unit quaternion of a rotation matrix, as ivc.rotations.from_matrix (Shepperd, then the
    sign rule of ivc.rotations.canonical), into q (4,)."""
    t00, t11, t22 = T[0, 0], T[1, 1], T[2, 2]
    d21, d02, d10 = T[2, 1] - T[1, 2], T[0, 2] - T[2, 0], T[1, 0] - T[0, 1]
    s01, s02, s12 = T[0, 1] + T[1, 0], T[0, 2] + T[2, 0], T[1, 2] + T[2, 1]
    sq0, sq1, sq2, sq3 = 1.0 + t00 + t11 + t22, 1.0 + t00 - t11 - t22, 1.0 - t00 + t11 - t22, 1.0 - t00 - t11 + t22
    largest = 0
    top = sq0
    if sq1 > top:
        largest, top = 1, sq1
    if sq2 > top:
        largest, top = 2, sq2
    if sq3 > top:
        largest, top = 3, sq3
    big = 0.5 * np.sqrt(max(top, 0.0))
    k = 0.25 / big
    if largest == 0:
        q[0], q[1], q[2], q[3] = big, d21 * k, d02 * k, d10 * k
    elif largest == 1:
        q[0], q[1], q[2], q[3] = d21 * k, big, s01 * k, s02 * k
    elif largest == 2:
        q[0], q[1], q[2], q[3] = d02 * k, s01 * k, big, s12 * k
    else:
        q[0], q[1], q[2], q[3] = d10 * k, s02 * k, s12 * k, big
    norm = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sign = 1.0
    for a in range(4):
        if abs(q[a] / norm) > 1e-12:
            if q[a] < 0.0:
                sign = -1.0
            break
    for a in range(4):
        q[a] = sign * q[a] / norm


@numba.njit(inline="always")
def qmul(p, q, out):
    """out = p ⊗ q (out may not alias p or q)."""
    out[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3]
    out[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2]
    out[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1]
    out[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0]


@numba.njit(inline="always")
def qmul_conj(p, q, out):
    """out = p ⊗ q* (the rotation from q to p for unit quaternions)."""
    out[0] = p[0] * q[0] + p[1] * q[1] + p[2] * q[2] + p[3] * q[3]
    out[1] = -p[0] * q[1] + p[1] * q[0] - p[2] * q[3] + p[3] * q[2]
    out[2] = -p[0] * q[2] + p[1] * q[3] + p[2] * q[0] - p[3] * q[1]
    out[3] = -p[0] * q[3] - p[1] * q[2] + p[2] * q[1] + p[3] * q[0]


@numba.njit(inline="always")
def quaternion_normalise(q):
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    for i in range(4):
        q[i] /= n


@numba.njit(cache=True, inline="always")
def q_matrix(q, out):
    """Q_r(q) (4, 3), eq. 18 corrected: q ⊗ (0, ω) = Q_r(q) ω."""
    out[0, 0], out[0, 1], out[0, 2] = -q[1], -q[2], -q[3]
    out[1, 0], out[1, 1], out[1, 2] = q[0], -q[3], q[2]
    out[2, 0], out[2, 1], out[2, 2] = q[3], q[0], -q[1]
    out[3, 0], out[3, 1], out[3, 2] = -q[2], q[1], q[0]


@numba.njit(cache=True, inline="always")
def omega_matrix(w, out):
    """Ω_r(ω) (4, 4), eq. 19: q ⊗ (0, ω) = Ω_r(ω) q."""
    out[0, 0], out[0, 1], out[0, 2], out[0, 3] = 0.0, -w[0], -w[1], -w[2]
    out[1, 0], out[1, 1], out[1, 2], out[1, 3] = w[0], 0.0, w[2], -w[1]
    out[2, 0], out[2, 1], out[2, 2], out[2, 3] = w[1], -w[2], 0.0, w[0]
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = w[2], w[1], -w[0], 0.0

