"""Stage 1: the AC dipole field model, the closed-form pose solver, and the tracker's own coil model.

The tracker's own pose solvers (what a pose-only tracker reports) are :mod:`ivc.pose.tracker_solver`."""

from ivc.dipole.field import field, field_jacobian, signal, signal_from_pose
from ivc.dipole.pose import HEMISPHERES, USABLE_RANGE_M, closed_form_pose, hemisphere_vector, usable_signals
from ivc.dipole.tracker import Tracker, load_tracker, save_tracker

__all__ = [
    "HEMISPHERES",
    "USABLE_RANGE_M",
    "Tracker",
    "closed_form_pose",
    "field",
    "field_jacobian",
    "hemisphere_vector",
    "load_tracker",
    "save_tracker",
    "signal",
    "signal_from_pose",
    "usable_signals",
]
