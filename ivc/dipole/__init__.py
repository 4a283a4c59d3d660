"""Stage 1: the AC dipole field model, the closed-form pose solver, and the tracker's own coil model."""

from ivc.dipole.field import field, field_jacobian, signal, signal_from_pose
from ivc.dipole.pose import HEMISPHERES, closed_form_pose, hemisphere_vector
from ivc.dipole.tracker import Tracker, load_tracker, save_tracker
from ivc.dipole.tracker_solver import SOLVERS as TRACKER_SOLVERS
from ivc.dipole.tracker_solver import distortion, reported_pose, reported_pose_jacobian

__all__ = [
    "HEMISPHERES",
    "TRACKER_SOLVERS",
    "Tracker",
    "closed_form_pose",
    "distortion",
    "field",
    "field_jacobian",
    "hemisphere_vector",
    "load_tracker",
    "reported_pose",
    "reported_pose_jacobian",
    "save_tracker",
    "signal",
    "signal_from_pose",
]
