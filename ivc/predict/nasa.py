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
parameter (10 entries: q_w, q_x, q_y, q_z, ω_x, ω_y, ω_z, α_x, α_y, α_z). A&B94's default W_r is
not listed by Adelstein, Jung & Ellis 2001: :data:`DEFAULT_W` is ours, chosen on the synthetic yaw record of
:mod:`ivc.predict.studies.compensator` (a placeholder for it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from ivc.linalg import congruence
from ivc.predict.base import (
    FixedRatePredictor,
    PredictorError,
    Stream,
    as_given,
    check_horizons,
    check_rate,
    check_stream,
)
from ivc.predict.qekf import quaternion_update
from ivc.predict.quat import normalise, qmul

#: V_r of the paper: variance of each measured quaternion component
V_QUATERNION = 1e-4
#: our default W_r (A&B94's is not in the paper): q, ω, α process variances per step. Chosen on the
#: synthetic yaw record of :mod:`ivc.predict.studies.compensator` so that, like the paper's default, it tracks
#: the yaw well (twist ratio 0.21 against the paper's 0.181) and amplifies tremor (noise gain ~2)
DEFAULT_W = (1e-9, 1e-9, 1e-9, 1e-9, 1e-6, 1e-6, 1e-6, 1.0, 1.0, 1.0)
#: terms of the Taylor series of expm(hF); ‖hF‖ < 0.1 for head motion at 120 Hz, error < 1e-12
EXPM_TERMS = 8
N = 10


@numba.njit(cache=True, inline="always")
def q_matrix(q, out):
    """Q_r(q) (4, 3), eq. 18 corrected: q ⊗ (0, ω) = Q_r(q) ω."""
    out[0, 0], out[0, 1], out[0, 2] = -q[1], -q[2], -q[3]
    out[1, 0], out[1, 1], out[1, 2] = q[0], -q[3], q[2]
    out[2, 0], out[2, 1], out[2, 2] = q[3], q[0], -q[1]
    out[3, 0], out[3, 1], out[3, 2] = -q[2], q[1], q[0]


@numba.njit(cache=True, inline="always")
def omega_matrix(w, out):
    """Ω_r(ω) (4, 4), eq. 19: q ⊗ (0, ω) = Ω_r(ω) q."""
    out[0, 0], out[0, 1], out[0, 2], out[0, 3] = 0.0, -w[0], -w[1], -w[2]
    out[1, 0], out[1, 1], out[1, 2], out[1, 3] = w[0], 0.0, w[2], -w[1]
    out[2, 0], out[2, 1], out[2, 2], out[2, 3] = w[1], -w[2], 0.0, w[0]
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = w[2], w[1], -w[0], 0.0


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
def _step(z_in, ok, x, P, status, W, V, h, p0, work):
    """One EKF cycle for one sensor; status = [initialised, have_prev]; returns whether x is an estimate."""
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
        Pp[a, a] += W[a]
    if not quaternion_update(z, xp, Pp, V, N, x, P, S, L, nu, U):
        status[0] = 0
        return False
    return True


@numba.njit(cache=True, parallel=True)
def _run(qs, ok, x, P, status, W, V, h, p0, out_x, out_ok):
    for s in numba.prange(qs.shape[1]):
        work = _work()
        for k in range(qs.shape[0]):
            good = _step(qs[k, s], ok[k, s], x[s], P[s], status[s], W, V, h, p0, work)
            out_ok[k, s] = good and ok[k, s]
            out_x[k, s] = x[s]


@numba.njit(cache=True)
def _extrapolate(x, usable, t, out):
    """Orientations t s after each state (…, 10) flattened to (n, 10); NaN where not usable."""
    dq = np.empty(4)
    for i in range(x.shape[0]):
        if usable[i]:
            advance(x[i, :4], x[i, 4:7], x[i, 7:], t, out[i], dq)
        else:
            out[i, :] = np.nan


def extrapolate(x: np.ndarray, usable: np.ndarray, t: float) -> np.ndarray:
    """The orientation ``t`` s after each state x (..., 10), by the filter's kinematics."""
    flat = np.ascontiguousarray(x.reshape(-1, N))
    out = np.empty((len(flat), 4))
    _extrapolate(flat, np.ascontiguousarray(usable.reshape(-1)), float(t), out)
    return out.reshape(*x.shape[:-1], 4)


@dataclass
class NasaEKF(FixedRatePredictor):
    """NASA's 10-state quaternion EKF; ``W`` (10,) its diagonal process noise per step, ``V`` the
    measurement variance of each quaternion component, ``p0`` the initial ω and α variances."""

    rate_hz: float = 120.0
    W: tuple = DEFAULT_W
    V: float = V_QUATERNION
    p0: tuple = (1.0, 1.0, 1.0, 10.0, 10.0, 10.0)
    name: str = "nasa-ekf"
    _config: tuple = field(init=False, repr=False)

    def __post_init__(self):
        self.rate_hz = check_rate(self.rate_hz)
        W, p0 = np.asarray(self.W, float), np.asarray(self.p0, float)
        if W.shape != (N,) or not np.all(np.isfinite(W)) or np.any(W < 0):
            raise PredictorError(f"W needs {N} non-negative variances (q ×4, ω ×3, α ×3), got {self.W}")
        if not (np.isfinite(self.V) and self.V > 0) or p0.shape != (6,) or np.any(p0 <= 0):
            raise PredictorError("V must be a positive variance and p0 six positive variances (ω ×3, α ×3)")
        self._config = (W, np.full(4, float(self.V)), 1.0 / self.rate_hz, p0)

    def filter(self, q, valid=None):
        """(checked q (F, S, 4), states [q̂, ω̂, α̂] (F, S, 10), usable (F, S))."""
        qs, ok, _ = check_stream(q, valid)
        F, S = ok.shape
        out_x, out_ok = np.zeros((F, S, N)), np.zeros((F, S), bool)
        _run(qs, ok, np.zeros((S, N)), np.zeros((S, N, N)), np.zeros((S, 2), np.int64), *self._config, out_x, out_ok)
        return qs, out_x, out_ok

    def rates(self, q, valid=None, time=None):  # a fixed-rate design: the nominal rate
        _, x, usable = self.filter(q, valid)
        out = np.where(usable[..., None], x[..., 4:7], np.nan)
        return as_given(out, np.ndim(q) == 2)

    def _predict_uniform(self, q, horizons, valid=None):
        h = check_horizons(horizons)
        _, x, usable = self.filter(q, valid)
        out = np.stack([extrapolate(x, usable, d) for d in h])
        return as_given(out, np.ndim(q) == 2)

    def _stream_uniform(self, n_sensors: int = 1) -> NasaStream:
        return NasaStream(self, n_sensors)


class NasaStream(Stream):
    def __init__(self, predictor: NasaEKF, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.x, self.P = np.zeros((n_sensors, N)), np.zeros((n_sensors, N, N))
        self.status = np.zeros((n_sensors, 2), np.int64)
        self.work = _work()
        self.ready = np.zeros(n_sensors, bool)

    def update(self, q, valid=None):
        qs, ok = self._check_frame(q, valid)
        for s in range(self.n_sensors):
            self.ready[s] = _step(qs[s], ok[s], self.x[s], self.P[s], self.status[s], *self.predictor._config,
                                  self.work) and ok[s]

    def predict(self, horizon):
        return extrapolate(self.x, self.ready, float(check_horizons(horizon)[0]))
