"""Delta quaternions, angular rates and orientation extrapolation, batched over leading axes.

Conventions (docs/math.md §11.1-§11.2): scalar-first Hamilton quaternions as in
:mod:`ivc.rotations`; ω in rad/s in the reference (source) frame, so ``q̇ = ½ ω ⊗ q`` and a
constant ω turns q into ``Δq(ω, t) ⊗ q``; ``Δq(k) = q(k) ⊗ q(k−1)*`` with its scalar part
forced non-negative.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ivc import rotations
from ivc.errors import InputError
from ivc.predict.quat import SMALL_ANGLE

FloatArray = NDArray[np.float64]


def delta_q(omega: ArrayLike, t: ArrayLike) -> FloatArray:
    """Δq(ω, t) (..., 4): the rotation of constant angular velocity ω (..., 3) rad/s over t seconds."""
    omega = np.asarray(omega, dtype=float)
    t = np.asarray(t, dtype=float)
    rate = np.linalg.norm(omega, axis=-1)
    phi = 0.5 * rate * t
    small = rate * np.abs(t) < SMALL_ANGLE
    safe = np.where(small, 1.0, rate)
    sigma = np.where(small, 0.5 * t * (1.0 - phi**2 / 6.0), np.sin(phi) / safe)
    w = np.where(small, 1.0 - 0.5 * phi**2, np.cos(phi))
    return np.concatenate([w[..., None], sigma[..., None] * omega], axis=-1)


def delta_q_jacobian(omega: ArrayLike, t: float) -> FloatArray:
    """∂Δq(ω, t)/∂ω (..., 4, 3), the singularity-free form of docs/math.md §11.3 (finite at ω = 0)."""
    omega = np.asarray(omega, dtype=float)
    rate2 = np.sum(omega**2, axis=-1)
    rate = np.sqrt(rate2)
    phi = 0.5 * rate * t
    small = rate * abs(t) < SMALL_ANGLE
    safe = np.where(small, 1.0, rate)
    sigma = np.where(small, 0.5 * t * (1.0 - phi**2 / 6.0), np.sin(phi) / safe)
    coupling = np.where(small, -(t**3) / 24.0, (0.5 * t * np.cos(phi) - sigma) / np.where(small, 1.0, rate2))
    J = np.empty(omega.shape[:-1] + (4, 3))
    J[..., 0, :] = -0.5 * t * sigma[..., None] * omega
    J[..., 1:, :] = coupling[..., None, None] * omega[..., :, None] * omega[..., None, :]
    J[..., 1:, :] += sigma[..., None, None] * np.eye(3)
    return J


def rate_from_delta(dq: ArrayLike, t: float) -> FloatArray:
    """The constant angular velocity (..., 3) rad/s that turns by dq (..., 4) in t seconds (inverse of Δq)."""
    dq = np.asarray(dq, dtype=float)
    v = np.linalg.norm(dq[..., 1:], axis=-1)
    angle = 2.0 * np.arctan2(v, dq[..., 0])
    scale = np.where(v > 1e-300, angle / (t * np.where(v > 1e-300, v, 1.0)), 0.0)
    return scale[..., None] * dq[..., 1:]


def deltas(q: ArrayLike) -> FloatArray:
    """Δq(k) = q(k) ⊗ q(k−1)* along axis 0, scalar part forced ≥ 0; shape (frames − 1, ..., 4)."""
    q = np.asarray(q, dtype=float)
    dq = rotations.multiply(q[1:], rotations.conjugate(q[:-1]))
    return np.where(dq[..., :1] < 0.0, -dq, dq)


def extrapolate(q: ArrayLike, omega: ArrayLike, alpha: ArrayLike | None, delta: float, tau: float) -> FloatArray:
    """Orientation δ seconds after q (..., 4) under rate ω and angular acceleration α (docs/math.md §11.4, corrected).

    Whole frames n = 1..⌊δ/τ⌋ turn at ω + nτα, the remaining fraction of a frame at the next
    step's rate; with α = 0 this is exactly ``Δq(ω, δ) ⊗ q``. δ need not be a whole frame.
    """
    q = np.asarray(q, dtype=float)
    omega = np.asarray(omega, dtype=float)
    if delta < 0.0:
        raise InputError(f"the prediction horizon must be >= 0 s, got {delta}")
    if alpha is None or not np.any(alpha):
        return rotations.multiply(delta_q(omega, delta), q)
    alpha = np.asarray(alpha, dtype=float)
    steps = int(np.floor(delta / tau + 1e-9))
    rest = delta - steps * tau
    out = q
    for n in range(1, steps + 2):
        span = tau if n <= steps else rest
        if span <= 0.0:
            break
        out = rotations.multiply(delta_q(omega + n * tau * alpha, span), out)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def extrapolate_each(q: ArrayLike, omega: ArrayLike, alpha: ArrayLike | None, delta: ArrayLike,
                     tau: float) -> FloatArray:
    """:func:`extrapolate` with a horizon per sample: δ (...) s, broadcast against q's leading shape."""
    q = np.asarray(q, dtype=float)
    omega = np.asarray(omega, dtype=float)
    delta = np.broadcast_to(np.asarray(delta, dtype=float), q.shape[:-1])
    if np.any(delta < 0.0):
        raise InputError("the prediction horizons must be >= 0 s")
    if alpha is None or not np.any(alpha):
        return rotations.multiply(delta_q(omega, delta), q)
    alpha = np.asarray(alpha, dtype=float)
    finite = np.where(np.isfinite(delta), delta, 0.0)
    steps = np.floor(finite / tau + 1e-9)
    rest = finite - steps * tau
    out = q
    for n in range(1, int(np.max(steps, initial=0)) + 2):
        span = np.where(n <= steps, tau, np.where(n == steps + 1, rest, 0.0))
        out = rotations.multiply(delta_q(omega + n * tau * alpha, span), out)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)
