"""Simulated imperfect trackers: the class of research devices a tracker calibration must hold on.

:func:`offset_tracker` builds a :class:`ivc.dipole.tracker.Tracker` whose source coils sit
``source_offset`` metres from their centroid (a dipole-approximating three-coil source,
not a concentric cube), with gains and cross-talk of a few percent, coil axes turned
against the fixture, and sensor coils off-centre too (docs/tracker.md). Free space only;
:func:`ivc.sim.stage.stage_recording` records it on a simulated rig.
"""

from __future__ import annotations

import numpy as np

from ivc import rotations
from ivc.dipole.tracker import Tracker
from ivc.errors import InputError

__all__ = ["offset_tracker", "ring_offsets"]


def ring_offsets(radius: float, rng: np.random.Generator) -> np.ndarray:
    """Three coil centres (3, 3), metres: each ``radius`` from their centroid (the origin), 120 degrees
    apart in a random plane (pairwise ``radius·√3`` apart)."""
    if not (np.isfinite(radius) and radius >= 0):
        raise InputError(f"a coil offset must be a finite length >= 0 m, got {radius}")
    frame = rotations.to_matrix(rotations.random(1, rng))[0]
    phase = rng.uniform(0.0, 2 * np.pi)
    angles = phase + 2 * np.pi * np.arange(3) / 3
    return radius * (np.cos(angles)[:, None] * frame[:, 0] + np.sin(angles)[:, None] * frame[:, 1])


def _coils(gain: float, crosstalk: float, turn_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Moment matrix (columns = coils): unit gains off by ``gain``, cross-talk ``crosstalk``, axes turned
    ``turn_deg`` degrees (about a random axis) against the frame."""
    M = np.diag(1.0 + gain * rng.standard_normal(3))
    off = ~np.eye(3, dtype=bool)
    M[off] = crosstalk * rng.standard_normal(6)
    axis = rng.standard_normal(3)
    turn = rotations.to_matrix(rotations.from_rotvec(np.radians(turn_deg) * axis / np.linalg.norm(axis)))
    return turn @ M


def offset_tracker(source_offset: float = 0.036, *, sensor_offset: float = 0.002, gain: float = 0.03,
                   crosstalk: float = 0.03, source_turn_deg: float = 5.0, sensor_turn_deg: float = 3.0,
                   rng: np.random.Generator | None = None) -> Tracker:
    """An imperfect tracker with non-concentric coils (lengths in metres, angles in degrees).

    Source coil ``i`` sits ``source_offset`` from the source's centroid and sensor coil ``j``
    ``sensor_offset`` from the sensor's (:func:`ring_offsets`); each coil's gain is off by
    ``gain`` (relative standard deviation), each pair couples by ``crosstalk``, and the coil
    axes are turned ``source_turn_deg`` / ``sensor_turn_deg`` against the fixture's frame,
    so that neither source coil x nor the declared ``+x`` is the fixture's x.
    """
    rng = np.random.default_rng() if rng is None else rng
    for name, value in (("gain", gain), ("crosstalk", crosstalk)):
        if not (np.isfinite(value) and 0 <= value < 0.3):
            raise InputError(f"{name} must be a fraction in [0, 0.3), got {value}")
    A = _coils(gain, crosstalk, source_turn_deg, rng)
    B = _coils(gain, crosstalk, sensor_turn_deg, rng)
    return Tracker(A, B, ring_offsets(source_offset, rng), ring_offsets(sensor_offset, rng))
