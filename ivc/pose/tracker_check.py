"""How well a tracker model and its fixtures explain recorded points: residue and pose error.

The residue of a point is ``‖S − S_pred‖_F / ‖S‖₂`` with ``S_pred`` the model's signal at the
chain's pose; the pose error compares the pose solved from ``S`` with the tracker model
(:func:`ivc.pose.tracker.tracker_pose`) with the chain's pose. The residue's spread
against range is reported in range quartiles, and so is the share of points whose solved pose
failed the model's gate (not converged), also against the off-axis angle (the angle between a
point's direction and the calibration's hemisphere). A converged pose more than
:data:`WRONG_MM` or :data:`WRONG_DEG` off the chain's is counted as a wrong minimum.
"""

from __future__ import annotations

import numpy as np

from ivc import rotations
from ivc.dipole.tracker import Tracker
from ivc.errors import TrackerError
from ivc.pose.calibrate import Fixtures, chain, predicted_signal, residue, solve_chain_poses

__all__ = ["BEYOND_FACTOR", "BEYOND_FLOOR_PERCENT", "BEYOND_FLOOR_MM", "WRONG_DEG", "WRONG_MM", "beyond_calibration",
           "check_tracker", "fixtures_of"]

#: a converged pose this far from the chain's (mm, degrees) sits in a wrong minimum
WRONG_MM = 10.0
WRONG_DEG = 5.0
#: a check's rms residue or pose error this many times the calibration's own (and above the floors) is data the
#: model and its fixtures do not describe: another source or sensor fixturing, another device
BEYOND_FACTOR = 5.0
BEYOND_FLOOR_PERCENT = 1.0
BEYOND_FLOOR_MM = 5.0


def fixtures_of(tracker: Tracker) -> Fixtures:
    """The fixtures a calibration stored in the tracker file."""
    entry = tracker.calibration.get("fixtures")
    if entry is None:
        raise TrackerError("the tracker file has no fitted fixtures: checking against a pose chain needs a "
                           "tracker calibrated by 'ivc tracker calibrate' on the same rig")
    return Fixtures.from_dict(entry)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def _quartiles(values: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Bin edges at the quantiles of ``values`` and each value's bin."""
    edges = np.quantile(values, np.linspace(0.0, 1.0, bins + 1))
    return edges, np.clip(np.searchsorted(edges, values, side="right") - 1, 0, bins - 1)


def _failures(failed: np.ndarray, values: np.ndarray, bins: int, key: str, scale: float) -> list[dict]:
    edges, which = _quartiles(values, bins)
    return [{key: [scale * edges[k], scale * edges[k + 1]], "points": int(np.sum(which == k)),
             "failed": int(np.sum(failed[which == k]))} for k in range(bins)]


def check_tracker(tracker: Tracker, fixtures: Fixtures, S: np.ndarray, J_so: np.ndarray, J_st: np.ndarray,
                  bins: int = 4) -> dict:
    """Residue and pose-error figures of the points (a JSON-ready dict; lengths in mm, angles in degrees).

    ``pose``: errors over every point, over the points that passed the gate, the share that
    failed it (by range and off-axis angle quartiles) and the converged poses in a wrong minimum.
    """
    S = np.asarray(S, dtype=float)
    if not np.all(np.isfinite(S)):
        raise TrackerError("signals must be finite")
    res = residue(S, predicted_signal(tracker, fixtures, J_so, J_st))
    P = chain(fixtures, J_so, J_st)
    ranges = np.linalg.norm(P[:, :3, 3], axis=1)
    edges, which = _quartiles(ranges, bins)
    by_range = [{"range_mm": [1e3 * edges[k], 1e3 * edges[k + 1]], "points": int(np.sum(which == k)),
                 "residue_rms_percent": 100 * _rms(res[which == k])} for k in range(bins)]
    out = {"points": int(len(S)), "residue_rms_percent": 100 * _rms(res), "residue_max_percent": 100 * float(res.max()),
           "residue_by_range": by_range}
    side = tracker.hemisphere if tracker.hemisphere is not None else P[:, :3, 3].mean(axis=0)
    off_axis = np.degrees(np.arccos(np.clip(P[:, :3, 3] @ side / (ranges * np.linalg.norm(side)), -1.0, 1.0)))
    for label, correct in (("pose", True), ("pose_uncorrected", False)):
        if label == "pose_uncorrected" and not tracker.has_output_correction:
            continue
        solution, _ = solve_chain_poses(tracker, fixtures, S, J_so, J_st, correct)
        position = 1e3 * np.linalg.norm(solution.position - P[:, :3, 3], axis=1)
        angle = np.degrees(rotations.angle_between_matrices(solution.rotation, P[:, :3, :3]))
        ok = solution.converged
        wrong = ok & ((position > WRONG_MM) | (angle > WRONG_DEG))
        out[label] = {"position_rms_mm": _rms(position), "position_max_mm": float(np.max(position)),
                      "angle_rms_deg": _rms(angle), "angle_max_deg": float(np.max(angle)),
                      "converged_fraction": float(np.mean(ok)),
                      "converged_position_rms_mm": _rms(position[ok]), "converged_angle_rms_deg": _rms(angle[ok]),
                      "failed": int(np.sum(~ok)), "converged_wrong": int(np.sum(wrong)),
                      "residual_gate_percent": 100 * tracker.pose_gate(),
                      "failed_by_range": _failures(~ok, ranges, bins, "range_mm", 1e3),
                      "failed_by_off_axis_angle": _failures(~ok, off_axis, bins, "angle_deg", 1.0)}
    return out


def beyond_calibration(tracker: Tracker, report: dict) -> str | None:
    """Plain words when :func:`check_tracker`'s ``report`` is far beyond the calibration's own figures (stored in
    the tracker file): an rms residue or pose error :data:`BEYOND_FACTOR` times the calibration's and above
    :data:`BEYOND_FLOOR_PERCENT` % or :data:`BEYOND_FLOOR_MM` mm. None when within, or when the file holds no
    calibration report."""
    own = tracker.calibration.get("report", {}).get("calibration") if isinstance(tracker.calibration, dict) else None
    if not own:
        return None
    found = []
    residue_now, residue_own = report["residue_rms_percent"], own.get("residue_rms_percent")
    if residue_own is not None and residue_now > max(BEYOND_FACTOR * residue_own, BEYOND_FLOOR_PERCENT):
        found.append(f"residue rms {residue_now:.3g} % (the calibration's: {residue_own:.3g} %)")
    pose_now, pose_own = report.get("pose", {}).get("position_rms_mm"), own.get("pose", {}).get("position_rms_mm")
    if pose_now is not None and pose_own is not None and pose_now > max(BEYOND_FACTOR * pose_own, BEYOND_FLOOR_MM):
        found.append(f"position error rms {pose_now:.3g} mm (the calibration's: {pose_own:.3g} mm)")
    if not found:
        return None
    return (f"{' and '.join(found)}: far beyond the calibration's own. These points were not recorded with the "
            "source and sensor fixturing (or the device) the model was calibrated on, so its fixtures do not place "
            "them: calibrate with these recordings among the calibration's, or check them against a model calibrated "
            "on their rig")
