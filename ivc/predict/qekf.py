"""Himberg 2010's Q-EKF: 7 states [q, ω], the measured quaternion as the measurement (docs/math.md §12.1).

Process: ω⁻ = ω̂ (constant velocity, angular-acceleration noise w), q⁻ = Δq(ω̂, τ) ⊗ q̂, with
A = [[L(Δq), R(q̂) J], [0, I]], W = [R(q̂) J τ; τ I] (eq. 18-25); measurement z = q + v, H = [I4 0].
Deviations from the thesis (docs/math.md §12.1): q̂ is renormalised after each update, and the
measurement's sign is aligned with q⁻ before the (additive) innovation. The prediction base is
the state q̂(k|k) by default (``base="state"``, the thesis's Q framework) or the measurement.
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass, field

import numba
import numpy as np

from ivc.linalg import cholesky, congruence, factored_update
from ivc.predict.base import Predictor, PredictorError, Stream, StreamClock, as_given, check_horizons, check_rate
from ivc.predict.delta import extrapolate_each
from ivc.predict.dq import SIGMA_CV1
from ivc.predict.quat import delta_q_jacobian, normalise, qmul, qmul_conj, rate_of
from ivc.predict.timing import MAX_GAP_S, check_stream, check_time, steps

#: Table 3, Q column: measurement variances of the 4 quaternion components
R_QUATERNION = (2.55e-07, 4.67e-07, 4.10e-07, 3.28e-07)


@numba.njit(cache=True)
def _step(z_in, ok, dt, x, P, status, clock, qvar, R, max_gap, p0w, work):
    """One Q-EKF cycle for one sensor, dt s after the previous frame; x = [q(4), ω(3)], status = [initialised,
    have_prev], clock = [age of x (s), s since the last valid sample, restarts, repeats, the last valid sample (4)].

    The time rules of :mod:`ivc.predict.timing`: an invalid sample is bridged (the next cycle spans the time), a
    stretch without one longer than ``max_gap`` s restarts the filter, an exact repeat of the last valid sample is
    dropped (the prediction then starts from x, ``age`` s old)."""
    z, dq, J, RJ, A, W, T, Pp, S, L, nu, xp, U, Rq = work
    clock[0] += dt
    clock[1] += dt
    if not ok:
        return status[0] == 1
    if status[1] == 1 and clock[1] > max_gap:
        status[0] = 0
        status[1] = 0
        clock[2] += 1.0
    clock[1] = 0.0
    if status[1] == 1 and z_in[0] == clock[4] and z_in[1] == clock[5] and z_in[2] == clock[6] \
            and z_in[3] == clock[7]:
        clock[3] += 1.0
        return status[0] == 1
    for i in range(4):
        z[i] = z_in[i]
        clock[4 + i] = z_in[i]
    tau = clock[0]
    clock[0] = 0.0
    if status[1] == 0 or status[0] == 0:
        if status[1] == 1:  # second frame: ω from the first Δq
            qmul_conj(z, x, dq)
            if dq[0] < 0.0:
                for i in range(4):
                    dq[i] = -dq[i]
            rate_of(dq, tau, nu)
            for i in range(3):
                x[4 + i] = nu[i]
            status[0] = 1
        P[:, :] = 0.0
        for i in range(4):
            P[i, i] = R[i]
        for i in range(4, 7):
            P[i, i] = p0w
        if np.dot(z, x[:4]) < 0.0:
            for i in range(4):
                z[i] = -z[i]
        for i in range(4):
            x[i] = z[i]
        status[1] = 1
        return status[0] == 1
    wx, wy, wz = x[4], x[5], x[6]
    delta_q_jacobian(wx, wy, wz, tau, J, dq)
    q = x[:4]
    Rq[0, 0], Rq[0, 1], Rq[0, 2], Rq[0, 3] = q[0], -q[1], -q[2], -q[3]
    Rq[1, 0], Rq[1, 1], Rq[1, 2], Rq[1, 3] = q[1], q[0], q[3], -q[2]
    Rq[2, 0], Rq[2, 1], Rq[2, 2], Rq[2, 3] = q[2], -q[3], q[0], q[1]
    Rq[3, 0], Rq[3, 1], Rq[3, 2], Rq[3, 3] = q[3], q[2], -q[1], q[0]
    for r in range(4):
        for c in range(3):
            acc = 0.0
            for m in range(4):
                acc += Rq[r, m] * J[m, c]
            RJ[r, c] = acc
    A[:, :] = 0.0
    p = dq
    A[0, 0], A[0, 1], A[0, 2], A[0, 3] = p[0], -p[1], -p[2], -p[3]
    A[1, 0], A[1, 1], A[1, 2], A[1, 3] = p[1], p[0], -p[3], p[2]
    A[2, 0], A[2, 1], A[2, 2], A[2, 3] = p[2], p[3], p[0], -p[1]
    A[3, 0], A[3, 1], A[3, 2], A[3, 3] = p[3], -p[2], p[1], p[0]
    for r in range(4):
        for c in range(3):
            A[r, 4 + c] = RJ[r, c]
            W[r, c] = RJ[r, c] * tau
    for i in range(3):
        A[4 + i, 4 + i] = 1.0
        for c in range(3):
            W[4 + i, c] = tau if i == c else 0.0
    congruence(A, P, 7, T, Pp)
    for a in range(7):
        for b in range(a + 1):
            acc = Pp[a, b]
            for c in range(3):
                acc += W[a, c] * qvar[c] * W[b, c]
            Pp[a, b] = acc
            Pp[b, a] = acc
    qmul(dq, q, xp[:4])
    for i in range(4, 7):
        xp[i] = x[i]
    if not quaternion_update(z, xp, Pp, R, np.int64(7), x, P, S, L, nu, U):  # np.int64: nasa's n shares it
        status[0] = 0
        status[1] = 0
        return False
    return True


@numba.njit(cache=True)
def quaternion_update(z, xp, Pp, R, n, x, P, S, L, nu, U):
    """EKF update of an n-state filter whose first 4 states are the orientation, measured directly
    (z (4,), H = [I₄ 0], variances R (4,)): z's sign is aligned with the predicted xp[:4] (q ≡ −q),
    x = xp + K ν with q̂ renormalised, P = P⁻ − K S Kᵀ (:func:`ivc.linalg.factored_update`).
    False (x, P untouched) when the innovation covariance, or the posterior, is not positive definite."""
    if z[0] * xp[0] + z[1] * xp[1] + z[2] * xp[2] + z[3] * xp[3] < 0.0:
        for i in range(4):
            z[i] = -z[i]
    for r in range(4):
        for c in range(4):
            S[r, c] = Pp[r, c]
        S[r, r] += R[r]
        nu[r] = z[r] - xp[r]
    if not cholesky(S, 4, L):
        return False
    # P⁻Hᵀ is the first 4 columns of P⁻; L⁻¹ν is solved in place in nu
    if factored_update(L, Pp, nu, xp, Pp, n, 4, U, nu, x, P) < 0.0:
        return False
    normalise(x[:4])
    return True


@numba.njit(cache=True)
def _work():
    """Scratch for :func:`_step`, made once per sensor (nothing is allocated per step)."""
    return (np.empty(4), np.empty(4), np.empty((4, 3)), np.empty((4, 3)), np.empty((7, 7)), np.empty((7, 3)),
            np.empty((7, 7)), np.empty((7, 7)), np.empty((4, 4)), np.empty((4, 4)), np.empty(4), np.empty(7),
            np.empty((7, 4)), np.empty((4, 4)))


#: The filter's configuration: process-noise variances ``qvar``, measurement variances ``R``, the gap ``max_gap`` s
#: that restarts it and the starting variance ``p0w`` of ω
Config = namedtuple("Config", "qvar R max_gap p0w")
#: A batch's outputs (F, S, ...): the state ``x`` [q̂, ω̂], whether it is an estimate ``ok``, and its ``age`` s
Output = namedtuple("Output", "x ok age")


@numba.njit(cache=True)
def _run(qs, ok, dt, x, P, status, clock, config, out):
    """Every sensor through its frames (``config`` a :data:`Config`) into ``out`` (an :data:`Output`)."""
    qvar, R, max_gap, p0w = config
    out_x, out_ok, out_age = out
    for s in range(qs.shape[1]):
        work = _work()
        for k in range(qs.shape[0]):
            good = _step(qs[k, s], ok[k, s], dt[k], x[s], P[s], status[s], clock[s], qvar, R, max_gap, p0w, work)
            out_ok[k, s] = good and ok[k, s]
            out_x[k, s] = x[s]
            out_age[k, s] = clock[s, 0]


class QStream(Stream):
    def __init__(self, predictor: QEKF, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.x, self.P = np.zeros((n_sensors, 7)), np.zeros((n_sensors, 7, 7))
        self.status = np.zeros((n_sensors, 2), np.int64)
        self.clock_state = np.zeros((n_sensors, 8))
        self.clock = StreamClock(predictor.rate_hz, n_sensors)
        self.work = _work()
        self.ready = np.zeros(n_sensors, bool)

    @property
    def restarts(self) -> int:
        return int(self.clock_state[:, 2].sum())

    def update(self, q, valid=None, time=None):
        qs, ok = self._check_frame(q, valid)
        dt = self.clock.tick(time)
        if time is None and self.clock.frames > 1:
            dt = self.predictor.tau  # exactly the nominal period, as the batch without time stamps
        qvar, R = self.predictor._config
        p = self.predictor
        for s in range(self.n_sensors):
            self.ready[s] = _step(qs[s], ok[s], dt, self.x[s], self.P[s], self.status[s], self.clock_state[s], qvar,
                                  R, p.max_gap_s, p.p0_omega, self.work) and ok[s]
        self.last = qs

    def predict(self, horizon):
        d = float(check_horizons(horizon)[0])
        if self.predictor.base == "state":
            base, age = self.x[:, :4], self.clock_state[:, 0]
        else:
            base, age = self.last, np.zeros(self.n_sensors)
        out = extrapolate_each(base, self.x[:, 4:], None, d + age, self.predictor.tau)
        out[~self.ready] = np.nan
        return out


@dataclass
class QEKF(Predictor):
    """7-state quaternion EKF (Himberg 2010 ch. 2 "Q"); ``base`` = "state" (default) or "measurement".

    Runs at the stream's own time steps (:mod:`ivc.predict.timing`)."""

    rate_hz: float = 120.0
    sigma_w: tuple[float, float, float] = SIGMA_CV1
    sigma_v: tuple[float, float, float, float] = tuple(np.sqrt(R_QUATERNION))
    base: str = "state"
    p0_omega: float = 1.0
    max_gap_s: float = MAX_GAP_S
    name: str = "q-ekf"
    _config: tuple = field(init=False, repr=False)

    def __post_init__(self):
        self.rate_hz = check_rate(self.rate_hz)
        if self.base not in ("state", "measurement"):
            raise PredictorError(f"base is 'state' or 'measurement', got {self.base!r}")
        qvar, R = np.square(np.asarray(self.sigma_w, float)), np.square(np.asarray(self.sigma_v, float))
        if qvar.shape != (3,) or R.shape != (4,) or np.any(qvar <= 0) or np.any(R <= 0):
            raise PredictorError("sigma_w needs 3 and sigma_v 4 positive standard deviations")
        self._config = (qvar, R)

    def filter(self, q, valid=None, time=None, ages=False):
        """(checked q (F, S, 4), states [q̂, ω̂] (F, S, 7), usable (F, S)), and with ``ages`` the age (F, S) s of
        the state each prediction starts from."""
        qs, ok, _ = check_stream(q, valid)
        F, S = ok.shape
        dt = steps(check_time(time, F, self.rate_hz))
        if time is None:
            dt[1:] = self.tau
        out_x, out_ok, age = np.zeros((F, S, 7)), np.zeros((F, S), bool), np.zeros((F, S))
        _run(qs, ok, dt, np.zeros((S, 7)), np.zeros((S, 7, 7)), np.zeros((S, 2), np.int64), np.zeros((S, 8)),
             Config(*self._config, self.max_gap_s, self.p0_omega), Output(out_x, out_ok, age))
        return (qs, out_x, out_ok, age) if ages else (qs, out_x, out_ok)

    def rates(self, q, valid=None, time=None):
        _, x, usable = self.filter(q, valid, time)
        out = np.where(usable[..., None], x[..., 4:], np.nan)
        return as_given(out, np.ndim(q) == 2)

    def predict(self, q, horizons, valid=None, time=None):
        h = check_horizons(horizons)
        qs, x, usable, age = self.filter(q, valid, time, ages=True)
        base = x[..., :4] if self.base == "state" else qs
        if self.base == "measurement":
            age = np.zeros_like(age)  # the measurement itself is the latest sample (a repeat equals it)
        out = np.stack([extrapolate_each(base, x[..., 4:], None, d + age, self.tau) for d in h])
        out[:, ~usable] = np.nan
        return as_given(out, np.ndim(q) == 2)

    #: the live form, made by :meth:`stream`
    stream_type = QStream
