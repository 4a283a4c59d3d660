"""Compiled pose-only correction for the closed-form tracker solver: solve ``φ(r) = v`` per sample.

``φ(r)`` is the closed-form dipole position of ``F = f_D(r) + g(r)`` (g from the table), and
``C(r)`` its orientation (docs/math.md §3). Per sample: from the given start and initial
inverse-Jacobian estimate ``H`` (:class:`ivc.correct.reported.SeedMap` gives both), step
``r ← r + H (v − φ(r))``, halving a step that does not lower the miss, with Broyden's good
update of ``H``; stop when ``|v − φ(r)| ≤ tolerance``. The steps need the position only; ``C``
is computed once, at the solution. The reference
(NumPy, any solver) is :func:`ivc.pose.reported.invert_distortion`.

:func:`compose_kernel` turns the solutions into corrected attitudes (``T = Cᵀ Q``, canonical
quaternions) and flags, for the batch; :func:`stream_kernel` does a live frame's whole
correction, warm starts, inversion, attitude, flags and the sensors' new warm starts, in one
call, with the same steps in the same order, so a frame streamed and the same samples batched
differ only by where each inversion started.

:func:`rivals_kernel` finds the probes the ambiguity test starts its other inversions from
(:meth:`ivc.correct.reported.SeedMap.rivals`): on a uniform grid over the probes' images, the probes
whose cells can map onto the reported position, one per region, the nearest regions first.
"""

from __future__ import annotations

from collections import namedtuple

import numba
import numpy as np

from ivc.correct.flags import HIGH_RESIDUAL, INVALID_INPUT, NOT_CONVERGED, OUTSIDE
from ivc.dipole.kernels import closed_form_one, closed_form_position, dipole_jacobian, field_matrix
from ivc.linalg import quaternion_of
from ivc.table.kernels import grid_value, pose_model

# The helpers below are plain compiled functions, not numba-inlined: inlined three and four times over into
# one function they made its first compile take over a minute. ``error_model="numpy"`` keeps the arithmetic
# of a parallel kernel (inf/NaN, no exception) that they had when inlined.

_OPTS = dict(parallel=True, cache=True, nogil=True)
#: step halvings tried before the inverse Jacobian is recomputed
BACKTRACKS = 12

# The bundles below name their fields once; they reach the kernels as plain tuples (``tuple(Limits(...))``,
# unpacked in this order): numba types a plain tuple in its C dispatcher, a namedtuple in Python (docs/kernels.md)
#: An inversion's limits: ``max_iterations``, the miss ``tolerance`` (m) and the Jacobian ``max_restarts``
Limits = namedtuple("Limits", "max_iterations tolerance max_restarts")
#: An inversion's outputs per sample: ``miss`` (m), ``converged``, ``iterations`` (int64), ``mapped``
InvertOutput = namedtuple("InvertOutput", "miss converged iterations mapped")
#: A stream's warm starts: each sample's sensor row ``slots`` (n,) int64, every sensor's ``offset`` r − v (K, 3)
#: and whether it is ``tracked`` (K,)
Tracks = namedtuple("Tracks", "slots offset tracked")
#: A live frame's outputs: ``r`` (n, 3), ``q`` (n, 4), ``flags`` (n,) uint8, ``miss`` (n,), ``iterations`` (n,)
StreamOutput = namedtuple("StreamOutput", "r q flags miss iterations")
#: The scratch arrays of one inversion (:func:`invert_workspace`), by name: the table's value ``g`` (C,) and the
#: look-up's weights ``wx wy wz`` and derivatives ``dx dy dz`` (4,); the field ``F`` and the closed form's
#: ``wa wb B Fd K`` (3, 3) and ``ev`` (3,); the iteration's ``phi trial e e_t step Hdy sH`` (3,)
InvertWork = namedtuple("InvertWork", "g wx wy wz dx dy dz F wa wb B Fd K ev phi trial e e_t step Hdy sH")
#: recomputations of the inverse Jacobian (central differences) before a search for another solution gives up
#: (the correction's own inversion makes none: where Broyden's estimate stalls, the sample is flagged, not pushed
#: into a fold's neighbourhood)
RESTARTS = 2
#: the step (m) of the central differences of φ
DIFFERENCE_STEP = 1e-5
#: how near (m) an iterate of a search for another solution must come to the solution known already to stop there:
#: the Broyden iteration from that near a regular solution converges to it (a search counts another solution only
#: beyond ``ivc.correct.reported.AMBIGUITY``, 1 mm). Measured on the default scene's check poses: seven in eight of
#: the ambiguity test's starts come back, and a third of the test's iterations were spent after this point
RETURNED = 1e-5


@numba.njit(cache=True, error_model="numpy")
def _field_at(r, grid, g, wx, wy, wz, dx, dy, dz, F):
    """F = f_D(r) + g(r) (3, 3); returns (usable, mapped)."""
    rho2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    if not (rho2 > 1e-12) or not np.isfinite(rho2):
        return False, False
    mapped = grid_value(grid, r, g, wx, wy, wz, dx, dy, dz)
    field_matrix(r[0], r[1], r[2], F)
    tr = 0.0
    for i in range(3):
        for j in range(3):
            F[i, j] += g[3 * i + j]
            tr += F[i, j] * F[i, j]
    return (tr > 0.0) and np.isfinite(tr), mapped


@numba.njit(cache=True, error_model="numpy")
def _inverse3(D, out):
    """out = D⁻¹ of a (3, 3) matrix by its adjugate; False where D is singular to 1e-12 of its scale."""
    c00 = D[1, 1] * D[2, 2] - D[1, 2] * D[2, 1]
    c01 = D[1, 2] * D[2, 0] - D[1, 0] * D[2, 2]
    c02 = D[1, 0] * D[2, 1] - D[1, 1] * D[2, 0]
    det = D[0, 0] * c00 + D[0, 1] * c01 + D[0, 2] * c02
    scale = 0.0
    for a in range(3):
        for b in range(3):
            scale += D[a, b] * D[a, b]
    if not (abs(det) > 1e-12 * scale * np.sqrt(scale)) or not np.isfinite(det):
        return False
    out[0, 0], out[1, 0], out[2, 0] = c00 / det, c01 / det, c02 / det
    out[0, 1] = (D[0, 2] * D[2, 1] - D[0, 1] * D[2, 2]) / det
    out[1, 1] = (D[0, 0] * D[2, 2] - D[0, 2] * D[2, 0]) / det
    out[2, 1] = (D[0, 1] * D[2, 0] - D[0, 0] * D[2, 1]) / det
    out[0, 2] = (D[0, 1] * D[1, 2] - D[0, 2] * D[1, 1]) / det
    out[1, 2] = (D[0, 2] * D[1, 0] - D[0, 0] * D[1, 2]) / det
    out[2, 2] = (D[0, 0] * D[1, 1] - D[0, 1] * D[1, 0]) / det
    return True


@numba.njit(cache=True, error_model="numpy")
def _jacobian_inverse(r, h, grid, H):
    """H = (∂φ/∂r)⁻¹ at r (3,), ∂φ/∂r by central differences of :data:`DIFFERENCE_STEP` (the position of the
    closed form only); False where the map is not defined at a step or ∂φ/∂r is singular."""
    nc = grid[0].shape[3]
    g = np.empty(nc)
    wx, wy, wz, dx, dy, dz = np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    F, B, D = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    ev, phi_p, phi_m, x = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for k in range(3):
        for a in range(3):
            x[a] = r[a]
        x[k] = r[k] + DIFFERENCE_STEP
        usable, _ = _field_at(x, grid, g, wx, wy, wz, dx, dy, dz, F)
        closed_form_position(F, h, phi_p, ev, B)
        x[k] = r[k] - DIFFERENCE_STEP
        usable_m, _ = _field_at(x, grid, g, wx, wy, wz, dx, dy, dz, F)
        closed_form_position(F, h, phi_m, ev, B)
        if not (usable and usable_m):
            return False
        for a in range(3):
            D[a, k] = (phi_p[a] - phi_m[a]) / (2 * DIFFERENCE_STEP)
    return _inverse3(D, H)


@numba.njit(cache=True)
def invert_workspace(channels):
    """The scratch arrays of one inversion (an :data:`InvertWork`) for a table of ``channels`` values per node,
    allocated once and reused over many samples (21 allocations per sample were 4 % of the batch)."""
    return InvertWork(np.empty(channels), np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4),
                      np.empty(4), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
                      np.empty((3, 3)), np.empty((3, 3)), np.empty(3), np.empty(3), np.empty(3), np.empty(3),
                      np.empty(3), np.empty(3), np.empty(3), np.empty(3))


@numba.njit(cache=True, error_model="numpy")
def invert_one(v, start, H, known, h, grid, limits, r, C, out, n, ws):
    """Invert one sample from ``start`` (3,) with the inverse-Jacobian estimate H (3, 3, updated in place) into
    r (3,) and C (3, 3) within ``limits`` (a :data:`Limits`); writes row n of ``out`` (an :data:`InvertOutput`).
    ``known`` (3,) m: a solution found already (NaN: none); an iterate that comes within :data:`RETURNED` of it
    stops there, not converged (a search for another solution has come back to the one it has). ``ws``: an
    :data:`InvertWork` (:func:`invert_workspace`)."""
    max_iterations, tolerance, max_restarts = limits
    miss_out, converged_out, iterations_out, mapped_out = out
    g, wx, wy, wz, dx, dy, dz = ws.g, ws.wx, ws.wy, ws.wz, ws.dx, ws.dy, ws.dz
    F, wa, wb, B, Fd, K, ev = ws.F, ws.wa, ws.wb, ws.B, ws.Fd, ws.K, ws.ev
    phi, trial, e, e_t, step, Hdy, sH = ws.phi, ws.trial, ws.e, ws.e_t, ws.step, ws.Hdy, ws.sH
    for a in range(3):
        r[a] = start[a] if np.isfinite(start[a]) else v[a]
    usable, mapped = _field_at(r, grid, g, wx, wy, wz, dx, dy, dz, F)
    if not usable:
        for a in range(3):
            r[a] = np.nan
            for b in range(3):
                C[a, b] = np.nan
        miss_out[n], converged_out[n], iterations_out[n], mapped_out[n] = np.nan, False, 0, False
        return
    closed_form_position(F, h, phi, ev, B)
    miss = 0.0
    for a in range(3):
        e[a] = v[a] - phi[a]
        miss += e[a] * e[a]
    miss = np.sqrt(miss)
    iterations = 0
    restarts = 0
    converged = miss <= tolerance
    while not converged and iterations < max_iterations:
        for a in range(3):
            step[a] = H[a, 0] * e[0] + H[a, 1] * e[1] + H[a, 2] * e[2]
        iterations += 1
        # backtracking: halve the step until the miss decreases (far from the solution H may be poor)
        accepted = False
        miss_t = miss
        mapped_t = mapped
        for _ in range(BACKTRACKS):
            for a in range(3):
                trial[a] = r[a] + step[a]
            usable, mapped_t = _field_at(trial, grid, g, wx, wy, wz, dx, dy, dz, F)
            if usable:
                closed_form_position(F, h, phi, ev, B)
                miss_t = 0.0
                for a in range(3):
                    e_t[a] = v[a] - phi[a]
                    miss_t += e_t[a] * e_t[a]
                miss_t = np.sqrt(miss_t)
                if miss_t < miss:
                    accepted = True
                    break
            for a in range(3):
                step[a] *= 0.5
        if not accepted:
            # Broyden's estimate has gone stale (near a fold of the map it does): restart from the Jacobian itself
            if restarts >= max_restarts or not _jacobian_inverse(r, h, grid, H):
                break
            restarts += 1
            continue
        # Broyden (good) update of the inverse Jacobian: H += (Δx − H Δy) Δxᵀ H / (Δxᵀ H Δy), Δy = Δφ = e − e_t
        den = 0.0
        for a in range(3):
            Hdy[a] = H[a, 0] * (e[0] - e_t[0]) + H[a, 1] * (e[1] - e_t[1]) + H[a, 2] * (e[2] - e_t[2])
            den += step[a] * Hdy[a]
        if abs(den) > 1e-300:
            for b in range(3):
                sH[b] = step[0] * H[0, b] + step[1] * H[1, b] + step[2] * H[2, b]
            for a in range(3):
                c = (step[a] - Hdy[a]) / den
                for b in range(3):
                    H[a, b] += c * sH[b]
        for a in range(3):
            r[a] = trial[a]
            e[a] = e_t[a]
        mapped = mapped_t
        miss = miss_t
        converged = miss <= tolerance
        if not converged and np.isfinite(known[0]):
            d = 0.0
            for a in range(3):
                d += (r[a] - known[a]) * (r[a] - known[a])
            if d <= RETURNED * RETURNED:
                break
    # the orientation part, once, at the solution: C(r) of the closed form
    _field_at(r, grid, g, wx, wy, wz, dx, dy, dz, F)
    closed_form_one(F, h, phi, C, wa, wb, ev, B, Fd, K)
    miss_out[n], converged_out[n], iterations_out[n], mapped_out[n] = miss, converged, iterations, mapped


#: samples per block of the parallel kernels: one workspace per block
BLOCK = 256


@numba.njit(cache=True, nogil=True)
def invert_serial(v, start, H, known, h, grid, limits, r, C, out):  # pragma: no cover - compiled
    """Invert every sample n from ``start[n]`` with the inverse-Jacobian estimates ``H[n]`` (updated in place) into
    r[n], C[n] and row n of ``out`` (an :data:`InvertOutput`), on the calling thread with one workspace: a few
    samples at a time (a live frame), and the loop body of :func:`invert_kernel`."""
    ws = invert_workspace(grid[0].shape[3])
    for n in range(v.shape[0]):
        invert_one(v[n], start[n], H[n], known[n], h, grid, limits, r[n], C[n], out, np.int64(n), ws)


@numba.njit(**_OPTS)
def invert_kernel(v, start, H, known, h, grid, limits, r, C, out):  # pragma: no cover - compiled
    """:func:`invert_serial` on blocks of :data:`BLOCK` samples on numba's threads, each block with its own
    workspace; ``out`` is written only through that call, into views of the block's rows (numba loses the writes a
    ``prange`` body makes through a tuple's arrays)."""
    miss, converged, iterations, mapped = out
    blocks = (v.shape[0] + BLOCK - 1) // BLOCK
    for block in numba.prange(blocks):
        a = BLOCK * block
        b = min(a + BLOCK, v.shape[0])
        invert_serial(v[a:b], start[a:b], H[a:b], known[a:b], h, grid, limits, r[a:b], C[a:b],
                      (miss[a:b], converged[a:b], iterations[a:b], mapped[a:b]))


_OUTSIDE, _NOT_CONVERGED, _HIGH_RESIDUAL, _INVALID_INPUT = OUTSIDE, NOT_CONVERGED, HIGH_RESIDUAL, INVALID_INPUT


@numba.njit(inline="always")
def _compose_one(C, Q, mapped, converged, miss, max_residual, q):
    """q (4,) = canonical quaternion of Cᵀ Q (NaN where C or Q is not finite); returns the sample's flags."""
    T = np.empty((3, 3))
    finite = True
    for i in range(3):
        for j in range(3):
            T[i, j] = C[0, i] * Q[0, j] + C[1, i] * Q[1, j] + C[2, i] * Q[2, j]
            finite = finite and np.isfinite(T[i, j])
    if finite:
        quaternion_of(T, q)
    else:
        for a in range(4):
            q[a] = np.nan
    flags = 0
    if not mapped:
        flags |= _OUTSIDE
    if not converged:
        flags |= _NOT_CONVERGED
    if not (miss <= max_residual):
        flags |= _HIGH_RESIDUAL
    return flags


@numba.njit(cache=True, nogil=True)
def compose_kernel(C, Q, mapped, converged, miss, max_residual, q, flags):  # pragma: no cover - compiled
    """Attitudes q (n, 4) and flags (n,) uint8 of n inverted samples (C (n, 3, 3), reported Q (n, 3, 3))."""
    for n in range(C.shape[0]):
        flags[n] = _compose_one(C[n], Q[n], mapped[n], converged[n], miss[n], max_residual, q[n])


@numba.njit(cache=True, nogil=True)
def stream_kernel(v, Q, tracks, h, grid, limits, max_residual, out):  # pragma: no cover - compiled
    """One live frame: sample n of sensor ``slots[n]`` starts at ``v[n] + offset[slot]`` where ``tracked[slot]``
    (else at v[n]), is inverted (H = I, as the batch), composed and flagged; a trusted sample sets its sensor's
    offset ``r − v`` and tracked, any other clears tracked. Non-finite input: NaN, INVALID_INPUT. ``tracks``: a
    :data:`Tracks`; ``limits``: a :data:`Limits`; ``out``: a :data:`StreamOutput`."""
    slots, offset, tracked = tracks
    r, q, flags, miss, iterations = out
    start = np.empty(3)
    H = np.empty((3, 3))
    C = np.empty((3, 3))
    m = np.empty(1)
    c = np.empty(1, dtype=np.bool_)
    it = np.empty(1, dtype=np.int64)
    mp = np.empty(1, dtype=np.bool_)
    none = np.full(3, np.nan)
    ws = invert_workspace(grid[0].shape[3])
    for n in range(v.shape[0]):
        slot = slots[n]
        finite = True
        for a in range(3):
            finite = finite and np.isfinite(v[n, a])
            for b in range(3):
                finite = finite and np.isfinite(Q[n, a, b])
        if not finite:
            for a in range(3):
                r[n, a] = np.nan
            for a in range(4):
                q[n, a] = np.nan
            flags[n], miss[n], iterations[n] = _INVALID_INPUT, np.nan, 0
            tracked[slot] = False
            continue
        for a in range(3):
            start[a] = v[n, a] + offset[slot, a] if tracked[slot] else v[n, a]
            for b in range(3):
                H[a, b] = 1.0 if a == b else 0.0
        invert_one(v[n], start, H, none, h, grid, limits, r[n], C, (m, c, it, mp), np.int64(0), ws)
        flags[n] = _compose_one(C, Q[n], mp[0], c[0], m[0], max_residual, q[n])
        miss[n], iterations[n] = m[0], it[0]
        tracked[slot] = flags[n] == 0
        if flags[n] == 0:
            for a in range(3):
                offset[slot, a] = r[n, a] - v[n, a]


@numba.njit(cache=True, error_model="numpy")
def closed_form_jacobian(F, h, J):
    """J (6, 9) = ∂(φ, ω)/∂F of the closed form at the field matrix F (3, 3): rows the position (m) and the left
    rotation increment (rad), columns F's entries row by row; analytic, the equations of the NumPy reference
    (``ivc.pose.tracker_solver._closed_form_jacobian``): the range from ``tr FᵀF``, the principal eigenvector's
    first-order change ``(λ I − B + v vᵀ)⁻¹ (I − v vᵀ) δB v`` (B = FᵀF, λ = vᵀ B v: the added v vᵀ makes the
    matrix invertible and keeps the change orthogonal to v), and the polar factor's from
    ``(tr P I − P) w = vee(Cᵀ δK − δKᵀ C)``, K = f_D(φ) Fᵀ, P = sym(Cᵀ K), ω = C w. False where not finite."""
    r, v, ev, u, dv, dr, rhs, w = (np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3),
                                    np.empty(3), np.empty(3))
    C, wa, wb, B, Fd, K = (np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
                           np.empty((3, 3)))
    closed_form_one(F, h, r, C, wa, wb, ev, B, Fd, K)  # leaves B = FᵀF, Fd = f_D(φ), K = Fd Fᵀ
    rng = np.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    if not (rng > 0.0 and np.isfinite(rng)):
        return False
    for a in range(3):
        v[a] = r[a] / rng
    tr = B[0, 0] + B[1, 1] + B[2, 2]
    lam = 0.0
    for a in range(3):
        for b in range(3):
            lam += v[a] * B[a, b] * v[b]
    for a in range(3):  # wa = λ I − B + v vᵀ
        for b in range(3):
            wa[a, b] = -B[a, b] + v[a] * v[b]
        wa[a, a] += lam
    Minv, Ainv, X, dK = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    trP = 0.0
    for a in range(3):  # wb = sym(Cᵀ K)
        for b in range(3):
            wb[a, b] = 0.5 * (C[0, a] * K[0, b] + C[1, a] * K[1, b] + C[2, a] * K[2, b]
                              + C[0, b] * K[0, a] + C[1, b] * K[1, a] + C[2, b] * K[2, a])
        trP += wb[a, a]
    for a in range(3):  # wb = tr P I − P
        for b in range(3):
            wb[a, b] = -wb[a, b]
        wb[a, a] += trP
    if not (_inverse3(wa, Minv) and _inverse3(wb, Ainv)):
        return False
    dfd = np.empty((3, 3, 3))
    dipole_jacobian(r, dfd)
    for d in range(9):
        i, j = d // 3, d % 3
        # δB v, with δB = δFᵀ F + Fᵀ δF and δF = e_i e_jᵀ
        Fv = F[i, 0] * v[0] + F[i, 1] * v[1] + F[i, 2] * v[2]
        for a in range(3):
            u[a] = F[i, a] * v[j]
        u[j] += Fv
        vu = v[0] * u[0] + v[1] * u[1] + v[2] * u[2]
        for a in range(3):
            u[a] -= vu * v[a]
        d_rng = -rng / (6.0 * tr) * 2.0 * F[i, j]
        for a in range(3):
            dv[a] = Minv[a, 0] * u[0] + Minv[a, 1] * u[1] + Minv[a, 2] * u[2]
            dr[a] = d_rng * v[a] + rng * dv[a]
        # δK = (∂f_D/∂r δr) Fᵀ + f_D δFᵀ
        for a in range(3):
            for c in range(3):
                X[a, c] = dfd[a, c, 0] * dr[0] + dfd[a, c, 1] * dr[1] + dfd[a, c, 2] * dr[2]
        for a in range(3):
            for b in range(3):
                dK[a, b] = X[a, 0] * F[b, 0] + X[a, 1] * F[b, 1] + X[a, 2] * F[b, 2]
            dK[a, i] += Fd[a, j]
        for a in range(3):  # X = Cᵀ δK
            for b in range(3):
                X[a, b] = C[0, a] * dK[0, b] + C[1, a] * dK[1, b] + C[2, a] * dK[2, b]
        rhs[0], rhs[1], rhs[2] = X[2, 1] - X[1, 2], X[0, 2] - X[2, 0], X[1, 0] - X[0, 1]
        for a in range(3):
            w[a] = Ainv[a, 0] * rhs[0] + Ainv[a, 1] * rhs[1] + Ainv[a, 2] * rhs[2]
        for a in range(3):
            J[a, d] = dr[a]
            J[3 + a, d] = C[a, 0] * w[0] + C[a, 1] * w[1] + C[a, 2] * w[2]
    for a in range(6):
        for d in range(9):
            if not np.isfinite(J[a, d]):
                return False
    return True


@numba.njit(cache=True, error_model="numpy")
def precision_one(r, h, grid, sigma):
    """Predicted RMS position (m) and orientation (rad) error of the pose corrected from a reported pose to the
    position ``r`` (3,), for white signal noise ``sigma``: the closed form's scatter at the field the sensor is
    in, ``J = ∂(φ, ω)/∂F`` at ``F = f_D(r) + g(r)`` (:func:`closed_form_jacobian`), carried through the inverse
    map, ``δr = (∂φ/∂r)⁻¹ J_φ δF`` and ``δt ∝ (J_ω − (∂ω/∂r) (∂φ/∂r)⁻¹ J_φ) δF``
    (:func:`ivc.pose.precision.reported_pose_covariance`; the orientation's trace does not depend on the frame it
    is written in), with ``∂(φ, ω)/∂r = J ∂F/∂r`` from the table's gradient. NaN where r is not finite; inf where
    the map is singular there (the reported pose does not fix the true one)."""
    for a in range(3):
        if not np.isfinite(r[a]):
            return np.nan, np.nan
    rho2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    if not rho2 > 1e-12:
        return np.inf, np.inf
    nc = grid[0].shape[3]
    F, dF, g, dg = np.empty((3, 3)), np.empty((3, 3, 3)), np.empty(nc), np.empty((nc, 3))
    wx, wy, wz, dx, dy, dz = np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    pose_model(r, grid, F, dF, g, dg, wx, wy, wz, dx, dy, dz)
    J = np.empty((6, 9))
    if not closed_form_jacobian(F, h, J):
        return np.inf, np.inf
    D = np.empty((3, 3))  # ∂φ/∂r
    W = np.empty((3, 3))  # ∂ω/∂r
    for a in range(3):
        for k in range(3):
            sd, sw = 0.0, 0.0
            for d in range(9):
                sd += J[a, d] * dF[d // 3, d % 3, k]
                sw += J[3 + a, d] * dF[d // 3, d % 3, k]
            D[a, k], W[a, k] = sd, sw
    H = np.empty((3, 3))
    if not _inverse3(D, H):
        return np.inf, np.inf
    p2, o2 = 0.0, 0.0
    P = np.empty(3)
    for d in range(9):
        for a in range(3):  # column d of (∂φ/∂r)⁻¹ J_φ
            P[a] = H[a, 0] * J[0, d] + H[a, 1] * J[1, d] + H[a, 2] * J[2, d]
            p2 += P[a] * P[a]
        for a in range(3):
            o = J[3 + a, d] - (W[a, 0] * P[0] + W[a, 1] * P[1] + W[a, 2] * P[2])
            o2 += o * o
    return sigma * np.sqrt(p2), sigma * np.sqrt(o2)


@numba.njit(parallel=True, cache=True, nogil=True)
def precision_kernel(r, h, grid, sigma, position_out, orientation_out):  # pragma: no cover - compiled
    """:func:`precision_one` for every sample n: corrected positions r (n, 3)."""
    for n in numba.prange(r.shape[0]):
        position_out[n], orientation_out[n] = precision_one(r[n], h, grid, sigma)


@numba.njit(cache=True, nogil=True)
def precision_serial(r, h, grid, sigma, position_out, orientation_out):  # pragma: no cover - compiled
    """:func:`precision_kernel` without threads: a live frame's few samples."""
    for n in range(r.shape[0]):
        position_out[n], orientation_out[n] = precision_one(r[n], h, grid, sigma)


# --- the rival search (SeedMap.rivals): probes elsewhere whose cells can map onto the reported position -----------

#: A seed map's probes for the rival search: ``points`` (M, 3) m, their ``images`` φ(points) (M, 3) m, each cell's
#: ``cell_reach`` (M,) m (every point of the probe's cell maps within it of the probe's image) and the ``region``
#: (M,) int64 key of the block of probes each lies in
RivalProbes = namedtuple("RivalProbes", "points images cell_reach region")
#: A uniform grid over image space (:class:`ivc.correct.reported.SeedMap` builds it): cell (i, j, k) spans
#: ``origin + size * [i, i+1)``… (m), ``shape`` (3,) int64 cells; the probes registered in cell c (each in every
#: cell its image's ball of cell_reach + 2 pad touches) are ``items[start[c]:start[c+1]]``, c = (i shape₁ + j) shape₂
#: + k; ``wide`` (K,) int64 the probes too wide to register, which every query tests; ``pad`` (m) widens the balls
#: and the query boxes so that the rounding of a cell's bounds never loses a probe
ImageGrid = namedtuple("ImageGrid", "origin size shape start items wide pad")
#: The rival probes of each sample n: ``probe[n, :count[n]]`` (n, limit) int64, nearest in image first
RivalOutput = namedtuple("RivalOutput", "probe count")
#: samples per task of the threaded rival search (each task keeps its own candidate buffer)
RIVAL_CHUNK = 64


@numba.njit(cache=True, error_model="numpy", inline="always")
def _rival_distance(p, v, r, tolerance, points, images, cell_reach, apart):
    """|φ(p) − v| (m) of probe p if its cell can map within ``tolerance`` of v (``|φ(p) − v| − cell_reach ≤
    tolerance``) and it lies farther than ``apart`` from r (m); else −1. The arithmetic of the NumPy reference:
    (d₀² + d₁²) + d₂², as ``np.linalg.norm`` sums a row."""
    d0, d1, d2 = images[p, 0] - v[0], images[p, 1] - v[1], images[p, 2] - v[2]
    d = np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)
    if not (d - cell_reach[p] <= tolerance):
        return -1.0
    a0, a1, a2 = points[p, 0] - r[0], points[p, 1] - r[1], points[p, 2] - r[2]
    if not (np.sqrt((a0 * a0 + a1 * a1) + a2 * a2) > apart):
        return -1.0
    return d


@numba.njit(cache=True, error_model="numpy")
def _nearest_regions(candidate, distance, m, region, found):
    """The nearest region not taken yet, ``len(found)`` times, into ``found``: the candidate of least (distance,
    region key, probe index) among those of the regions not taken (so each region's pick is its nearest probe,
    and the regions come nearest first); returns how many regions there were, at most ``len(found)``."""
    for rank in range(found.shape[0]):
        best = -1
        for s in range(m):
            p = candidate[s]
            fresh = True
            for u in range(rank):
                fresh = fresh and region[p] != region[found[u]]
            if not fresh:
                continue
            if best < 0 or distance[s] < distance[best] or (distance[s] == distance[best] and (
                    region[p] < region[candidate[best]]
                    or (region[p] == region[candidate[best]] and p < candidate[best]))):
                best = s
        if best < 0:
            return rank
        found[rank] = candidate[best]
    return found.shape[0]


@numba.njit(cache=True, error_model="numpy")
def rivals_range(v, r, tolerance, probes, grid, apart, out, first, last):
    """The rival probes of samples ``first``…``last − 1``: reported positions v (n, 3) m solved at r (n, 3) m,
    with their ``tolerance`` (n,) m; per sample, among the probes :func:`_rival_distance` takes (farther than ``apart``
    (m) from r), the nearest in image of each region, then the ``limit`` nearest regions (:func:`_nearest_regions`;
    ``limit``: the width of ``out.probe``). ``probes``, ``grid``, ``out``: a :data:`RivalProbes`, :data:`ImageGrid`
    and :data:`RivalOutput`. No rivals where v or the tolerance is not finite."""
    origin, size, shape, start, items, wide, pad = grid
    points, images, cell_reach, region = probes
    found, count = out
    candidate, distance = np.empty(16, dtype=np.int64), np.empty(16)
    lo, hi, width = np.empty(3, dtype=np.int64), np.empty(3, dtype=np.int64), np.empty(3, dtype=np.int64)
    for n in range(first, last):
        t = tolerance[n]
        count[n] = 0
        if not (np.isfinite(t) and t >= 0.0 and np.isfinite(v[n, 0]) and np.isfinite(v[n, 1])
                and np.isfinite(v[n, 2])):
            continue
        cells = 1
        for a in range(3):  # the query box's cells in the grid (clipped as floats: no integer overflow)
            lo[a] = np.int64(max(np.floor((v[n, a] - t - pad - origin[a]) / size), 0.0))
            hi[a] = np.int64(min(np.floor((v[n, a] + t + pad - origin[a]) / size), shape[a] - 1.0))
            width[a] = max(hi[a] - lo[a] + 1, 0)
            cells *= width[a]
        m = 0
        here, solved = v[n], r[n]
        for c in range(cells + 1):  # the query box's cells, then the wide probes
            if c < cells:
                i, j, k = lo[0] + c // (width[1] * width[2]), lo[1] + (c // width[2]) % width[1], lo[2] + c % width[2]
                cell = (i * shape[1] + j) * shape[2] + k
                listed, begin, end = items, start[cell], start[cell + 1]
            else:
                listed, begin, end = wide, 0, wide.shape[0]
            for s in range(begin, end):
                p = listed[s]
                d = _rival_distance(p, here, solved, t, points, images, cell_reach, apart)
                if d < 0.0:
                    continue
                if cells > 1:  # a probe registered in several cells of the query box: taken once
                    again = False
                    for u in range(m):
                        again = again or candidate[u] == p
                    if again:
                        continue
                if m == candidate.shape[0]:
                    candidate = np.concatenate((candidate, np.empty(m, dtype=np.int64)))
                    distance = np.concatenate((distance, np.empty(m)))
                candidate[m], distance[m] = p, d
                m += 1
        count[n] = _nearest_regions(candidate, distance, m, region, found[n])


@numba.njit(parallel=True, cache=True, nogil=True)
def rivals_kernel(v, r, tolerance, probes, grid, apart, out):  # pragma: no cover - compiled
    """:func:`rivals_range` over every sample, :data:`RIVAL_CHUNK` samples per thread task."""
    n = v.shape[0]
    for c in numba.prange((n + RIVAL_CHUNK - 1) // RIVAL_CHUNK):
        rivals_range(v, r, tolerance, probes, grid, apart, out, c * RIVAL_CHUNK, min(n, (c + 1) * RIVAL_CHUNK))


@numba.njit(cache=True, nogil=True)
def rivals_serial(v, r, tolerance, probes, grid, apart, out):  # pragma: no cover - compiled
    """:func:`rivals_kernel` without threads: a live frame's few samples."""
    rivals_range(v, r, tolerance, probes, grid, apart, out, 0, v.shape[0])
