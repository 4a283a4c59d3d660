"""The α-β and kinematic filters (:mod:`ivc.predict.linear`) on a stream's actual time steps.

Both are steady-state Kalman filters of one rate: A&B95's Case 1 α-β filter is the steady state of a
2-state [θ, ω] filter with piecewise-constant white acceleration (Kalata's tracking index
λ² = β² / (1 − α), process noise σ_w² [h²/2, h][h²/2, h]ᵀ with σ_w² = λ² σ_v² / T⁴), NASA's
kinematic filter that of a 3-state [θ, ω, α] filter with noise w_a on α per nominal step T. On a
stream with time stamps they run as the time-varying Kalman filter of the same model: each step
propagates over its actual h (A(h), Q(h); the kinematic filter's noise scaled by h / T), started at
the steady-state covariance of the nominal rate, so that at steps of exactly T they are the
steady-state filters (to rounding). Per axis of the accumulated rotation vector θ (reference frame),
as the steady-state forms; exact repeats are dropped and predicted from the sample they repeat, as
old as it is; a gap longer than ``max_gap_s`` restarts the filter (θ from 0 at the next sample).
"""

from __future__ import annotations

from collections import namedtuple

import numba
import numpy as np
from scipy.linalg import solve_discrete_are

from ivc.predict.quat import delta_q, qmul, qmul_conj, rate_of

#: the models: the α-β filter's (white acceleration per step) and the kinematic filter's (noise on α)
WHITE_ACCELERATION, ACCELERATION_NOISE = 0, 1
#: A filter's configuration: states ``n`` (2 or 3), the model ``kind``, its ``noise``, the measurement variance
#: ``R``, the nominal step ``T`` s and the starting covariance ``P0`` (n, n) (:func:`steady_posterior`)
Config = namedtuple("Config", "n kind noise R T P0")
#: Every sensor's state (:func:`state`): ``x`` (S, n, 3), ``P`` (S, n, n), ``theta`` (S, 3), ``base`` (S, 4) and
#: ``scal`` (S, 2) = [started, time of the latest usable sample]
State = namedtuple("State", "x P theta base scal")


def transition(n: int, h: float) -> np.ndarray:
    A = np.eye(n)
    A[0, 1] = h
    if n == 3:
        A[0, 2], A[1, 2] = h * h / 2, h
    return A


def process_noise(n: int, kind: int, noise: float, h: float, T: float) -> np.ndarray:
    if kind == WHITE_ACCELERATION:
        g = np.array([h * h / 2, h])
        return noise * np.outer(g, g)
    Q = np.zeros((n, n))
    Q[n - 1, n - 1] = noise * h / T
    return Q


def steady_posterior(n: int, kind: int, noise: float, R: float, T: float) -> np.ndarray:
    """The steady-state covariance (n, n) after an update, at steps of T."""
    A, Q, H = transition(n, T), process_noise(n, kind, noise, T, T), np.eye(1, n)
    prior = solve_discrete_are(A.T, H.T, Q, np.array([[R]]))
    K = prior @ H.T / (H @ prior @ H.T + R)
    return (np.eye(n) - K @ H) @ prior


@numba.njit(cache=True)
def step_frame(q, ok, use, restart, now, config, state):
    """One frame for every sensor (``config`` a :data:`Config`, ``state`` a :data:`State`)."""
    n, kind, noise, R, T, P0 = config
    x, P, theta, base, scal = state
    S = q.shape[0]
    A = np.zeros((n, n))
    Q = np.zeros((n, n))
    d = np.empty(4)
    step = np.empty(3)
    for s in range(S):
        if not ok[s]:
            continue
        if restart[s]:
            scal[s, 0] = 0.0
        if not use[s]:
            continue
        if scal[s, 0] == 0.0:
            theta[s, :] = 0.0
            x[s, :, :] = 0.0
            P[s, :, :] = P0
            scal[s, 0] = 1.0
        else:
            qmul_conj(q[s], base[s], d)
            if d[0] < 0.0:
                for i in range(4):
                    d[i] = -d[i]
            rate_of(d, 1.0, step)
            for c in range(3):
                theta[s, c] += step[c]
            h = now - scal[s, 1]
            for i in range(n):
                for j in range(n):
                    A[i, j] = 1.0 if i == j else 0.0
                    Q[i, j] = 0.0
            A[0, 1] = h
            if n == 3:
                A[0, 2] = h * h / 2
                A[1, 2] = h
            if kind == 0:
                g0, g1 = h * h / 2, h
                Q[0, 0], Q[0, 1], Q[1, 0], Q[1, 1] = noise * g0 * g0, noise * g0 * g1, noise * g0 * g1, noise * g1 * g1
            else:
                Q[n - 1, n - 1] = noise * h / T
            Pp = A @ P[s] @ np.ascontiguousarray(A.T) + Q
            gain = Pp[:, 0] / (Pp[0, 0] + R)
            xp = A @ np.ascontiguousarray(x[s])
            for c in range(3):
                r = theta[s, c] - xp[0, c]
                for i in range(n):
                    x[s, i, c] = xp[i, c] + gain[i] * r
            for i in range(n):
                for j in range(n):
                    P[s, i, j] = Pp[i, j] - gain[i] * Pp[0, j]
        scal[s, 1] = now
        for i in range(4):
            base[s, i] = q[s, i]


@numba.njit(cache=True)
def show_frame(ok, now, horizon, n, x, theta, base, scal, out):
    """out (S, 4) = exp(D(horizon + age) x − θ) ⊗ base; NaN where not ok or not started."""
    dq = np.empty(4)
    for s in range(ok.shape[0]):
        if not (ok[s] and scal[s, 0] > 0.0):
            out[s, :] = np.nan
            continue
        p = horizon + now - scal[s, 1]
        v = np.empty(3)
        for c in range(3):
            v[c] = x[s, 0, c] + p * x[s, 1, c] - theta[s, c]
            if n == 3:
                v[c] += 0.5 * p * p * x[s, 2, c]
        delta_q(v[0], v[1], v[2], 1.0, dq)
        qmul(dq, base[s], out[s])


@numba.njit(cache=True)
def run_steps(q, ok, use, restart, t, horizons, config, state, out):
    """The batch: every frame through :func:`step_frame`, then :func:`show_frame` at each horizon into out
    (H, F, S, 4)."""
    n, kind, noise, R, T, P0 = config
    x, P, theta, base, scal = state
    for k in range(q.shape[0]):
        step_frame(q[k], ok[k], use[k], restart[k], t[k], config, state)
        for i in range(horizons.shape[0]):
            show_frame(ok[k], t[k], horizons[i], n, x, theta, base, scal, out[i, k])


def state(n_sensors: int, n: int) -> State:
    """The :data:`State` of ``n_sensors``."""
    return State(np.zeros((n_sensors, n, 3)), np.zeros((n_sensors, n, n)), np.zeros((n_sensors, 3)),
            np.zeros((n_sensors, 4)), np.zeros((n_sensors, 2)))
