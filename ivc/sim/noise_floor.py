"""The single-frame noise floor of a pose: the Cramér-Rao bound from the tracker's signal noise.

The simulated tracker's noise is *absolute*: white Gaussian noise of one standard deviation
``σ`` (:func:`ivc.sim.tracker.noise_sigma`) on each of the nine signal entries, the same at every
range, as a receiver's fixed noise floor gives (docs/simulator.md, "Noise"). The signal falls
as ``1/r³``, so the relative noise grows as ``r³`` and the pose noise faster still.

With ``S = Tᵀ M(r) + N``, ``N ~ N(0, σ² I₉)``, the Fisher information of the pose ``(r, ω)``
(position and a rotation increment ``T ← T exp([ω]×)``) is ``JᵀJ / σ²`` with ``J`` the 9 x 6
Jacobian of ``Tᵀ M(r)`` (``M = f_D + G``), so no unbiased single-frame estimate does better than
the covariance ``σ² (JᵀJ)⁻¹``. :func:`pose_noise_floor` returns its RMS position and orientation
errors, ``sqrt(tr C_rr)`` and ``sqrt(tr C_ωω)``: the floor any correction's error sits on.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ivc import dipole, rotations
from ivc.errors import InputError
from ivc.pose import signal_residual

__all__ = ["finite_difference_jacobian", "pose_noise_floor"]


def finite_difference_jacobian(field: Callable[[np.ndarray], np.ndarray], step: float = 1e-4
                               ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """``r -> (G, ∂G/∂r)`` for a field ``r -> G (..., 3, 3)`` without one (central differences, ``step`` m)."""

    def value_and_jacobian(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.asarray(r, float)
        G = field(r)
        dG = np.empty(G.shape + (3,))
        for k in range(3):
            offset = np.zeros(3)
            offset[k] = step
            dG[..., k] = (field(r + offset) - field(r - offset)) / (2 * step)
        return G, dG

    return value_and_jacobian


def pose_noise_floor(positions: np.ndarray, quaternions: np.ndarray, sigma: float,
                     secondary: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Cramér-Rao bound of single-frame poses at ``positions`` (N, 3) m, ``quaternions`` (N, 4), for white noise
    ``sigma`` per signal entry (normalised dipole units). ``secondary(r) -> (G, ∂G/∂r)``: the secondary field
    the signal carries (None: free space). Returns the RMS position bound (N,) m and orientation bound (N,) rad.
    """
    positions = np.asarray(positions, float).reshape(-1, 3)
    quaternions = np.asarray(quaternions, float).reshape(-1, 4)
    if len(positions) != len(quaternions):
        raise InputError(f"{len(positions)} positions but {len(quaternions)} orientations")
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"the signal noise must be a positive number, got {sigma}")
    T = rotations.to_matrix(quaternions)
    M, dM = dipole.field(positions), dipole.field_jacobian(positions)
    if secondary is not None:
        G, dG = secondary(positions)
        M, dM = M + G, dM + dG
    _, J = signal_residual(np.swapaxes(T, -1, -2) @ M, M, dM, T)
    covariance = sigma**2 * np.linalg.inv(np.swapaxes(J, -1, -2) @ J)
    return (np.sqrt(np.trace(covariance[:, :3, :3], axis1=1, axis2=2)),
            np.sqrt(np.trace(covariance[:, 3:, 3:], axis1=1, axis2=2)))
