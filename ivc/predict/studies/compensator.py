"""The predictive-compensator optimisation of Adelstein, Jung & Ellis 2001 (docs/math.md §17.3).

The design parameter is the 10-state EKF's diagonal process noise W_r (:mod:`ivc.predict.nasa`).
Powell's method (scipy) tunes its logarithm against one of two costs, at τ = 50 ms:

- **twist** (eqs. 21-23): the rms angle between the recorded and the predicted orientation;
- **hybrid** (eq. 27): tracking (the rms displacement of a target 0.8 m ahead, horizontal and
  vertical, eqs. 24-25) plus noise (the same displacement produced by the predictor fed a
  high-passed still record, eq. 26), each divided by its value for the default W_r.

Conventions (docs/math.md §17.3): errors are in the HMD frame, q_Δ = q_p⁻¹ ⊗ q_a; the
displacement is Δr = q_Δ ⊗ r ⊗ q_Δ* − r with r = (0.8, 0, 0) m (HMD x forward, y horizontal,
z vertical); the twist is 2·acos(min(1, |q_Δw|)); "RMS" includes the 1/N. The evaluation is the
offline protocol of Table 1: the predictor sees the record up to frame k and its N-step
prediction is compared with frame k + N; the baseline is frame k itself (the delayed measurement).

The paper's records (a subject yawing to an 80 beat/min metronome; the same subject sitting
still) are not available: :func:`yaw_records` synthesises them, 0.67 Hz yaw plus ~5 Hz
mostly-pitch physiological tremor plus sensor noise (docs/math.md §17.4).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import optimize, signal

from ivc import rotations
from ivc.errors import InputError
from ivc.predict.nasa import DEFAULT_W, NasaEKF

#: the target: 0.8 m in front of the HMD (x forward, y horizontal, z vertical)
TARGET_M = np.array([0.8, 0.0, 0.0])
HORIZON_S = 0.05
#: the high-pass filter of the noise record: H(s) = s² / ((s + 2π·0.5)(s + 2π·5)) (docs/math.md §17.3)
HPF_CORNERS_HZ = (0.5, 5.0)
#: NASA's Table 1 (ratios at 50 ms): twist, horizontal and vertical displacement, horizontal and
#: vertical noise
PAPER_TABLE1 = {"default": (0.181, 0.161, 1.047, 2.250, 2.251), "twist": (0.135, 0.104, 0.934, 2.703, 1.993),
                "hybrid": (0.457, 0.108, 1.041, 2.449, 1.043)}
COLUMNS = ("twist", "disp. horizontal", "disp. vertical", "noise horizontal", "noise vertical")
WARMUP_S = 1.0
#: log10 W_r is kept in these ranges by the optimiser: q (a unit quaternion's components), ω, α
LOG_W_BOUNDS = ((-16.0, -2.0),) * 4 + ((-16.0, 2.0),) * 3 + ((-16.0, 4.0),) * 3


@dataclass
class YawRecords:
    """``tracking``: the yaw task as measured (F, 4); ``still``: sitting still, high-passed (F, 4)."""

    tracking: np.ndarray
    still: np.ndarray
    rate_hz: float


def high_pass(q: np.ndarray, rate_hz: float) -> np.ndarray:
    """The record's rotation vectors about its mean orientation, each high-passed causally by
    H(s) = s² / ((s + 2π·0.5)(s + 2π·5)) (bilinear transform), as orientations about the identity."""
    reference = rotations.mean(q)
    v = rotations.to_rotvec(rotations.multiply(rotations.conjugate(reference), q))
    p1, p2 = (2 * np.pi * f for f in HPF_CORNERS_HZ)
    b, a = signal.bilinear([1.0, 0.0, 0.0], [1.0, p1 + p2, p1 * p2], fs=rate_hz)
    return rotations.from_rotvec(signal.lfilter(b, a, v, axis=0))


def yaw_records(seconds: float = 20.0, rate_hz: float = 120.0, seed: int = 0, yaw_rad: float = 0.5,
                pitch_rad: float = 0.08, tremor_rad: tuple[float, float] = (1.5e-3, 0.4e-3), tremor_hz: float = 5.0,
                noise_rad: float = 2e-4) -> YawRecords:
    """Synthetic stand-ins for the paper's records: side-to-side yaw at 0.67 Hz (±``yaw_rad``) with the
    head dipping by ``pitch_rad`` at each side (pitch at twice the yaw frequency), physiological
    tremor near ``tremor_hz`` (pitch, yaw amplitudes) and white sensor noise; and a still record
    (tremor and noise only), high-passed."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * rate_hz)) / rate_hz

    def tremor() -> np.ndarray:  # narrow-band: a 5 Hz carrier with a slowly wandering phase and amplitude
        phase = np.cumsum(rng.normal(0.0, 0.15, (len(t), 2)), axis=0)
        envelope = 1.0 + 0.3 * np.sin(2 * np.pi * 0.3 * t[:, None] + rng.uniform(0, 2 * np.pi, 2))
        return np.asarray(tremor_rad) * envelope * np.sin(2 * np.pi * tremor_hz * t[:, None] + phase)

    def record(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
        pitch_yaw = tremor()
        rotvec = np.zeros((len(t), 3))
        rotvec[:, 1] = pitch + pitch_yaw[:, 0]
        rotvec[:, 2] = yaw + pitch_yaw[:, 1]
        noise = rotations.from_rotvec(rng.normal(0.0, noise_rad, (len(t), 3)))
        return rotations.multiply(rotations.from_rotvec(rotvec), noise)

    side = 2 * np.pi * 0.67 * t
    tracking = record(yaw_rad * np.sin(side), pitch_rad * np.sin(side) ** 2)
    still = record(np.zeros_like(t), np.zeros_like(t))
    return YawRecords(tracking, high_pass(still, rate_hz), rate_hz)


def displacement(actual: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Δr (..., 3) m of the target, in the HMD frame, for the error q_Δ = q_p⁻¹ ⊗ q_a (eq. 24 corrected)."""
    error = rotations.multiply(rotations.conjugate(predicted), actual)
    return rotations.rotate(error, TARGET_M) - TARGET_M


def twist(actual: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Δθ (rad) between actual and predicted orientations (eq. 22 with |q_Δw| clipped to 1)."""
    w = np.abs(rotations.multiply(rotations.conjugate(predicted), actual)[..., 0])
    return 2.0 * np.arccos(np.minimum(1.0, w))


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def _predicted(W: np.ndarray, q: np.ndarray, rate_hz: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(actual x(k + N), predicted x̂(k + N | k)) over the frames after the warm-up; diverged filters
    give NaN predictions, which the costs turn into +inf."""
    predicted = NasaEKF(rate_hz, tuple(W)).predict(q, steps / rate_hz)[0]
    start = int(WARMUP_S * rate_hz)
    return q[start + steps:], predicted[start:len(q) - steps]


@dataclass
class Scores:
    """One design's costs on the records: twist rms (rad), displacement rms (m: horizontal, vertical)
    of tracking, and of the still record's noise, with the no-prediction baselines."""

    twist: float
    tracking: tuple[float, float]
    noise: tuple[float, float]
    base_twist: float
    base_tracking: tuple[float, float]
    base_noise: tuple[float, float]

    @property
    def ratios(self) -> tuple[float, ...]:
        """Table 1's five ratios: prediction against no prediction (< 1: prediction helps)."""
        return (self.twist / self.base_twist, *(a / b for a, b in zip(self.tracking, self.base_tracking, strict=True)),
                *(a / b for a, b in zip(self.noise, self.base_noise, strict=True)))


def score(W: np.ndarray, records: YawRecords, horizon: float = HORIZON_S) -> Scores:
    """The costs of a design W_r (10,) on the records (see :class:`Scores`)."""
    steps = int(round(horizon * records.rate_hz))
    W = np.asarray(W, float)
    actual, predicted = _predicted(W, records.tracking, records.rate_hz, steps)
    _, still = _predicted(W, records.still, records.rate_hz, steps)
    if not (np.all(np.isfinite(predicted)) and np.all(np.isfinite(still))):  # the filter diverged
        inf = (np.inf, np.inf)
        return Scores(np.inf, inf, inf, 1.0, (1.0, 1.0), (1.0, 1.0))
    start = int(WARMUP_S * records.rate_hz)
    delayed = records.tracking[start:len(records.tracking) - steps]
    identity = np.broadcast_to(rotations.IDENTITY, still.shape)
    return Scores(_rms(twist(actual, predicted)), _horizontal_vertical(displacement(actual, predicted)),
                  _horizontal_vertical(displacement(identity, still)), _rms(twist(actual, delayed)),
                  _horizontal_vertical(displacement(actual, delayed)),
                  _horizontal_vertical(displacement(identity, records.still[start:len(records.still) - steps])))


def _horizontal_vertical(d: np.ndarray) -> tuple[float, float]:
    """RMS of the target's horizontal (y) and vertical (z) displacement."""
    return _rms(d[:, 1]), _rms(d[:, 2])


def design_cost(design: str, records: YawRecords, default: Scores, horizon: float = HORIZON_S
                ) -> Callable[[np.ndarray], float]:
    """The cost of log10 W_r for ``design``: ``twist`` (eq. 23) or ``hybrid`` (eq. 27, a = b = 1, β = γ, α = 0)."""
    if design not in ("twist", "hybrid"):
        raise InputError(f"design is 'twist' or 'hybrid', got {design!r}")
    tracking0 = np.hypot(*default.tracking)
    noise0 = np.hypot(*default.noise)

    def cost(log_w: np.ndarray) -> float:
        s = score(10.0 ** np.asarray(log_w), records, horizon)
        if design == "twist":
            return s.twist
        return float(np.hypot(*s.tracking) / tracking0 + np.hypot(*s.noise) / noise0)

    return cost


def optimise(design: str, records: YawRecords, start: tuple = DEFAULT_W, horizon: float = HORIZON_S,
             max_evaluations: int = 2000, progress: Callable[[int], None] | None = None
             ) -> tuple[np.ndarray, optimize.OptimizeResult]:
    """W_r minimising ``design``'s cost by Powell's method over log10 W_r (10 entries), from ``start``."""
    default = score(np.asarray(start, float), records, horizon)
    cost = design_cost(design, records, default, horizon)

    def counted(log_w):
        if progress is not None:
            progress(1)
        return cost(log_w)

    low, high = np.array(LOG_W_BOUNDS).T
    x0 = np.clip(np.log10(np.maximum(np.asarray(start, float), 1e-300)), low, high)
    result = optimize.minimize(counted, x0, method="Powell", bounds=LOG_W_BOUNDS,
                               options={"maxfev": max_evaluations, "xtol": 1e-2, "ftol": 1e-4})
    return 10.0 ** result.x, result


def render_table1(rows: dict[str, tuple[float, ...]], evaluations: dict[str, int] | None = None) -> str:
    """Adelstein, Jung & Ellis 2001's Table 1 layout: ratios to no prediction at 50 ms, ours beside the paper's."""
    head = f"{'design':<16}" + "".join(f"{c:>18}" for c in COLUMNS)
    lines = ["Ratios to no prediction at 50 ms (< 1: prediction helps); paper's values in brackets", head]
    for name, ratios in rows.items():
        paper = PAPER_TABLE1.get(name)
        cells = "".join(f"{r:>10.3f} [{p:5.3f}]" if paper else f"{r:>18.3f}"
                        for r, p in zip(ratios, paper or ratios, strict=True))
        note = f"  ({evaluations[name]} cost evaluations)" if evaluations and name in evaluations else ""
        lines.append(f"{name:<16}{cells}{note}")
    return "\n".join(lines)
