"""Compiled rigid-wand solve of the joint map (numba, parallel over frames).

The problem and Levenberg-Marquardt rules of :func:`ivc.lut.joint.solve_wand` (its NumPy form, kept
as the reference a test holds this one to) with the field a look-up table: per frame, sensor 0's
pose ``(r_0, T_0)`` moves every sensor, ``r_n = r_0 + T_0 b_n``, ``T_n = T_0 R_n``; residuals
``e_n = S_n − T_nᵀ (f_D + g)(r_n)`` weighted by ``1 / rms(S_n)`` for the sensors ``use`` marks,
zero for the others. Unlike the refinement's kernel (:mod:`ivc.lut.refine_kernels`) no sensor
is tied to the cube: every used sensor counts, wherever the table places it. Only ``JᵀJ``,
``Jᵀe`` and the cost are kept per frame; each sensor's share of them is
:func:`ivc.lut.rigid_kernels.add_sensor`, the refinement's too.
"""

from __future__ import annotations

import numba
import numpy as np

from ivc.linalg import rotate_increment, solve_spd6
from ivc.lut.rigid_kernels import accept_trial, add_sensor, clear, symmetrise
from ivc.pose.kernels import damped_matrix, pose_residual
from ivc.table.kernels import pose_model


@numba.njit(cache=True)  # not inlined: wand_kernel calls it twice, and two copies of its IR doubled the compile
def _normal(S, use, scale, b, R, grid, r0, T0, H, grad, work):
    """Cost Σ|e|², H = JᵀJ (6, 6) and grad = −Jᵀe (6,) of the rigid wand at (r0, T0)."""
    M, dM, g, dg, wx, wy, wz, dx, dy, dz, p, Tn, e, J, Jc, lever = work
    clear(H, grad)
    cost = 0.0
    for n in range(S.shape[0]):
        if not use[n]:
            continue
        for i in range(3):
            p[i] = r0[i] + T0[i, 0] * b[n, 0] + T0[i, 1] * b[n, 1] + T0[i, 2] * b[n, 2]
            for j in range(3):
                Tn[i, j] = T0[i, 0] * R[n, 0, j] + T0[i, 1] * R[n, 1, j] + T0[i, 2] * R[n, 2, j]
        pose_model(p, grid, M, dM, g, dg, wx, wy, wz, dx, dy, dz)
        pose_residual(S[n], M, dM, Tn, e, J)
        cost += add_sensor(e, J, 1.0 / scale[n], b[n], R[n], T0, H, grad, Jc, lever)
    symmetrise(H)
    return cost


@numba.njit(parallel=True, cache=True, nogil=True)
def wand_kernel(S, use, scale, b, R, grid, max_iterations, tolerance, active, r, T, converged, cost_out,
                H_out):  # pragma: no cover - compiled
    """Solve every active frame of S (F, W, 3, 3) in place from (r, T), sensor 0's pose; converged (F,),
    the final cost (F,) and JᵀJ (F, 6, 6) at the solution."""
    for f in numba.prange(S.shape[0]):
        work = (np.empty((3, 3)), np.empty((3, 3, 3)), np.empty(9), np.empty((9, 3)), np.empty(4), np.empty(4),
                np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(3), np.empty((3, 3)), np.empty(9),
                np.empty((9, 6)), np.empty((9, 6)), np.empty((3, 3)))
        H, Ht, grad, gradt, A, step = (np.empty((6, 6)), np.empty((6, 6)), np.empty(6), np.empty(6),
                                       np.empty((6, 6)), np.empty(6))
        rt, Tt = np.empty(3), np.empty((3, 3))
        converged[f] = False
        if not active[f]:
            cost_out[f] = 0.0
            for a in range(6):
                for c in range(6):
                    H_out[f, a, c] = 1.0 if a == c else 0.0
            continue
        cost = _normal(S[f], use[f], scale[f], b, R, grid, r[f], T[f], H, grad, work)
        damping = 1e-3
        for _ in range(max_iterations):
            damped_matrix(H, damping, A)
            if not solve_spd6(A, grad, step):
                damping *= 10.0
                if damping > 1e8:
                    break
                continue
            for a in range(3):
                rt[a] = r[f, a] + step[a]
            rotate_increment(T[f], step[3:], Tt)
            trial = _normal(S[f], use[f], scale[f], b, R, grid, rt, Tt, Ht, gradt, work)
            small = np.sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2]) < tolerance
            if trial <= cost:
                accept_trial(r[f], rt, T[f], Tt, H, Ht, grad, gradt)
                cost = trial
                damping = max(damping * 0.3, 1e-12)
                if small:
                    converged[f] = True
                    break
            else:
                damping *= 10.0
                if damping > 1e8:  # no step lowers the cost: at the numerical minimum
                    converged[f] = True
                    break
        cost_out[f] = cost
        for a in range(6):
            for c in range(6):
                H_out[f, a, c] = H[a, c]
