"""Synthetic head motion for evaluating predictors (docs/math.md §14.2-§14.3).

Motion is a sequence of minimum-jerk rotations about random axes with holds between them,
composed in the reference frame. Axis weights are 1 : 0.6 : 0.3 on the x, y, z components
(the order of Table 10's σ_w, the thesis's azimuth, elevation, roll). Moves that would take
the head more than ``reach`` rad (69°) from its rest orientation are redrawn or turned back
(the thesis's subjects looked around a cockpit; it also keeps Euler angles far from gimbal lock). Categories
(mean speed A/T in rad/s, move time T and hold in s) are calibrated to the thesis's Table 7:

* ``benign``: slow drifts with velocity jitter and rare small twitches;
* ``moderate`` and ``aggressive``: continuous scanning / tracking;
* ``full``: a regime-switching mix (about 35 % benign, 50 % moderate, 15 % aggressive) with
  short violent bursts (Table 7 "Motion 0/1", Table 8).

The noise model (docs/math.md §14.3) is white rotation-vector noise (rad, per axis) plus an optional slow
AR(1) error proportional to the angular speed (the "dynamic error" in the thesis's R).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from ivc import rotations
from ivc.errors import InputError
from ivc.predict.quat import delta_q, normalise, qmul

FloatArray = NDArray[np.float64]

MOTIONS = ("benign", "moderate", "aggressive", "full")
AXIS_WEIGHTS = np.array([1.0, 0.6, 0.3])
#: white rotation noise per axis (rad), in the range of docs/math.md §14.3 (0.9e-4 to 3.1e-4). The Δq noise it
#: gives is σ/√2 per axis, [1.56e-4, 6.4e-5, 6.4e-5]: Table 3's DQ values on the 2nd and 3rd axes, 0.71 x
#: eq. 67's on all three (√2 x eq. 67, the top of the range, would match eq. 67 itself)
NOISE_RAD = (2.2e-4, 0.9e-4, 0.9e-4)
#: slow error per unit angular speed (rad per rad/s), AR(1) with φ = 0.99
DYNAMIC_ERROR = 2e-4


@dataclass(frozen=True)
class Category:
    """Move statistics: mean speed A/T (rad/s), duration T (s), hold (s), each a uniform range."""

    speed: tuple[float, float]
    duration: tuple[float, float]
    hold: tuple[float, float]
    jitter: float = 0.0  # AR(1) velocity jitter, rad/s per step (φ = 0.9)
    twitch_rate: float = 0.0  # small fast moves per second


CATEGORIES = {
    "benign": Category((0.01, 0.03), (1.0, 2.0), (6.0, 12.0), jitter=2.5e-4, twitch_rate=0.05),
    "moderate": Category((0.25, 0.40), (0.8, 2.6), (0.0, 0.3)),
    "aggressive": Category((0.8, 1.6), (0.45, 1.2), (0.0, 0.15)),
}
#: short violent moves of the full-range mix: amplitude (rad) and duration (s)
BURST_AMPLITUDE, BURST_DURATION = (0.04, 0.10), (0.2, 0.4)


@dataclass
class HeadMotion:
    """A synthetic recording: measured and true orientations (F, 4), true angular velocity (F, 3) rad/s."""

    motion: str
    rate_hz: float
    measured: FloatArray
    truth: FloatArray
    omega: FloatArray

    @property
    def time(self) -> FloatArray:
        return np.arange(len(self.truth)) / self.rate_hz


@numba.njit(cache=True)
def _integrate(omega, tau, q0, out):
    """out[k+1] = Δq(ω_k, τ) ⊗ out[k]: ω_k is the mean angular velocity over frame k."""
    out[0] = q0
    dq = np.empty(4)
    for k in range(omega.shape[0] - 1):
        delta_q(omega[k, 0], omega[k, 1], omega[k, 2], tau, dq)
        qmul(dq, out[k], out[k + 1])
        normalise(out[k + 1])


def _axis(rng: np.random.Generator, current: FloatArray, amplitude: float,
          reach: float) -> tuple[FloatArray, float]:
    """A random move axis (weighted 1 : 0.6 : 0.3) and amplitude that keep the head within ``reach`` rad of rest.

    ``current`` is the head's orientation (quaternion) before the move.
    """
    amplitude = min(amplitude, reach)
    for _ in range(10):
        a = rng.standard_normal(3) * AXIS_WEIGHTS
        a /= np.linalg.norm(a)
        for candidate in (a, -a):
            after = rotations.multiply(rotations.from_rotvec(amplitude * candidate), current)
            if rotations.angle(after) <= reach:
                return candidate, amplitude
    home = -rotations.to_rotvec(current)  # nothing fits: turn back towards rest
    size = np.linalg.norm(home)
    return home / size, min(amplitude, size)


def _minimum_jerk(n: int) -> FloatArray:
    s = np.linspace(0.0, 1.0, n + 1)
    return 10 * s**3 - 15 * s**4 + 6 * s**5


def _moves(rng, category: Category, n_frames: int, tau: float, reach: float,
           current: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per-frame angular velocity (n_frames, 3) of one category's move/hold sequence, and the final orientation."""
    omega = np.zeros((n_frames, 3))
    k = int(rng.uniform(*category.hold) / tau * rng.random())
    while k < n_frames:
        twitch = category.twitch_rate > 0 and rng.random() < category.twitch_rate * 8.0
        duration = rng.uniform(0.25, 0.35) if twitch else rng.uniform(*category.duration)
        amplitude = 0.006 if twitch else rng.uniform(*category.speed) * duration
        n = max(2, int(round(duration / tau)))
        if k + n > n_frames:  # only whole moves: a cut move would be a velocity step
            break
        axis, amplitude = _axis(rng, current, amplitude, reach)
        omega[k:k + n] += (amplitude * np.diff(_minimum_jerk(n)) / tau)[:, None] * axis
        current = rotations.multiply(rotations.from_rotvec(amplitude * axis), current)
        k += n + int(round(rng.uniform(*category.hold) / tau))
    return omega, current


def _jitter(rng, n_frames: int, sigma: float) -> FloatArray:
    """AR(1) velocity jitter (φ = 0.9), σ rad/s per step, weighted like the move axes."""
    noise = rng.standard_normal((n_frames, 3)) * sigma * AXIS_WEIGHTS
    return lfilter([1.0], [1.0, -0.9], noise, axis=0)


def _full(rng, n_frames: int, tau: float, reach: float) -> FloatArray:
    omega = np.zeros((n_frames, 3))
    k = 0
    current = rotations.IDENTITY
    names, weights = ("benign", "moderate", "aggressive"), (0.35, 0.50, 0.15)
    while k < n_frames:
        name = names[rng.choice(3, p=weights)]
        n = min(int(rng.uniform(2.0, 8.0) / tau), n_frames - k)
        omega[k:k + n], current = _category_omega(rng, name, n, tau, reach, current)
        k += n
    bursts = rng.poisson(n_frames * tau / 6.0)
    for start in rng.integers(0, n_frames, bursts):
        n = max(2, int(rng.uniform(*BURST_DURATION) / tau))
        if start + n <= n_frames:
            axis, amplitude = _axis(rng, rotations.IDENTITY, rng.uniform(*BURST_AMPLITUDE), reach)
            profile = amplitude * np.diff(_minimum_jerk(n)) / tau
            omega[start:start + n] += profile[:, None] * axis
    return omega


def _category_omega(rng, name: str, n_frames: int, tau: float, reach: float,
                    current: FloatArray) -> tuple[FloatArray, FloatArray]:
    category = CATEGORIES[name]
    omega, current = _moves(rng, category, n_frames, tau, reach, current)
    if category.jitter:
        omega += _jitter(rng, n_frames, category.jitter)
    return omega, current


def head_motion(motion: str = "moderate", n_frames: int = 12_000, rate_hz: float = 120.0, seed: int = 0,
                noise_rad: tuple[float, float, float] | None = NOISE_RAD, dynamic_error: float = DYNAMIC_ERROR,
                reach: float = 1.2) -> HeadMotion:
    """A synthetic head-orientation recording of ``motion`` (one of :data:`MOTIONS`) at ``rate_hz``.

    ``noise_rad=None`` and ``dynamic_error=0`` give a noiseless recording (measured = truth).
    """
    if motion not in MOTIONS:
        raise InputError(f"motion is one of {', '.join(MOTIONS)}, got {motion!r}")
    if n_frames < 2 or rate_hz <= 0:
        raise InputError(f"need n_frames >= 2 and rate_hz > 0, got {n_frames}, {rate_hz}")
    rng = np.random.default_rng(seed)
    tau = 1.0 / rate_hz
    if motion == "full":
        omega = _full(rng, n_frames, tau, reach)
    else:
        omega, _ = _category_omega(rng, motion, n_frames, tau, reach, rotations.IDENTITY)
    truth = np.empty((n_frames, 4))
    _integrate(omega, tau, rotations.IDENTITY, truth)
    measured = truth
    error = np.zeros((n_frames, 3))
    if noise_rad is not None:
        error += rng.standard_normal((n_frames, 3)) * np.asarray(noise_rad, dtype=float)
    if dynamic_error:
        phi = 0.99
        speed = np.linalg.norm(omega, axis=1, keepdims=True)
        drive = rng.standard_normal((n_frames, 3)) * np.sqrt(1 - phi**2) * dynamic_error * speed
        error += lfilter([1.0], [1.0, -phi], drive, axis=0)
    if np.any(error):
        measured = rotations.multiply(rotations.from_rotvec(error), truth)
    return HeadMotion(motion, rate_hz, measured, truth, omega)


def statistics(omega: FloatArray, rate_hz: float) -> dict[str, float]:
    """|ω| and |α| = |Δω|/τ statistics (rad/s, rad/s²) in the layout of Table 7."""
    speed = np.linalg.norm(omega, axis=1)
    accel = np.linalg.norm(np.diff(omega, axis=0), axis=1) * rate_hz
    return {"omega_mean": speed.mean(), "omega_std": speed.std(), "omega_max": speed.max(),
            "alpha_mean": accel.mean(), "alpha_std": accel.std(), "alpha_max": accel.max()}
