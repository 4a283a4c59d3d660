"""A simulated precision-stage calibration rig (like ILEMT's), for the tracker calibration.

The stage steps a sensor fixture through an XYZ grid times a set of turns about the
stage's z axis, in one or more sensor-fixture orientations; the pose chain is
``P = F_so · J_so · F_st · J_st · F_se`` (:mod:`ivc.pose.calibrate`) with fixtures the
caller chooses (the truth a calibration must recover). Free space only.
"""

from __future__ import annotations

import itertools

import numpy as np

from ivc.collect.ilemt import stage_transforms
from ivc.dipole.tracker import Tracker
from ivc.errors import InputError
from ivc.pose.calibrate import Fixtures, chain

__all__ = ["stage_pattern", "stage_recording"]


def stage_pattern(xyz_mm=(-50.0, 0.0, 50.0), rz_deg=(-90.0, -45.0, 0.0, 45.0, 90.0),
                  sensor_fixtures=("YoutZup", "ZinYup", "ZinXdown")) -> tuple[np.ndarray, np.ndarray]:
    """Known motions of a grid pattern: ``J_so`` (N, 4, 4) (identity) and ``J_st`` (N, 4, 4), metres.

    Every (x, y, z) of ``xyz_mm`` cubed, at every stage turn ``rz_deg``, in every sensor
    fixture (ILEMT fixture codes, :data:`ivc.collect.ilemt.FIXTURES`).
    """
    stage = np.array([(x, y, z, 0.0, 0.0, rz) for rz, z, y, x in itertools.product(rz_deg, xyz_mm, xyz_mm, xyz_mm)])
    if len(stage) == 0 or not sensor_fixtures:
        raise InputError("a stage pattern needs at least one position, one turn and one sensor fixture")
    J_st = np.concatenate([stage_transforms(stage, code) for code in sensor_fixtures])
    return np.broadcast_to(np.eye(4), J_st.shape).copy(), J_st


def stage_recording(tracker: Tracker, fixtures: Fixtures, J_so: np.ndarray, J_st: np.ndarray, *,
                    noise_relative: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """Signal matrices (N, 3, 3) the tracker measures along the chain, with white noise.

    ``noise_relative``: standard deviation of each entry's noise as a fraction of that
    point's ``‖S‖₂`` (like a receiver whose noise follows its gain range).
    """
    if noise_relative < 0:
        raise InputError(f"noise_relative must be >= 0, got {noise_relative}")
    P = chain(fixtures, J_so, J_st)
    S = tracker.signal(P[:, :3, 3], P[:, :3, :3])
    if noise_relative > 0:
        rng = np.random.default_rng() if rng is None else rng
        scale = np.linalg.norm(S, ord=2, axis=(1, 2))[:, None, None]
        S = S + noise_relative * scale * rng.standard_normal(S.shape)
    return S
