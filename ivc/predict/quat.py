"""Compiled quaternion motion helpers shared by the predictor kernels (scalar-first Hamilton, as ivc.rotations),
on top of the quaternion primitives of :mod:`ivc.linalg`.

Δq(ω, t) is the rotation a constant angular velocity ω (rad/s, reference frame) makes in t
seconds: ``[cos(|ω|t/2), ω/|ω| sin(|ω|t/2)]`` (docs/math.md §11.2, with the
OCR's factor 2 removed). Its Jacobian uses the singularity-free form of docs/math.md §11.3, exact at ω = 0.
"""

from __future__ import annotations

import numba
import numpy as np

from ivc.linalg import qmul, qmul_conj
from ivc.linalg import quaternion_normalise as normalise

#: the quaternion primitives (product, normalisation) are ivc.linalg's, named here as the predictors import them
__all__ = ["SMALL_ANGLE", "delta_q", "delta_q_jacobian", "normalise", "predict_orientation", "qmul", "qmul_conj",
           "rate_of", "slerp"]

#: below this |ω|t the series forms are used (their error is O((|ω|t)^4), below 1e-16 relative)
SMALL_ANGLE = 1e-4


@numba.njit(inline="always")
def delta_q(wx, wy, wz, t, out):
    """out = Δq(ω, t)."""
    omega = np.sqrt(wx * wx + wy * wy + wz * wz)
    phi = 0.5 * omega * t
    if omega * abs(t) < SMALL_ANGLE:
        sigma = 0.5 * t * (1.0 - phi * phi / 6.0)
        out[0] = 1.0 - 0.5 * phi * phi
    else:
        sigma = np.sin(phi) / omega
        out[0] = np.cos(phi)
    out[1] = sigma * wx
    out[2] = sigma * wy
    out[3] = sigma * wz


@numba.njit(inline="always")
def delta_q_jacobian(wx, wy, wz, t, J, value):
    """J (4, 3) = ∂Δq(ω, t)/∂ω, singularity-free (docs/math.md §11.3), and value = Δq(ω, t) (shared sin and cos)."""
    w = (wx, wy, wz)
    omega2 = wx * wx + wy * wy + wz * wz
    omega = np.sqrt(omega2)
    phi = 0.5 * omega * t
    if omega * abs(t) < SMALL_ANGLE:
        delta_q(wx, wy, wz, t, value)
        # series to the next order: σ ≈ t/2 (1 − φ²/6), dσ/dΩ ≈ −t³Ω/24
        for j in range(3):
            J[0, j] = -0.25 * t * t * w[j]
            for m in range(3):
                J[m + 1, j] = -t * t * t / 24.0 * w[m] * w[j]
            J[j + 1, j] += 0.5 * t * (1.0 - phi * phi / 6.0)
        return
    s = np.sin(phi)
    c = np.cos(phi)
    sigma = s / omega
    value[0] = c
    value[1] = sigma * wx
    value[2] = sigma * wy
    value[3] = sigma * wz
    coupling = (0.5 * t * c - sigma) / omega2
    for j in range(3):
        J[0, j] = -0.5 * t * sigma * w[j]
        for m in range(3):
            J[m + 1, j] = coupling * w[m] * w[j]
        J[j + 1, j] += sigma


@numba.njit(inline="always")
def rate_of(dq, t, out):
    """The constant angular velocity (rad/s) that turns by dq in t seconds: the inverse of Δq(·, t)."""
    v = np.sqrt(dq[1] * dq[1] + dq[2] * dq[2] + dq[3] * dq[3])
    if v < 1e-300:
        out[0] = out[1] = out[2] = 0.0
        return
    scale = 2.0 * np.arctan2(v, dq[0]) / (t * v)
    out[0] = scale * dq[1]
    out[1] = scale * dq[2]
    out[2] = scale * dq[3]


@numba.njit(inline="always")
def predict_orientation(q, wx, wy, wz, ax, ay, az, delta, tau, out, tmp, dq):
    """out = orientation ``delta`` seconds after q, turning at ω + n τ α over frame n (docs/math.md §11.4, corrected).

    Whole frames n = 1..N (N = ⌊δ/τ⌋) use ω + nτα; the remaining ρ = δ − Nτ uses ω + (N+1)τα.
    With α = 0 it is one rotation Δq(ω, δ) ⊗ q, exact for constant angular velocity.
    """
    for i in range(4):
        out[i] = q[i]
    if ax == 0.0 and ay == 0.0 and az == 0.0:
        delta_q(wx, wy, wz, delta, dq)
        qmul(dq, q, out)
        normalise(out)
        return
    steps = int(np.floor(delta / tau + 1e-9))
    rest = delta - steps * tau
    for n in range(1, steps + 2):
        span = tau if n <= steps else rest
        if span <= 0.0:
            break
        delta_q(wx + n * tau * ax, wy + n * tau * ay, wz + n * tau * az, span, dq)
        qmul(dq, out, tmp)
        for i in range(4):
            out[i] = tmp[i]
    normalise(out)


@numba.njit(inline="always")
def slerp(q0, q1, u, out):
    """out = slerp from q0 (u = 0) to q1 (u = 1) along the shorter arc: exp(u log(q1 ⊗ q0*)) ⊗ q0."""
    d = np.empty(4)
    qmul_conj(q1, q0, d)
    if d[0] < 0.0:
        for i in range(4):
            d[i] = -d[i]
    v = np.sqrt(d[1] ** 2 + d[2] ** 2 + d[3] ** 2)
    half = np.arctan2(v, d[0]) * u
    scale = np.sin(half) / v if v > 1e-300 else u
    d[0] = np.cos(half)
    for i in range(1, 4):
        d[i] *= scale
    qmul(d, q0, out)
