"""Steady-state Kalman gains of the linear predictors (Welch & Bishop 2001; docs/math.md §16).

Equations: docs/math.md §16.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import solve_discrete_are

FloatArray = NDArray[np.float64]

__all__ = ["kinematic_gain", "steady_state_gain"]


def steady_state_gain(Phi: ArrayLike, H: ArrayLike, W: ArrayLike, V: ArrayLike) -> FloatArray:
    """Steady-state Kalman gain (N, F) of x(k+1) = Φx + w, y = Hx + v, from the discrete Riccati equation."""
    Phi, H, W, V = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (Phi, H, W, V))
    P = solve_discrete_are(Phi.T, H.T, W, V)  # a-priori covariance
    return P @ H.T @ np.linalg.inv(H @ P @ H.T + V)


def kinematic_gain(h: float, w_a: float, V: float) -> FloatArray:
    """NASA's per-axis translational KF (eq. 12-14): 3 states [p, v, a], position measured, noise on a only."""
    Phi = np.array([[1, h, h * h / 2], [0, 1, h], [0, 0, 1]])
    return steady_state_gain(Phi, [[1.0, 0, 0]], np.diag([0.0, 0.0, w_a]), [[V]])
