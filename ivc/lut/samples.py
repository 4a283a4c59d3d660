"""Secondary-field samples for a LUT fit (docs/math.md §7-8), and how much each one counts.

A sample is a wand sensor's position ``r`` (m, source frame as declared by the cube
placement), its ``G = T S − f_D(r)`` (eq. 89) and the estimated error ``ε`` of its
position (eq. 101). Errors are compared in one currency, the *pose-equivalent* error:
near a dipole a field error ``δG`` moves the solved position by about
``λ |δG|_F`` with ``λ = |r| / (3 |f_D(r)|_F)``, so a sample counts with weight
``λ² / (ε² + ε_0²)`` (relative to the mean), and residuals are reported in millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ivc import dipole
from ivc.errors import InputError

#: error floor added to eq. 101's estimate (m), so no sample dominates the fit
ERROR_FLOOR = 1e-4


def leverage(positions: np.ndarray) -> np.ndarray:
    """``λ = |r| / (3 |f_D(r)|_F)`` (N,) at positions (N, 3): metres of position per unit of field error."""
    return np.linalg.norm(positions, axis=1) / (3 * np.linalg.norm(dipole.field(positions), axis=(1, 2)))


@dataclass
class FieldSamples:
    """``positions`` (N, 3) m; ``fields`` (N, 3, 3); ``error`` (N,) m; ``frame``, ``sensor`` (N,) int."""

    positions: np.ndarray
    fields: np.ndarray
    error: np.ndarray
    frame: np.ndarray
    sensor: np.ndarray

    def __post_init__(self):
        n = len(self.positions)
        if (self.positions.shape != (n, 3) or self.fields.shape != (n, 3, 3) or self.error.shape != (n,)
                or self.frame.shape != (n,) or self.sensor.shape != (n,)):
            raise InputError("field samples: inconsistent array shapes")
        if not (np.all(np.isfinite(self.positions)) and np.all(np.isfinite(self.fields))):
            raise InputError("field samples must be finite; drop the gated-out samples first")

    def __len__(self) -> int:
        return len(self.positions)

    @classmethod
    def from_mapping(cls, mapping) -> FieldSamples:
        """The kept samples of a :class:`~ivc.fixtures.mapping.SweepMapping`."""
        frame, sensor = np.nonzero(mapping.keep)
        return cls(mapping.positions[frame, sensor], mapping.fields[frame, sensor],
                   mapping.error_estimate[frame, sensor], frame, sensor)

    def subset(self, mask: np.ndarray) -> FieldSamples:
        return FieldSamples(self.positions[mask], self.fields[mask], self.error[mask], self.frame[mask],
                            self.sensor[mask])

    def leverage(self) -> np.ndarray:
        """``λ = |r| / (3 |f_D(r)|_F)`` (N,): metres of position per unit of field error."""
        return self.leverage_of(slice(None))

    def leverage_of(self, index) -> np.ndarray:
        """:meth:`leverage` of the samples selected by ``index`` (slice, mask or indices)."""
        return leverage(self.positions[index])

    def weights(self, error_floor: float = ERROR_FLOOR) -> np.ndarray:
        """Fit weights (N,): ``λ² / (ε² + ε_0²)`` with ``ε_0 = error_floor`` (m), scaled so the mean precision
        factor is 1."""
        precision = 1.0 / (self.error**2 + error_floor**2)
        return self.leverage() ** 2 * precision / precision.mean()

    def folds(self, k: int = 5, block_frames: int = 500) -> np.ndarray:
        """Cross-validation fold of each sample (N,): blocks of consecutive frames dealt round-robin,
        so that neighbouring (correlated) frames are held out together."""
        return (self.frame // block_frames) % k


def pose_equivalent_rms(samples: FieldSamples, predicted: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Weighted RMS of ``λ |G_predicted − G|_F`` over samples: the fit residual as a position error (m)."""
    residual = samples.leverage() * np.linalg.norm(predicted - samples.fields, axis=(1, 2))
    w = np.ones(len(samples)) if weights is None else weights
    ok = np.isfinite(residual)
    return float(np.sqrt(np.sum(w[ok] * residual[ok] ** 2) / np.sum(w[ok])))
