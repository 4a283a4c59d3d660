"""How well a tracker model and its fixtures explain recorded points: residue and pose error.

The residue of a point is ``‖S − S_pred‖_F / ‖S‖₂`` with ``S_pred`` the model's signal at the
chain's pose; the pose error compares the pose solved from ``S`` with the tracker model
(:func:`ivc.pose.tracker.tracker_pose`) with the chain's pose. The residue's spread
against range is reported in range quartiles.
"""

from __future__ import annotations

import numpy as np

from ivc import rotations
from ivc.dipole.tracker import Tracker
from ivc.errors import TrackerError
from ivc.pose.calibrate import Fixtures, chain, predicted_signal, residue, solve_chain_poses

__all__ = ["check_tracker", "fixtures_of"]


def fixtures_of(tracker: Tracker) -> Fixtures:
    """The fixtures a calibration stored in the tracker file."""
    entry = tracker.calibration.get("fixtures")
    if entry is None:
        raise TrackerError("the tracker file has no fitted fixtures: checking against a pose chain needs a "
                           "tracker calibrated by 'ivc tracker calibrate' on the same rig")
    return Fixtures.from_dict(entry)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def check_tracker(tracker: Tracker, fixtures: Fixtures, S: np.ndarray, J_so: np.ndarray, J_st: np.ndarray,
                  bins: int = 4) -> dict:
    """Residue and pose-error figures of the points (a JSON-ready dict; lengths in mm, angles in degrees)."""
    S = np.asarray(S, dtype=float)
    if not np.all(np.isfinite(S)):
        raise TrackerError("signals must be finite")
    res = residue(S, predicted_signal(tracker, fixtures, J_so, J_st))
    P = chain(fixtures, J_so, J_st)
    ranges = np.linalg.norm(P[:, :3, 3], axis=1)
    edges = np.quantile(ranges, np.linspace(0.0, 1.0, bins + 1))
    which = np.clip(np.searchsorted(edges, ranges, side="right") - 1, 0, bins - 1)
    by_range = [{"range_mm": [1e3 * edges[k], 1e3 * edges[k + 1]], "points": int(np.sum(which == k)),
                 "residue_rms_percent": 100 * _rms(res[which == k])} for k in range(bins)]
    out = {"points": int(len(S)), "residue_rms_percent": 100 * _rms(res), "residue_max_percent": 100 * float(res.max()),
           "residue_by_range": by_range}
    for label, correct in (("pose", True), ("pose_uncorrected", False)):
        if label == "pose_uncorrected" and not tracker.has_output_correction:
            continue
        solution, _ = solve_chain_poses(tracker, fixtures, S, J_so, J_st, correct)
        position = 1e3 * np.linalg.norm(solution.position - P[:, :3, 3], axis=1)
        angle = np.degrees(rotations.angle_between_matrices(solution.rotation, P[:, :3, :3]))
        out[label] = {"position_rms_mm": _rms(position), "position_max_mm": float(np.max(position)),
                      "angle_rms_deg": _rms(angle), "angle_max_deg": float(np.max(angle)),
                      "converged_fraction": float(np.mean(solution.converged))}
    return out
