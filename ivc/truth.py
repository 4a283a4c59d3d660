"""Evaluation against truth, shared by every stage that has it (fixtures, correction, the report).

Errors are millimetres and milliradians. Solved and corrected poses live in the frame of
the *declared* cube pose (docs/math.md §5): :func:`declared_frame_map` moves true
source-frame poses into that frame, so a method is judged there (its own accuracy) and
against raw truth (which adds the cube-placement error) beside it.
"""

from __future__ import annotations

import numpy as np

from ivc import rotations
from ivc.fixtures.cube import declared_pose, fixture_frame
from ivc.session import Session

__all__ = ["DECLARED_FRAME", "PERCENTILES", "RAW_FRAME", "declared_frame_map", "percentiles", "pose_errors"]

PERCENTILES = (25, 50, 75, 95, 99, 100)
#: the frames errors against truth are judged in
DECLARED_FRAME = "declared cube frame (true poses moved by the declared-pose error)"
RAW_FRAME = "raw truth (source frame)"


def percentiles(values: np.ndarray, scale: float = 1.0) -> dict[str, float]:
    """The :data:`PERCENTILES` of the finite ``values`` times ``scale``, keyed p25 … p99 and max; {} if none."""
    values = np.asarray(values)[np.isfinite(values)]
    if len(values) == 0:
        return {}
    return {("max" if p == 100 else f"p{p}"): float(scale * np.percentile(values, p)) for p in PERCENTILES}


def declared_frame_map(session: Session) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``(D_R, D_t, offset)``: the rigid map taking true source-frame points into the declared
    frame, from /truth/cube_survey, and the declared cube origin's offset from the true one (m)."""
    truth = session.truth.get("cube_survey")
    declared = declared_pose(session.steps["cube_survey"]) if truth is not None else None
    if declared is None:
        return None
    r0_true, T_true = fixture_frame(truth.position[0])
    r0_declared, q_declared = declared
    D_R = rotations.to_matrix(q_declared) @ T_true.T
    return D_R, r0_declared - D_R @ r0_true, float(np.linalg.norm(r0_declared - r0_true))


def pose_errors(position: np.ndarray, rotation: np.ndarray, true_position: np.ndarray,
                true_rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error (mm) and orientation error (mrad, the angle of ``R Rᵀ_true``) per pose.

    Positions (..., 3) m and rotation matrices (..., 3, 3), in one frame.
    """
    return (1000 * np.linalg.norm(position - true_position, axis=-1),
            1000 * rotations.angle_between_matrices(rotation, true_rotation))
