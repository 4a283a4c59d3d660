"""Bringing a research tracker's recordings into ideal-dipole units with its coil model (docs/tracker.md).

:func:`apply_tracker` is what ``--tracker-model FILE`` does in ``ivc collect``, ``fixtures``,
``fit``, ``correct`` and ``evaluate``: every signal matrix of a step becomes
:func:`ivc.pose.tracker.to_ideal` of itself, and a step that also held the
device's own reported poses gets the closed-form poses of the converted signals instead.
The step's ``tracker`` attribute names the model applied, so that it is never applied twice;
``tracker_gate_failed`` counts the samples whose model pose failed the model's residual gate
(converted all the same: in a distorted room the residual also holds what the room adds).
"""

from __future__ import annotations

import hashlib
from dataclasses import replace
from pathlib import Path

import numpy as np

from ivc import rotations
from ivc.dipole import closed_form_pose
from ivc.dipole.tracker import Tracker, load_tracker
from ivc.errors import TrackerError
from ivc.pose.tracker import ideal_signals
from ivc.session import Session, Step

__all__ = ["GATE_ATTR", "TRACKER_ATTR", "apply_tracker", "apply_tracker_to_session", "load_labelled_tracker",
           "tracker_label"]

#: the step attribute that names the tracker model its signals were converted with
TRACKER_ATTR = "tracker"
#: the step attribute that counts the samples whose model pose failed the gate in the conversion
GATE_ATTR = "tracker_gate_failed"


def tracker_label(path: str | Path) -> str:
    """``name sha256:<12 hex>`` of a tracker file: what a converted step records."""
    path = Path(path)
    return f"{path.name} sha256:{hashlib.sha256(path.read_bytes()).hexdigest()[:12]}"


def load_labelled_tracker(path: str | Path) -> tuple[Tracker, str]:
    """The tracker of a file and its label (:func:`tracker_label`)."""
    return load_tracker(path), tracker_label(path)


def apply_tracker(step: Step, tracker: Tracker, hemisphere: str, label: str, name: str = "step") -> Step:
    """``step`` with its signals in ideal-dipole units (a new step; the input is not changed).

    ``hemisphere``: the session's declared side, in the tracker's source frame. A step already
    converted with the same model comes back as it is; one converted with another model, or
    holding reported poses only (a tracker that calibrates itself), is an error.
    """
    done = step.attrs.get(TRACKER_ATTR)
    if done is not None:
        if done == label:
            return step
        raise TrackerError(f"{name}: its signals were already converted with tracker {done!r}, not {label!r}")
    if step.signal is None:
        raise TrackerError(f"{name}: holds reported poses only; a tracker model applies to signal matrices "
                           "(a device that reports poses has calibrated its coils itself)")
    valid = step.valid_mask
    signal = np.where(valid[..., None, None], step.signal, np.nan)
    converted = ideal_signals(signal, tracker, hemisphere)
    ideal = np.where(valid[..., None, None], converted.signal, step.signal)  # invalid samples keep what they had
    attrs = dict(step.attrs, **{TRACKER_ATTR: label, GATE_ATTR: int(np.sum(valid & ~converted.passed))})
    if step.position is None:
        return replace(step, signal=ideal, attrs=attrs)
    with np.errstate(invalid="ignore"):
        position, T = closed_form_pose(np.where(valid[..., None, None], ideal, np.nan), hemisphere)
        quaternion = rotations.from_matrix(T)
    position = np.where(valid[..., None], position, step.position)
    quaternion = np.where(valid[..., None], quaternion, step.quaternion)
    return replace(step, signal=ideal, position=position, quaternion=quaternion, attrs=attrs)


def apply_tracker_to_session(data: Session, tracker: Tracker, label: str,
                             steps: list[str] | None = None) -> Session:
    """A copy of ``data`` whose steps (all, or ``steps``) hold ideal-unit signals; truth is unchanged."""
    converted = dict(data.steps)
    for name in steps if steps is not None else list(data.steps):
        converted[name] = apply_tracker(data.steps[name], tracker, data.hemisphere, label, name)
    return Session(data.hemisphere, converted, dict(data.truth), dict(data.attrs))


def apply_tracker_file(data: Session, path: str | Path | None, steps: list[str] | None = None) -> Session:
    """:func:`apply_tracker_to_session` with the model of the tracker file ``path`` (what ``--tracker-model FILE``
    and ``tracker_model=FILE`` do); None: ``data`` as it is."""
    if path is None:
        return data
    model, label = load_labelled_tracker(path)
    return apply_tracker_to_session(data, model, label, steps)
