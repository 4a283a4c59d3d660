"""Stage 5: corrected poses from live or recorded measurements with a look-up table."""

from ivc.correct.pose_domain import PoseCorrector
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
           "Correction", "Corrector", "PoseCorrector", "describe"]
