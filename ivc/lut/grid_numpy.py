""":func:`ivc.lut.kernels.grid_kernel` in vectorised NumPy, same arguments, the same sums in the same
order (results agree to rounding, tested to 1e-12): what a command runs on a small input while the
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


def grid_kernel(padded, valid_cells, origin, spacing, shape, points, cubic, values, gradients, inside):
    """Table value, gradient and validity at every point (N, 3), as the compiled kernel."""
    with np.errstate(invalid="ignore", over="ignore"):
        cells = [_cell(points[:, a], origin[a], spacing, shape[a]) for a in range(3)]
        (i, tx, in_x), (j, ty, in_y), (k, tz, in_z) = cells
        (wx, dx), (wy, dy), (wz, dz) = (_weights(t, cubic) for t in (tx, ty, tz))
        values[:] = 0.0
        gradients[:] = 0.0
        for a in range(4):
            use_a = (wx[:, a] != 0.0) | (dx[:, a] != 0.0)
            for b in range(4):
                use_b = use_a & ((wy[:, b] != 0.0) | (dy[:, b] != 0.0))
                for d in range(4):
                    use = use_b & ((wz[:, d] != 0.0) | (dz[:, d] != 0.0))
                    if not use.any():
                        continue
                    w = wx[:, a] * wy[:, b] * wz[:, d]
                    gx = dx[:, a] * wy[:, b] * wz[:, d]
                    gy = wx[:, a] * dy[:, b] * wz[:, d]
                    gz = wx[:, a] * wy[:, b] * dz[:, d]
                    node = padded[i + a, j + b, k + d]
                    m = use[:, None]
                    values += np.where(m, w[:, None] * node, 0.0)
                    gradients[:, :, 0] += np.where(m, gx[:, None] * node, 0.0)
                    gradients[:, :, 1] += np.where(m, gy[:, None] * node, 0.0)
                    gradients[:, :, 2] += np.where(m, gz[:, None] * node, 0.0)
        gradients /= spacing
        inside[:] = in_x & in_y & in_z & valid_cells[i, j, k]
