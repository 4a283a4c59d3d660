"""The single-frame noise floor of a pose: the Cramér-Rao bound from the tracker's signal noise.

The simulated tracker's noise is *absolute*: white Gaussian noise of one standard deviation
``σ`` (:func:`ivc.sim.tracker.noise_sigma`) on each of the nine signal entries, the same at every
range, as a receiver's fixed noise floor gives (docs/simulator.md, "Noise"). The signal falls
as ``1/r³``, so the relative noise grows as ``r³`` and the pose noise faster still.

The bound is ``ivc.pose.precision``'s Cramér-Rao covariance ``σ² (JᵀJ)⁻¹``; :func:`pose_noise_floor`
evaluates it at a check pose's *true* pose and field: the floor any correction's error sits on.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ivc.pose.precision import pose_precision

pose_noise_floor = pose_precision

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
