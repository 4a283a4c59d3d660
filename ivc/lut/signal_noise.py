"""The tracker's signal noise, measured from a session's static steps.

The fixtures hold still through the cube calibration, the cube survey and the wand calibration, so
what changes between two consecutive frames of one sensor there is noise. Each signal entry's
frame-to-frame difference has standard deviation ``σ √2`` for white noise of ``σ``; a slow drift of
the source's gain (a fraction of the signal per second) adds almost nothing to a difference over one
frame. The estimate is robust: ``1.4826 · MAD / √2`` of the differences, per sensor and entry, and
their median over all of them.

It assumes *absolute* noise (the same ``σ`` on every entry and at every range, a receiver's fixed
noise floor), which is what the precision of a corrected pose (``ivc.pose.precision``) is computed
with. :attr:`SignalNoise.spread` says how far the per-sensor estimates differ (a tracker whose noise
scales with the signal shows a large spread: its nearest sensors are noisiest).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ivc.session import Session

__all__ = ["STATIC_STEPS", "SignalNoise", "measure_signal_noise", "robust_sigma"]

#: the steps in which every sensor holds still
STATIC_STEPS = ("cube_calibration", "cube_survey", "wand_calibration")
#: frame pairs a sensor needs before its differences are used
MIN_PAIRS = 20


@dataclass(frozen=True)
class SignalNoise:
    """``sigma``: white noise per signal entry (the session's signal units; normalised dipole units
    for calibrated signals); ``steps``: the steps measured; ``pairs``: consecutive valid frame pairs
    used; ``spread``: ratio of the largest to the smallest per-sensor estimate."""

    sigma: float
    steps: tuple[str, ...]
    pairs: int
    spread: float

    def as_dict(self) -> dict:
        """Json-ready, as a table's fit report stores it."""
        return {**asdict(self), "steps": list(self.steps), "method": "static steps, MAD of frame differences"}


def robust_sigma(d: np.ndarray) -> np.ndarray:
    """Per-column white-noise standard deviation from frame differences ``d`` (pairs, columns) of a static
    stream: ``1.4826 MAD / √2`` (robust to a few jumps and to slow drift)."""
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(2.0)


def measure_signal_noise(session: Session, steps: tuple[str, ...] = STATIC_STEPS) -> SignalNoise | None:
    """The signal noise of ``session``'s static ``steps`` that carry signal matrices (steps of reported
    poses carry no signal noise to measure and are skipped). None when none of them has a sensor with
    at least :data:`MIN_PAIRS` consecutive valid frames whose signal changes (a frozen or exactly repeated
    stream has nothing to measure)."""
    per_sensor, used, pairs = [], [], 0
    for name in steps:
        step = session.steps.get(name)
        if step is None or step.signal is None or step.n_frames < 2:
            continue
        S = np.asarray(step.signal, float).reshape(step.n_frames, step.n_sensors, 9)
        valid = step.valid_mask & np.all(np.isfinite(S), axis=2)
        both = valid[1:] & valid[:-1]
        d = np.diff(S, axis=0)
        measured = False
        for k in range(step.n_sensors):
            if both[:, k].sum() < MIN_PAIRS:
                continue
            sigma = float(np.median(robust_sigma(d[both[:, k], k])))
            if not sigma > 0:
                continue
            per_sensor.append(sigma)
            pairs += int(both[:, k].sum())
            measured = True
        if measured:
            used.append(name)
    if not per_sensor:
        return None
    per_sensor = np.array(per_sensor)
    return SignalNoise(float(np.median(per_sensor)), tuple(used), pairs, float(per_sensor.max() / per_sensor.min()))
