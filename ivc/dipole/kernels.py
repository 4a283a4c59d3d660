"""Compiled per-sample kernels behind :mod:`ivc.dipole` (numba, parallel over samples).

Each kernel takes flat arrays (M samples) and writes into a preallocated output.
The public, shape-checking, documented functions live in ``field.py`` and ``pose.py``;
the pure-NumPy forms of the same equations are in the tests as a reference.
"""

from __future__ import annotations

import numba
import numpy as np

from ivc.linalg import principal_eigenvector, rotation_polar_factor

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


@numba.njit(inline="always")
def dipole_jacobian(r, dM):
    """∂f_D/∂r (3, 3, 3) at r: 3 (δ_ik r_j + δ_jk r_i + δ_ij r_k)/|r|⁵ − 15 r_i r_j r_k/|r|⁷."""
    rho2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    inv5 = 1.0 / (rho2 * rho2 * np.sqrt(rho2))
    inv7 = inv5 / rho2
    for i in range(3):
        for j in range(3):
            for k in range(3):
                s = 0.0
                if i == k:
                    s += r[j]
                if j == k:
                    s += r[i]
                if i == j:
                    s += r[k]
                dM[i, j, k] = 3.0 * s * inv5 - 15.0 * r[i] * r[j] * r[k] * inv7


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


@numba.njit(cache=True, error_model="numpy")  # compiled once; inf/NaN as in a parallel kernel
def closed_form_position(S, hemisphere, r, v, B):
    """The position of :func:`closed_form_one` (the same operations) into r (3,), without the orientation: range
    from tr SᵀS, direction its principal eigenvector on the hemisphere's side (docs/math.md §3)."""
    for i in range(3):
        for j in range(3):
            B[i, j] = S[0, i] * S[0, j] + S[1, i] * S[1, j] + S[2, i] * S[2, j]
    tr = B[0, 0] + B[1, 1] + B[2, 2]
    principal_eigenvector(B, v)
    sign = 1.0
    if v[0] * hemisphere[0] + v[1] * hemisphere[1] + v[2] * hemisphere[2] < 0.0:
        sign = -1.0
    rng = sign * (6.0 / tr) ** (1.0 / 6.0)  # docs/math.md §3
    for a in range(3):
        r[a] = rng * v[a]



@numba.njit(cache=True, error_model="numpy")  # not inlined: compiled once; inf/NaN as in a parallel kernel
def closed_form_one(s, hemisphere, r_out, T_out, work_a, work_b, v, B, F, K):
    """Closed-form dipole pose (docs/math.md §3) of one signal matrix s, into r_out (3,) and T_out (3, 3).

    ``work_a``, ``work_b``, ``B``, ``F``, ``K`` are (3, 3) and ``v`` (3,) scratch arrays.
    """
    closed_form_position(s, hemisphere, r_out, v, B)  # eq. 75
    # K = f_D(r) Sᵀ; the rotation maximising tr(Tᵀ K) minimises ‖S − Tᵀ f_D‖
    field_matrix(r_out[0], r_out[1], r_out[2], F)
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

