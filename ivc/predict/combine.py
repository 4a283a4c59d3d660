"""Forecast combination: the bank members' turns over the horizon, averaged with weights learned online.

``auto`` selects among its members by their recent errors; this module combines them instead. At frame
k each member c predicts a turn r_c(k) from the measured orientation q(k) (a rotation vector, rad; ``auto``
writes it in the body frame of q(k): log(q(k)* ⊗ q̂_c)); the combination shows, on each axis a,
Σ_c w_ac r_ac(k). Each axis's weights solve, at every frame,

    min_w  Σ_k e^{−(t − t_k)/τ} (y_a(k) − Σ_c w_c r_ac(k))²  +  (λ/3) |w − 1/C|²    subject to  Σ_c w_c = 1,

y(k) the stream's own turn from q(k) to its orientation at t(k) + h (rad, same frame; the scoring's
slerped reference), over the targets whose time has arrived only: a target enters the sums at the frame
its reference is first known (the sample after t(k) + h), so the weights at t use samples up to t. The
sums forget with time constant ``memory_s`` (:data:`MEMORY_S`, 3 s, ``direct``'s memory: a few head
movements); the ridge λ = h² rad² (split over the three axes) pulls toward the equal-weight average,
what the weights are before anything is learned (h² is one target of a 1 rad/s turn over the horizon: a
static or slow stream, whose turns are far smaller, keeps near the average; a turning one is ruled by
its errors). Weights may be negative or above 1 (the combination can extrapolate beyond its members),
their sum is 1 (a bias every member shares is not "learned away" as a gain). The axes have weights of
their own because in the head's frame they differ (a turn about the neck is large and smooth, a roll
small): the members that predict each best differ.

The constrained minimum, per axis: with M = A + (λ/3)I and rhs = b + (λ/3)/C (A the forgotten Σ r rᵀ,
b the forgotten Σ r y), w = M⁻¹ rhs + μ M⁻¹ 1, μ = (1 − 1ᵀM⁻¹rhs) / (1ᵀM⁻¹1).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import ArrayLike

from ivc.errors import PredictorError
from ivc.predict.base import FloatArray

#: time constant (s) of the forgetting of the combination's sums
MEMORY_S = 3.0


def ridge_for(horizon_s: float) -> float:
    """The ridge λ (rad²) toward equal weights at a horizon (s): one 1 rad/s turn over it, squared."""
    return float(horizon_s) ** 2


@numba.njit(cache=True)
def solve_weights(A, b, ridge, out):
    """out (3, C) = each axis's constrained ridge solution (module docstring) from the sums A (3, C, C), b (3, C);
    ``ridge`` is λ, split over the axes. M = A + (λ/3)I is symmetric positive definite (λ > 0): solved by Cholesky."""
    C = b.shape[1]
    lam = ridge / 3.0
    L = np.empty((C, C))
    x0 = np.empty(C)
    x1 = np.empty(C)
    for a in range(3):
        for i in range(C):  # L Lᵀ = A[a] + lam I
            for j in range(i + 1):
                acc = A[a, i, j] + (lam if i == j else 0.0)
                for k in range(j):
                    acc -= L[i, k] * L[j, k]
                if i == j:
                    L[i, i] = np.sqrt(acc)
                else:
                    L[i, j] = acc / L[j, j]
        for i in range(C):  # forward: L z = rhs (two right-hand sides: b + lam / C, and 1)
            r0 = b[a, i] + lam / C
            r1 = 1.0
            for k in range(i):
                r0 -= L[i, k] * x0[k]
                r1 -= L[i, k] * x1[k]
            x0[i] = r0 / L[i, i]
            x1[i] = r1 / L[i, i]
        for i in range(C - 1, -1, -1):  # back: Lᵀ x = z
            r0 = x0[i]
            r1 = x1[i]
            for k in range(i + 1, C):
                r0 -= L[k, i] * x0[k]
                r1 -= L[k, i] * x1[k]
            x0[i] = r0 / L[i, i]
            x1[i] = r1 / L[i, i]
        s0 = 0.0
        s1 = 0.0
        for c in range(C):
            s0 += x0[c]
            s1 += x1[c]
        mu = (1.0 - s0) / s1
        for c in range(C):
            out[a, c] = x0[c] + mu * x1[c]


@numba.njit(cache=True)
def decay(A, b, factor):
    """A *= factor, b *= factor in place (the forgetting of the sums between two frames)."""
    A *= factor
    b *= factor


@numba.njit(cache=True)
def accumulate(turns, target, A, b):
    """Add one target: A[a] (C, C) += r_a r_aᵀ and b[a] (C,) += r_a y_a on each axis a; turns (C, 3), target (3,),
    rad."""
    C = turns.shape[0]
    for a in range(3):
        for c in range(C):
            b[a, c] += turns[c, a] * target[a]
            for e in range(C):
                A[a, c, e] += turns[c, a] * turns[e, a]


@numba.njit(cache=True)
def _combine(turns, target, known, dt, memory, ridge, out, weights):
    """The batch of :func:`combine` for one sensor and horizon (arguments as there, checked)."""
    C, F = turns.shape[0], turns.shape[1]
    order = np.argsort(known, kind="mergesort")
    A = np.zeros((3, C, C))
    b = np.zeros((3, C))
    tk = np.empty((C, 3))
    e = 0
    while e < F and known[order[e]] < 0:
        e += 1
    for j in range(F):
        if dt[j] > 0.0:
            decay(A, b, np.exp(-dt[j] / memory))
        while e < F and known[order[e]] == j:
            k = order[e]
            if np.isfinite(target[k, 0]) and np.isfinite(target[k, 1]) and np.isfinite(target[k, 2]):
                tk[:, :] = turns[:, k]  # contiguous, as auto's live step passes it: one specialisation
                accumulate(tk, target[k], A, b)
            e += 1
        solve_weights(A, b, ridge, weights[j])
        for i in range(3):
            acc = 0.0
            for c in range(C):
                acc += weights[j, i, c] * turns[c, j, i]
            out[j, i] = acc


def combine(turns: ArrayLike, target: ArrayLike, known: ArrayLike, time: ArrayLike, horizon_s: float,
            memory_s: float = MEMORY_S) -> tuple[FloatArray, FloatArray]:
    """The online combination of one sensor's member turns at one horizon.

    turns (C, F, 3): each member's predicted turn from the measured orientation at each frame (rad, finite);
    target (F, 3): the stream's own turn from there to its orientation at t + ``horizon_s`` (rad; NaN where it
    is not scored); known (F,): the frame at which each target is first known (−1: never); time (F,) s.
    Returns (the combined turns (F, 3) rad, the weights (F, 3, C) of each axis in force at each frame).
    """
    r = np.ascontiguousarray(turns, dtype=float)
    y = np.ascontiguousarray(target, dtype=float)
    kn = np.ascontiguousarray(known, dtype=np.int64)
    t = np.ascontiguousarray(time, dtype=float)
    if r.ndim != 3 or r.shape[2] != 3 or r.shape[0] < 1:
        raise PredictorError(f"combine: turns must be (members, frames, 3), got {r.shape}")
    C, F = r.shape[:2]
    if y.shape != (F, 3) or kn.shape != (F,) or t.shape != (F,):
        raise PredictorError(f"combine: target (F, 3), known (F,) and time (F,) must match {F} frames; got "
                             f"{y.shape}, {kn.shape}, {t.shape}")
    if not np.all(np.isfinite(r)):
        raise PredictorError("combine: the members' turns must be finite (show the measured orientation, turn 0, "
                             "where a member has no prediction)")
    if not (np.isfinite(horizon_s) and horizon_s > 0 and np.isfinite(memory_s) and memory_s > 0):
        raise PredictorError("combine: horizon_s and memory_s must be positive numbers of seconds")
    if F and (np.any(kn >= F) or np.any(np.diff(t) < 0)):
        raise PredictorError("combine: known frames must be below the number of frames and times must not decrease")
    out = np.empty((F, 3))
    weights = np.empty((F, 3, C))
    dt = np.diff(t, prepend=t[:1]) if F else t
    _combine(r, y, kn, dt, float(memory_s), ridge_for(horizon_s), out, weights)
    return out, weights


__all__ = ["MEMORY_S", "accumulate", "combine", "decay", "ridge_for", "solve_weights"]
