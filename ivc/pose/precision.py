"""How precisely one frame's signal fixes a pose: the Cramér-Rao bound of a single-frame solve.

With a measured signal ``S = Tᵀ M(r) + N``, ``M = f_D + G`` (free-space dipole plus the secondary
field) and white noise ``N ~ N(0, σ² I₉)`` on the nine entries, the Fisher information of the pose
``(r, ω)`` (position and a rotation increment ``T ← T exp([ω]×)``) is ``JᵀJ / σ²``, with ``J`` the
9 x 6 Jacobian of ``Tᵀ M(r)`` (:func:`ivc.pose.signal_residual`). No unbiased estimate from that
frame does better than the covariance ``σ² (JᵀJ)⁻¹``, and a converged least-squares solve reaches it
(tests/test_noise_floor.py checks both against Monte Carlo solves).

Used twice: by the simulator, to state the noise floor of its check poses against their true pose
(``ivc.sim.noise_floor``), and by the correction, to predict each corrected pose's precision from
the table's field and the tracker's measured signal noise (``ivc.correct``, ``--max-precision``).
The noise is *absolute* (the same ``σ`` at every range, as a receiver's fixed noise floor gives), so
the signal-to-noise ratio falls as ``r³`` and the pose precision faster still.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ivc import compiled, dipole, rotations
from ivc.dipole import numpy_kernels
from ivc.errors import InputError
from ivc.pose import precision_kernels
from ivc.pose.solver import signal_residual

__all__ = ["pose_covariance", "pose_precision", "reported_noise", "reported_pose_covariance", "traces"]

#: at most this many poses are evaluated in NumPy (a live frame's sensors)
SMALL = 64

SecondaryField = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def pose_covariance(positions: np.ndarray, quaternions: np.ndarray, sigma: float,
                    secondary: SecondaryField | None = None) -> np.ndarray:
    """Cramér-Rao covariance (N, 6, 6) of single-frame poses at ``positions`` (N, 3) m with orientations
    ``quaternions`` (N, 4) [w, x, y, z], for white noise ``sigma`` per signal entry (the signal's units:
    normalised dipole units for calibrated signals). Rows/columns: position (m, source frame), then the
    rotation increment (rad, sensor frame). ``secondary(r) -> (G (N, 3, 3), ∂G/∂r (N, 3, 3, 3))``: the
    secondary field the signal carries (None: free space). A pose the signal cannot fix (a singular
    information matrix) gets an infinite covariance."""
    positions = np.asarray(positions, float).reshape(-1, 3)
    quaternions = np.asarray(quaternions, float).reshape(-1, 4)
    if len(positions) != len(quaternions):
        raise InputError(f"{len(positions)} positions but {len(quaternions)} orientations")
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"the signal noise must be a positive number, got {sigma}")
    T = rotations.to_matrix(quaternions)
    if len(positions) > SMALL:
        M = dipole.field(positions)
    else:  # the NumPy form: a parallel kernel's thread start costs more than a few poses' work
        M = np.empty((len(positions), 3, 3))
        numpy_kernels.field_kernel(positions, M)
    dM = dipole.field_jacobian(positions)
    if secondary is not None:
        G, dG = secondary(positions)
        M, dM = M + G, dM + dG
    _, J = signal_residual(np.swapaxes(T, -1, -2) @ M, M, dM, T)
    information = np.swapaxes(J, -1, -2) @ J
    covariance = np.full(information.shape, np.inf)
    finite = np.all(np.isfinite(information), axis=(1, 2))
    finite[finite] = np.linalg.cond(information[finite]) < 1e14
    covariance[finite] = sigma**2 * np.linalg.inv(information[finite])
    return covariance


def pose_precision(positions: np.ndarray, quaternions: np.ndarray, sigma: float,
                   secondary: SecondaryField | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The RMS position error (N,) m and RMS orientation error (N,) rad a single frame cannot beat:
    ``sqrt(tr C_rr)`` and ``sqrt(tr C_ωω)`` of :func:`pose_covariance` (same arguments)."""
    return traces(pose_covariance(positions, quaternions, sigma, secondary))


def reported_pose_covariance(rotation: np.ndarray, d_phi: np.ndarray, d_omega: np.ndarray, d_field: np.ndarray,
                             sigma: float) -> np.ndarray:
    """Covariance (N, 6, 6) of poses corrected from reported poses alone, for white signal noise ``sigma``.

    The tracker reports ``(v, Q) = (φ(r), C(r) T)`` for a sensor at ``(r, T)``: its solver applied to the
    signal ``S = Tᵀ F(r)``, ``F = f_D + g``. White noise on S is white noise on F (a rotation keeps it
    white), so the reported pose scatters as ``(δv, δω_Q) = J δF`` with ``J = ∂(φ, ω)/∂F`` (``d_field``
    (N, 6, 9), rows position and left rotation increment, columns F's entries row by row) taken at the
    field the sensor is in. That is the Cramér-Rao bound only where F is a free-space field; beside
    metal F is not one, and the solver's scatter is wider (by about 10 % on the default scene, 1.8x at
    worst). ivc corrects ``r = φ⁻¹(v)``, ``T = C(r)ᵀ Q``, which carries it through ``δr = (∂φ/∂r)⁻¹ δv``
    and ``δt = Qᵀ (δω_Q − (∂ω/∂r) δr)`` (``d_phi`` = ∂φ/∂r, ``d_omega`` = ∂ω/∂r, the left increment of C
    per metre, both (N, 3, 3) at the corrected position: :func:`ivc.pose.tracker_solver.distortion` with
    ``jacobian=True`` returns all three). Rows/columns: position (m, source frame), then the rotation
    increment (rad, sensor frame) of ``rotation`` = Q (N, 3, 3). A singular ∂φ/∂r (the reported pose does
    not fix the true one) gives an infinite covariance."""
    rotation = np.asarray(rotation, float).reshape(-1, 3, 3)
    n = len(rotation)
    d_phi, d_omega = np.asarray(d_phi, float).reshape(n, 3, 3), np.asarray(d_omega, float).reshape(n, 3, 3)
    d_field = np.asarray(d_field, float).reshape(n, 6, 9)
    covariance = np.full((n, 6, 6), np.inf)
    usable = np.all(np.isfinite(d_phi.reshape(n, 9)), axis=1) & np.all(np.isfinite(d_omega.reshape(n, 9)), axis=1)
    usable &= np.all(np.isfinite(d_field.reshape(n, 54)), axis=1)
    usable[usable] = np.linalg.cond(d_phi[usable]) < 1e12
    B = np.empty((int(usable.sum()), 6, 9))
    B[:, :3] = np.linalg.inv(d_phi[usable]) @ d_field[usable, :3]
    B[:, 3:] = np.swapaxes(rotation[usable], -1, -2) @ (d_field[usable, 3:] - d_omega[usable] @ B[:, :3])
    covariance[usable] = sigma**2 * B @ np.swapaxes(B, -1, -2)
    return covariance


def traces(covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RMS position (m) and orientation (rad) errors of pose covariances (N, 6, 6): ``sqrt(tr C_rr)``,
    ``sqrt(tr C_ωω)``."""
    return (np.sqrt(np.trace(covariance[:, :3, :3], axis1=1, axis2=2)),
            np.sqrt(np.trace(covariance[:, 3:, 3:], axis1=1, axis2=2)))


def reported_noise(position: np.ndarray, rotation: np.ndarray, sigma: float) -> np.ndarray:
    """The RMS noise (N,) m of reported positions ``position`` (N, 3) m with orientations ``rotation`` (N, 3, 3),
    for white signal noise ``sigma``: the free-space Cramér-Rao bound at the reported pose (compiled;
    :func:`pose_precision` without a secondary field is the NumPy form). NaN where the pose is not finite."""
    position = np.ascontiguousarray(np.asarray(position, float).reshape(-1, 3))
    rotation = np.ascontiguousarray(np.asarray(rotation, float).reshape(-1, 3, 3))
    n = len(position)
    zero = np.zeros((n, 3, 3))
    out, _ = np.empty(n), np.empty(n)
    kernel = compiled.choose(precision_kernels.precision_serial if n < SMALL else precision_kernels.precision_kernel, n)
    kernel(position, rotation, zero, np.zeros((n, 3, 3, 3)), float(sigma), out, _)
    return out
