"""Compiled per-frame correction: the pose that explains S with the dipole field plus the mapped
secondary field (docs/math.md §4 and §9), one frame at a time, parallel over frames.

Per frame: a seed (the previous pose of the same sensor; else the closed-form dipole position
``v = φ(r)`` moved by the correction map ``r − v`` tabulated at ``v`` (``ivc.correct.seed_map``) where that
map covers ``v``; else a fixed-point start: closed-form dipole pose of ``S − Tᵀ g(r)``, repeated), then
Levenberg-Marquardt over position and a rotation increment ``T ← T exp([ω]×)`` on the 9 residuals
``e = S − Tᵀ (f_D(r) + g(r))`` with analytic Jacobians.

The table is one argument ``grid``, the tuple of ``ivc.table.kernels.GRID``; so is the correction map (3 channels).
"""

from __future__ import annotations

from collections import namedtuple

import numba
import numpy as np

from ivc.dipole.kernels import closed_form_one, closed_form_position
from ivc.linalg import copy_pose, quaternion_of, relative_residual, rotation_polar_factor
from ivc.pose.kernels import (
    NO_COUNTS,
    accept_pose,
    lm_driver,
    pose_residual,
    residual_accept,
    residual_cost,
    residual_normal,
)
from ivc.pose.precision_kernels import crb_covariance_one, traces
from ivc.table.kernels import grid_contains, grid_point_separable, grid_value, pose_model, with_dipole

FIXED_POINT_STEPS = 2

# The helpers below are plain (not numba-inlined) functions: LLVM still inlines what pays, but numba
# no longer copies their IR into every call site, which made the first compile of the correction
# kernels take minutes (the cold start of `ivc correct`).


@numba.njit(cache=True)
def _closed_form(S, hemisphere, r, T, work_a, work_b, v, B, F, K):
    """ivc.dipole's closed-form pose of one frame, compiled once here rather than inlined at each use."""
    closed_form_one(S, hemisphere, r, T, work_a, work_b, v, B, F, K)


#: The scratch arrays of one frame's correction (:func:`workspace`), by name: the model ``M`` (3, 3) and
#: ``dM`` (3, 3, 3); the table's value ``g`` (9,) and gradient ``dg`` (9, 3) with the look-up's weights
#: ``wx wy wz`` and their derivatives ``dx dy dz`` (4,); the closed form's ``work_a work_b B F K`` (3, 3) and
#: ``v`` (3,); the signal less the table's field ``Sc`` and the model at the accepted position ``Ma`` (3, 3);
#: the residuals ``e``/``et`` (9,) and Jacobians ``J``/``Jt`` (9, 6) of the current pose and the trial;
#: ``H`` (6, 6), ``grad`` and ``step`` (6,), the trial pose ``rt`` (3,), ``Tt`` (3, 3); the retries'
#: ``best_r``/``trial_r`` (3,), ``best_T``/``trial_T`` (3, 3) and ``candidates`` (4, 3); the separable
#: look-up's partial sums ``scratch`` (3, C).
Workspace = namedtuple("Workspace", "M dM g dg wx wy wz dx dy dz work_a work_b B F K v Sc Ma e J et Jt H grad step "
                       "rt Tt best_r best_T trial_r trial_T candidates scratch")
#: What one frame's look-up writes and reads (a :class:`Workspace`'s fields of the same names).
Lookup = namedtuple("Lookup", "g dg wx wy wz dx dy dz scratch")
#: The settings of a batch: whether cold frames start from the correction map, the iteration limit, the
#: step tolerance (m) and the residual above which a frame is retried (:func:`correct_best`).
Config = namedtuple("Config", "use_map max_iterations tolerance retry_residual")
#: A batch's outputs, row n per frame: position ``r`` (n, 3) m, rotation ``T`` (n, 3, 3), quaternion ``q``
#: (n, 4), ``converged`` (n,) bool, ``iterations`` (n,) int64, relative ``residual`` (n,), ``mapped`` (n,) bool.
Output = namedtuple("Output", "r T q converged iterations residual mapped")


@numba.njit(cache=True)
def pose_model_separable(r, grid, M, dM, lookup):
    """:func:`pose_model` with the separable look-up, its scratch arrays a :data:`Lookup`."""
    mapped = grid_point_separable(grid, r, lookup.g, lookup.dg, lookup.wx, lookup.wy, lookup.wz, lookup.dx,
                                  lookup.dy, lookup.dz, lookup.scratch)
    with_dipole(r, lookup.g, lookup.dg, M, dM)
    return mapped


#: The model of one frame's Levenberg-Marquardt loop (:func:`ivc.pose.kernels.lm_driver`): the signal ``S``, the
#: table ``grid``, its look-up's scratch ``lookup`` (a :data:`Lookup`), and of a :class:`Workspace` the model
#: ``M``/``dM``, the residuals and Jacobians ``e``/``J`` (current pose) and ``et``/``Jt`` (trial), and ``Ma``, the
#: model at the accepted position.
Frame = namedtuple("Frame", "S grid lookup M dM e J et Jt Ma")


@numba.njit(inline="always")
def _trial(model, rt, Tt):
    mapped = pose_model_separable(rt, model.grid, model.M, model.dM, model.lookup)
    pose_residual(model.S, model.M, model.dM, Tt, model.et, model.Jt)
    return residual_cost(model.et), mapped


@numba.njit(cache=True)
def _copy_model(M, Ma):
    for i in range(3):
        for j in range(3):
            Ma[i, j] = M[i, j]


@numba.njit(inline="always")
def _accept(model, r, rt, T, Tt):
    _copy_model(model.M, model.Ma)
    residual_accept(model, r, rt, T, Tt)


@numba.njit(cache=True)
def _move_model(J, step, T, e, Ma):
    """The model at the accepted position moved along its Jacobian by ``step`` (``e`` is scratch)."""
    for a in range(9):
        e[a] = J[a, 0] * step[0] + J[a, 1] * step[1] + J[a, 2] * step[2]  # −Tᵀ ∂M/∂r · δr
    for i in range(3):
        for j in range(3):
            Ma[i, j] -= T[i, 0] * e[j] + T[i, 1] * e[3 + j] + T[i, 2] * e[6 + j]


@numba.njit(inline="always")
def _shortcut(model, step, r, T, rt, Tt, tolerance, mapped):
    # a step below the tolerance (0.1 µm) is taken without the look-up that would confirm it: the model
    # there is the current one moved along its Jacobian (an error of |step|², far below the noise), and
    # whether the point is mapped comes from the grid's cell flags.
    if not np.sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2]) < tolerance:
        return False, mapped
    _move_model(model.J, step, T, model.e, model.Ma)
    accept_pose(r, rt, T, Tt)
    return True, grid_contains(model.grid, r)


_lm_solve = lm_driver(residual_normal, _trial, _accept, _shortcut)


@numba.njit(**NO_COUNTS)
def _solve(S, grid, ws, r, T, cost, mapped, limits):
    """The Levenberg-Marquardt loop of :func:`correct_one_in` from the pose (r, T) of cost ``cost``; ``limits``:
    (max_iterations, tolerance m). Returns (converged, iterations, cost, mapped). Allocates nothing."""
    lookup = Lookup(ws.g, ws.dg, ws.wx, ws.wy, ws.wz, ws.dx, ws.dy, ws.dz, ws.scratch)
    model = Frame(S, grid, lookup, ws.M, ws.dM, ws.e, ws.J, ws.et, ws.Jt, ws.Ma)
    return _lm_solve(model, r, T, cost, mapped, limits, (ws.H, ws.grad, ws.H, ws.step, ws.rt, ws.Tt))


@numba.njit(cache=True)
def workspace(channels):
    """The scratch arrays of one frame's correction (a :data:`Workspace`), allocated once and reused over many
    frames (per-frame allocation was a measurable share of the batched correction)."""
    return Workspace(np.empty((3, 3)), np.empty((3, 3, 3)), np.empty(9), np.empty((9, 3)),  # M, dM, g, dg
                     np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4),  # wx .. dz
                     np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
                     np.empty(3), np.empty((3, 3)), np.empty((3, 3)),  # v, Sc, Ma
                     np.empty(9), np.empty((9, 6)), np.empty(9), np.empty((9, 6)),  # e, J, et, Jt
                     np.empty((6, 6)), np.empty(6), np.empty(6), np.empty(3), np.empty((3, 3)),  # H grad step rt Tt
                     np.empty(3), np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty((4, 3)),  # the retries'
                     np.empty((3, channels)))  # the look-up's partial sums


@numba.njit(cache=True)
def correct_one(S, seed, hemisphere, grid, seed_map, use_map, max_iterations, tolerance, r, T):
    """Correct one frame: S (3, 3), seed (3,) (NaN: no warm start) -> r (3,), T (3, 3) written in place.
    ``grid``: the table; ``seed_map``: the correction map (used for a cold start when ``use_map``).

    Returns (converged, iterations, relative residual rms(M − T S)/rms(S), mapped).
    """
    return correct_one_in(S, seed, hemisphere, grid, seed_map, use_map, max_iterations, tolerance, r, T,
                          workspace(grid[0].shape[3]))


@numba.njit(cache=True)
def correct_one_in(S, seed, hemisphere, grid, seed_map, use_map, max_iterations, tolerance, r, T, ws):
    """:func:`correct_one` with its scratch arrays from ``ws`` (:func:`workspace`)."""
    M, dM, g, dg, wx, wy, wz, dx, dy, dz = ws.M, ws.dM, ws.g, ws.dg, ws.wx, ws.wy, ws.wz, ws.dx, ws.dy, ws.dz
    work_a, work_b, B, F, K, v, Sc, Ma = ws.work_a, ws.work_b, ws.B, ws.F, ws.K, ws.v, ws.Sc, ws.Ma
    e, J = ws.e, ws.J
    lookup = Lookup(g, dg, wx, wy, wz, dx, dy, dz, ws.scratch)
    seeded = np.isfinite(seed[0]) and np.isfinite(seed[1]) and np.isfinite(seed[2])
    if seeded:
        for a in range(3):
            r[a] = seed[a]
    elif use_map:
        # the closed-form position v and the map's r − v at v (one closed form and a 3-channel look-up,
        # landing about 10 µm from the answer, where the fixed point below costs three closed forms)
        closed_form_position(S, hemisphere, r, v, B)
        if grid_value(seed_map, r, g, wx, wy, wz, dx, dy, dz):
            for a in range(3):
                r[a] += g[a]
            seeded = True
    if not seeded:
        _closed_form(S, hemisphere, r, T, work_a, work_b, v, B, F, K)
        for step_number in range(FIXED_POINT_STEPS):  # docs/math.md §9: subtract Tᵀ g(r), re-solve the dipole pose
            grid_value(grid, r, g, wx, wy, wz, dx, dy, dz)
            for i in range(3):
                for j in range(3):
                    Sc[i, j] = S[i, j] - (T[0, i] * g[j] + T[1, i] * g[3 + j] + T[2, i] * g[6 + j])
            if step_number < FIXED_POINT_STEPS - 1:
                _closed_form(Sc, hemisphere, r, T, work_a, work_b, v, B, F, K)
            else:  # the last step's orientation would be replaced below: its position is all that is used
                closed_form_position(Sc, hemisphere, r, v, B)
    mapped = pose_model_separable(r, grid, M, dM, lookup)
    for i in range(3):  # the model at the accepted position, and whether it is mapped: no re-evaluation at the end
        for j in range(3):
            Ma[i, j] = M[i, j]
    for i in range(3):
        for j in range(3):
            K[i, j] = M[i, 0] * S[j, 0] + M[i, 1] * S[j, 1] + M[i, 2] * S[j, 2]
    rotation_polar_factor(K, work_a, work_b, T)
    pose_residual(S, M, dM, T, e, J)
    converged, iterations, _, mapped = _solve(S, grid, ws, r, T, residual_cost(e), mapped,
                                              (max_iterations, tolerance))
    return converged, iterations, relative_residual(S, Ma, T), mapped


@numba.njit(cache=True)
def correct_best(S, seed, hemisphere, grid, seed_map, use_map, max_iterations, tolerance, retry_residual, r, T):
    """correct_one, retried when the result is poor (not converged, or residual above ``retry_residual``).

    Distortion makes the dipole field's near-mirror images (the position reflected across the
    planes through the hemisphere axis) into local minima with small residuals; the retries
    start from the cold fixed-point seed (never the map's) and from those reflections, and the lowest
    residual among the converged solutions wins.
    """
    return correct_best_in(S, seed, hemisphere, grid, seed_map, use_map, max_iterations, tolerance, retry_residual,
                           r, T, workspace(grid[0].shape[3]))


@numba.njit(cache=True)
def correct_best_in(S, seed, hemisphere, grid, seed_map, use_map, max_iterations, tolerance, retry_residual, r, T,
                    ws):
    """:func:`correct_best` with its scratch arrays from ``ws`` (:func:`workspace`)."""
    c, it, res, m = correct_one_in(S, seed, hemisphere, grid, seed_map, use_map, max_iterations, tolerance, r, T, ws)
    if c and res <= retry_residual:
        return c, it, res, m
    best_r, best_T, trial_r, trial_T, candidates = ws.best_r, ws.best_T, ws.trial_r, ws.trial_T, ws.candidates
    copy_pose(r, T, best_r, best_T)
    best = (c, it, res, m)
    for a in range(3):
        candidates[0, a] = np.nan
    axis = 0
    for a in range(3):
        if hemisphere[a] != 0.0:
            axis = a
    for k in range(1, 4):
        for a in range(3):
            candidates[k, a] = r[a]
        other = 0
        for a in range(3):
            if a != axis:
                other += 1
                if (k == 1 and other == 1) or (k == 2 and other == 2) or k == 3:
                    candidates[k, a] = -r[a]
    for k in range(4):
        if k > 0 and not (np.isfinite(candidates[k, 0]) and np.isfinite(candidates[k, 1])
                          and np.isfinite(candidates[k, 2])):
            continue
        # np.bool_(False), not a literal False: the same specialisation of correct_one_in as the first call
        c2, it2, res2, m2 = correct_one_in(S, candidates[k], hemisphere, grid, seed_map, np.bool_(False),
                                           max_iterations, tolerance, trial_r, trial_T, ws)
        it += it2
        if (c2 and not best[0]) or (c2 == best[0] and res2 < best[2]):
            best = (c2, it, res2, m2)
            copy_pose(trial_r, trial_T, best_r, best_T)
    copy_pose(best_r, best_T, r, T)
    return best[0], it, best[2], best[3]


#: frames per block of the parallel kernel: one workspace per block
BLOCK = 256


@numba.njit(cache=True, nogil=True)
def correct_serial(S, seeds, hemisphere, grid, seed_map, config, out):  # pragma: no cover - compiled
    """Correct every frame of S (n, 3, 3) from ``seeds`` (n, 3) with the settings ``config`` (a :data:`Config`)
    into ``out`` (an :data:`Output`), on the calling thread: no thread start-up, for a few frames at a time. The
    loop body of :func:`correct_kernel` too, which runs it on blocks of frames."""
    use_map, max_iterations, tolerance, retry_residual = config
    r, T, q, converged, iterations, residual, mapped = out
    ws = workspace(grid[0].shape[3])
    for n in range(S.shape[0]):
        converged[n], iterations[n], residual[n], mapped[n] = correct_best_in(
            S[n], seeds[n], hemisphere, grid, seed_map, use_map, max_iterations, tolerance, retry_residual, r[n],
            T[n], ws)
        quaternion_of(T[n], q[n])


@numba.njit(parallel=True, cache=True, nogil=True)
def correct_kernel(S, seeds, hemisphere, grid, seed_map, config, out):  # pragma: no cover - compiled
    """:func:`correct_serial` on blocks of :data:`BLOCK` frames on numba's threads, each block with its own
    workspace. The loop body writes the outputs only through that call, into views of the block's rows: numba
    0.68 loses the writes a ``prange`` body makes through a tuple's arrays, not those of a function it calls."""
    r, T, q, converged, iterations, residual, mapped = out
    blocks = (S.shape[0] + BLOCK - 1) // BLOCK
    for block in numba.prange(blocks):
        a = BLOCK * block
        b = min(a + BLOCK, S.shape[0])
        correct_serial(S[a:b], seeds[a:b], hemisphere, grid, seed_map, config,
                       (r[a:b], T[a:b], q[a:b], converged[a:b], iterations[a:b], residual[a:b], mapped[a:b]))


@numba.njit(cache=True, error_model="numpy")
def _precision_at(r, T, grid, sigma):
    """Predicted RMS position (m) and orientation (rad) error of the pose (r (3,), T (3, 3)) whose signal carries
    the table's field (``grid``) and white noise ``sigma``: ivc.pose.precision_kernels.crb_covariance_one with
    M and ∂M/∂r from the table (ivc.table.kernels.pose_model). NaN where r is not finite."""
    if not (np.isfinite(r[0]) and np.isfinite(r[1]) and np.isfinite(r[2])):
        return np.nan, np.nan
    nc = grid[0].shape[3]
    g, dg = np.empty(nc), np.empty((nc, 3))
    wx, wy, wz, dx, dy, dz = np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    M, dM, J, covariance = np.empty((3, 3)), np.empty((3, 3, 3)), np.empty((9, 6)), np.empty((6, 6))
    pose_model(r, grid, M, dM, g, dg, wx, wy, wz, dx, dy, dz)
    crb_covariance_one(T, M, dM, J, covariance)
    p, a = traces(covariance)
    return sigma * p, sigma * a


@numba.njit(parallel=True, cache=True, nogil=True)
def precision_kernel(r, T, grid, sigma, position_out, orientation_out):  # pragma: no cover - compiled
    """:func:`_precision_at` of every pose n: r (n, 3) m, T (n, 3, 3)."""
    for n in numba.prange(r.shape[0]):
        position_out[n], orientation_out[n] = _precision_at(r[n], T[n], grid, sigma)


@numba.njit(cache=True, nogil=True)
def precision_serial(r, T, grid, sigma, position_out, orientation_out):  # pragma: no cover - compiled
    """:func:`precision_kernel` without threads: a live frame's few poses."""
    for n in range(r.shape[0]):
        position_out[n], orientation_out[n] = _precision_at(r[n], T[n], grid, sigma)
