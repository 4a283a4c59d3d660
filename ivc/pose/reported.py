"""Inverting the pose-domain distortion: the true position a tracker's reported position came from.

A rotation-equivariant tracker reports ``v = φ(r)`` and ``Q = C(r) T`` for a sensor at ``(r, T)``
(:mod:`ivc.pose.tracker_solver`). Given ``v`` and a secondary field ``g(r)``, the true position
solves ``φ(r) = v``; the true orientation is then ``T = C(r)ᵀ Q``, exactly.

``φ`` is close to the identity (its gradient differs from I by the distortion's, a few per
cent), so the solve starts at ``r = v`` and steps ``r ← r + H (v − φ(r))`` with ``H`` an
estimate of ``(∂φ/∂r)⁻¹`` that starts at I and is improved by Broyden's ("good") update from
each step (a step that does not lower the miss is halved until it does): superlinear
convergence with one evaluation of ``φ`` per step and no derivatives,
so any field model and either tracker solver can be inverted. Batched: every sample steps
together as arrays.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ivc.pose.tracker_solver import check_solver, distortion

#: the solve stops when the reported position is reproduced to this (m)
TOLERANCE = 1e-11
MAX_ITERATIONS = 40
#: step halvings tried before a sample is given up (far from the solution the estimate H may be poor)
BACKTRACKS = 12

Secondary = Callable[[np.ndarray], np.ndarray]  # positions (n, 3) -> g (n, 3, 3)


@dataclass
class Inversion:
    """True positions (n, 3) m and ``turn`` C(r) (n, 3, 3) at them; ``miss`` |v − φ(r)| (n,) m;
    ``converged`` (n,) bool; ``iterations`` (n,) int."""

    position: np.ndarray
    turn: np.ndarray
    miss: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray


def invert_distortion(v: np.ndarray, secondary: Secondary | None, solver: str = "closed-form",
                      hemisphere: str = "+x", start: np.ndarray | None = None, tolerance: float = TOLERANCE,
                      max_iterations: int = MAX_ITERATIONS) -> Inversion:
    """Solve ``φ(r) = v`` for reported positions ``v`` (n, 3) m (see the module docstring).

    ``secondary(r)``: the field model g (None: free space). ``start``: first guesses (n, 3), default v.
    Non-finite ``v`` gives NaN, not converged.
    """
    check_solver(solver)
    v = np.asarray(v, float).reshape(-1, 3)
    n = len(v)
    finite = np.all(np.isfinite(v), axis=1)
    r = np.where(finite[:, None], v if start is None else np.asarray(start, float).reshape(-1, 3), 1.0)
    r = np.where(np.isfinite(r), r, np.where(finite[:, None], v, 1.0))

    def forward(points):
        g = None if secondary is None else secondary(points)
        return distortion(points, g, solver=solver, hemisphere=hemisphere)

    phi, turn = forward(r)
    miss = np.where(finite[:, None], v - phi, 0.0)
    H = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    iterations = np.zeros(n, dtype=int)
    converged = finite & (np.linalg.norm(miss, axis=1) <= tolerance)
    active = finite & ~converged
    for _ in range(max_iterations):
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        step = np.einsum("nij,nj->ni", H[idx], miss[idx])
        before = np.linalg.norm(miss[idx], axis=1)
        trial = r[idx] + step
        phi_t, turn_t = forward(trial)
        miss_t = v[idx] - phi_t
        for _ in range(BACKTRACKS):  # halve the steps that do not lower the miss
            worse = ~(np.linalg.norm(miss_t, axis=1) < before)
            if not worse.any():
                break
            step[worse] *= 0.5
            trial[worse] = r[idx[worse]] + step[worse]
            phi_w, turn_w = forward(trial[worse])
            miss_t[worse], turn_t[worse] = v[idx[worse]] - phi_w, turn_w
        ok = np.linalg.norm(miss_t, axis=1) < before
        dy = miss[idx] - miss_t  # change of φ
        Hdy = np.einsum("nij,nj->ni", H[idx], dy)
        denominator = np.einsum("ni,ni->n", step, Hdy)
        usable = ok & (np.abs(denominator) > 1e-300)
        stepH = np.einsum("ni,nij->nj", step, H[idx])
        update = np.einsum("ni,nj->nij", step - Hdy, stepH) / np.where(usable, denominator, 1.0)[:, None, None]
        H[idx[usable]] += update[usable]
        keep = idx[ok]
        r[keep], miss[keep], turn[keep] = trial[ok], miss_t[ok], turn_t[ok]
        iterations[idx] += 1
        done = np.linalg.norm(miss[idx], axis=1) <= tolerance
        converged[idx[done & ok]] = True
        active[idx[done | ~ok]] = False
    r[~finite] = np.nan
    turn[~finite] = np.nan
    distance = np.linalg.norm(miss, axis=1)
    distance[~finite] = np.nan
    return Inversion(r, turn, distance, converged, iterations)
