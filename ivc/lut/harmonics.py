"""Regular solid harmonics and their gradients, for fields that are gradients of harmonic potentials.

Complex regular solid harmonics normalised as ``R_l^m = r^l P_l^m(cos θ) e^{imφ} / (l + m)!``
(Condon-Shortley phase) obey simple recurrences and derivative ladders:

    R_l^l = −(x + iy) R_{l−1}^{l−1} / (2l)
    R_l^m = ((2l − 1) z R_{l−1}^m − r² R_{l−2}^m) / ((l + m)(l − m))
    ∂_z R_l^m = R_{l−1}^m,   ∂_x R_l^m = (R_{l−1}^{m+1} − R_{l−1}^{m−1}) / 2,
    ∂_y R_l^m = −i (R_{l−1}^{m−1} + R_{l−1}^{m+1}) / 2,   R_l^{−m} = (−1)^m conj(R_l^m).

The real basis of degree ``l`` is ``Re R_l^0``, and ``Re R_l^m``, ``Im R_l^m`` for ``m = 1..l``:
``2l + 1`` harmonic functions, so degrees ``1..L`` give ``(L + 1)² − 1`` potentials.
"""

from __future__ import annotations

import numpy as np

from ivc.errors import InputError


def count(degree: int) -> int:
    """Number of real harmonic potentials of degrees 1..degree."""
    return (degree + 1) ** 2 - 1


def _complex_harmonics(x: np.ndarray, degree: int) -> np.ndarray:
    """``R[l, m]`` (degree + 1, degree + 1, N) for m = 0..l (zero above the diagonal)."""
    X, Y, Z = x[:, 0], x[:, 1], x[:, 2]
    w = X + 1j * Y
    r2 = X * X + Y * Y + Z * Z
    R = np.zeros((degree + 1, degree + 1, len(x)), dtype=complex)
    R[0, 0] = 1.0
    for l in range(1, degree + 1):  # noqa: E741 - l is the degree, as in the literature
        R[l, l] = -w * R[l - 1, l - 1] / (2 * l)
        for m in range(l):
            previous = R[l - 2, m] if l >= 2 else 0.0
            R[l, m] = ((2 * l - 1) * Z * R[l - 1, m] - r2 * previous) / ((l + m) * (l - m))
    return R


def gradients(x: np.ndarray, degree: int) -> np.ndarray:
    """Gradients (N, count(degree), 3) of the real harmonic potentials of degree 1..degree at x (N, 3).

    Ordered by degree, then ``Re R_l^0, Re R_l^1, Im R_l^1, …, Re R_l^l, Im R_l^l``, so the
    basis of a lower degree is a prefix of a higher one.
    """
    x = np.asarray(x, float)
    R = _complex_harmonics(x, degree - 1)

    def lower(l, m):  # R_l^m for any m, zero outside |m| <= l
        if abs(m) > l:
            return 0.0
        return R[l, m] if m >= 0 else (-1) ** m * np.conj(R[l, -m])

    out = np.empty((len(x), count(degree), 3))
    k = 0
    for l in range(1, degree + 1):  # noqa: E741
        for m in range(l + 1):
            up, down = lower(l - 1, m + 1), lower(l - 1, m - 1)
            grad = np.stack(np.broadcast_arrays((up - down) / 2, -0.5j * (down + up), lower(l - 1, m)), axis=-1)
            out[:, k] = grad.real
            k += 1
            if m > 0:
                out[:, k] = grad.imag
                k += 1
    return out


def gradient_rows(x: np.ndarray, degree: int, out: np.ndarray | None = None) -> np.ndarray:
    """The gradients of :func:`gradients`, compiled and laid out as (N, 3, count(degree)): row
    ``(n, i)`` holds ``∂_i Φ_k`` of every potential at point n, so ``reshape(-1, K)`` is the
    design matrix of the (sample, component) rows without a copy. ``out``: an array to fill."""
    from ivc.table.kernels import harmonic_gradient_rows

    x = np.ascontiguousarray(np.asarray(x, float).reshape(-1, 3))
    K = count(degree)
    if out is None:
        out = np.empty((len(x), 3, K))
    elif out.shape != (len(x), 3, K) or not out.flags.c_contiguous or out.dtype != np.float64:
        raise InputError(f"out must be a C-contiguous float64 array of shape {(len(x), 3, K)}")
    harmonic_gradient_rows(x, int(degree), out)
    return out
