"""Stage 5: corrected poses from live or recorded measurements with a look-up table."""

from ivc.correct import reported_kernels as pose_kernels  # the kernels' module under its earlier name
from ivc.correct.reported import PoseCorrector
from ivc.correct.solver import (
    FLAG_NAMES,
    HIGH_RESIDUAL,
    INVALID_INPUT,
    LOW_PRECISION,
    NOT_CONVERGED,
    OUTSIDE,
    Correction,
    Corrector,
    describe,
)

__all__ = ["FLAG_NAMES", "HIGH_RESIDUAL", "INVALID_INPUT", "LOW_PRECISION", "NOT_CONVERGED", "OUTSIDE",
           "Correction", "Corrector", "PoseCorrector", "describe", "pose_kernels"]
