"""The kernels of :mod:`ivc.dipole.kernels` in vectorised NumPy, same arguments, same arithmetic in the
same order (so results agree to rounding, tested to 1e-12): what a command runs on a small input
while the compiled kernels are not yet in numba's cache (:func:`ivc.compiled.choose`)."""

from __future__ import annotations

import numpy as np


def _entries(r):
    x, y, z = r[:, 0], r[:, 1], r[:, 2]
    rho2 = x * x + y * y + z * z
    inv3 = 1.0 / (rho2 * np.sqrt(rho2))
    inv5 = 3.0 * inv3 / rho2
    return inv5 * x * x - inv3, inv5 * y * y - inv3, inv5 * z * z - inv3, inv5 * x * y, inv5 * x * z, inv5 * y * z


def _field_into(r, out):
    f00, f11, f22, f01, f02, f12 = _entries(r)
    out[:, 0, 0], out[:, 1, 1], out[:, 2, 2] = f00, f11, f22
    out[:, 0, 1] = out[:, 1, 0] = f01
    out[:, 0, 2] = out[:, 2, 0] = f02
    out[:, 1, 2] = out[:, 2, 1] = f12


def field_kernel(r, out):
    """f_D(r[n]) (eq. 72) into out (M, 3, 3)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        _field_into(r, out)


def signal_kernel(r, T, out):
    """out[n] = T[n]ᵀ f_D(r[n]) (eq. 73 with G = 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        f00, f11, f22, f01, f02, f12 = _entries(r)
        for i in range(3):
            a, b, c = T[:, 0, i], T[:, 1, i], T[:, 2, i]
            out[:, i, 0] = a * f00 + b * f01 + c * f02
            out[:, i, 1] = a * f01 + b * f11 + c * f12
            out[:, i, 2] = a * f02 + b * f12 + c * f22


def _matmul3(A, B):
    return (A[:, :, 0, None] * B[:, None, 0, :] + A[:, :, 1, None] * B[:, None, 1, :]
            + A[:, :, 2, None] * B[:, None, 2, :])


def _trace(A):
    return A[:, 0, 0] + A[:, 1, 1] + A[:, 2, 2]


def _det3(A):
    return (A[:, 0, 0] * (A[:, 1, 1] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 1])
            - A[:, 0, 1] * (A[:, 1, 0] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 0])
            + A[:, 0, 2] * (A[:, 1, 0] * A[:, 2, 1] - A[:, 1, 1] * A[:, 2, 0]))


def _inverse_transpose3(A):
    d = _det3(A)
    out = np.empty_like(A)
    out[:, 0, 0] = (A[:, 1, 1] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 1]) / d
    out[:, 0, 1] = -(A[:, 1, 0] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 0]) / d
    out[:, 0, 2] = (A[:, 1, 0] * A[:, 2, 1] - A[:, 1, 1] * A[:, 2, 0]) / d
    out[:, 1, 0] = -(A[:, 0, 1] * A[:, 2, 2] - A[:, 0, 2] * A[:, 2, 1]) / d
    out[:, 1, 1] = (A[:, 0, 0] * A[:, 2, 2] - A[:, 0, 2] * A[:, 2, 0]) / d
    out[:, 1, 2] = -(A[:, 0, 0] * A[:, 2, 1] - A[:, 0, 1] * A[:, 2, 0]) / d
    out[:, 2, 0] = (A[:, 0, 1] * A[:, 1, 2] - A[:, 0, 2] * A[:, 1, 1]) / d
    out[:, 2, 1] = -(A[:, 0, 0] * A[:, 1, 2] - A[:, 0, 2] * A[:, 1, 0]) / d
    out[:, 2, 2] = (A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]) / d
    return out


def _sum_in_order(A):
    """Σ_ij A_ij in row-major order (as the compiled loops add them)."""
    s = np.zeros(len(A))
    for i in range(3):
        for j in range(3):
            s = s + A[:, i, j]
    return s


def _principal_eigenvector(B):
    """ivc.linalg.principal_eigenvector for every B[n]: repeated squaring, then two power steps."""
    a = B / _trace(B)[:, None, None]
    for _ in range(12):
        b = _matmul3(a, a)
        a = b / _trace(b)[:, None, None]
    norms = a[:, 0, :] ** 2 + a[:, 1, :] ** 2 + a[:, 2, :] ** 2  # (M, 3): column norms
    v = np.take_along_axis(a, np.argmax(norms, axis=1)[:, None, None], axis=2)[:, :, 0]
    for _ in range(2):
        w = B[:, :, 0] * v[:, 0, None] + B[:, :, 1] * v[:, 1, None] + B[:, :, 2] * v[:, 2, None]
        v = w / np.sqrt(w[:, 0] * w[:, 0] + w[:, 1] * w[:, 1] + w[:, 2] * w[:, 2])[:, None]
    return v


def _rotation_polar_factor(K):
    """ivc.linalg.rotation_polar_factor for every K[n]: scaled Newton, SVD where det K <= 0."""
    out = np.full_like(K, np.nan)
    det = _det3(K)
    newton = det > 0.0
    flip = ~newton & np.isfinite(det)
    if flip.any():
        U, _, Vt = np.linalg.svd(K[flip])
        d = np.sign(_det3(U) * _det3(Vt))
        U[:, :, 2] *= d[:, None]
        out[flip] = _matmul3(U, Vt)
    X = K[newton].copy()
    active = np.arange(len(X))
    done = np.empty_like(X)
    for it in range(60):
        if not len(active):
            break
        Xa = X[active]
        work = _inverse_transpose3(Xa)
        fro_w = np.sqrt(_sum_in_order(work * work))
        fro_x = np.sqrt(_sum_in_order(Xa * Xa))
        gamma = np.sqrt(fro_w / fro_x) if it < 10 else np.ones(len(Xa))
        new = 0.5 * (gamma[:, None, None] * Xa + work / gamma[:, None, None])
        change = _sum_in_order((new - Xa) ** 2)
        X[active] = new
        stop = change < 1e-30
        done[active[stop]] = new[stop]
        active = active[~stop]
    done[active] = X[active]
    out[newton] = done
    return out


def closed_form_pose_kernel(S, hemisphere, r_out, T_out):
    """Closed-form dipole pose (docs/math.md §3) of each S[n], as ivc.dipole.kernels.closed_form_pose_kernel."""
    with np.errstate(all="ignore"):
        B = S[:, 0, :, None] * S[:, 0, None, :] + S[:, 1, :, None] * S[:, 1, None, :] \
            + S[:, 2, :, None] * S[:, 2, None, :]
        tr = _trace(B)
        v = _principal_eigenvector(B)
        side = v[:, 0] * hemisphere[0] + v[:, 1] * hemisphere[1] + v[:, 2] * hemisphere[2]
        sign = np.where(side < 0.0, -1.0, 1.0)
        rng = sign * (6.0 / tr) ** (1.0 / 6.0)
        r_out[:] = rng[:, None] * v
        F = np.empty_like(S)
        _field_into(r_out, F)
        K = F[:, :, 0, None] * S[:, None, :, 0] + F[:, :, 1, None] * S[:, None, :, 1] \
            + F[:, :, 2, None] * S[:, None, :, 2]
        T_out[:] = _rotation_polar_factor(K)
