"""One blocked cross-validation for every LUT fitter (docs/lut.md, "Fit" and "Adding a fitter").

Neighbouring wand frames are a fraction of a millimetre apart and carry correlated errors,
so samples are held out in blocks of consecutive frames (``block_frames``), dealt
round-robin into ``k`` folds. A fitter is scored by fitting it without each fold and
predicting the held-out samples; the score is their pose-equivalent RMS error (m), each
sample weighed by its precision ``1 / (ε² + ε₀²)`` (docs/math.md §8). Samples a fitter
says nothing about (its prediction is NaN) do not count.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ivc.errors import InputError
from ivc.lut.samples import FieldSamples, pose_equivalent_rms

if TYPE_CHECKING:
    from ivc.lut.fitter import Fitter
    from ivc.table.grid import Grid

__all__ = ["BLOCK_FRAMES", "FOLDS", "BlockedKFold", "cross_validate", "held_out_score"]

#: default number of folds and of consecutive frames held out together
FOLDS = 5
BLOCK_FRAMES = 500


@dataclass(frozen=True)
class BlockedKFold:
    """``k`` folds of blocks of ``block_frames`` consecutive frames: frame ``f`` is in fold
    ``(f // block_frames) % k``."""

    k: int = FOLDS
    block_frames: int = BLOCK_FRAMES

    def __post_init__(self):
        for name, low in (("k", 2), ("block_frames", 1)):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or value < low:
                raise InputError(f"cross-validation {name} must be a whole number of at least {low}, got {value!r}")

    def folds(self, samples: FieldSamples) -> np.ndarray:
        """The fold of each sample (N,) int."""
        return samples.folds(self.k, block_frames=self.block_frames)


def held_out_score(samples: FieldSamples, predicted: np.ndarray) -> float:
    """Precision-weighted pose-equivalent RMS (m) of the predictions ``predicted`` (N, 3, 3) of ``samples``' fields.

    The fit weight ``λ² / (ε² + ε₀²)`` divided by ``λ²``: each held-out sample counts by how well its
    field is known, its residual by how far it moves the solved position.
    """
    precision = samples.weights() / samples.leverage() ** 2
    return pose_equivalent_rms(samples, predicted, precision)


def cross_validate(fitter: Fitter, samples: FieldSamples, grid: Grid, cv: BlockedKFold | None = None) -> float:
    """Held-out score (m, :func:`held_out_score`) of ``fitter``'s configuration: for each fold, a fresh copy
    (:meth:`~ivc.lut.fitter.Fitter.clone`) is fitted to the other folds on ``grid`` and predicts the fold.
    ``cv``: the folds (default: the fitter's own ``cv``)."""
    cv = fitter.cv if cv is None else cv
    fold = cv.folds(samples)
    predicted = np.full_like(samples.fields, np.nan)
    for f in range(cv.k):
        held = fold == f
        if not held.any():
            continue
        predicted[held] = fitter.clone().fit(samples.subset(~held), grid).predict(samples.positions[held])
    return held_out_score(samples, predicted)
