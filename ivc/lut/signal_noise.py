"""The tracker's signal noise, measured from a session's static steps.

The fixtures hold still through the cube calibration, the cube survey and the wand calibration, so
what changes between two consecutive frames of one sensor there is noise. Each signal entry's
frame-to-frame difference has standard deviation ``σ √2`` for white noise of ``σ``; a slow drift of
the source's gain (a fraction of the signal per second) adds almost nothing to a difference over one
frame. The estimate is robust: ``1.4826 · MAD / √2`` of the differences, per sensor and entry, and
their median over all of them.

A session of reported poses only (a tracker that gives no signals) has its noise measured from the
reported poses of the free-space static steps (the cube and the wand calibration): a sensor's
frame-to-frame pose difference ``d`` (position, m, and rotation, rad, sensor frame) scatters as
``2 σ² P`` with ``P`` the Cramér-Rao covariance of a unit-noise solve at that pose
(``ivc.pose.precision``; the closed form reaches it in free space), so ``dᵀ (2P)⁻¹ d / σ²`` is
χ² with 6 degrees of freedom: ``σ² = median(dᵀ (2P)⁻¹ d) / 5.348`` per sensor, and the median over
the sensors. The σ found is the signal noise that would make the tracker report the scatter it does,
in normalised dipole units, the same quantity as from signals.

It assumes *absolute* noise (the same ``σ`` on every entry and at every range, a receiver's fixed
noise floor), which is what the precision of a corrected pose (``ivc.pose.precision``) is computed
with. :attr:`SignalNoise.spread` says how far the per-sensor estimates differ (a tracker whose noise
scales with the signal shows a large spread: its nearest sensors are noisiest).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ivc import rotations
from ivc.pose.precision import pose_covariance
from ivc.session import Session

__all__ = ["FREE_SPACE_STEPS", "STATIC_STEPS", "SignalNoise", "measure_signal_noise", "robust_sigma"]

#: the steps in which every sensor holds still
STATIC_STEPS = ("cube_calibration", "cube_survey", "wand_calibration")
#: the static steps recorded in free space (their reported poses scatter as a free-space solve does)
FREE_SPACE_STEPS = ("cube_calibration", "wand_calibration")
#: the median of a χ² variable with 6 degrees of freedom
CHI2_6_MEDIAN = 5.348120627447116
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
    source: str = "signals"

    def as_dict(self) -> dict:
        """Json-ready, as a table's fit report stores it."""
        method = ("static steps, MAD of frame differences" if self.source == "signals" else
                  "reported poses of the free-space static steps, median Mahalanobis length of frame differences")
        return {**asdict(self), "steps": list(self.steps), "method": method}


def robust_sigma(d: np.ndarray) -> np.ndarray:
    """Per-column white-noise standard deviation from frame differences ``d`` (pairs, columns) of a static
    stream: ``1.4826 MAD / √2`` (robust to a few jumps and to slow drift)."""
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(2.0)


def measure_signal_noise(session: Session, steps: tuple[str, ...] = STATIC_STEPS) -> SignalNoise | None:
    """The signal noise of ``session``'s static ``steps`` that carry signal matrices; when none does, from the
    reported poses of its free-space static steps (:func:`measure_reported_noise`). None when no step has a
    sensor with at least :data:`MIN_PAIRS` consecutive valid frames that change (a frozen or exactly repeated
    stream has nothing to measure)."""
    found = _from_signals(session, steps)
    return found if found is not None else measure_reported_noise(session)


def measure_reported_noise(session: Session, steps: tuple[str, ...] = FREE_SPACE_STEPS) -> SignalNoise | None:
    """The signal noise, in normalised dipole units, that makes a tracker report the pose scatter of
    ``session``'s free-space static ``steps`` (see the module docstring); None when none has a sensor with
    :data:`MIN_PAIRS` consecutive valid frames that change."""
    return _measure(session, steps, _reported_sigmas, "reported poses")


def _reported_sigmas(step) -> list[tuple[float, int]] | None:
    """Per sensor of a step of reported poses: (σ, frame pairs used); None when the step has no poses."""
    if step.position is None or step.quaternion is None:
        return None
    position = np.asarray(step.position, float)
    T = rotations.to_matrix(np.where(np.isfinite(step.quaternion), step.quaternion, rotations.IDENTITY))
    valid = step.valid_mask & np.all(np.isfinite(position), axis=2) & np.all(np.isfinite(step.quaternion), axis=2)
    both = valid[1:] & valid[:-1]
    found = []
    for k in range(step.n_sensors):
        use = np.flatnonzero(both[:, k])
        if len(use) < MIN_PAIRS:
            continue
        d = np.empty((len(use), 6))
        d[:, :3] = position[use + 1, k] - position[use, k]
        d[:, 3:] = rotations.to_rotvec(rotations.from_matrix(np.swapaxes(T[use, k], -1, -2) @ T[use + 1, k]))
        at = np.flatnonzero(valid[:, k])
        P = pose_covariance(np.median(position[at, k], axis=0), rotations.from_matrix(T[at[len(at) // 2], k]),
                            1.0)[0]
        if not np.all(np.isfinite(P)):
            continue
        m = np.einsum("ni,ij,nj->n", d, np.linalg.inv(2 * P), d)
        found.append((float(np.sqrt(np.median(m) / CHI2_6_MEDIAN)), len(use)))
    return found


def _signal_sigmas(step) -> list[tuple[float, int]] | None:
    """Per sensor of a step of signals: (σ, frame pairs used); None when the step has no signals."""
    if step.signal is None:
        return None
    S = np.asarray(step.signal, float).reshape(step.n_frames, step.n_sensors, 9)
    valid = step.valid_mask & np.all(np.isfinite(S), axis=2)
    both = valid[1:] & valid[:-1]
    d = np.diff(S, axis=0)
    return [(float(np.median(robust_sigma(d[both[:, k], k]))), int(both[:, k].sum()))
            for k in range(step.n_sensors) if both[:, k].sum() >= MIN_PAIRS]


def _from_signals(session: Session, steps: tuple[str, ...]) -> SignalNoise | None:
    return _measure(session, steps, _signal_sigmas, "signals")


def _measure(session: Session, steps: tuple[str, ...], sigmas, source: str) -> SignalNoise | None:
    """The median over every sensor of ``steps`` of ``sigmas(step)`` (per sensor: σ and frame pairs), with the
    steps that gave one, the pairs used and the spread; None when no sensor gave a positive σ."""
    per_sensor, used, pairs = [], [], 0
    for name in steps:
        step = session.steps.get(name)
        if step is None or step.n_frames < 2:
            continue
        found = [(sigma, n) for sigma, n in (sigmas(step) or []) if sigma > 0]
        if found:
            used.append(name)
            per_sensor += [sigma for sigma, _ in found]
            pairs += sum(n for _, n in found)
    if not per_sensor:
        return None
    per_sensor = np.array(per_sensor)
    return SignalNoise(float(np.median(per_sensor)), tuple(used), pairs, float(per_sensor.max() / per_sensor.min()),
                       source)
