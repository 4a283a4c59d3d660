"""Compiled evaluation of a field tabulated on a regular grid (numba, parallel over points).

The table is ``padded``: (nx + 2, ny + 2, nz + 2, C) with one ghost node on every face,
so that the 4-node Catmull-Rom stencil of every cell is in range. Node ``(i, j, k)`` of
the grid is ``padded[i + 1, j + 1, k + 1]``.

Every look-up takes the table as one argument, the tuple :data:`GRID` describes
(``ivc.table.grid.GridField.kernel_grid`` builds it).
"""

from __future__ import annotations

import numba
import numpy as np

from ivc.dipole.kernels import dipole_jacobian, field_matrix

_OPTS = dict(parallel=True, cache=True, nogil=True)

#: the fields of the bundled table argument, in order: padded values (nx+2, ny+2, nz+2, C) float64, valid
#: cells (nx-1, ny-1, nz-1) bool, origin (3,) m, spacing m (float), shape (3,) int64, cubic (bool)
GRID = ("padded", "valid_cells", "origin", "spacing", "shape", "cubic")


@numba.njit(inline="always")
def cell_of(p, origin, spacing, n):
    """Cell index in [0, n − 2] and the local coordinate clamped to [0, 1], and whether p is in the grid.
    A NaN p gives cell 0 and a NaN coordinate (clamped before the integer conversion, which NaN or inf
    would break)."""
    u = (p - origin) / spacing
    inside = 0.0 <= u <= n - 1.0
    if u >= n - 2.0:
        i = n - 2
    elif u >= 0.0:
        i = int(np.floor(u))
    else:
        i = 0
    t = u - i
    if t < 0.0:
        t = 0.0
    elif t > 1.0:
        t = 1.0
    return i, t, inside


@numba.njit(inline="always")
def axis_weights(t, cubic, w, dw):
    """Stencil weights of nodes i − 1 .. i + 2 at local coordinate t, and their derivatives in t.

    Cubic: Catmull-Rom (interpolating, C1, exact for quadratics). Otherwise linear.
    """
    if cubic:
        t2 = t * t
        t3 = t2 * t
        w[0] = 0.5 * (-t3 + 2.0 * t2 - t)
        w[1] = 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0)
        w[2] = 0.5 * (-3.0 * t3 + 4.0 * t2 + t)
        w[3] = 0.5 * (t3 - t2)
        dw[0] = 0.5 * (-3.0 * t2 + 4.0 * t - 1.0)
        dw[1] = 0.5 * (9.0 * t2 - 10.0 * t)
        dw[2] = 0.5 * (-9.0 * t2 + 8.0 * t + 1.0)
        dw[3] = 0.5 * (3.0 * t2 - 2.0 * t)
    else:
        w[0] = 0.0
        w[1] = 1.0 - t
        w[2] = t
        w[3] = 0.0
        dw[0] = 0.0
        dw[1] = -1.0
        dw[2] = 1.0
        dw[3] = 0.0


@numba.njit(cache=True)
def grid_point(grid, p, value, gradient, wx, wy, wz, dx, dy, dz):
    """Value (C,) and gradient (C, 3) of the table ``grid`` (:data:`GRID`) at one point p; returns whether p
    is in a valid cell."""
    padded, valid_cells, origin, spacing, shape, cubic = grid
    i, tx, in_x = cell_of(p[0], origin[0], spacing, shape[0])
    j, ty, in_y = cell_of(p[1], origin[1], spacing, shape[1])
    k, tz, in_z = cell_of(p[2], origin[2], spacing, shape[2])
    axis_weights(tx, cubic, wx, dx)
    axis_weights(ty, cubic, wy, dy)
    axis_weights(tz, cubic, wz, dz)
    C = padded.shape[3]
    for c in range(C):
        value[c] = 0.0
        gradient[c, 0] = 0.0
        gradient[c, 1] = 0.0
        gradient[c, 2] = 0.0
    # the linear stencil's outer nodes carry zero weight and zero derivative: only nodes 1..2 are read
    lo, hi = (0, 4) if cubic else (1, 3)
    for a in range(lo, hi):
        if wx[a] == 0.0 and dx[a] == 0.0:
            continue
        for b in range(lo, hi):
            if wy[b] == 0.0 and dy[b] == 0.0:
                continue
            wab = wx[a] * wy[b]
            gxab = dx[a] * wy[b]
            gyab = wx[a] * dy[b]
            for d in range(lo, hi):
                if wz[d] == 0.0 and dz[d] == 0.0:
                    continue
                w = wab * wz[d]
                gx = gxab * wz[d]
                gy = gyab * wz[d]
                gz = wab * dz[d]
                for c in range(C):
                    v = padded[i + a, j + b, k + d, c]
                    value[c] += w * v
                    gradient[c, 0] += gx * v
                    gradient[c, 1] += gy * v
                    gradient[c, 2] += gz * v
    for c in range(C):
        gradient[c, 0] /= spacing
        gradient[c, 1] /= spacing
        gradient[c, 2] /= spacing
    return in_x and in_y and in_z and valid_cells[i, j, k]


@numba.njit(cache=True)
def grid_point_separable(grid, p, value, gradient, wx, wy, wz, dx, dy, dz, scratch):
    """:func:`grid_point` contracted one axis at a time (z, then y, then x) with the partial sums in
    ``scratch`` (3, C): 1,728 multiply-adds for the cubic stencil of 9 channels instead of 2,304, and
    the innermost sums held in registers rather than re-stored at every node. Equal to
    :func:`grid_point` up to rounding (the summation order differs)."""
    padded, valid_cells, origin, spacing, shape, cubic = grid
    i, tx, in_x = cell_of(p[0], origin[0], spacing, shape[0])
    j, ty, in_y = cell_of(p[1], origin[1], spacing, shape[1])
    k, tz, in_z = cell_of(p[2], origin[2], spacing, shape[2])
    axis_weights(tx, cubic, wx, dx)
    axis_weights(ty, cubic, wy, dy)
    axis_weights(tz, cubic, wz, dz)
    C = padded.shape[3]
    for c in range(C):
        value[c] = 0.0
        gradient[c, 0] = 0.0
        gradient[c, 1] = 0.0
        gradient[c, 2] = 0.0
    lo, hi = (0, 4) if cubic else (1, 3)
    for a in range(lo, hi):
        for c in range(C):
            scratch[0, c] = 0.0
            scratch[1, c] = 0.0
            scratch[2, c] = 0.0
        for b in range(lo, hi):
            wyb = wy[b]
            dyb = dy[b]
            for c in range(C):
                sv = 0.0
                sd = 0.0
                for d in range(lo, hi):
                    v = padded[i + a, j + b, k + d, c]
                    sv += wz[d] * v
                    sd += dz[d] * v
                scratch[0, c] += wyb * sv
                scratch[1, c] += dyb * sv
                scratch[2, c] += wyb * sd
        wxa = wx[a]
        dxa = dx[a]
        for c in range(C):
            value[c] += wxa * scratch[0, c]
            gradient[c, 0] += dxa * scratch[0, c]
            gradient[c, 1] += wxa * scratch[1, c]
            gradient[c, 2] += wxa * scratch[2, c]
    for c in range(C):
        gradient[c, 0] /= spacing
        gradient[c, 1] /= spacing
        gradient[c, 2] /= spacing
    return in_x and in_y and in_z and valid_cells[i, j, k]


@numba.njit(cache=True)
def grid_contains(grid, p):
    """Whether p (3,) is in a valid cell: what :func:`grid_point` returns, without the interpolation."""
    _, valid_cells, origin, spacing, shape, _ = grid
    i, _, in_x = cell_of(p[0], origin[0], spacing, shape[0])
    j, _, in_y = cell_of(p[1], origin[1], spacing, shape[1])
    k, _, in_z = cell_of(p[2], origin[2], spacing, shape[2])
    return in_x and in_y and in_z and valid_cells[i, j, k]


@numba.njit(cache=True)
def grid_value(grid, p, value, wx, wy, wz, dx, dy, dz):
    """:func:`grid_point` without the gradient (a quarter of its arithmetic): value (C,) at p, and
    whether p is in a valid cell. The same weights and summation order, so the same value."""
    padded, valid_cells, origin, spacing, shape, cubic = grid
    i, tx, in_x = cell_of(p[0], origin[0], spacing, shape[0])
    j, ty, in_y = cell_of(p[1], origin[1], spacing, shape[1])
    k, tz, in_z = cell_of(p[2], origin[2], spacing, shape[2])
    axis_weights(tx, cubic, wx, dx)
    axis_weights(ty, cubic, wy, dy)
    axis_weights(tz, cubic, wz, dz)
    C = padded.shape[3]
    lo, hi = (0, 4) if cubic else (1, 3)
    # a field matrix (9 channels) keeps its nine sums in registers instead of storing them back at every node (1.5x
    # faster); any other table sums into value. Either way the same sums in the same order
    nine = C == 9
    v0 = v1 = v2 = v3 = v4 = v5 = v6 = v7 = v8 = 0.0
    for c in range(C):
        value[c] = 0.0
    for a in range(lo, hi):
        if wx[a] == 0.0 and dx[a] == 0.0:
            continue
        for b in range(lo, hi):
            if wy[b] == 0.0 and dy[b] == 0.0:
                continue
            wab = wx[a] * wy[b]
            for d in range(lo, hi):
                if wz[d] == 0.0 and dz[d] == 0.0:
                    continue
                w = wab * wz[d]
                node = padded[i + a, j + b, k + d]
                if nine:
                    v0 += w * node[0]
                    v1 += w * node[1]
                    v2 += w * node[2]
                    v3 += w * node[3]
                    v4 += w * node[4]
                    v5 += w * node[5]
                    v6 += w * node[6]
                    v7 += w * node[7]
                    v8 += w * node[8]
                else:
                    for c in range(C):
                        value[c] += w * node[c]
    if nine:
        value[0], value[1], value[2], value[3], value[4] = v0, v1, v2, v3, v4
        value[5], value[6], value[7], value[8] = v5, v6, v7, v8
    return in_x and in_y and in_z and valid_cells[i, j, k]


@numba.njit(inline="always")
def with_dipole(r, g, dg, M, dM):
    """M = f_D(r) + g (3, 3) and ∂M/∂r = ∂f_D/∂r + dg (3, 3, 3), from the table's value g (9,) and gradient
    dg (9, 3) at r."""
    field_matrix(r[0], r[1], r[2], M)
    dipole_jacobian(r, dM)
    for i in range(3):
        for j in range(3):
            M[i, j] += g[3 * i + j]
            for k in range(3):
                dM[i, j, k] += dg[3 * i + j, k]


@numba.njit(cache=True)
def pose_model(r, grid, M, dM, g, dg, wx, wy, wz, dx, dy, dz):
    """M = f_D(r) + g(r) (3, 3) and ∂M/∂r (3, 3, 3); returns whether r is in the mapped volume."""
    mapped = grid_point(grid, r, g, dg, wx, wy, wz, dx, dy, dz)
    with_dipole(r, g, dg, M, dM)
    return mapped


@numba.njit(**_OPTS)
def grid_kernel(grid, points, values, gradients, inside):
    """Table value, gradient and validity at every point (N, 3)."""
    for n in numba.prange(points.shape[0]):
        w = np.empty((6, 4))  # the stencil's weights along x, y, z, then their derivatives
        inside[n] = grid_point(grid, points[n], values[n], gradients[n], w[0], w[1], w[2], w[3], w[4], w[5])


@numba.njit(inline="always")
def _regular(re, im, l, m):  # noqa: E741 - l is the degree, as in the literature
    """R_l^m for any m (zero outside |m| <= l), from the m >= 0 table: R_l^{-m} = (-1)^m conj(R_l^m)."""
    if m > l or -m > l:
        return 0.0, 0.0
    if m >= 0:
        return re[l, m], im[l, m]
    sign = 1.0 if (-m) % 2 == 0 else -1.0
    return sign * re[l, -m], -sign * im[l, -m]


@numba.njit(**_OPTS)
def harmonic_gradient_rows(x, degree, out):  # pragma: no cover - compiled
    """Gradients of the real solid harmonics of degree 1..degree at x (N, 3) into out (N, 3, K):
    ``out[n, i, k] = ∂_i Φ_k(x_n)``, the same functions and order as ``ivc.lut.harmonics.gradients``
    (which returns them as (N, K, 3)), built by the same recurrences one point at a time."""
    top = degree - 1
    blocks = (x.shape[0] + 255) // 256
    for block in numba.prange(blocks):  # scratch tables allocated once per block of points
        re = np.zeros((top + 1, top + 1))
        im = np.zeros((top + 1, top + 1))
        for n in range(256 * block, min(256 * block + 256, x.shape[0])):
            _gradient_row(x[n, 0], x[n, 1], x[n, 2], degree, re, im, out[n])


@numba.njit(inline="always")
def _gradient_row(X, Y, Z, degree, re, im, out):
    """One point of :func:`harmonic_gradient_rows`: R_l^m (l < degree) into re, im, then out (3, K)."""
    top = degree - 1
    r2 = X * X + Y * Y + Z * Z
    re[0, 0] = 1.0
    im[0, 0] = 0.0
    for l in range(1, top + 1):  # noqa: E741
        a, b = re[l - 1, l - 1], im[l - 1, l - 1]
        re[l, l] = -(X * a - Y * b) / (2 * l)
        im[l, l] = -(X * b + Y * a) / (2 * l)
        for m in range(l):
            pr, pi = (re[l - 2, m], im[l - 2, m]) if l >= 2 else (0.0, 0.0)
            d = (l + m) * (l - m)
            re[l, m] = ((2 * l - 1) * Z * re[l - 1, m] - r2 * pr) / d
            im[l, m] = ((2 * l - 1) * Z * im[l - 1, m] - r2 * pi) / d
    k = 0
    for l in range(1, degree + 1):  # noqa: E741
        for m in range(l + 1):
            ur, ui = _regular(re, im, l - 1, m + 1)
            dr, di = _regular(re, im, l - 1, m - 1)
            zr, zi = _regular(re, im, l - 1, m)
            # ∂x = (up − down) / 2, ∂y = −i (down + up) / 2, ∂z = R_{l−1}^m
            out[0, k] = 0.5 * (ur - dr)
            out[1, k] = 0.5 * (di + ui)
            out[2, k] = zr
            k += 1
            if m > 0:
                out[0, k] = 0.5 * (ui - di)
                out[1, k] = -0.5 * (dr + ur)
                out[2, k] = zi
                k += 1

