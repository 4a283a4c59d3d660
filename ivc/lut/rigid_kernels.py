"""One sensor's share of a rigid wand's normal equations (numba), shared by the compiled wand solves.

Both the refinement's solve (:mod:`ivc.lut.refine_kernels`) and the joint map's
(:mod:`ivc.lut.joint_kernels`) move every wand sensor with sensor 0's pose ``(r_0, T_0)``:
``r_n = r_0 + T_0 b_n``, ``T_n = T_0 R_n``. Given sensor n's residual ``e`` (9,) and its Jacobian
``J`` (9, 6) with respect to its own position and rotation increment, the chain to sensor 0's
increments is ``∂r_n/∂r_0 = I``, ``∂r_n/∂ω = −T_0 [b_n]×`` and ``ω_n = R_nᵀ ω``; the sensor's rows are
weighted by ``w = 1 / rms(S_n)``. :func:`add_sensor` adds them to ``H = JᵀJ`` (lower triangle) and
``grad = −Jᵀe``; :func:`symmetrise` fills the upper triangle once all sensors are in;
:func:`accept_trial` makes an accepted Levenberg-Marquardt trial the current pose and equations.

:func:`normal_equations` sums them over the wand for either problem (``field``'s ``tied``: sensor 0 in the cube's
field, the sensors the table does not map left out), and :func:`solve_frame` is the Levenberg-Marquardt loop of one
frame (:func:`ivc.pose.kernels.lm_driver` with this model) both kernels run.
"""

from __future__ import annotations

from collections import namedtuple

import numba
import numpy as np

from ivc.fixtures.kernels import cube_model
from ivc.pose.kernels import NO_COUNTS, accept_pose, lm_driver, no_normal, pose_residual
from ivc.table.kernels import pose_model

#: The wand's geometry: each sensor's position ``b`` (W, 3) m and rotation ``R`` (W, 3, 3) in sensor 0's frame.
Wand = namedtuple("Wand", "b R")
#: A solve's limits: ``max_iterations`` and the position step ``tolerance`` (m) below which it has converged.
Limits = namedtuple("Limits", "max_iterations tolerance")
#: :func:`normal_equations`' scratch arrays: the model ``M`` (3, 3) and ``dM`` (3, 3, 3), the cube's basis ``G``
#: (15, 3) and its gradient ``H3`` (15, 3, 3), the table's ``g`` (9,), ``dg`` (9, 3) and stencil weights
#: ``wx wy wz dx dy dz`` (4,), a sensor's position ``p`` (3,), rotation ``Tn`` (3, 3), residual ``e`` (9,),
#: Jacobian ``J`` and chained Jacobian ``Jc`` (9, 6), and ``lever`` (3, 3).
Work = namedtuple("Work", "M dM G H3 g dg wx wy wz dx dy dz p Tn e J Jc lever")
#: :func:`solve_frame`'s: ``H`` (6, 6) and ``grad`` (6,) at the current pose, ``Ht`` and ``gradt`` at the trial,
#: the damped matrix ``A`` (6, 6), the ``step`` (6,) and the trial pose ``rt`` (3,), ``Tt`` (3, 3).
LMWork = namedtuple("LMWork", "H Ht grad gradt A step rt Tt")


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
    accept_pose(r, rt, T, Tt)
    for a in range(6):
        grad[a] = gradt[a]
        for c in range(6):
            H[a, c] = Ht[a, c]


@numba.njit(cache=True)
def workspace():
    """One frame's scratch arrays: (work, lm), a :data:`Work` and an :data:`LMWork`."""
    work = Work(np.empty((3, 3)), np.empty((3, 3, 3)), np.empty((15, 3)), np.empty((15, 3, 3)), np.empty(9),
                np.empty((9, 3)), np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4),
                np.empty(3), np.empty((3, 3)), np.empty(9), np.empty((9, 6)), np.empty((9, 6)), np.empty((3, 3)))
    lm = LMWork(np.empty((6, 6)), np.empty((6, 6)), np.empty(6), np.empty(6), np.empty((6, 6)), np.empty(6),
                np.empty(3), np.empty((3, 3)))
    return work, lm


@numba.njit(cache=True)  # not inlined: solve_frame calls it twice, and two copies of its IR doubled the compile
def normal_equations(S, use, scale, wand, field, r0, T0, H, grad, work):
    """Cost Σ|e|², H = JᵀJ (6, 6) and grad = −Jᵀe (6,) of the rigid wand at sensor 0's pose (r0, T0), for the
    sensors ``use`` marks. ``wand``: a :data:`Wand`; ``work``: a :data:`Work`; ``field``: (grid, centre,
    cube_scale, coefficients, tied): the table (:data:`ivc.table.kernels.GRID`) for every sensor, or, ``tied``,
    the cube's harmonic field (:func:`ivc.fixtures.kernels.cube_model`) for sensor 0 and the table for the others
    it maps."""
    b, R = wand
    grid, centre, cube_scale, coefficients, tied = field
    M, dM, G, H3, g, dg, wx, wy, wz, dx, dy, dz, p, Tn, e, J, Jc, lever = work
    clear(H, grad)
    cost = 0.0
    for n in range(S.shape[0]):
        if not use[n]:
            continue
        for i in range(3):
            p[i] = r0[i] + T0[i, 0] * b[n, 0] + T0[i, 1] * b[n, 1] + T0[i, 2] * b[n, 2]
            for j in range(3):
                Tn[i, j] = T0[i, 0] * R[n, 0, j] + T0[i, 1] * R[n, 1, j] + T0[i, 2] * R[n, 2, j]
        if tied and n == 0:
            cube_model(p, centre, cube_scale, coefficients, M, dM, G, H3)
        elif not pose_model(p, grid, M, dM, g, dg, wx, wy, wz, dx, dy, dz) and tied:
            continue  # a sensor where the map says nothing does not pull the wand tied to the cube
        pose_residual(S[n], M, dM, Tn, e, J)
        cost += add_sensor(e, J, 1.0 / scale[n], b[n], R[n], T0, H, grad, Jc, lever)
    symmetrise(H)
    return cost


#: The model of one frame's Levenberg-Marquardt loop (:func:`ivc.pose.kernels.lm_driver`): the frame's signals ``S``
#: (W, 3, 3), the sensors it ``use``\ s, their ``scale``, the ``wand``, the ``field``, :func:`normal_equations`'
#: ``work``, and the normal equations at the current pose (``H``, ``grad``) and at the trial (``Ht``, ``gradt``).
Frame = namedtuple("Frame", "S use scale wand field work H Ht grad gradt")


@numba.njit(inline="always")
def _trial(model, rt, Tt):
    cost = normal_equations(model.S, model.use, model.scale, model.wand, model.field, rt, Tt, model.Ht, model.gradt,
                            model.work)
    return cost, False


@numba.njit(inline="always")
def _accept(model, r, rt, T, Tt):
    accept_trial(r, rt, T, Tt, model.H, model.Ht, model.grad, model.gradt)


_lm_solve = lm_driver(no_normal, _trial, _accept)


@numba.njit(**NO_COUNTS)
def solve_frame(S, use, scale, wand, field, limits, r, T, work, lm):
    """Levenberg-Marquardt for one frame's sensor 0 pose (r (3,), T (3, 3), updated in place from the start they
    hold) on :func:`normal_equations`; ``limits``: a :data:`Limits`; ``work``, ``lm``: :func:`workspace`.
    Returns (converged, cost); JᵀJ at the solution is left in ``lm.H``. Allocates nothing."""
    H, Ht, grad, gradt, A, step, rt, Tt = lm
    cost = normal_equations(S, use, scale, wand, field, r, T, H, grad, work)
    model = Frame(S, use, scale, wand, field, work, H, Ht, grad, gradt)
    converged, _, cost, _ = _lm_solve(model, r, T, cost, False, limits, (H, grad, A, step, rt, Tt))
    return converged, cost
