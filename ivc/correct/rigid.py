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
are flagged. :func:`decide_with_body` then settles, from the same consensus, the sensors a reported pose alone
left ambiguous: each is solved again from where the body puts it, and trusted where that solution agrees with
the body.
"""

from __future__ import annotations

import numpy as np

from ivc import rotations
from ivc.correct.reported import PoseCorrector
from ivc.correct.reported_kernels import RESTARTS
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


def decide_with_body(corrector: PoseCorrector, position: np.ndarray, quaternion: np.ndarray, out: Correction,
                     body: WandCalibration, agreement: tuple[float, float] = AGREEMENT, min_sensors: int = 2
                     ) -> np.ndarray:
    """Trust, in place, the sensors of ``out`` that their rigid body puts on one branch: frames (F, W) of the body's W
    sensors in its calibration's order, corrected by ``corrector`` from reported ``position`` (F, W, 3) m and
    ``quaternion`` (F, W, 4) [w, x, y, z] (NaN: no reported pose, nothing to decide). A sensor flagged HIGH_RESIDUAL
    alone (the map produces its reported pose twice, or not within the residual limit) in a frame where the body's
    trusted sensors agree on its pose (:meth:`~ivc.fixtures.wand.WandCalibration.consensus`, ``agreement`` (m, rad),
    ``min_sensors``) is solved again, started where the body puts it
    (:meth:`~ivc.correct.reported.PoseCorrector.correct_from`: no other start, as a continuing track, with the
    ambiguity test's Jacobian restarts); where that solution passes every test and lies within ``agreement`` of the
    body's pose for it, it replaces the sample's. Run :func:`agree_with_body` first, so that the consensus is of
    agreeing sensors. Returns the samples newly trusted (F, W) bool."""
    flags = out.flags
    W = len(body.positions)
    position, quaternion = np.asarray(position, float), np.asarray(quaternion, float)
    if flags.ndim != 2 or flags.shape[1] != W or position.shape != flags.shape + (3,) \
            or quaternion.shape != flags.shape + (4,):
        raise InputError(f"a rigid body of {W} sensors needs corrected frames (F, {W}) and the reported positions "
                         f"(F, {W}, 3) and quaternions (F, {W}, 4) they came from, got {flags.shape}, "
                         f"{position.shape} and {quaternion.shape}")
    decided = np.zeros(flags.shape, dtype=bool)
    consensus = body.consensus(out.position, out.quaternion, flags == 0, agreement, min_sensors)
    has_pose = np.all(np.isfinite(position), axis=-1) & np.all(np.isfinite(quaternion), axis=-1)
    frame, sensor = np.nonzero((flags == HIGH_RESIDUAL) & has_pose & consensus.kept[:, None])
    if not len(frame):
        return decided
    # where the body puts each candidate: T_n = T_0 R_n, r_n = r_0 + T_0 p_n
    T0, r0 = consensus.rotation[frame], consensus.position[frame]
    T = T0 @ body.rotations[sensor]
    r = r0 + np.einsum("nij,nj->ni", T0, body.positions[sensor])
    v = position[frame, sensor]
    Q = rotations.to_matrix(quaternion[frame, sensor])
    # near a fold Broyden's estimate from the identity stalls: the search recomputes it, as the ambiguity test's do
    again = corrector.correct_from(v, Q, r - v, restarts=RESTARTS)
    turned = rotations.to_matrix(np.where(np.isfinite(again.quaternion), again.quaternion, [1.0, 0.0, 0.0, 0.0]))
    cos = np.clip((np.trace(np.swapaxes(turned, -1, -2) @ T, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    ok = (again.flags == 0) & (np.linalg.norm(again.position - r, axis=1) <= agreement[0]) \
        & (np.arccos(cos) <= agreement[1])
    f, n = frame[ok], sensor[ok]
    out.position[f, n], out.quaternion[f, n] = again.position[ok], again.quaternion[ok]
    out.flags[f, n], out.residual[f, n], out.iterations[f, n] = 0, again.residual[ok], again.iterations[ok]
    for name in ("precision", "orientation_precision"):
        mine, theirs = getattr(out, name), getattr(again, name)
        if mine is not None and theirs is not None:
            mine[f, n] = theirs[ok]
    decided[f, n] = True
    return decided
