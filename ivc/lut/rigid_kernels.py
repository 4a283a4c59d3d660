"""One sensor's share of a rigid wand's normal equations (numba), shared by the compiled wand solves.

Both the refinement's solve (:mod:`ivc.lut.refine_kernels`) and the joint map's
(:mod:`ivc.lut.joint_kernels`) move every wand sensor with sensor 0's pose ``(r_0, T_0)``:
``r_n = r_0 + T_0 b_n``, ``T_n = T_0 R_n``. Given sensor n's residual ``e`` (9,) and its Jacobian
``J`` (9, 6) with respect to its own position and rotation increment, the chain to sensor 0's
increments is ``∂r_n/∂r_0 = I``, ``∂r_n/∂ω = −T_0 [b_n]×`` and ``ω_n = R_nᵀ ω``; the sensor's rows are
weighted by ``w = 1 / rms(S_n)``. :func:`add_sensor` adds them to ``H = JᵀJ`` (lower triangle) and
``grad = −Jᵀe``; :func:`symmetrise` fills the upper triangle once all sensors are in;
:func:`accept_trial` makes an accepted Levenberg-Marquardt trial the current pose and equations.
"""

from __future__ import annotations

import numba


@numba.njit(inline="always")
def add_sensor(e, J, w, b, R, T0, H, grad, Jc, lever):
    """Add sensor n's weighted rows to ``H`` (6, 6, lower triangle) and ``grad`` (6,); returns its cost
    ``Σ (w e)²``. ``e`` (9,) is scaled by ``w`` in place; ``b`` (3,), ``R`` (3, 3) its place and rotation in
    the wand; ``Jc`` (9, 6) and ``lever`` (3, 3) work arrays."""
    bx, by, bz = b[0], b[1], b[2]
    for i in range(3):  # ∂r_n/∂ω = −T_0 [b_n]×
        lever[i, 0] = -(T0[i, 1] * bz - T0[i, 2] * by)
        lever[i, 1] = -(-T0[i, 0] * bz + T0[i, 2] * bx)
        lever[i, 2] = -(T0[i, 0] * by - T0[i, 1] * bx)
    cost = 0.0
    for k in range(9):
        for a in range(3):
            Jc[k, a] = w * J[k, a]
            s = 0.0
            for c in range(3):
                s += J[k, c] * lever[c, a] + J[k, 3 + c] * R[a, c]  # ω_n = R_nᵀ ω
            Jc[k, 3 + a] = w * s
        e[k] *= w
        cost += e[k] * e[k]
    for a in range(6):
        s = 0.0
        for k in range(9):
            s -= Jc[k, a] * e[k]
        grad[a] += s
        for c in range(a + 1):
            s = 0.0
            for k in range(9):
                s += Jc[k, a] * Jc[k, c]
            H[a, c] += s
    return cost


@numba.njit(inline="always")
def clear(H, grad):
    """Zero ``H`` (6, 6) and ``grad`` (6,) before the sensors are added."""
    for a in range(6):
        grad[a] = 0.0
        for c in range(6):
            H[a, c] = 0.0


@numba.njit(inline="always")
def symmetrise(H):
    """Copy the lower triangle of ``H`` (6, 6) into the upper."""
    for a in range(6):
        for c in range(a):
            H[c, a] = H[a, c]


@numba.njit(inline="always")
def accept_trial(r, rt, T, Tt, H, Ht, grad, gradt):
    """The trial pose (rt (3,), Tt (3, 3)) and its normal equations (Ht (6, 6), gradt (6,)) become the
    current ones (r, T, H, grad; copied in place)."""
    for a in range(3):
        r[a] = rt[a]
        for c in range(3):
            T[a, c] = Tt[a, c]
    for a in range(6):
        grad[a] = gradt[a]
        for c in range(6):
            H[a, c] = Ht[a, c]
