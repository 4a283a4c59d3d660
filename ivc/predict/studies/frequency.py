"""Frequency-domain analysis of linear predictors (Azuma & Bishop 1995; docs/math.md §16): a study.

Reproduces Azuma & Bishop 1995's transfer functions and their steady-state Kalman cases (the
tables of docs/predict.md); the predictors themselves live in :mod:`ivc.predict`, which does
not import this module.

Equations: docs/math.md §16.

A linear predictor with steady-state recursion ``X(k) = G X(k−1) + K Y(k)`` and output
``D(p) X(k)`` has the transfer function ``O(z) = D (zI − G)⁻¹ z K M(ω)`` at z = e^{jωT}, where
M(ω) generates the measurements a sinusoid would give (position, velocity ``jω``,
acceleration ``−ω²``). For A&B's Kalman cases ``G = A − K H A``. The ideal predictor is
``e^{jωp}``; the error transfer function is ``U = O − e^{jωp}`` and the RMS error of a unit
sinusoid is ``|U|/√2`` (docs/math.md §16.6, closed form). Frequencies f are in Hz, p and T in seconds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

#: A&B95 do not give their sample period; 5 ms reproduces all their crossovers (docs/math.md §16.3)
AB_PERIOD = 1.0 / 200.0


def polynomial_response(f: ArrayLike, p: float, order: int = 2) -> ComplexArray:
    """H/G of polynomial extrapolation with exact derivatives: 1 + jωp (− ½(ωp)² for order 2)."""
    u = 2j * np.pi * np.asarray(f, dtype=float) * p
    return 1 + u + (u**2 / 2 if order == 2 else 0)


def polynomial_magnitude(f: ArrayLike, p: float) -> FloatArray:
    """Eq. 1: |H/G| = √(1 + (ωp)⁴/4)."""
    u = 2 * np.pi * np.asarray(f, dtype=float) * p
    return np.sqrt(1 + u**4 / 4)


def polynomial_phase(f: ArrayLike, p: float) -> FloatArray:
    """Eq. 2 with atan2 (rad): phase lead atan2(ωp, 1 − (ωp)²/2), 90° at ωp = √2, → 180°."""
    u = 2 * np.pi * np.asarray(f, dtype=float) * p
    return np.arctan2(u, 1 - u**2 / 2)


def rms_error(response: ArrayLike, f: ArrayLike, p: float) -> FloatArray:
    """RMS error of a unit sinusoid: |O − e^{jωp}|/√2 (A&B §6.1 in closed form)."""
    return np.abs(np.asarray(response) - np.exp(2j * np.pi * np.asarray(f, dtype=float) * p)) / np.sqrt(2)


def response(f: ArrayLike, T: float, G: ArrayLike, K: ArrayLike, D: ArrayLike,
             M: Callable[[float], ArrayLike] | None = None) -> ComplexArray:
    """O(e^{jωT}) = D (zI − G)⁻¹ z K M(ω) for each f (Hz); M defaults to position only ([1])."""
    G, K, D = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (G, K, D))
    if K.shape[0] != G.shape[0]:
        K = K.T
    f = np.atleast_1d(np.asarray(f, dtype=float))
    n = G.shape[0]
    out = np.empty(f.shape, complex)
    for i, fi in enumerate(f):  # one small complex solve per frequency
        w = 2 * np.pi * fi
        z = np.exp(1j * w * T)
        m = np.ones((1, 1)) if M is None else np.asarray(M(w), complex).reshape(-1, 1)
        C = np.linalg.solve(z * np.eye(n) - G, z * K)
        out[i] = (D @ C @ m)[0, 0]
    return out


def crossovers(f: ArrayLike, a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Frequencies where curves a and b cross (linear interpolation of a − b between samples)."""
    f, d = np.asarray(f, dtype=float), np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    i = np.nonzero(np.sign(d[:-1]) * np.sign(d[1:]) < 0)[0]
    return f[i] - d[i] * (f[i + 1] - f[i]) / (d[i + 1] - d[i])


@dataclass(frozen=True)
class ABCase:
    """One of A&B95's steady-state Kalman + polynomial predictors (docs/math.md §16.3)."""

    name: str
    H: FloatArray
    K: FloatArray
    derivatives: tuple[int, ...]  # measured derivative orders: 0 position, 1 velocity, 2 acceleration

    def A(self, T: float) -> FloatArray:
        n = self.K.shape[0]
        return np.array([[1, T], [0, 1]]) if n == 2 else np.array([[1, T, T * T / 2], [0, 1, T], [0, 0, 1]])

    def G(self, T: float) -> FloatArray:
        A = self.A(T)
        return A - self.K @ self.H @ A

    def D(self, p: float) -> FloatArray:
        return np.array([[1, p]]) if self.K.shape[0] == 2 else np.array([[1, p, p * p / 2]])

    def M(self, w: float) -> ComplexArray:
        return np.array([(1j * w) ** d for d in self.derivatives])

    def response(self, f: ArrayLike, p: float, T: float = AB_PERIOD) -> ComplexArray:
        return response(f, T, self.G(T), self.K, self.D(p), self.M)


AB_CASES = {
    1: ABCase("case 1: position", np.array([[1.0, 0.0]]), np.array([[0.568], [41.967]]), (0,)),
    2: ABCase("case 2: position + velocity", np.array([[1.0, 0, 0], [0, 1.0, 0]]),
              np.array([[0.0576, 0.0032], [0.0034, 0.568], [-0.0528, 41.967]]), (0, 1)),
    3: ABCase("case 3: position + acceleration", np.array([[1.0, 0, 0], [0, 0, 1.0]]),
              np.array([[0.0807, 0.000016], [0.342, 0.00345], [0.0467, 0.618]]), (0, 2)),
}
