"""The HDF5 session file every command reads and writes (docs/session-format.md)."""

from ivc.session.io import add_step, atomic_path, is_recording_csv, read, write
from ivc.session.model import (
    CUBE_SENSORS,
    DECLARED_POSE_ATTRS,
    FIT_STEPS,
    FORMAT_VERSION,
    STEP_DESCRIPTIONS,
    STEPS,
    Lack,
    Session,
    SessionError,
    Step,
    Truth,
)

__all__ = [
    "CUBE_SENSORS",
    "DECLARED_POSE_ATTRS",
    "FIT_STEPS",
    "FORMAT_VERSION",
    "Lack",
    "STEPS",
    "STEP_DESCRIPTIONS",
    "Session",
    "SessionError",
    "Step",
    "Truth",
    "add_step",
    "atomic_path",
    "is_recording_csv",
    "read",
    "write",
]
