"""Stage 3: sensor pose with a known secondary field (inside the cube, or anywhere a LUT covers).

Also what builds on the pose solve below the fixtures: the tracker's own solvers (what a pose-only tracker
reports, :mod:`ivc.pose.tracker_solver`), a field fitted through them from (true, reported) pose pairs
(:mod:`ivc.pose.reported_fit`), and the tracker's coil-model calibration and its check
(:mod:`ivc.pose.calibrate`, :mod:`ivc.pose.tracker_check`), which score a model by the poses it solves."""

from ivc.pose.precision import pose_covariance, pose_precision
from ivc.pose.reported import Inversion, invert_distortion
from ivc.pose.solver import (
    METHODS,
    PoseSolution,
    damped_step,
    dipole_plus,
    levenberg_marquardt,
    procrustes,
    signal_residual,
    solve_pose,
)
from ivc.pose.tracker import tracker_pose
from ivc.pose.tracker_solver import SOLVERS as TRACKER_SOLVERS
from ivc.pose.tracker_solver import distortion, reported_pose, reported_pose_jacobian

__all__ = ["METHODS", "TRACKER_SOLVERS", "Inversion", "PoseSolution", "damped_step", "dipole_plus", "invert_distortion",
           "levenberg_marquardt", "pose_covariance", "pose_precision", "procrustes", "signal_residual", "solve_pose",
           "tracker_pose", "distortion", "reported_pose", "reported_pose_jacobian"]
