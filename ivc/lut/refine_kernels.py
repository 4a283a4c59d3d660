"""Compiled rigid-wand solve of the refinement (numba, parallel over frames).

The same problem and Levenberg-Marquardt rules as :func:`ivc.lut.refine.solve_rigid` with the
cube's harmonic field for sensor 0: per frame, sensor 0's pose ``(r_0, T_0)`` moves every
sensor, ``r_n = r_0 + T_0 b_n``, ``T_n = T_0 R_n``; residuals ``e_n = S_n − T_nᵀ M_n(r_n)``
weighted by ``1 / rms(S_n)``, zero for an invalid sensor or (n ≥ 1) one outside the map;
``M_0 = f_D + g_cube``, ``M_n = f_D + g_map``. Only ``JᵀJ``, ``Jᵀe`` and the cost are kept; each
sensor's share of them is :func:`ivc.lut.rigid_kernels.add_sensor`, the joint solve's too.
"""

from __future__ import annotations

import numba
import numpy as np

from ivc.fixtures.kernels import cube_model
from ivc.linalg import rotate_increment, solve_spd6
from ivc.lut.rigid_kernels import accept_trial, add_sensor, clear, symmetrise
from ivc.pose.kernels import damped_matrix, pose_residual
from ivc.table.kernels import pose_model


@numba.njit(cache=True)  # not inlined: rigid_kernel calls it twice, and two copies of its IR doubled the compile
def _normal(S, valid, scale, b, R, centre, cube_scale, coefficients, grid, r0, T0, H, grad, work):
    """Cost Σ|e|², H = JᵀJ (6, 6) and grad = −Jᵀe (6,) of the rigid wand at (r0, T0)."""
    M, dM, G, H3, g, dg, wx, wy, wz, dx, dy, dz, p, Tn, e, J, Jc, lever = work
    clear(H, grad)
    cost = 0.0
    for n in range(S.shape[0]):
        if not valid[n]:
            continue
        for i in range(3):
            p[i] = r0[i] + T0[i, 0] * b[n, 0] + T0[i, 1] * b[n, 1] + T0[i, 2] * b[n, 2]
            for j in range(3):
                Tn[i, j] = T0[i, 0] * R[n, 0, j] + T0[i, 1] * R[n, 1, j] + T0[i, 2] * R[n, 2, j]
        if n == 0:
            cube_model(p, centre, cube_scale, coefficients, M, dM, G, H3)
        elif not pose_model(p, grid, M, dM, g, dg, wx, wy, wz, dx,
                            dy, dz):
            continue  # a sensor where the map says nothing does not pull the wand
        pose_residual(S[n], M, dM, Tn, e, J)
        cost += add_sensor(e, J, 1.0 / scale[n], b[n], R[n], T0, H, grad, Jc, lever)
    symmetrise(H)
    return cost


@numba.njit(parallel=True, cache=True, nogil=True)
def rigid_kernel(S, valid, scale, b, R, centre, cube_scale, coefficients, grid, max_iterations, tolerance, r, T,
                 converged):  # pragma: no cover - compiled
    """Solve every frame of S (F, W, 3, 3) in place from (r, T), sensor 0's pose; converged (F,)."""
    for f in numba.prange(S.shape[0]):
        work = (np.empty((3, 3)), np.empty((3, 3, 3)), np.empty((15, 3)), np.empty((15, 3, 3)), np.empty(9),
                np.empty((9, 3)), np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4),
                np.empty(3), np.empty((3, 3)), np.empty(9), np.empty((9, 6)), np.empty((9, 6)), np.empty((3, 3)))
        H, Ht, grad, gradt, A, step = (np.empty((6, 6)), np.empty((6, 6)), np.empty(6), np.empty(6),
                                       np.empty((6, 6)), np.empty(6))
        rt, Tt = np.empty(3), np.empty((3, 3))
        converged[f] = False
        if not (valid[f, 0] and np.isfinite(r[f, 0]) and np.isfinite(r[f, 1]) and np.isfinite(r[f, 2])):
            for i in range(3):
                r[f, i] = np.nan
                for j in range(3):
                    T[f, i, j] = np.nan
            continue
        cost = _normal(S[f], valid[f], scale[f], b, R, centre, cube_scale, coefficients, grid, r[f], T[f], H, grad,
                       work)
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
            trial = _normal(S[f], valid[f], scale[f], b, R, centre, cube_scale, coefficients, grid, rt, Tt, Ht, gradt,
                            work)
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
