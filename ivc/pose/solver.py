"""Sensor pose with a known secondary field, batched over frames (Himberg 2010, eq. 91-93; docs/math.md §4).

Model: ``S = Tᵀ M(r)`` with ``M(r) = f_D(r) + g(r)``. ``min ‖S − Tᵀ M(r)‖_F`` is solved
by Levenberg-Marquardt over position and a rotation increment (``T ← T exp([ω]×)``)
with the analytic Jacobian of ``M``, the orientation starting from the orthogonal
Procrustes solution ``T = polar(M Sᵀ)`` at the seed, and every frame of the batch
stepping together as arrays. (Holding ``T`` fixed while stepping ``r`` converges only
linearly here: position and orientation are strongly coupled through ``f_D``.)

``method="joint"`` (default) minimises the full signal residual. ``method="two-stage"`` is
Himberg 2010's: position from the rotation-invariant ``‖SᵀS − MᵀM‖_F`` (eq. 92), then
orientation (eq. 93), kept for comparison.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ivc import dipole, rotations
from ivc.errors import InputError

FieldModel = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
METHODS = ("joint", "two-stage")


def dipole_plus(secondary: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None) -> FieldModel:
    """``r -> (M, ∂M/∂r)`` for ``M = f_D + g``, from ``secondary(r) -> (g, ∂g/∂r)`` (None: free space)."""

    def model(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        M, dM = dipole.field(r), dipole.field_jacobian(r)
        if secondary is not None:
            g, dg = secondary(r)
            M, dM = M + g, dM + dg
        return M, dM

    return model


@dataclass
class PoseSolution:
    """Solved poses of a batch: position (F, 3) m, rotation (F, 3, 3), and per-frame diagnostics."""

    position: np.ndarray
    rotation: np.ndarray
    converged: np.ndarray  # (F,) bool
    iterations: np.ndarray  # (F,) int
    residual: np.ndarray  # (F,) rms(Λ) / rms(S), Λ = M(r) − T S (eq. 99)
    position_sigma: np.ndarray  # (F,) m, estimated standard error of the position
    angle_sigma: np.ndarray  # (F,) rad, estimated standard error of the orientation

    @property
    def quaternion(self) -> np.ndarray:
        return rotations.from_matrix(self.rotation)


def procrustes(M: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Rotation ``T`` minimising ``‖S − Tᵀ M‖_F``: ``U diag(1, 1, det(U Vᵀ)) Vᵀ`` of ``M Sᵀ``."""
    return rotations.nearest_rotation(M @ np.swapaxes(S, -1, -2))


def procrustes_cost(M: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``min_T ‖S − Tᵀ M‖_F²`` over rotations ``T`` (the cost at :func:`procrustes`), without forming ``T``.

    ``‖S‖² + ‖M‖² − 2 (σ₁ + σ₂ + sign(det X) σ₃)`` with ``σ`` the singular values of ``X = M Sᵀ``, from the
    eigenvalues of ``XᵀX`` in closed form (Smith 1961's trigonometric roots of the characteristic cubic): no
    per-matrix LAPACK call, for searches over many positions. The smallest singular value is good to about
    ``1e-8 σ₁``: a ranking of starts, not a fit.
    """
    X = M @ np.swapaxes(S, -1, -2)
    Y = np.swapaxes(X, -1, -2) @ X
    q = np.einsum("...ii->...", Y) / 3.0
    off = Y[..., 0, 1] ** 2 + Y[..., 0, 2] ** 2 + Y[..., 1, 2] ** 2
    d0, d1, d2 = Y[..., 0, 0] - q, Y[..., 1, 1] - q, Y[..., 2, 2] - q
    p = np.sqrt((d0**2 + d1**2 + d2**2 + 2.0 * off) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    # det((Y − qI) / p) / 2, clipped against rounding
    det = (d0 * (d1 * d2 - Y[..., 1, 2] ** 2) - Y[..., 0, 1] * (Y[..., 0, 1] * d2 - Y[..., 1, 2] * Y[..., 0, 2])
           + Y[..., 0, 2] * (Y[..., 0, 1] * Y[..., 1, 2] - d1 * Y[..., 0, 2]))
    phi = np.arccos(np.clip(det / (2.0 * safe**3), -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    sigma = np.sqrt(np.maximum(np.stack([largest, 3.0 * q - largest - smallest, smallest]), 0.0))
    handed = np.sum(X[..., 0, :] * np.cross(X[..., 1, :], X[..., 2, :]), axis=-1)
    trace = sigma[0] + sigma[1] + np.sign(handed) * sigma[2]
    return np.sum(S**2, axis=(-2, -1)) + np.sum(M**2, axis=(-2, -1)) - 2.0 * trace


_SKEW = np.array(  # [e_a]× for a = x, y, z
    [[[0, 0, 0], [0, 0, -1], [0, 1, 0]], [[0, 0, 1], [0, 0, 0], [-1, 0, 0]], [[0, -1, 0], [1, 0, 0], [0, 0, 0]]],
    dtype=float,
)


def signal_residual(S: np.ndarray, M: np.ndarray, dM: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """e = S − Tᵀ M(r) and its Jacobian in (δr, ω), with T ← T exp([ω]×): ∂e/∂ω_a = [e_a]× Tᵀ M."""
    F = len(S)
    Tt = np.swapaxes(T, -1, -2)
    P = Tt @ M
    e = S - P
    J = np.zeros((F, 3, 3, 6))
    J[..., :3] = -(Tt @ dM.reshape(F, 3, 9)).reshape(F, 3, 3, 3)  # −Σ_a T_ai ∂M_aj/∂r_k
    # row i of [e_a]× P: a = x: (0, −P_2, P_1); a = y: (P_2, 0, −P_0); a = z: (−P_1, P_0, 0)
    J[:, 1, :, 3], J[:, 2, :, 3] = -P[:, 2], P[:, 1]
    J[:, 0, :, 4], J[:, 2, :, 4] = P[:, 2], -P[:, 0]
    J[:, 0, :, 5], J[:, 1, :, 5] = -P[:, 1], P[:, 0]
    return e.reshape(F, 9), J.reshape(F, 9, 6)


def _residual_two_stage(S, M, dM, T):
    B = np.swapaxes(S, -1, -2) @ S
    e = B - np.swapaxes(M, -1, -2) @ M  # eq. 92, rotation invariant: T plays no part
    MtdM = np.einsum("fai,fajk->fijk", M, dM)
    J = -(MtdM + np.swapaxes(MtdM, 1, 2))
    return e.reshape(len(S), 9), J.reshape(len(S), 9, 3)


def damped_step(J: np.ndarray, e: np.ndarray, damping: np.ndarray) -> np.ndarray:
    """Levenberg-Marquardt step of each frame: ``−(JᵀJ + λ diag(JᵀJ))⁻¹ Jᵀe`` for J (F, m, n), e (F, m), λ (F,).

    Marquardt's diagonal scaling makes the damping independent of the unknowns' units.
    """
    Jt = np.swapaxes(J, -1, -2)
    H = Jt @ J
    g = (Jt @ e[..., None])[..., 0]
    diag = np.einsum("fii->fi", H)
    scale = np.maximum(diag, 1e-30 * diag.max(axis=1, keepdims=True))
    A = H + (damping[:, None] * scale)[:, :, None] * np.eye(J.shape[-1])
    return -np.linalg.solve(A, g[..., None])[..., 0]


Trial = Callable[[np.ndarray, np.ndarray], tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray]]


def levenberg_marquardt(unknowns: tuple[np.ndarray, ...], e: np.ndarray, J: np.ndarray, active: np.ndarray,
                        trial: Trial, max_iterations: int, step_tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Batched Levenberg-Marquardt: every active frame steps at once, each with its own damping.

    ``unknowns``: arrays with frames first, position (F, 3) m the first of them; ``e`` (F, m) and
    ``J`` (F, m, n) the residuals and their Jacobian there; ``active`` (F,) the frames to solve.
    ``trial(idx, step)`` returns the unknowns of frames ``idx`` moved by ``step`` (len(idx), n),
    with their residuals and Jacobian. Accepted steps update ``unknowns``, ``e`` and ``J`` in
    place. A frame has converged when an accepted step moves its position by less than
    ``step_tolerance`` m, or when no step decreases its cost (it sits at the numerical minimum).
    Returns per-frame convergence and iteration counts.
    """
    active = active.copy()
    cost = np.sum(e**2, axis=1)
    converged = np.zeros(len(e), dtype=bool)
    iterations = np.zeros(len(e), dtype=int)
    damping = np.full(len(e), 1e-3)
    for _ in range(max_iterations):
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        step = damped_step(J[idx], e[idx], damping[idx])
        moved, et, Jt = trial(idx, step)
        trial_cost = np.sum(et**2, axis=1)
        better = trial_cost <= cost[idx]
        accept = idx[better]
        for value, new in zip(unknowns, moved, strict=True):
            value[accept] = new[better]
        e[accept], J[accept], cost[accept] = et[better], Jt[better], trial_cost[better]
        damping[accept] = np.maximum(damping[accept] * 0.3, 1e-12)
        damping[idx[~better]] *= 10.0
        iterations[idx] += 1
        small = np.linalg.norm(step[:, :3], axis=1) < step_tolerance
        done = idx[(better & small) | (~better & (damping[idx] > 1e8))]
        converged[done] = True
        active[done] = False
    return converged, iterations


def solve_pose(
    S: np.ndarray,
    model: FieldModel,
    initial_position: np.ndarray,
    *,
    method: str = "joint",
    max_iterations: int = 60,
    step_tolerance: float = 1e-9,
) -> PoseSolution:
    """Solve ``S`` (F, 3, 3) for pose, starting at ``initial_position`` (F, 3) metres.

    ``model(r)`` gives ``M = f_D + g`` (F, 3, 3) and ``∂M/∂r`` (F, 3, 3, 3). A frame has
    converged when its position step falls below ``step_tolerance`` metres (or its cost
    can no longer decrease) within ``max_iterations``. Non-finite input frames are
    returned as NaN, not converged.
    """
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; use one of {', '.join(METHODS)}")
    residual_fn = signal_residual if method == "joint" else _residual_two_stage
    S = np.asarray(S, float)
    r = np.array(initial_position, dtype=float)
    F = len(S)
    finite = np.all(np.isfinite(S.reshape(F, -1)), axis=1) & np.all(np.isfinite(r), axis=1)
    S = np.where(finite[:, None, None], S, np.eye(3))  # placeholders, never reported
    M, dM = model(np.where(finite[:, None], r, 1.0))
    T = procrustes(M, S)
    e, J = residual_fn(S, M, dM, T)
    six = J.shape[-1] == 6

    def trial(idx, step):
        trial_r = r[idx] + step[:, :3]
        Mt, dMt = model(trial_r)
        if six:
            trial_T = T[idx] @ rotations.to_matrix(rotations.from_rotvec(step[:, 3:]))
        else:  # the two-stage method steps position only; orientation follows from Procrustes
            trial_T = procrustes(Mt, S[idx])
        return (trial_r, trial_T), *residual_fn(S[idx], Mt, dMt, trial_T)

    converged, iterations = levenberg_marquardt((r, T), e, J, finite, trial, max_iterations, step_tolerance)
    M, dM = model(np.where(finite[:, None], r, 1.0))
    T = procrustes(M, S)
    position_sigma, angle_sigma = _standard_errors(S, M, dM, T)
    r[~finite] = np.nan
    T[~finite] = np.nan
    lam = M - T @ S  # eq. 99
    rms_s = np.sqrt(np.mean(S**2, axis=(1, 2)))
    residual = np.sqrt(np.mean(lam**2, axis=(1, 2))) / rms_s
    return PoseSolution(r, T, converged & finite, iterations, residual, position_sigma, angle_sigma)


def _standard_errors(S, M, dM, T) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and orientation (rad) standard errors from the 6-DOF fit.

    ``Cov = σ² (JᵀJ)⁻¹`` with ``σ²`` the residual variance per degree of freedom
    (9 residuals, 6 unknowns): what the signal residual says about the pose's error.
    """
    e, J = signal_residual(S, M, dM, T)
    sigma2 = np.sum(e**2, axis=1) / 3.0
    with np.errstate(invalid="ignore"):
        covariance = np.linalg.pinv(np.einsum("fki,fkj->fij", J, J)) * sigma2[:, None, None]
        diag = np.einsum("fii->fi", covariance)
        return np.sqrt(diag[:, :3].sum(axis=1)), np.sqrt(diag[:, 3:].sum(axis=1))
