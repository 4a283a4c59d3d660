"""Compiled rigid-wand solve of the joint map (numba, parallel over frames).

The problem and Levenberg-Marquardt rules of :func:`ivc.lut.joint.solve_wand` (its NumPy form, kept
as the reference a test holds this one to) with the field a look-up table: per frame, sensor 0's
pose ``(r_0, T_0)`` moves every sensor, ``r_n = r_0 + T_0 b_n``, ``T_n = T_0 R_n``; residuals
``e_n = S_n − T_nᵀ (f_D + g)(r_n)`` weighted by ``1 / rms(S_n)`` for the sensors ``use`` marks,
zero for the others. Unlike the refinement's kernel (:mod:`ivc.lut.refine_kernels`) no sensor
is tied to the cube: every used sensor counts, wherever the table places it. Only ``JᵀJ``,
``Jᵀe`` and the cost are kept per frame; each sensor's share of them is
:func:`ivc.lut.rigid_kernels.add_sensor`, and the loop :func:`ivc.lut.rigid_kernels.solve_frame`, the refinement's too.
"""

from __future__ import annotations

import numba
import numpy as np

from ivc.lut.rigid_kernels import solve_frame, workspace


@numba.njit(parallel=True, cache=True, nogil=True)
def wand_kernel(S, use, scale, wand, grid, limits, active, r, T, converged, cost_out, H_out):  # pragma: no cover
    """Solve every active frame of S (F, W, 3, 3) in place from (r, T), sensor 0's pose; converged (F,),
    the final cost (F,) and JᵀJ (F, 6, 6) at the solution. ``wand``: a :data:`ivc.lut.rigid_kernels.Wand`;
    ``limits``: a :data:`ivc.lut.rigid_kernels.Limits`."""
    no_cube = np.zeros(3), np.zeros((15, 3))  # every sensor through the table: no sensor tied to the cube
    for f in numba.prange(S.shape[0]):
        work, lm = workspace()
        field = (grid, no_cube[0], 1.0, no_cube[1], np.bool_(False))
        converged[f] = False
        if not active[f]:
            cost_out[f] = 0.0
            for a in range(6):
                for c in range(6):
                    H_out[f, a, c] = 1.0 if a == c else 0.0
            continue
        converged[f], cost_out[f] = solve_frame(S[f], use[f], scale[f], wand, field, limits, r[f], T[f], work, lm)
        H = lm.H
        for a in range(6):
            for c in range(6):
                H_out[f, a, c] = H[a, c]
