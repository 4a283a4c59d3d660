"""Stage 1: the AC dipole field model and the closed-form pose solver."""

from ivc.dipole.field import field, field_jacobian, signal, signal_from_pose
from ivc.dipole.pose import HEMISPHERES, closed_form_pose, hemisphere_vector

__all__ = [
    "HEMISPHERES",
    "closed_form_pose",
    "field",
    "field_jacobian",
    "hemisphere_vector",
    "signal",
    "signal_from_pose",
]
