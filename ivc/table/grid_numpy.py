""":func:`ivc.table.kernels.grid_kernel` in vectorised NumPy, same arguments, the same weights and
nodes (results agree to rounding, tested to 1e-12): what a command runs on a small input while the
compiled kernel is not yet in numba's cache (:func:`ivc.compiled.choose`)."""

from __future__ import annotations

import numpy as np


def _cell(p, origin, spacing, n):
    u = (p - origin) / spacing
    inside = (0.0 <= u) & (u <= n - 1.0)
    i = np.clip(np.where(np.isfinite(u), np.floor(u), 0.0), 0, n - 2).astype(np.int64)
    t = np.clip(u - i, 0.0, 1.0)
    return i, t, inside


def _weights(t, cubic):
    if cubic:
        t2 = t * t
        t3 = t2 * t
        w = np.stack([0.5 * (-t3 + 2.0 * t2 - t), 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
                      0.5 * (-3.0 * t3 + 4.0 * t2 + t), 0.5 * (t3 - t2)], axis=1)
        dw = np.stack([0.5 * (-3.0 * t2 + 4.0 * t - 1.0), 0.5 * (9.0 * t2 - 10.0 * t),
                       0.5 * (-9.0 * t2 + 8.0 * t + 1.0), 0.5 * (3.0 * t2 - 2.0 * t)], axis=1)
        return w, dw
    zero = np.zeros_like(t)
    return (np.stack([zero, 1.0 - t, t, zero], axis=1),
            np.stack([zero, zero - 1.0, zero + 1.0, zero], axis=1))


#: points per block (the block's 64-node stencils: CHUNK x 64 x channels doubles)
CHUNK = 8192
_STENCIL = np.arange(4)


def grid_kernel(grid, points, values, gradients, inside):
    """Table value, gradient and validity at every point (N, 3), as the compiled kernel (the 64-node sums
    contracted axis by axis: equal to rounding)."""
    padded, valid_cells, origin, spacing, shape, cubic = grid
    with np.errstate(invalid="ignore", over="ignore"):
        for lo in range(0, len(points), CHUNK):
            block = slice(lo, lo + CHUNK)
            (i, tx, in_x), (j, ty, in_y), (k, tz, in_z) = (
                _cell(points[block, a], origin[a], spacing, shape[a]) for a in range(3))
            (wx, dx), (wy, dy), (wz, dz) = (_weights(t, cubic) for t in (tx, ty, tz))
            nodes = padded[(i[:, None] + _STENCIL)[:, :, None, None], (j[:, None] + _STENCIL)[:, None, :, None],
                           (k[:, None] + _STENCIL)[:, None, None, :]]  # (n, 4, 4, 4, C)
            vz = np.einsum("nabdc,nd->nabc", nodes, wz)
            gz = np.einsum("nabdc,nd->nabc", nodes, dz)
            vyz = np.einsum("nabc,nb->nac", vz, wy)
            values[block] = np.einsum("nac,na->nc", vyz, wx)
            gradients[block, :, 0] = np.einsum("nac,na->nc", vyz, dx) / spacing
            gradients[block, :, 1] = np.einsum("nac,na->nc", np.einsum("nabc,nb->nac", vz, dy), wx) / spacing
            gradients[block, :, 2] = np.einsum("nac,na->nc", np.einsum("nabc,nb->nac", gz, wy), wx) / spacing
            inside[block] = in_x & in_y & in_z & valid_cells[i, j, k]
