"""Compiled pieces of a Levenberg-Marquardt pose solve on the 9 residuals of one signal matrix.

The pose is a position r and a rotation T updated as ``T ← T exp([ω]×)``
(:func:`ivc.linalg.rotate_increment`); the residual is ``e = S − Tᵀ M(r)`` with ``M = f_D + g``
(docs/math.md §4 and §9). The correction (``ivc.correct.kernels``), the cube solve
(``ivc.fixtures.kernels``), the rigid-wand refinement and the joint map (``ivc.lut``) share these;
the model of a table, ``f_D + g`` and its gradient, is :func:`ivc.table.kernels.pose_model`.
The batched NumPy form of the same solve is :func:`ivc.pose.solve_pose`.
"""

from __future__ import annotations

import numba
import numpy as np

from ivc.linalg import rotate_increment, solve_spd6


@numba.njit(cache=True)
def pose_residual(S, M, dM, T, e, J):
    """e = S − Tᵀ M (9,) and its Jacobian (9, 6) in (δr, ω)."""
    for i in range(3):
        for j in range(3):
            p = T[0, i] * M[0, j] + T[1, i] * M[1, j] + T[2, i] * M[2, j]
            e[3 * i + j] = S[i, j] - p
    for i in range(3):
        for j in range(3):
            for k in range(3):
                J[3 * i + j, k] = -(T[0, i] * dM[0, j, k] + T[1, i] * dM[1, j, k] + T[2, i] * dM[2, j, k])
    # ∂e/∂ω_a = [e_a]× P with P = Tᵀ M = S − e
    for j in range(3):
        p0 = S[0, j] - e[j]
        p1 = S[1, j] - e[3 + j]
        p2 = S[2, j] - e[6 + j]
        # a = x: rows (0, −p2, p1); a = y: (p2, 0, −p0); a = z: (−p1, p0, 0)
        J[j, 3] = 0.0
        J[3 + j, 3] = -p2
        J[6 + j, 3] = p1
        J[j, 4] = p2
        J[3 + j, 4] = 0.0
        J[6 + j, 4] = -p0
        J[j, 5] = -p1
        J[3 + j, 5] = p0
        J[6 + j, 5] = 0.0



@numba.njit(inline="always")
def residual_cost(e):
    c = 0.0
    for a in range(9):
        c += e[a] * e[a]
    return c



@numba.njit(cache=True)
def gauss_newton_matrix(J, e, H, grad):
    """H = JᵀJ (6, 6) and grad = −Jᵀe (6,) of a 9-residual, 6-unknown pose step."""
    for a in range(6):
        s = 0.0
        for k in range(9):
            s -= J[k, a] * e[k]
        grad[a] = s
        for b in range(a + 1):
            s = 0.0
            for k in range(9):
                s += J[k, a] * J[k, b]
            H[a, b] = s
            H[b, a] = s



@numba.njit(cache=True)
def damped_matrix(H, damping, A):
    """A = H with Levenberg-Marquardt damping on its diagonal, ``damping · max(H_aa, 1e-30 · max_b H_bb)``
    (A may be H itself)."""
    scale_max = 0.0
    for a in range(6):
        scale_max = max(scale_max, H[a, a])
    for a in range(6):
        for c in range(6):
            A[a, c] = H[a, c]
        A[a, a] += damping * max(H[a, a], 1e-30 * scale_max)



@numba.njit(cache=True)
def lm_step(H, grad, damping, A, step, r, T, rt, Tt):
    """A Levenberg-Marquardt trial: solve ``(H + damping·D) step = grad`` (:func:`damped_matrix` into A, which
    may be H) and move the pose (r (3,), T (3, 3)) by it into the trial (rt = r + step[:3], Tt = T exp([step[3:]]×)).
    Returns (solved, damping): where the damped matrix is not positive definite, not solved and the damping ×10."""
    damped_matrix(H, damping, A)
    if not solve_spd6(A, grad, step):
        return False, damping * 10.0
    for a in range(3):
        rt[a] = r[a] + step[a]
    rotate_increment(T, step[3:], Tt)
    return True, damping


@numba.njit(inline="always")
def lm_verdict(trial, cost, damping, step, tolerance):
    """Levenberg-Marquardt's rule for a trial of cost ``trial`` against the current ``cost``: (accept, damping,
    converged). Accepted when it does not raise the cost, the damping then ×0.3 (at least 1e-12), converged when
    its position step was below ``tolerance`` m; rejected otherwise, the damping ×10, converged above 1e8 (no step
    lowers the cost: at the numerical minimum)."""
    if trial <= cost:
        small = np.sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2]) < tolerance
        return True, max(damping * 0.3, 1e-12), small
    damping *= 10.0
    return False, damping, damping > 1e8


@numba.njit(inline="always")
def accept_pose(r, rt, T, Tt):
    """The trial pose (rt (3,), Tt (3, 3)) becomes the current one (r, T; copied in place)."""
    for a in range(3):
        r[a] = rt[a]
    for i in range(3):
        for j in range(3):
            T[i, j] = Tt[i, j]


@numba.njit(cache=True)
def accept_step(r, rt, T, Tt, e, et, J, Jt):
    """The trial pose (rt, Tt), its residual et and Jacobian Jt become the current ones (copied in place)."""
    accept_pose(r, rt, T, Tt)
    for k in range(9):
        e[k] = et[k]
        for a in range(6):
            J[k, a] = Jt[k, a]



#: Compile options of a function that runs :func:`lm_driver`'s loop: cached, and without numba's reference
#: counts. numba 0.68 counts a reference (an atomic add, and a subtract later) for every array a tuple carries each
#: time an inlined function binds it, and a hook of the loop binds its model at every iteration: about 70 counts per
#: iteration of the correction, which made the loop 6-7 % slower than written out by hand (docs/kernels.md, "One
#: loop, not four"). Without counts, binding is free. The rule that comes with it: such a function, and everything it
#: calls, allocates nothing (numba compiles a callee first reached from it without counts too); the caller allocates
#: the scratch arrays and passes them in.
NO_COUNTS = {"cache": True, "_nrt": False}


@numba.njit(inline="always")
def no_shortcut(model, step, r, T, rt, Tt, tolerance, state):
    """The shortcut of a model that has none: never taken (``(False, state)``)."""
    return False, state


@numba.njit(inline="always")
def no_normal(model, H, grad):
    """The normal equations of a model whose ``H`` and ``grad`` are kept current by its accept step."""
    return None


@numba.njit(inline="always")
def residual_normal(model, H, grad):
    """``normal`` of a model that keeps the current pose's residual ``model.e`` (9,) and Jacobian ``model.J`` (9, 6):
    :func:`gauss_newton_matrix`."""
    gauss_newton_matrix(model.J, model.e, H, grad)


@numba.njit(inline="always")
def residual_accept(model, r, rt, T, Tt):
    """``accept`` of the same model, whose trial residual and Jacobian are ``model.et``, ``model.Jt``:
    :func:`accept_step`."""
    accept_step(r, rt, T, Tt, model.e, model.et, model.J, model.Jt)


def lm_driver(normal, trial, accept, shortcut=no_shortcut):
    """One Levenberg-Marquardt loop over a pose (r (3,), T (3, 3)), given its model's kernels.

    The model is one tuple of the arrays its kernels read and write; each kernel is a compiled function:

    - ``normal(model, H, grad)``: ``H = JᵀJ`` (6, 6) and ``grad = −Jᵀe`` (6,) at the current pose
      (:func:`residual_normal` for a model that keeps its residual and Jacobian, :func:`no_normal` when the accept
      step keeps them current);
    - ``trial(model, rt, Tt) -> (cost, state)``: the cost Σe² at the trial pose and the model's value of ``state``
      there (a scalar the loop carries: the correction's "mapped");
    - ``accept(model, r, rt, T, Tt)``: the trial becomes the current pose (the pose and what the model keeps of it);
    - ``shortcut(model, step, r, T, rt, Tt, tolerance, state) -> (done, state)``: a step the model takes without
      evaluating the trial (the correction's step below the tolerance), or :func:`no_shortcut`.

    Returns the loop ``run(model, r, T, cost, state, limits, lm) -> (converged, iterations, cost, state)``, from the
    pose in (r, T) of cost ``cost`` (updated in place); ``limits``: (max_iterations, tolerance m); ``lm``: the loop's
    scratch (H, grad, A, step, rt, Tt), A the damped matrix ((6, 6), may be H itself). The rules are
    :func:`lm_step` and :func:`lm_verdict`. The loop and the model's kernels are inlined into the caller, which is
    compiled with :data:`NO_COUNTS`; keep the kernels thin (calls of compiled functions), since inlining copies them.
    """

    @numba.njit(inline="always")
    def run(model, r, T, cost, state, limits, lm):
        max_iterations, tolerance = limits
        H, grad, A, step, rt, Tt = lm
        damping = 1e-3
        converged = False
        iterations = 0
        while iterations < max_iterations:
            iterations += 1
            normal(model, H, grad)
            solved, damping = lm_step(H, grad, damping, A, step, r, T, rt, Tt)
            if not solved:
                if damping > 1e8:
                    break
                continue
            done, state = shortcut(model, step, r, T, rt, Tt, tolerance, state)
            if done:
                converged = True
                break
            trial_cost, trial_state = trial(model, rt, Tt)
            take, damping, converged = lm_verdict(trial_cost, cost, damping, step, tolerance)
            if take:
                accept(model, r, rt, T, Tt)
                cost = trial_cost
                state = trial_state
            if converged:
                break
        return converged, iterations, cost, state

    return run
