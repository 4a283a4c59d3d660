"""Stage 1: the AC dipole field model and the closed-form pose solver."""

from ivc.dipole.field import field, field_jacobian, signal, signal_from_pose
from ivc.dipole.pose import HEMISPHERES, closed_form_pose, hemisphere_vector
from ivc.dipole.tracker_solver import SOLVERS as TRACKER_SOLVERS
from ivc.dipole.tracker_solver import distortion, reported_pose, reported_pose_jacobian

__all__ = [
    "HEMISPHERES",
    "TRACKER_SOLVERS",
    "closed_form_pose",
    "distortion",
    "field",
    "field_jacobian",
    "hemisphere_vector",
    "reported_pose",
    "reported_pose_jacobian",
    "signal",
    "signal_from_pose",
]
