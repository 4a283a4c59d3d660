"""``direct``: an h-step-ahead predictor learned online from the stream itself, by recursive least squares.

Instead of a motion model, ``direct`` learns the map from a sensor's recent motion to its turn over
the horizon. At each usable sample k (valid, not a repeat) its features are the angular velocities
of the last ``lags`` intervals between usable samples, each the rotation between two samples over
their actual time step, expressed in the frame of sample k (rad/s; 3 x ``lags`` numbers φ). Its
prediction is the mean angular velocity over the horizon, ``v = φ W`` (body frame of sample k,
rad/s), shown as ``q̂ = q(k) ⊗ exp((h + age) v)`` (``age``: the time since sample k, nonzero at a
repeat). W (3·lags x 3) is fitted by weighted least squares with exponential forgetting:

* the target of sample k is the turn from q(k) to the stream's own orientation at t(k) + h, slerped
  between the usable samples around it (:func:`ivc.predict.recording.future_reference`'s rule:
  samples at most ``max_step_s`` apart), divided by h. It is learned only when the first sample at
  or after t(k) + h arrives, so the predictor is causal: at time t it has used samples up to t only;
* sums forget with time constant ``memory_s`` (3 s: a few of a head's movements, each about
  0.3-1 s, and about 15 samples per coefficient at 60 Hz);
* each sample is weighted 1 / sqrt(|v₁|² + ``floor``²) (v₁ the newest interval's velocity, floor
  0.1 rad/s), so slow and fast motion count alike (the fit is nearer a relative error);
* a ridge of strength ``prior`` pulls W toward the backward difference (v = v₁, the ``poly1``
  predictor), which W is while nothing has been learned.

Each horizon of a batch call is learned on its own. The live form learns at ``horizon_s`` and uses
that W at any horizon asked. A gap longer than ``max_gap_s`` without a valid sample restarts the
history (no prediction until ``lags`` + 1 usable samples) and drops the pending targets; W, which
describes the head rather than the moment, is kept, as an IMM keeps its mode probabilities.
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import numba
import numpy as np

from ivc.linalg import cholesky, cholesky_solve
from ivc.predict.base import Predictor, PredictorError, Stream, as_given, check_horizons, check_rate
from ivc.predict.quat import delta_q, qmul, qmul_conj, rate_of, slerp
from ivc.predict.recording import REFERENCE_MAX_STEP_S
from ivc.predict.timing import MAX_GAP_S, check_stream, check_time

#: interval velocities in the features
LAGS = 4
#: time constant of the forgetting (s)
MEMORY_S = 3.0
#: ridge strength toward the backward difference
PRIOR = 1.0
#: speed (rad/s) below which a sample's weight stops growing
FLOOR = 0.1
#: predictions awaiting their target, per sensor (a 1 s horizon at 500 Hz); the oldest is dropped beyond
PENDING = 512

# indices into the per-sensor scalars (S, _NS)
_N, _LAST_VALID, _BASE_T, _READY, _HEAD, _LEN, _RESTARTS = range(7)
_NS = 7


@numba.njit(cache=True, inline="always")
def _conj_mul(p, q, out):
    """out = p* ⊗ q (for unit quaternions: q in the frame of p)."""
    out[0] = p[0] * q[0] + p[1] * q[1] + p[2] * q[2] + p[3] * q[3]
    out[1] = p[0] * q[1] - p[1] * q[0] - p[2] * q[3] + p[3] * q[2]
    out[2] = p[0] * q[2] + p[1] * q[3] - p[2] * q[0] - p[3] * q[1]
    out[3] = p[0] * q[3] - p[1] * q[2] + p[2] * q[1] - p[3] * q[0]


@numba.njit(cache=True)
def _rotate_into(rel, w, out, tmp, vq):
    """out = rel ⊗ (0, w) ⊗ rel*: the vector w (frame of a sample) in the frame rel turns it into."""
    vq[0] = 0.0
    vq[1], vq[2], vq[3] = w[0], w[1], w[2]
    qmul(rel, vq, tmp)
    qmul_conj(tmp, rel, vq)
    out[0], out[1], out[2] = vq[1], vq[2], vq[3]


@numba.njit(cache=True)
def _features(ht, hq, lags, phi):
    """phi (3·lags,) = the interval velocities (rad/s) of history ht (lags + 1,), hq (lags + 1, 4) (newest first),
    each in the frame of the newest sample."""
    d = np.empty(4)
    rel = np.empty(4)
    tmp = np.empty(4)
    vq = np.empty(4)
    w = np.empty(3)
    v = np.empty(3)
    for j in range(1, lags + 1):
        _conj_mul(hq[j], hq[j - 1], d)  # the interval's turn, in the older sample's frame
        if d[0] < 0.0:
            for i in range(4):
                d[i] = -d[i]
        rate_of(d, ht[j - 1] - ht[j], w)
        _conj_mul(hq[0], hq[j], rel)  # the older sample's frame in the newest's
        _rotate_into(rel, w, v, tmp, vq)
        for c in range(3):
            phi[3 * (j - 1) + c] = v[c]


#: The predictor's settings (:meth:`DirectPredictor._args`): the learning ``horizon`` s, the ``memory`` s of its
#: sums, the ridge ``prior``, the weight ``floor``, the gap ``max_gap`` s that restarts a sensor, the longest step
#: ``max_step`` s a reference is interpolated over, and the number of ``lags``.
Settings = namedtuple("Settings", "horizon memory prior floor max_gap max_step lags")
#: Every sensor's state (:func:`_state`, leading axis the sensor): scalars ``scal`` (S, _NS), the sample history
#: ``ht`` (S, lags + 1) s and ``hq`` (S, lags + 1, 4), the sums ``L`` (S, D, D) and ``B`` (S, D, 3), the velocity
#: ``vel`` (S, 3) and the base ``base_q`` (S, 4) of the prediction, the pending predictions' target times
#: ``pend_t``, features ``pend_phi``, bases ``pend_q`` and weights ``pend_w``, and the last sample ``prev_q``.
State = namedtuple("State", "scal ht hq L B vel base_q pend_t pend_phi pend_q pend_w prev_q")


@numba.njit(cache=True)
def _frame(q, ok, now, dt, settings, state):
    """Feed one frame q (S, 4), ok (S,) at ``now`` s (dt since the previous frame) to every sensor's state (a
    :data:`State`), with the predictor's :data:`Settings`."""
    horizon, memory, prior, floor, max_gap, max_step, lags = settings
    scal, ht, hq, L, B, vel, base_q, pend_t, pend_phi, pend_q, pend_w, prev_q = state
    S = q.shape[0]
    D = 3 * lags
    P = pend_t.shape[1]
    phi = np.empty(D)
    A = np.empty((D, D))
    rhs = np.empty(D)
    col = np.empty(D)
    y = np.empty(3)
    ref = np.empty(4)
    d = np.empty(4)
    if dt > 0.0:
        decay = np.exp(-dt / memory)
        for s in range(S):
            for a in range(D):
                for c in range(3):
                    B[s, a, c] *= decay
                for b in range(D):
                    L[s, a, b] *= decay
    for s in range(S):
        if not ok[s]:
            continue
        if np.isfinite(scal[s, _LAST_VALID]) and now - scal[s, _LAST_VALID] > max_gap:
            scal[s, _N] = 0.0
            scal[s, _LEN] = 0.0
            scal[s, _READY] = 0.0
            scal[s, _RESTARTS] += 1.0
            prev_q[s, :] = np.nan
        scal[s, _LAST_VALID] = now
        same = True
        for i in range(4):
            same = same and q[s, i] == prev_q[s, i]
        for i in range(4):
            prev_q[s, i] = q[s, i]
        if same:  # a repeat: a stale frame, predicted from the sample it repeats
            continue
        n = int(scal[s, _N])
        # learn the pending predictions whose target time has come
        while scal[s, _LEN] > 0.0:
            head = int(scal[s, _HEAD])
            target = pend_t[s, head]
            if target > now:
                break
            if n >= 1 and (target == now or (target >= ht[s, 0] and now - ht[s, 0] <= max_step)):
                if target == now:
                    for i in range(4):
                        ref[i] = q[s, i]
                else:
                    slerp(hq[s, 0], q[s], (target - ht[s, 0]) / (now - ht[s, 0]), ref)
                _conj_mul(pend_q[s, head], ref, d)  # the turn from the prediction's base to its target
                if d[0] < 0.0:
                    for i in range(4):
                        d[i] = -d[i]
                rate_of(d, horizon, y)
                w = pend_w[s, head]
                for a in range(D):
                    fa = w * pend_phi[s, head, a]
                    for c in range(3):
                        B[s, a, c] += fa * y[c]
                    for b in range(D):
                        L[s, a, b] += fa * pend_phi[s, head, b]
            scal[s, _HEAD] = (head + 1) % P
            scal[s, _LEN] -= 1.0
        for j in range(lags, 0, -1):
            ht[s, j] = ht[s, j - 1]
            for i in range(4):
                hq[s, j, i] = hq[s, j - 1, i]
        ht[s, 0] = now
        for i in range(4):
            hq[s, 0, i] = q[s, i]
            base_q[s, i] = q[s, i]
        scal[s, _BASE_T] = now
        n = min(n + 1, lags + 1)
        scal[s, _N] = n
        if n <= lags:
            scal[s, _READY] = 0.0
            continue
        _features(ht[s], hq[s], lags, phi)
        for a in range(D):  # A = L + prior I: symmetric positive definite (prior > 0), solved by Cholesky
            for b in range(D):
                A[a, b] = L[s, a, b]
            A[a, a] += prior
        if not cholesky(A, D, A):  # NaN in the sums: no prediction from this sample
            scal[s, _READY] = 0.0
            continue
        for c in range(3):
            for a in range(D):
                rhs[a] = B[s, a, c]
            rhs[c] += prior  # the prior W0: the newest interval's velocity (identity on the first 3 features)
            cholesky_solve(A, D, rhs, col)
            acc = 0.0
            for a in range(D):
                acc += phi[a] * col[a]
            vel[s, c] = acc
        scal[s, _READY] = 1.0
        if scal[s, _LEN] >= P:  # full: the oldest pending prediction is not learned
            scal[s, _HEAD] = (scal[s, _HEAD] + 1) % P
            scal[s, _LEN] -= 1.0
        slot = int((scal[s, _HEAD] + scal[s, _LEN]) % P)
        pend_t[s, slot] = now + horizon
        for a in range(D):
            pend_phi[s, slot, a] = phi[a]
        for i in range(4):
            pend_q[s, slot, i] = q[s, i]
        pend_w[s, slot] = 1.0 / np.sqrt(phi[0] ** 2 + phi[1] ** 2 + phi[2] ** 2 + floor * floor)
        scal[s, _LEN] += 1.0


@numba.njit(cache=True)
def _show(ok, now, horizon, scal, vel, base_q, out):
    """out (S, 4) = each ready sensor's base ⊗ exp((horizon + age) v); NaN where not ok or not ready."""
    dq = np.empty(4)
    for s in range(ok.shape[0]):
        if not (ok[s] and scal[s, _READY] > 0.0):
            out[s, :] = np.nan
            continue
        span = horizon + now - scal[s, _BASE_T]
        delta_q(vel[s, 0], vel[s, 1], vel[s, 2], span, dq)
        qmul(base_q[s], dq, out[s])


@numba.njit(cache=True)
def _run(q, ok, t, settings, state, out):
    """The batch: every frame through :func:`_frame`, then :func:`_show` at the settings' horizon into out
    (F, S, 4)."""
    horizon, memory, prior, floor, max_gap, max_step, lags = settings
    scal, ht, hq, L, B, vel, base_q, pend_t, pend_phi, pend_q, pend_w, prev_q = state
    for k in range(q.shape[0]):
        dt = t[k] - t[k - 1] if k > 0 else 0.0
        _frame(q[k], ok[k], t[k], dt, settings, state)
        _show(ok[k], t[k], horizon, scal, vel, base_q, out[k])


def _state(n_sensors: int, lags: int) -> State:
    S, D, M = n_sensors, 3 * lags, lags + 1
    scal = np.zeros((S, _NS))
    scal[:, _LAST_VALID] = np.nan
    return State(scal, np.zeros((S, M)), np.zeros((S, M, 4)), np.zeros((S, D, D)), np.zeros((S, D, 3)),
            np.zeros((S, 3)), np.zeros((S, 4)), np.zeros((S, PENDING)), np.zeros((S, PENDING, D)),
            np.zeros((S, PENDING, 4)), np.zeros((S, PENDING)), np.full((S, 4), np.nan))


class DirectStream(Stream):
    """The live ``direct``: learns at the predictor's ``horizon_s``; one compiled step per frame."""

    def __init__(self, predictor: DirectPredictor, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.state = _state(self.n_sensors, int(predictor.lags))
        self._kernel_state = tuple(self.state)  # the same arrays, as the kernels take them (docs/kernels.md)
        self.args = tuple(predictor._args(predictor.horizon_s))
        self.now: float | None = None
        self.ok = np.zeros(self.n_sensors, bool)
        self._frames = 0

    @property
    def restarts(self) -> int:
        return int(self.state.scal[:, _RESTARTS].sum())

    def update(self, q, valid=None, time=None):
        qs, ok = self._check_frame(q, valid)
        if time is None:
            t = self._frames / self.predictor.rate_hz
        else:
            t = float(time)
            if not np.isfinite(t) or (self.now is not None and not t > self.now):
                raise PredictorError(f"frame time {t!r} s does not come after the previous frame's ({self.now!r} s): "
                                     "feed frames in time order, without repeated time stamps")
        dt = 0.0 if self.now is None else t - self.now
        self._frames += 1
        self.now = t
        _frame(qs, ok, t, dt, self.args, self._kernel_state)
        self.ok, self.last = ok, qs

    def predict(self, horizon):
        d = float(check_horizons(horizon)[0])
        out = np.empty((self.n_sensors, 4))
        if self.now is None:
            out[:] = np.nan
            return out
        _show(self.ok, self.now, d, self.state.scal, self.state.vel, self.state.base_q, out)
        return out


@dataclass
class DirectPredictor(Predictor):
    """The h-step-ahead least-squares predictor learned online (module docstring)."""

    rate_hz: float = 120.0
    lags: int = LAGS
    memory_s: float = MEMORY_S
    prior: float = PRIOR
    floor: float = FLOOR
    horizon_s: float = 0.05  # the live form's learning horizon
    max_gap_s: float = MAX_GAP_S
    max_step_s: float = REFERENCE_MAX_STEP_S
    name: str = "direct"

    def __post_init__(self):
        self.rate_hz = check_rate(self.rate_hz)
        if not (isinstance(self.lags, int | np.integer) and 1 <= self.lags <= 32):
            raise PredictorError(f"direct's lags must be a whole number in 1-32, got {self.lags!r}")
        if not all(np.isfinite(v) and v > 0 for v in (self.memory_s, self.prior, self.floor, self.max_gap_s,
                                                        self.max_step_s)):
            raise PredictorError("direct's memory_s, prior, floor, max_gap_s and max_step_s must be positive numbers")
        self.horizon_s = float(check_horizons(self.horizon_s)[0])
        if self.horizon_s == 0.0:
            raise PredictorError("direct learns a turn over its horizon: horizon_s must be above 0 s")

    def _args(self, horizon: float) -> Settings:
        return Settings(horizon, self.memory_s, self.prior, self.floor, self.max_gap_s, self.max_step_s, int(self.lags))

    def predict(self, q, horizons, valid=None, time=None):
        h = check_horizons(horizons)
        qs, ok, single = check_stream(q, valid)
        F, S = ok.shape
        t = check_time(time, F, self.rate_hz)
        out = np.empty((len(h), F, S, 4))
        for i, d in enumerate(h):
            if d == 0.0:  # nothing to learn: the measurement, as the backward difference shows it at 0 s
                out[i] = np.where(ok[..., None], qs, np.nan)
                continue
            _run(qs, ok, t, tuple(self._args(float(d))), tuple(_state(S, int(self.lags))), out[i])
        return as_given(out, single)

    #: the live form, made by :meth:`stream`
    stream_type = DirectStream


def direct(rate_hz: float = 120.0, **kwargs) -> DirectPredictor:
    """The ``direct`` predictor with its defaults (module docstring) at ``rate_hz``."""
    return DirectPredictor(rate_hz, **kwargs)


__all__ = ["DirectPredictor", "DirectStream", "direct"]
