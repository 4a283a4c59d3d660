"""Compiled DQ-EKF / MMDQ step (docs/math.md §12.2-§12.5), one sensor at a time.

One kernel serves every DQ filter: a single DQ-EKF (CV or CA) is an IMM with one model, where
mixing is the identity and the mode probability stays 1. States are embedded in 6-D
``[ω, α]`` (rad/s, rad/s²); a CV model uses the first 3 and carries α = 0 (the "zero-padding"
mixing of docs/math.md §12.4). The measurement is ``Δq(k) = q(k) ⊗ q(k−1)*`` (scalar part ≥ 0).

Per-sensor state arrays (leading axis = sensor):
  x (M, 6), P (M, 6, 6), probs (3, M) = [μ(k), μ(k−1), normalised likelihoods L(k)],
  tpm (2, M, M) = [Π, γ (Dirichlet counts)], q_prev (4,), status (2,) = [initialised, have_prev],
  est (6,) = the combined [ω̄, ᾱ], clock (4,) = [age: s since q_prev was measured, s since the
  last valid sample, restarts at gaps, repeated samples dropped].

Time steps are the actual ones: each step takes the time since the previous frame, dt (s). An
invalid sample is bridged (q_prev is kept and the next Δq spans the whole time); a gap without a
valid sample longer than cfg's max gap restarts the filter from the next Δq; a sample that
repeats q_prev exactly is not a measurement (a stale frame): it is dropped and the prediction made
from q_prev, ``age`` seconds old.
Configuration: kinds (M,) 0 = CV, 1 = CA; qvar (M, 3) process-noise variances (rad/s²)² for CV
or (rad/s³)² for CA; R (4,) measurement variances; cfg = [τ, ε_mix, ε_μ, adaptive TPM,
mode-weight form (0 c̄_j, 1 μ_j(k−1)), H of CA (0 standard [J, 0], 1 thesis [J, τJ], 2 midpoint
[J, −τJ/2]), P0 of ω, P0 of α, max gap (s)]; mu0 (M,), Pi0 (M, M). τ is the nominal frame period.
"""

from __future__ import annotations

from collections import namedtuple

import numba
import numpy as np

from ivc.linalg import cholesky, cholesky_logdet, factored_update
from ivc.predict.quat import delta_q_jacobian, predict_orientation, qmul_conj, rate_of

LOG_2PI = np.log(2.0 * np.pi)
TPM_FLOOR = 1e-50  # docs/math.md §12.5; Himberg 2010, eq. 47

CFG_TAU, CFG_EPS_MIX, CFG_EPS_MU, CFG_ADAPTIVE, CFG_WEIGHTS, CFG_H, CFG_P0W, CFG_P0A, CFG_MAX_GAP = range(9)
CLOCK_AGE, CLOCK_MISSING, CLOCK_RESTARTS, CLOCK_REPEATS = range(4)

# The bundles below name their fields once; they reach the kernels as plain tuples (``tuple(State(...))``),
# unpacked in this order: numba types a plain tuple argument in its C dispatcher, a namedtuple in Python
# (about 2 µs more per call, a third of the live step's time), docs/kernels.md.

#: A filter's state (the arrays above, with a leading sensor axis)
State = namedtuple("State", "x P probs tpm q_prev status est clock")
#: Its configuration: kinds (M,), qvar (M, 3), R (4,), cfg (9,)
Model = namedtuple("Model", "kinds qvar R cfg")
#: A batch's outputs (:func:`run`): est (S, F, 6), ok (S, F), mu (S, F, M), age (S, F)
Output = namedtuple("Output", "est ok mu age")


@numba.njit(cache=True)
def make_work(n_models):
    """Scratch arrays for one sensor's step (allocated once per sensor in batch runs).

    (x0, P0, mix, ell, cbar, z) for the mixing, then the EKF's vectors (4, 6) and matrices (7, 6, 6):
    the EKF takes its scratch as two arrays because each array argument of a compiled call is
    passed as 7-11 machine words: passing its 11 scratch arrays one by one made the MMDQ2 step
    about 15% slower.
    """
    return (np.empty((n_models, 6)), np.empty((n_models, 6, 6)), np.empty((n_models, n_models)),
            np.empty(n_models), np.empty(n_models), np.empty(4), np.empty((4, 6)), np.empty((7, 6, 6)))


@numba.njit(cache=True)
def reset(x, P, probs, tpm, q_prev, status, est, clock, mu0, Pi0):
    """Forget everything (start of a stream or after a restart). The arrays are copied entry by entry: an array
    assigned to a slice makes numba compile the message of its shape check (seconds of string formatting on a cold
    cache, docs/kernels.md)."""
    x[:] = 0.0
    P[:] = 0.0
    for m in range(mu0.shape[0]):
        probs[0, m] = mu0[m]
        probs[1, m] = mu0[m]
    probs[2, :] = 1.0
    for i in range(Pi0.shape[0]):
        for j in range(Pi0.shape[1]):
            tpm[0, i, j] = Pi0[i, j]
            tpm[1, i, j] = Pi0[i, j]
    q_prev[:] = 0.0
    status[:] = 0
    est[:] = 0.0
    clock[:] = 0.0


@numba.njit(cache=True)
def _ekf(n, hcols, qv, z, R, cfg, tau, x0, P0, x, P, scratch):
    """One EKF predict+update over tau s from the mixed (x0, P0) into (x, P); returns the log-likelihood of z.

    n = 3 (CV) or 6 (CA) states; H = [J, cJ] has hcols = 6 non-zero columns, or 3 when c = 0
    (CV, and CA with the standard H); the products skip H's zero columns (exact zeros: the same
    result to the bit). Compiled once, with the sizes as run-time numbers: inlined three times with
    constant sizes (unrolled loops), it took 19 of the DQ filters' 47 CPU seconds of compilation for
    about 1 % of the live step (4.6 µs of MMDQ2's update and prediction, loaded machine).
    The covariance update is P⁻ − K S Kᵀ through the Cholesky factor of S (:func:`factored_update`).
    ``scratch``: (vecs (4, 6), mats (7, 6, 6)), the end of :func:`make_work`'s tuple.
    """
    vecs, mats = scratch
    xp, h, nu, w = vecs[0], vecs[1], vecs[2], vecs[3]
    Pp, J, H, PHt, S, L, U = mats[0], mats[1], mats[2], mats[3], mats[4], mats[5], mats[6]
    ca = n == 6
    for a in range(n):
        xp[a] = x0[a]
        for b in range(n):
            Pp[a, b] = P0[a, b]
    if ca:
        for i in range(3):
            xp[i] += tau * x0[3 + i]
        # A P Aᵀ with A = [[I, τI], [0, I]], then + W Q Wᵀ with W = [τ²/2 I; τ I]
        for a in range(3):
            for b in range(6):
                Pp[a, b] += tau * P0[a + 3, b]
        for a in range(6):
            for b in range(3):
                Pp[a, b] += tau * Pp[a, b + 3]
        for i in range(3):
            Pp[i, i] += 0.25 * tau**4 * qv[i]
            Pp[i, i + 3] += 0.5 * tau**3 * qv[i]
            Pp[i + 3, i] += 0.5 * tau**3 * qv[i]
            Pp[i + 3, i + 3] += tau * tau * qv[i]
    else:
        for i in range(3):
            Pp[i, i] += tau * tau * qv[i]
    shift = 0.0
    if ca and cfg[CFG_H] == 2.0:
        shift = -0.5 * tau
    wx = xp[0] + shift * (xp[3] if ca else 0.0)
    wy = xp[1] + shift * (xp[4] if ca else 0.0)
    wz = xp[2] + shift * (xp[5] if ca else 0.0)
    delta_q_jacobian(wx, wy, wz, tau, J, h)
    alpha_col = 0.0
    if ca:
        alpha_col = tau if cfg[CFG_H] == 1.0 else shift
    for r in range(4):
        for c in range(3):
            H[r, c] = J[r, c]
            if hcols == 6:
                H[r, c + 3] = alpha_col * J[r, c]
    for a in range(n):
        for r in range(4):
            acc = 0.0
            for b in range(hcols):
                acc += Pp[a, b] * H[r, b]
            PHt[a, r] = acc
    for r in range(4):  # the lower triangle: all the Cholesky factorisation reads
        for c in range(r + 1):
            acc = 0.0
            for a in range(hcols):
                acc += H[r, a] * PHt[a, c]
            S[r, c] = acc
        S[r, r] += R[r]
        nu[r] = z[r] - h[r]
    if not cholesky(S, 4, L):
        return -np.inf
    maha = factored_update(L, PHt, nu, xp, Pp, n, 4, U, w, x, P)
    if maha < 0.0:
        return -np.inf
    if not ca:
        for a in range(3, 6):
            x[a] = 0.0
            for b in range(6):
                P[a, b] = 0.0
                P[b, a] = 0.0
    return -0.5 * maha - 0.5 * (cholesky_logdet(L, 4) + 4.0 * LOG_2PI)


@numba.njit(cache=True, _nrt=False)
def _ekf_model(kind, qv, z, R, cfg, tau, x0, P0, x, P, vecs, mats):
    """:func:`_ekf` for a CV (kind 0) or CA (kind 1) model (np.int64 sizes: one specialisation, not one per literal)."""
    if kind == 0:
        return _ekf(np.int64(3), np.int64(3), qv, z, R, cfg, tau, x0, P0, x, P, (vecs, mats))
    if cfg[CFG_H] == 0.0:
        return _ekf(np.int64(6), np.int64(3), qv, z, R, cfg, tau, x0, P0, x, P, (vecs, mats))
    return _ekf(np.int64(6), np.int64(6), qv, z, R, cfg, tau, x0, P0, x, P, (vecs, mats))


@numba.njit(cache=True, inline="always")
def _update_tpm(probs, tpm, M):
    """Quasi-Bayesian TPM update (Jilkov & Li; docs/math.md §12.5), from the previous frame's L and μ."""
    Pi, gamma = tpm[0], tpm[1]
    mu_b, L = probs[1], probs[2]
    denom = 0.0
    for i in range(M):
        for m in range(M):
            denom += mu_b[i] * Pi[i, m] * L[m]
    if not denom > 0.0:
        return
    for i in range(M):
        row = 0.0
        for m in range(M):
            row += Pi[i, m] * L[m]
        total = 0.0
        for j in range(M):
            total += gamma[i, j] * (1.0 + mu_b[i] * (L[j] - row) / denom)
        for j in range(M):
            g = 1.0 + mu_b[i] * (L[j] - row) / denom
            gamma[i, j] += gamma[i, j] * g / total
        gsum = 0.0
        for j in range(M):
            gsum += gamma[i, j]
        psum = 0.0
        for j in range(M):
            Pi[i, j] = max(TPM_FLOOR, gamma[i, j] / gsum)
            psum += Pi[i, j]
        for j in range(M):
            Pi[i, j] /= psum


@numba.njit(cache=True)
def step(q, ok, dt, states, s, model, work):
    """Feed one measured orientation q (4,) of sensor s, dt s after the previous frame; ok = False skips it.
    ``states``: every sensor's :data:`State` (sensor s's is row s of each); ``model``: the :data:`Model`;
    ``work``: :func:`make_work`'s.

    Returns True when the filter has an estimate (est holds ω̄, ᾱ; the prediction starts from q_prev,
    clock[CLOCK_AGE] s old).
    """
    xs, Ps, probss, tpms, q_prevs, statuss, ests, clocks = states
    x, P, probs, tpm, q_prev, status = xs[s], Ps[s], probss[s], tpms[s], q_prevs[s], statuss[s]
    est, clock = ests[s], clocks[s]
    kinds, qvar, R, cfg = model
    M = kinds.shape[0]
    x0, P0, mix, ell, cbar, z, vecs, mats = work
    clock[CLOCK_AGE] += dt
    clock[CLOCK_MISSING] += dt
    if not ok:  # bridged: q_prev is kept, the next Δq spans the gap
        return status[0] == 1
    if status[1] == 1 and clock[CLOCK_MISSING] > cfg[CFG_MAX_GAP]:  # too long to bridge: start again
        status[0] = 0
        status[1] = 0
        clock[CLOCK_RESTARTS] += 1.0
    clock[CLOCK_MISSING] = 0.0
    if status[1] == 0:
        for i in range(4):
            q_prev[i] = q[i]
        status[1] = 1
        clock[CLOCK_AGE] = 0.0
        return status[0] == 1
    if q[0] == q_prev[0] and q[1] == q_prev[1] and q[2] == q_prev[2] and q[3] == q_prev[3]:
        clock[CLOCK_REPEATS] += 1.0  # a stale frame, not a measurement of no motion
        return status[0] == 1
    tau = clock[CLOCK_AGE]
    clock[CLOCK_AGE] = 0.0
    qmul_conj(q, q_prev, z)
    if z[0] < 0.0:
        for i in range(4):
            z[i] = -z[i]
    for i in range(4):
        q_prev[i] = q[i]
    if status[0] == 0:
        rate_of(z, tau, est)
        for j in range(M):
            P[j, :, :] = 0.0  # a restart after divergence must not keep the old off-diagonals
            for a in range(3):
                x[j, a] = est[a]
                x[j, a + 3] = 0.0
                P[j, a, a] = cfg[CFG_P0W]
                P[j, a + 3, a + 3] = cfg[CFG_P0A] if kinds[j] == 1 else 0.0
        for a in range(3, 6):
            est[a] = 0.0
        status[0] = 1
        return True
    mu = probs[0]
    if cfg[CFG_ADAPTIVE] != 0.0 and M > 1:
        _update_tpm(probs, tpm, M)
    Pi = tpm[0]
    if M == 1:  # a single filter: no mixing, the mode probability stays 1
        if _ekf_model(kinds[0], qvar[0], z, R, cfg, tau, x[0], P[0], x[0], P[0], vecs, mats) == -np.inf:
            status[0] = 0  # lost positive definiteness: restart from the next Δq, as the IMM does
            return False
        for a in range(6):
            est[a] = x[0, a]
        return True
    # mixing (docs/math.md §12.4)
    for j in range(M):
        c = 0.0
        for i in range(M):
            c += Pi[i, j] * mu[i]
        cbar[j] = c
        total = 0.0
        for i in range(M):
            mix[i, j] = max(Pi[i, j] * mu[i] / c, cfg[CFG_EPS_MIX])
            total += mix[i, j]
        for i in range(M):
            mix[i, j] /= total
    for j in range(M):
        n = 6 if kinds[j] == 1 else 3  # a CV model reads only its ω block
        for a in range(n):
            acc = 0.0
            for i in range(M):
                acc += mix[i, j] * x[i, a]
            x0[j, a] = acc
        for a in range(n):
            for b in range(a + 1):  # P0 is symmetric to the bit: each P is, and the products commute
                acc = 0.0
                for i in range(M):
                    acc += mix[i, j] * (P[i, a, b] + (x[i, a] - x0[j, a]) * (x[i, b] - x0[j, b]))
                P0[j, a, b] = acc
                P0[j, b, a] = acc
    # filters, log-likelihoods, mode probabilities
    best = -np.inf
    for j in range(M):
        ell[j] = _ekf_model(kinds[j], qvar[j], z, R, cfg, tau, x0[j], P0[j], x[j], P[j], vecs, mats)
        best = max(best, ell[j])
    if best == -np.inf:  # every filter lost positive definiteness: restart from this Δq
        status[0] = 0
        return False
    total = 0.0
    for j in range(M):
        prior = cbar[j] if cfg[CFG_WEIGHTS] == 0.0 else mu[j]
        probs[2, j] = np.exp(ell[j] - best)
        probs[1, j] = mu[j]
        ell[j] = prior * probs[2, j]
        total += ell[j]
    total2 = 0.0
    for j in range(M):
        mu[j] = max(ell[j] / total, cfg[CFG_EPS_MU])
        total2 += mu[j]
    for j in range(M):
        mu[j] /= total2
    for a in range(6):
        acc = 0.0
        for j in range(M):
            acc += mu[j] * x[j, a]
        est[a] = acc
    return True


@numba.njit(cache=True, _nrt=False)
def filter_sensor(s, qs, ok, dt, states, model, work, q, out):
    """Every frame of sensor s (see :func:`run`), with its own state (row s of ``states``, a :data:`State`) and
    scratch, into its rows of ``out`` (an :data:`Output`).

    Compiled without reference counting (nothing here allocates or keeps an array): the
    counting of the views taken in each step otherwise costs more than the filter's arithmetic.
    """
    kinds, qvar, R, cfg = model
    xs, Ps, probss, tpms, q_prevs, statuss, ests, clocks = states
    M = kinds.shape[0]
    est, clock, probs = ests[s], clocks[s], probss[s]
    out_est, out_ok, out_mu, out_age = out
    for k in range(qs.shape[0]):
        for i in range(4):
            q[i] = qs[k, s, i]
        good = step(q, ok[k, s], dt[k], states, s, model, work)
        out_ok[s, k] = good and ok[k, s]
        out_age[s, k] = clock[CLOCK_AGE]
        for a in range(6):
            out_est[s, k, a] = est[a]
        for j in range(M):
            out_mu[s, k, j] = probs[0, j]


@numba.njit(cache=True)
def run(qs, ok, dt, states, model, out):
    """Filter frames (F, S, 4), dt (F,) s apart, for S sensors (``states``: a :data:`State` with a leading sensor
    axis), one sensor after the other; writes ω̄, ᾱ per frame to out.est (S, F, 6) and the age of the sample the
    prediction starts from to out.age (S, F) (out.ok (S, F), out.mu (S, F, M); ``out`` an :data:`Output`).

    Serial: the batch already runs at about a million sensor-frames a second, far beyond any recording, and
    a parallel loop costs several seconds more to compile on first use (docs/kernels.md). Sensor s's state
    is its row of each state array, updated in place.
    """
    kinds, qvar, R, cfg = model
    for s in range(qs.shape[1]):
        filter_sensor(s, qs, ok, dt, states, model, make_work(kinds.shape[0]), np.empty(4), out)


@numba.njit(cache=True)
def update_frame(qs, ok, dt, states, model, ready):
    """One live frame, dt s after the previous one, for every sensor (qs (S, 4), ok (S,); ``states`` a :data:`State`
    with a leading sensor axis); ready[s] says whether sensor s has an estimate.

    The scratch arrays are made here: cheaper than passing a tuple of them in from Python.
    Returns −1, or the first sensor whose valid sample is not a unit quaternion (then nothing is updated).
    NaN samples are skipped; the others are normalised in place.
    """
    for s in range(qs.shape[0]):
        n2 = qs[s, 0] ** 2 + qs[s, 1] ** 2 + qs[s, 2] ** 2 + qs[s, 3] ** 2
        if ok[s] and abs(np.sqrt(n2) - 1.0) > 1e-3:
            return s
    kinds, qvar, R, cfg = model
    work = make_work(kinds.shape[0])
    for s in range(qs.shape[0]):
        good = ok[s] and np.isfinite(qs[s, 0] + qs[s, 1] + qs[s, 2] + qs[s, 3])
        if good:
            n = np.sqrt(qs[s, 0] ** 2 + qs[s, 1] ** 2 + qs[s, 2] ** 2 + qs[s, 3] ** 2)
            for i in range(4):
                qs[s, i] /= n
        ready[s] = step(qs[s], good, dt, states, s, model, work) and good
    return -1


@numba.njit(cache=True)
def predict_frame(last, est, clock, ready, delta, tau, out):
    """Orientations (S, 4) ``delta`` s after the last frame, NaN where a sensor has no estimate (from the last
    measured sample, ``age`` s older when the last frames repeated it)."""
    tmp = np.empty(4)
    dq = np.empty(4)
    for s in range(last.shape[0]):
        if not ready[s]:
            out[s, :] = np.nan
            continue
        predict_orientation(last[s], est[s, 0], est[s, 1], est[s, 2], est[s, 3], est[s, 4], est[s, 5],
                            delta + clock[s, CLOCK_AGE], tau, out[s], tmp, dq)
