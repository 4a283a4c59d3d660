"""Sensors of one rigid body decide each other's branch: a corrected sensor is trusted only where the body's
other trusted sensors agree with it.

Next to metal a reported pose can have two true poses the map cannot tell apart, and where the other one lies
beyond the map (or in a hole the model there misses) the ambiguity test cannot see it (docs/trust.md, "Poses
beyond the map, and in its holes"). Sensors fixed to one body see different places of the room at once: a
wrong branch puts its sensor where the body's other sensors say it is not. Given the body's geometry (each
sensor's pose in the frame of sensor 0, :class:`~ivc.fixtures.wand.WandCalibration`: the mapping wand's own
calibration, or any tool's), :func:`agree_with_body` keeps, per frame, the trusted sensors that agree on the
body's pose (:meth:`~ivc.fixtures.wand.WandCalibration.consensus`: the largest set within 2 mm and 20 mrad,
at least two sensors and more than half the trusted ones) and flags the others HIGH_RESIDUAL (a pose the map
does not produce uniquely); a frame where no such set exists has nothing to decide with, and all its sensors
are flagged.
"""

from __future__ import annotations

import numpy as np

from ivc.correct.solver import HIGH_RESIDUAL, Correction
from ivc.errors import InputError
from ivc.fixtures.wand import AGREEMENT, WandCalibration


def agree_with_body(out: Correction, body: WandCalibration, agreement: tuple[float, float] = AGREEMENT,
                    min_sensors: int = 2) -> np.ndarray:
    """Flag HIGH_RESIDUAL, in place, every trusted sensor of ``out`` (frames (F, W), the body's W sensors in its
    calibration's order) that the body's trusted sensors do not agree on, to ``agreement`` (m, rad) with at least
    ``min_sensors`` of them and more than half. Returns the flagged samples (F, W) bool (the newly flagged: the
    sensors that were trusted)."""
    flags = out.flags
    if flags.ndim != 2 or flags.shape[1] != len(body.positions):
        raise InputError(f"a rigid body of {len(body.positions)} sensors needs corrected frames of as many sensors "
                         f"(F, {len(body.positions)}), got {flags.shape}: give the body's geometry in the order "
                         f"of the recording's sensors")
    trusted = flags == 0
    members = body.consensus(out.position, out.quaternion, trusted, agreement, min_sensors).members
    disagree = trusted & ~members
    flags[disagree] |= HIGH_RESIDUAL
    return disagree
