"""Compiled rigid-wand solve of the refinement (numba, parallel over frames).

The same problem and Levenberg-Marquardt rules as :func:`ivc.lut.refine.solve_rigid` with the
cube's harmonic field for sensor 0: per frame, sensor 0's pose ``(r_0, T_0)`` moves every
sensor, ``r_n = r_0 + T_0 b_n``, ``T_n = T_0 R_n``; residuals ``e_n = S_n − T_nᵀ M_n(r_n)``
weighted by ``1 / rms(S_n)``, zero for an invalid sensor or (n ≥ 1) one outside the map;
``M_0 = f_D + g_cube``, ``M_n = f_D + g_map``. Only ``JᵀJ``, ``Jᵀe`` and the cost are kept; each
sensor's share of them is :func:`ivc.lut.rigid_kernels.add_sensor`, and the loop
:func:`ivc.lut.rigid_kernels.solve_frame`, the joint solve's too.
"""

from __future__ import annotations

import numba
import numpy as np

from ivc.lut.rigid_kernels import solve_frame, workspace


@numba.njit(parallel=True, cache=True, nogil=True)
def rigid_kernel(S, valid, scale, wand, cube, grid, limits, r, T, converged):  # pragma: no cover - compiled
    """Solve every frame of S (F, W, 3, 3) in place from (r, T), sensor 0's pose; converged (F,). ``wand``: a
    :data:`ivc.lut.rigid_kernels.Wand`; ``cube``: a :data:`ivc.fixtures.kernels.Cube`; ``limits``: a
    :data:`ivc.lut.rigid_kernels.Limits`."""
    for f in numba.prange(S.shape[0]):
        work, lm = workspace()
        field = (grid, cube.centre, cube.scale, cube.coefficients, np.bool_(True))  # sensor 0 in the cube's field
        converged[f] = False
        if not (valid[f, 0] and np.isfinite(r[f, 0]) and np.isfinite(r[f, 1]) and np.isfinite(r[f, 2])):
            for i in range(3):
                r[f, i] = np.nan
                for j in range(3):
                    T[f, i, j] = np.nan
            continue
        converged[f], _ = solve_frame(S[f], valid[f], scale[f], wand, field, limits, r[f], T[f], work, lm)
