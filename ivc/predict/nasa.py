"""The 10-state quaternion EKF of Adelstein, Jung & Ellis 2001 (docs/math.md §17.1).

State x = [q (4), ω (3, rad/s, body frame), α (3, rad/s²)], kinematics dq/dt = ½ q ⊗ (0, ω)
(eq. 16), ω̇ = α, α̇ = w. As docs/math.md §17.1 explains (eq. 20 as printed doubles the quaternion
rate when used to propagate):

- the state is propagated with the exact kinematics: q⁻ = q ⊗ exp(½(hω + ½h²α)), ω⁻ = ω + hα;
- eq. 20's matrix, with the corrected Q_r (eq. 18), is only the Jacobian F of the covariance
  propagation P⁻ = Φ P Φᵀ + W_r with Φ = expm(hF);
- the measured quaternion's sign is aligned with q⁻ before the innovation, and q̂ is
  renormalised after each update (neither is stated in the paper; both are needed).

Measurement z = q + v, H = [I₄ 0], V_r = diag(1e-4) (the paper's). W_r is diagonal, the design
parameter (10 entries: q_w, q_x, q_y, q_z, ω_x, ω_y, ω_z, α_x, α_y, α_z), per nominal frame 1 / rate_hz.

Real time steps (:mod:`ivc.predict.timing`): each cycle propagates over the actual time h since the
sensor's previous usable sample (across invalid samples), with Φ = expm(hF) and process noise
W_r · h · rate_hz (white noise whose variance grows with the time elapsed, W_r at the nominal step);
exact repeats are dropped and predicted from the sample they repeat, as old as it is; a gap longer
than ``max_gap_s`` restarts the filter at the next sample. A&B94's default W_r is
not listed by Adelstein, Jung & Ellis 2001: :data:`DEFAULT_W` is ours, chosen on the synthetic yaw record of
:mod:`ivc.predict.studies.compensator` (a placeholder for it).
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass, field

import numba
import numpy as np

from ivc.linalg import congruence, omega_matrix, q_matrix, qmul
from ivc.linalg import quaternion_normalise as normalise
from ivc.predict.base import Predictor, PredictorError, Stream, StreamClock, as_given, check_horizons, check_rate
from ivc.predict.qekf import quaternion_update
from ivc.predict.timing import MAX_GAP_S, check_stream, check_time, repeats, restarts

#: V_r of the paper: variance of each measured quaternion component
V_QUATERNION = 1e-4
#: our default W_r (A&B94's is not in the paper): q, ω, α process variances per step. Chosen on the
#: synthetic yaw record of :mod:`ivc.predict.studies.compensator` so that, like the paper's default, it tracks
#: the yaw well (twist ratio 0.21 against the paper's 0.181) and amplifies tremor (noise gain ~2)
DEFAULT_W = (1e-9, 1e-9, 1e-9, 1e-9, 1e-6, 1e-6, 1e-6, 1.0, 1.0, 1.0)
#: terms of the Taylor series of expm(hF); ‖hF‖ < 0.1 for head motion at 120 Hz, error < 1e-12
EXPM_TERMS = 8
N = 10


@numba.njit(cache=True)
def jacobian(x, F):
    """F (10, 10) = ∂ẋ/∂x of ẋ = [½ q ⊗ ω, α, 0] (eq. 20 with Q_r corrected)."""
    F[:, :] = 0.0
    omega_matrix(x[4:7], F[:4, :4])
    q_matrix(x[:4], F[:4, 4:7])
    for r in range(4):
        for c in range(7):
            F[r, c] *= 0.5
    for i in range(3):
        F[4 + i, 7 + i] = 1.0


@numba.njit(cache=True)
def expm_taylor(A, out, term, tmp):
    """out = expm(A) by its Taylor series (EXPM_TERMS terms), for A = h F with F of :func:`jacobian`'s
    pattern: only A[:4, :7] and A[4 + i, 7 + i] are non-zero, which the products exploit."""
    n = A.shape[0]
    for a in range(n):
        for b in range(n):
            term[a, b] = 1.0 if a == b else 0.0
            out[a, b] = term[a, b]
    for k in range(1, EXPM_TERMS):
        for a in range(n):
            for b in range(7):
                acc = 0.0
                for c in range(4):
                    acc += term[a, c] * A[c, b]
                tmp[a, b] = acc / k
            for i in range(3):
                tmp[a, 7 + i] = term[a, 4 + i] * A[4 + i, 7 + i] / k
        for a in range(n):
            for b in range(n):
                term[a, b] = tmp[a, b]
                out[a, b] += tmp[a, b]


@numba.njit(cache=True, inline="always")
def advance(q, w, a, t, out, dq):
    """out = q ⊗ exp(½ (t ω + ½ t² α)): the orientation t s later (body-frame rates)."""
    vx = t * w[0] + 0.5 * t * t * a[0]
    vy = t * w[1] + 0.5 * t * t * a[1]
    vz = t * w[2] + 0.5 * t * t * a[2]
    angle = np.sqrt(vx * vx + vy * vy + vz * vz)
    dq[0] = np.cos(0.5 * angle)
    s = 0.5 - angle * angle / 48.0 if angle < 1e-6 else np.sin(0.5 * angle) / angle
    dq[1], dq[2], dq[3] = s * vx, s * vy, s * vz
    qmul(q, dq, out)
    normalise(out)


@numba.njit(cache=True)
def _work():
    return (np.empty(4), np.empty(4), np.empty((N, N)), np.empty((N, N)), np.empty((N, N)), np.empty((N, N)),
            np.empty((N, N)), np.empty((4, 4)), np.empty((4, 4)), np.empty(4), np.empty((N, 4)), np.empty(N))


@numba.njit(cache=True)
def _step(z_in, ok, x, P, status, W, V, h, p0, work, tau):
    """One EKF cycle for one sensor over h s (W per nominal step tau); status = [initialised, have_prev];
    returns whether x is an estimate."""
    z, dq, F, Phi, term, tmp, Pp, S, L, nu, U, xp = work
    if not ok:
        status[1] = 0
        return status[0] == 1
    for i in range(4):
        z[i] = z_in[i]
    if status[0] == 0:  # start at the measurement, at rest, with a wide prior on ω and α
        for i in range(4):
            x[i] = z[i]
        for i in range(4, N):
            x[i] = 0.0
        P[:, :] = 0.0
        for i in range(4):
            P[i, i] = V[i]
        for i in range(4, N):
            P[i, i] = p0[i - 4]
        status[0] = 1
        status[1] = 1
        return False
    status[1] = 1
    jacobian(x, F)
    for a in range(N):
        for b in range(N):
            F[a, b] *= h
    expm_taylor(F, Phi, term, tmp)
    advance(x[:4], x[4:7], x[7:], h, xp[:4], dq)
    for i in range(3):
        xp[4 + i] = x[4 + i] + h * x[7 + i]
        xp[7 + i] = x[7 + i]
    congruence(Phi, P, N, tmp, Pp)
    for a in range(N):
        Pp[a, a] += W[a] * (h / tau)
    if not quaternion_update(z, xp, Pp, V, np.int64(N), x, P, S, L, nu, U):  # one specialisation with qekf's
        status[0] = 0
        return False
    return True


#: The filter's configuration (:attr:`NasaEKF._config`): the process noise ``W`` per nominal step, the measurement
#: variances ``V`` (4,), the nominal step ``tau`` s and the starting covariance's diagonal ``p0``
Config = namedtuple("Config", "W V tau p0")
#: A batch's outputs (F, S, ...): the state ``x`` at each frame's latest usable sample, whether it is an estimate
#: ``ok``, and that sample's time ``t`` s
Output = namedtuple("Output", "x ok t")


@numba.njit(cache=True)
def _run(qs, ok, use, restart, t, x, P, status, config, out):
    """Every sensor through its frames (``config`` a :data:`Config`) into ``out`` (an :data:`Output`): out.x the
    state at the latest usable sample, out.t that sample's time, out.ok where it is an estimate (and the frame
    valid)."""
    W, V, tau, p0 = config
    out_x, out_ok, out_t = out
    for s in range(qs.shape[1]):
        work = _work()
        ready = False
        last = 0.0
        for k in range(qs.shape[0]):
            if restart[k, s]:
                status[s, 0] = 0
                ready = False
            if use[k, s]:
                h = t[k] - last if status[s, 0] == 1 else tau
                ready = _step(qs[k, s], np.bool_(True), x[s], P[s], status[s], W, V, h, p0, work, tau)
                last = t[k]
            out_ok[k, s] = ready and ok[k, s]
            out_x[k, s] = x[s]
            out_t[k, s] = last


@numba.njit(cache=True)
def _extrapolate(x, usable, t, out):
    """Orientations t[i] s after each state (…, 10) flattened to (n, 10); NaN where not usable."""
    dq = np.empty(4)
    for i in range(x.shape[0]):
        if usable[i]:
            advance(x[i, :4], x[i, 4:7], x[i, 7:], t[i], out[i], dq)
        else:
            out[i, :] = np.nan


def extrapolate(x: np.ndarray, usable: np.ndarray, t) -> np.ndarray:
    """The orientation ``t`` s (a number, or one per state) after each state x (..., 10), by the filter's kinematics."""
    flat = np.ascontiguousarray(x.reshape(-1, N))
    span = np.ascontiguousarray(np.broadcast_to(np.asarray(t, float), x.shape[:-1]).reshape(-1))
    out = np.empty((len(flat), 4))
    _extrapolate(flat, np.ascontiguousarray(usable.reshape(-1)), span, out)
    return out.reshape(*x.shape[:-1], 4)


class NasaStream(Stream):
    """The live NASA EKF: a cycle per usable sample over its actual step; repeats dropped, gaps restart."""

    def __init__(self, predictor: NasaEKF, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.x, self.P = np.zeros((n_sensors, N)), np.zeros((n_sensors, N, N))
        self.status = np.zeros((n_sensors, 2), np.int64)
        self.work = _work()
        self.ready = np.zeros(n_sensors, bool)
        self.ok = np.zeros(n_sensors, bool)
        self.clock = StreamClock(predictor.rate_hz, n_sensors)
        self.base_t = np.zeros(n_sensors)  # each sensor's latest usable sample's time
        self.previous = np.full((n_sensors, 4), np.nan)
        self.restarts = 0

    def update(self, q, valid=None, time=None):
        qs, ok = self._check_frame(q, valid)
        gap = self.clock.advance(time, ok, self.predictor.max_gap_s)
        now = self.clock.now
        W, V, tau, p0 = self.predictor._config
        for s in np.flatnonzero(ok):
            if gap[s]:
                self.status[s, 0] = 0
                self.ready[s] = False
                self.restarts += 1
            if np.all(qs[s] == self.previous[s]):
                continue  # a repeat: predicted from the sample it repeats
            h = now - self.base_t[s] if self.status[s, 0] == 1 else tau
            self.ready[s] = _step(qs[s], True, self.x[s], self.P[s], self.status[s], W, V, h, p0, self.work, tau)
            self.base_t[s] = now
        self.previous = np.where(ok[:, None], qs, self.previous)
        self.ok = ok
        self.last = qs

    def predict(self, horizon):
        d = float(check_horizons(horizon)[0])
        return extrapolate(self.x, self.ready & self.ok, d + (self.clock.now or 0.0) - self.base_t)


@dataclass
class NasaEKF(Predictor):
    """NASA's 10-state quaternion EKF; ``W`` (10,) its diagonal process noise per nominal step 1 / rate_hz, ``V``
    the measurement variance of each quaternion component, ``p0`` the initial ω and α variances."""

    rate_hz: float = 120.0
    W: tuple = DEFAULT_W
    V: float = V_QUATERNION
    p0: tuple = (1.0, 1.0, 1.0, 10.0, 10.0, 10.0)
    name: str = "nasa-ekf"
    max_gap_s: float = MAX_GAP_S
    _config: tuple = field(init=False, repr=False)

    def __post_init__(self):
        self.rate_hz = check_rate(self.rate_hz)
        W, p0 = np.asarray(self.W, float), np.asarray(self.p0, float)
        if W.shape != (N,) or not np.all(np.isfinite(W)) or np.any(W < 0):
            raise PredictorError(f"W needs {N} non-negative variances (q ×4, ω ×3, α ×3), got {self.W}")
        if not (np.isfinite(self.V) and self.V > 0) or p0.shape != (6,) or np.any(p0 <= 0):
            raise PredictorError("V must be a positive variance and p0 six positive variances (ω ×3, α ×3)")
        if not (np.isfinite(self.max_gap_s) and self.max_gap_s > 0):
            raise PredictorError(f"max_gap_s must be a positive number of seconds, got {self.max_gap_s}")
        self._config = Config(W, np.full(4, float(self.V)), 1.0 / self.rate_hz, p0)

    def filter(self, q, valid=None, time=None):
        """(checked q (F, S, 4), states [q̂, ω̂, α̂] (F, S, 10) at each frame's latest usable sample, usable (F, S),
        that sample's time (F, S) s)."""
        qs, ok, _ = check_stream(q, valid)
        F, S = ok.shape
        t = check_time(time, F, self.rate_hz)
        use = ok & ~repeats(qs, ok)
        out_x, out_ok, out_t = np.zeros((F, S, N)), np.zeros((F, S), bool), np.zeros((F, S))
        _run(qs, ok, use, restarts(t, ok, self.max_gap_s), t, np.zeros((S, N)), np.zeros((S, N, N)),
             np.zeros((S, 2), np.int64), self._config, Output(out_x, out_ok, out_t))
        return qs, out_x, out_ok, t[:, None] - out_t

    def rates(self, q, valid=None, time=None):
        _, x, usable, _ = self.filter(q, valid, time)
        out = np.where(usable[..., None], x[..., 4:7], np.nan)
        return as_given(out, np.ndim(q) == 2)

    def predict(self, q, horizons, valid=None, time=None):
        h = check_horizons(horizons)
        _, x, usable, age = self.filter(q, valid, time)
        out = np.stack([extrapolate(x, usable, d + age) for d in h])
        return as_given(out, np.ndim(q) == 2)

    #: the live form, made by :meth:`stream`
    stream_type = NasaStream
