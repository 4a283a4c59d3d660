"""Linear per-axis predictors on orientation streams (Azuma & Bishop 1995; NASA 2001): polynomial, α-β, kinematic KF.

A&B95 linearise orientation into three independent small-angle signals. Here each frame's
rotation ``Δq(k) = q(k) ⊗ q(k−1)*`` is turned into a rotation vector and accumulated into
θ(k) (rad, reference frame, per axis); a linear predictor with steady-state recursion
``X(k) = G X(k−1) + K θ(k)`` predicts θ(k + p) = D(p) X(k), and the prediction is applied to
the measurement: ``q̂(k + p) = exp(D(p) X(k) − θ(k)) ⊗ q(k)``. Because the whole chain is
linear in θ, its frequency response is exactly :func:`ivc.predict.studies.frequency.response` of
(G, K, D), which the tests check against the time-domain output.

* ``polynomial``: x + v p (+ ½ a p²) with v, a from a least-squares fit to the last samples of θ;
* ``alpha-beta``: A&B's Case 1 (position-only steady-state KF, α = 0.568, β from Kalata's relation);
* ``kinematic``: NASA's 3-state [θ, ω, α] KF with noise on α only and Φᴺ extrapolation [1, p, p²/2].
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numba
import numpy as np
from scipy.signal import lfilter, ss2tf

from ivc import rotations
from ivc.predict.base import (
    MAX_HORIZON,
    FixedRatePredictor,
    FloatArray,
    PredictorError,
    Stream,
    StreamClock,
    TimedStepStream,
    as_given,
    check_horizons,
    check_rate,
)
from ivc.predict.delta import deltas
from ivc.predict.gains import kinematic_gain
from ivc.predict.linear_steps import ACCELERATION_NOISE, WHITE_ACCELERATION, steady_posterior
from ivc.predict.linear_steps import Config as StepsConfig
from ivc.predict.linear_steps import run_steps as _steps_run
from ivc.predict.linear_steps import show_frame as _steps_show
from ivc.predict.linear_steps import state as steps_state
from ivc.predict.linear_steps import step_frame as _steps_frame
from ivc.predict.quat import delta_q, qmul, qmul_conj, rate_of
from ivc.predict.timing import check_stream, check_time, repeats, restarts


@dataclass
class LinearPredictor(FixedRatePredictor):
    """Per-axis linear predictor: X(k) = G X(k−1) + K θ(k), θ̂(k + p) = D(p) X(k).

    The α-β and kinematic filters are steady-state designs at ``rate_hz`` (:class:`FixedRatePredictor`).
    A polynomial predictor (``order`` 1 or 2) instead fits its last ``window`` samples at their actual
    times, so it follows a stream's own time steps; on a uniform stream it is the same linear filter.
    """

    G: FloatArray
    K: FloatArray
    D: Callable[[float], FloatArray]
    rate_hz: float = 120.0
    name: str = "linear"
    order: int = 0  # 1 or 2 for a polynomial predictor, 0 otherwise
    #: the Kalman model (states, kind, noise, measurement variance) behind a steady-state design, to run it on a
    #: stream's own time steps (:mod:`ivc.predict.linear_steps`); None: the nominal step only
    model: tuple | None = None
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        self.rate_hz = check_rate(self.rate_hz)
        self.G = np.atleast_2d(np.asarray(self.G, float))
        self.K = np.asarray(self.K, float).reshape(-1)
        if self.G.shape != (self.K.size, self.K.size) or np.max(np.abs(np.linalg.eigvals(self.G))) >= 1.0:
            raise PredictorError("G must be square, match K and be stable (spectral radius < 1)")

    def transfer(self, horizon: float) -> tuple[FloatArray, FloatArray]:
        """(b, a) of the filter θ → θ̂(k + horizon), for lfilter."""
        if horizon not in self._cache:
            D = np.atleast_2d(self.D(horizon))
            # X(k) = G X(k−1) + K θ(k): state x'(k) = X(k−1), x'(k+1) = G x'(k) + K θ(k), out = D G x' + D K θ
            b, a = ss2tf(self.G, self.K[:, None], D @ self.G, D @ self.K[:, None])
            self._cache[horizon] = (np.real(b[0]), np.real(a))
        return self._cache[horizon]

    @staticmethod
    def angles(qs: FloatArray, ok: np.ndarray) -> FloatArray:
        """Accumulated rotation vector θ (F, S, 3) rad, from θ(0) = 0; an invalid frame adds no rotation."""
        filled = qs.copy()
        for k in np.nonzero(~np.all(ok, axis=1))[0]:  # rare: carry the last valid orientation forward
            bad = ~ok[k]
            filled[k, bad] = filled[k - 1, bad] if k else rotations.IDENTITY
        steps = rotations.to_rotvec(deltas(filled))
        return np.concatenate([np.zeros((1,) + steps.shape[1:]), np.cumsum(steps, axis=0)])

    def predict(self, q, horizons, valid=None, time=None):
        if not self.order:
            if self.model is None or time is None:
                return super().predict(q, horizons, valid, time)
            return self._predict_steps(q, horizons, valid, time)
        h = check_horizons(horizons)
        qs, ok, single = check_stream(q, valid)
        t = check_time(time, qs.shape[0], self.rate_hz)
        use = ok & ~repeats(qs, ok)
        segment = np.cumsum(restarts(t, ok, self.max_gap_s), axis=0)
        out = np.full((len(h),) + qs.shape, np.nan)
        window = self.K.size
        for s in range(qs.shape[1]):
            idx = np.flatnonzero(use[:, s])
            if len(idx) < window:
                continue
            seg = segment[idx, s]
            dq = rotations.multiply(qs[idx[1:], s], rotations.conjugate(qs[idx[:-1], s]))
            theta = np.concatenate([np.zeros((1, 3)), np.cumsum(rotations.to_rotvec(np.where(dq[:, :1] < 0, -dq, dq)),
                                                                axis=0)])
            ends = np.arange(window - 1, len(idx))
            rows = ends[:, None] - np.arange(window)[None, :]  # newest first
            whole = seg[rows[:, -1]] == seg[ends]  # the window lies within one stretch between gaps
            ends, rows = ends[whole], rows[whole]
            coef = polynomial_fit(t[idx[rows]] - t[idx[ends]][:, None], theta[rows], self.order)
            # every valid frame predicts from the latest accepted sample (itself, or the one it repeats)
            latest = np.maximum.accumulate(np.where(use[:, s], np.arange(len(t)), -1))
            frames = np.flatnonzero(ok[:, s] & (latest >= 0))
            pos = np.searchsorted(idx, latest[frames])
            fitted = np.full(len(idx), -1)
            fitted[ends] = np.arange(len(ends))
            has = (fitted[pos] >= 0) & (segment[frames, s] == seg[pos])
            frames, pos = frames[has], pos[has]
            c = coef[fitted[pos]]  # (n, order + 1, 3)
            age = t[frames] - t[idx[pos]]
            for i, d in enumerate(h):
                p = (d + age)[:, None] ** np.arange(self.order + 1)[None, :]
                ahead = np.einsum("nj,njc->nc", p, c) - theta[pos]
                out[i, frames, s] = rotations.multiply(rotations.from_rotvec(ahead), qs[idx[pos], s])
        return as_given(out, single)

    def _predict_uniform(self, qs, horizons, ok):
        h = check_horizons(horizons)
        theta = self.angles(qs, ok)
        out = []
        for d in h:
            b, a = self.transfer(d)
            ahead = lfilter(b, a, theta, axis=0) - theta
            out.append(rotations.multiply(rotations.from_rotvec(ahead), qs))
        out = np.stack(out)
        out[:, ~ok] = np.nan
        return out

    def _steps_config(self) -> StepsConfig:
        n, kind, noise, R = self.model
        T = 1.0 / self.rate_hz
        return StepsConfig(int(n), int(kind), float(noise), float(R), T, steady_posterior(n, kind, noise, R, T))

    def _predict_steps(self, q, horizons, valid, time):
        """The time-varying Kalman filter of the design's model at the stream's own steps (linear_steps)."""
        h = check_horizons(horizons)
        qs, ok, single = check_stream(q, valid)
        F, S = ok.shape
        t = check_time(time, F, self.rate_hz)
        use = ok & ~repeats(qs, ok)
        cfg = self._steps_config()
        out = np.empty((len(h), F, S, 4))
        _steps_run(qs, ok, use, restarts(t, ok, self.max_gap_s), t, h, tuple(cfg), tuple(steps_state(S, cfg.n)), out)
        return as_given(out, single)

    def stream(self, n_sensors: int = 1) -> Stream:
        if self.order:
            return PolynomialStream(self, n_sensors)
        return StepLinearStream(self, n_sensors) if self.model is not None else super().stream(n_sensors)

    def _stream_uniform(self, n_sensors: int) -> LinearStream:
        return LinearStream(self, n_sensors)


def polynomial_fit(times: FloatArray, theta: FloatArray, order: int) -> FloatArray:
    """Least-squares polynomial coefficients (n, order + 1, 3) of θ (n, w, 3) at ``times`` (n, w) s, lowest first."""
    V = times[..., None] ** np.arange(order + 1)  # (n, w, order + 1)
    if V.shape[1] == order + 1:  # as many samples as coefficients: the interpolating polynomial
        return np.linalg.solve(V, theta)
    return np.linalg.solve(np.einsum("nwi,nwj->nij", V, V), np.einsum("nwi,nwc->nic", V, theta))


@numba.njit(cache=True)
def _solve_small(A, b, n):
    """b := A⁻¹ b for an n x n (n <= 3) symmetric positive definite A, by Gaussian elimination (in place)."""
    for i in range(n):
        for r in range(i + 1, n):
            f = A[r, i] / A[i, i]
            for c in range(i, n):
                A[r, c] -= f * A[i, c]
            for k in range(3):
                b[r, k] -= f * b[i, k]
    for i in range(n - 1, -1, -1):
        for k in range(3):
            acc = b[i, k]
            for c in range(i + 1, n):
                acc -= A[i, c] * b[c, k]
            b[i, k] = acc / A[i, i]


@numba.njit(cache=True)
def _poly_update(qs, new, now, theta, times, count, base, coef, order):
    """Push each new sample into its sensor's window (newest first) and refit the polynomial where it is full."""
    S, w = times.shape
    dq = np.empty(4)
    step = np.empty(3)
    A = np.empty((3, 3))
    for s in range(S):
        if not new[s]:
            continue
        if count[s] > 0:
            qmul_conj(qs[s], base[s], dq)
            if dq[0] < 0.0:
                for i in range(4):
                    dq[i] = -dq[i]
            rate_of(dq, 1.0, step)
        for j in range(w - 1, 0, -1):
            times[s, j] = times[s, j - 1]
            for k in range(3):
                theta[s, j, k] = theta[s, j - 1, k]
        times[s, 0] = now
        for k in range(3):
            theta[s, 0, k] = theta[s, 1, k] + step[k] if count[s] > 0 else 0.0
        for i in range(4):
            base[s, i] = qs[s, i]
        count[s] += 1
        if count[s] < w:
            continue
        n = order + 1
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for m in range(w):
                    acc += (times[s, m] - now) ** (i + j)
                A[i, j] = acc
            for k in range(3):
                acc = 0.0
                for m in range(w):
                    acc += (times[s, m] - now) ** i * theta[s, m, k]
                coef[s, i, k] = acc
        _solve_small(A, coef[s], n)


@numba.njit(cache=True)
def _poly_predict(base, theta, times, coef, ok, now, delta, order, out):
    """exp(x̂(δ + age) − θ) ⊗ base per sensor, NaN where ``ok`` is False."""
    step = np.empty(3)
    dq = np.empty(4)
    for s in range(base.shape[0]):
        if not ok[s]:
            out[s, :] = np.nan
            continue
        p = delta + now - times[s, 0]
        for k in range(3):
            acc = 0.0
            for i in range(order + 1):
                acc += coef[s, i, k] * p**i
            step[k] = acc - theta[s, 0, k]
        delta_q(step[0], step[1], step[2], 1.0, dq)
        qmul(dq, base[s], out[s])


class PolynomialStream(Stream):
    """The live polynomial predictor: the last ``window`` accepted samples of each sensor at their times."""

    def __init__(self, predictor: LinearPredictor, n_sensors: int):
        super().__init__(predictor, n_sensors)
        w = predictor.K.size
        self.window = w
        self.clock = StreamClock(predictor.rate_hz, n_sensors)
        self.theta = np.zeros((n_sensors, w, 3))  # newest first
        self.times = np.zeros((n_sensors, w))
        self.count = np.zeros(n_sensors, np.int64)  # accepted samples since the start or the last gap
        self.base = np.full((n_sensors, 4), np.nan)  # the latest accepted sample
        self.previous = np.full((n_sensors, 4), np.nan)  # the latest valid sample
        self.coef = np.zeros((n_sensors, predictor.order + 1, 3))
        self.ok = np.zeros(n_sensors, bool)

    def update(self, q, valid=None, time=None):
        qs, ok = self._check_frame(q, valid)
        gap = self.clock.advance(time, ok, self.predictor.max_gap_s)
        now = self.clock.now
        if gap.any():
            self.restarts += int(gap.sum())
            self.count[gap] = 0
        new = ok & ~np.all(qs == self.previous, axis=1)
        self.previous = np.where(ok[:, None], qs, self.previous)
        _poly_update(qs, new, now, self.theta, self.times, self.count, self.base, self.coef, self.predictor.order)
        self.ok = ok & (self.count >= self.window)
        self.last = qs

    def predict(self, horizon):
        d = float(horizon)
        if not 0.0 <= d <= MAX_HORIZON:
            check_horizons(horizon)
        out = np.empty((self.n_sensors, 4))
        _poly_predict(self.base, self.theta, self.times, self.coef, self.ok, self.clock.now, d,
                      self.predictor.order, out)
        return out


class LinearStream(Stream):
    """The steady-state filter at the nominal rate (the inner stream of :class:`FixedRateStream`)."""

    def __init__(self, predictor: LinearPredictor, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.X = np.zeros((n_sensors, predictor.K.size, 3))
        self.theta = np.zeros((n_sensors, 3))
        self.started = np.zeros(n_sensors, bool)
        self.ok = np.zeros(n_sensors, bool)

    def update(self, q, valid=None, time=None):
        qs, ok = self._check_frame(q, valid)
        step = np.zeros((self.n_sensors, 3))
        moving = ok & self.started
        if np.any(moving):
            dq = rotations.multiply(qs[moving], rotations.conjugate(self.last[moving]))
            step[moving] = rotations.to_rotvec(np.where(dq[:, :1] < 0, -dq, dq))
        self.theta += step
        p = self.predictor
        self.X = np.einsum("ij,sjc->sic", p.G, self.X) + p.K[None, :, None] * self.theta[:, None, :]
        self.last = np.where(ok[:, None], qs, self.last)
        self.started |= ok
        self.ok = ok

    def predict(self, horizon):
        d = float(check_horizons(horizon)[0])
        D = np.atleast_2d(self.predictor.D(d))[0]
        ahead = np.einsum("i,sic->sc", D, self.X) - self.theta
        out = rotations.multiply(rotations.from_rotvec(ahead), self.last)
        out[~self.ok] = np.nan
        return out


class StepLinearStream(TimedStepStream):
    """The live α-β or kinematic filter: fed time stamps, on the actual steps (:mod:`ivc.predict.linear_steps`);
    fed none (decided at the first frame), the steady-state filter at the nominal rate, as the batch without times."""

    def __init__(self, predictor: LinearPredictor, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.cfg = predictor._steps_config()
        self.state = steps_state(self.n_sensors, self.cfg.n)
        self._kernel_args = tuple(self.cfg), tuple(self.state)  # as the kernels take them (docs/kernels.md)

    def _step(self, qs, ok, new, gap, now):
        _steps_frame(qs, ok, new, gap, now, *self._kernel_args)

    def _show(self, horizon):
        out = np.empty((self.n_sensors, 4))
        x, _, theta, base, scal = self.state
        _steps_show(self.ok, self.clock.now if self.clock.now is not None else 0.0, horizon, self.cfg.n, x, theta,
                    base, scal, out)
        return out


def polynomial(rate_hz: float = 120.0, order: int = 2, window: int | None = None) -> LinearPredictor:
    """x + v p (+ ½ a p²), A&B's polynomial predictor with derivatives estimated from the stream.

    The derivatives at the latest frame are those of the least-squares polynomial of ``order``
    through the last ``window`` samples (a Savitzky-Golay differentiator). ``window = order + 1``
    interpolates exactly: for order 1 that is the backward difference v = (θ(k) − θ(k−1))/T.
    Defaults: 2 samples for order 1; for order 2, the samples of the last 0.1 s (12 at 120 Hz),
    since the exact three-point parabola multiplies white tracker noise by about 60 at 50 ms
    (the norm of its coefficients; 3.4 with 12 samples).
    """
    if order not in (1, 2):
        raise PredictorError(f"polynomial order is 1 or 2, got {order}")
    rate_hz = check_rate(rate_hz)
    T = 1.0 / rate_hz
    default = 2 if order == 1 else max(3, round(0.1 * rate_hz))
    window = default if window is None else window
    if int(window) != window or window < order + 1:
        raise PredictorError(f"a polynomial of order {order} needs a window of at least {order + 1} samples, "
                             f"got {window}")
    window = int(window)
    G = np.eye(window, k=-1)  # shift register [θ(k), θ(k−1), …, θ(k−window+1)]
    K = np.zeros(window)
    K[0] = 1.0
    times = -T * np.arange(window)  # s, relative to the latest sample
    fit = np.linalg.pinv(np.vander(times, order + 1, increasing=True))  # samples -> [x, v, a/2 (…)]

    def D(p):
        return (float(p) ** np.arange(order + 1)) @ fit

    name = f"poly{order}" if window == default else f"poly{order}-w{window}"
    return LinearPredictor(G, K, D, rate_hz, name=name, order=order)


def alpha_beta(rate_hz: float = 120.0, alpha: float = 0.568) -> LinearPredictor:
    """A&B95 Case 1: steady-state α-β filter (β by Kalata's relation for white acceleration), D = [1, p]."""
    if not 0 < alpha < 1:
        raise PredictorError(f"alpha must be in (0, 1), got {alpha}")
    T = 1.0 / rate_hz
    beta = 2 * (2 - alpha) - 4 * np.sqrt(1 - alpha)
    K = np.array([alpha, beta / T])
    A = np.array([[1.0, T], [0, 1]])
    G = A - np.outer(K, [1.0, 0]) @ A
    # the white-acceleration model whose steady state this is: λ² = β² / (1 − α), σ_w² = λ² σ_v² / T⁴ (σ_v = 1)
    model = (2, WHITE_ACCELERATION, beta**2 / (1 - alpha) / T**4, 1.0)
    return LinearPredictor(G, K, lambda p: np.array([1.0, p]), rate_hz, name="alpha-beta", model=model)


def kinematic(rate_hz: float = 120.0, w_a: float = 100.0, v: float = 1e-6) -> LinearPredictor:
    """NASA's 3-state kinematic KF per axis (noise density w_a on α, measurement variance v) with Φᴺ prediction."""
    if not (w_a > 0 and v > 0):
        raise PredictorError("w_a and v must be positive")
    h = 1.0 / rate_hz
    A = np.array([[1.0, h, h * h / 2], [0, 1, h], [0, 0, 1]])
    K = kinematic_gain(h, w_a, v)[:, 0]
    G = A - np.outer(K, [1.0, 0, 0]) @ A
    return LinearPredictor(G, K, lambda p: np.array([1.0, p, p * p / 2]), rate_hz, name="kinematic",
                           model=(3, ACCELERATION_NOISE, w_a, v))
