"""The pose-only self-calibration (ivc.lut.reported_bundle): its Jacobians, and that it recovers the wand's poses."""

import numpy as np
import pytest

from ivc import rotations
from ivc.lut import harmonics
from ivc.lut.reported_bundle import WandFrames, adjust, sample_terms, solve_frames
from ivc.pose.reported_fit import PosePairs, fit_through_tracker
from ivc.pose.tracker_solver import distortion

CENTRE, SCALE, DEGREE = np.array([0.45, 0.05, 0.1]), 0.35, 3
LEVERS = np.array([[0.0, 0.0, 0.0], [0.08, 0.01, 0.0], [0.17, -0.01, 0.01], [0.26, 0.0, -0.01]])


def basis(r):
    return harmonics.gradients((r - CENTRE) / SCALE, DEGREE)


def _room(seed=0, frames=200):
    """A secondary field of degree 3 (about a fifth of the source's), a rigid wand of 4 sensors swept about the
    cube, its exact reported poses, and the cube's 8 vertices as anchors."""
    rng = np.random.default_rng(seed)
    K = harmonics.count(DEGREE)
    c = rng.normal(size=(K, 3)) * 4e-3 / np.sqrt(np.arange(1, K + 1))[:, None]
    turns = rotations.to_matrix(rotations.from_rotvec(rng.normal(size=(4, 3)) * 0.2))
    turns[0] = np.eye(3)
    p = CENTRE + rng.uniform(-0.05, 0.05, size=(frames, 3))
    R = rotations.to_matrix(rotations.from_rotvec(rng.normal(size=(frames, 3))))
    r = p[:, None] + np.einsum("fij,nj->fni", R, LEVERS)
    T = R[:, None] @ turns[None]
    G = np.einsum("nki,kj->nij", basis(r.reshape(-1, 3)), c)
    v, C = distortion(r.reshape(-1, 3), G)
    frames_ = WandFrames(p, R, v.reshape(frames, 4, 3), C.reshape(frames, 4, 3, 3) @ T, np.ones((frames, 4), bool))
    vertices = CENTRE + 0.05 * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    Tv = rotations.to_matrix(rotations.from_rotvec(rng.normal(size=(8, 3))))
    va, Ca = distortion(vertices, np.einsum("nki,kj->nij", basis(vertices), c))
    anchors = PosePairs(vertices, Tv, va, Ca @ Tv, np.zeros(8, int), np.arange(8))
    return c, turns, frames_, anchors


def _displaced(frames: WandFrames, rng, mm=1.0, mrad=3.0) -> WandFrames:
    """The frames' poses off by a smooth error: a shift that grows across the cube, and a turn."""
    shift = 1e-3 * mm * (frames.position - CENTRE) / 0.05 + 1e-3 * mm * np.array([0.5, -0.3, 0.2])
    turn = rotations.to_matrix(rotations.from_rotvec(np.broadcast_to(1e-3 * mrad * np.array([1.0, 0.5, -0.5]),
                                                                     frames.position.shape)))
    return WandFrames(frames.position + shift, turn @ frames.rotation, frames.reported_position,
                      frames.reported_rotation, frames.use)


def test_jacobians_match_central_differences():
    c, turns, frames, _ = _room(frames=5)
    rng = np.random.default_rng(3)
    frames = _displaced(frames, rng, 0.01, 0.01)  # near the solution, where the Jacobians are exact to first order
    e, f, Xc, Xp = sample_terms(frames, LEVERS, turns, basis, c, "closed-form", "+x")
    h = 1e-6
    for k in range(6):
        d = np.zeros((len(frames), 6))
        d[:, k] = h

        def moved(dp):
            turn = rotations.to_matrix(rotations.from_rotvec(dp[:, 3:]))
            return WandFrames(frames.position + dp[:, :3], turn @ frames.rotation, frames.reported_position,
                              frames.reported_rotation, frames.use)

        plus, _ = sample_terms(moved(d), LEVERS, turns, basis, c, "closed-form", "+x", jacobians=False)
        minus, _ = sample_terms(moved(-d), LEVERS, turns, basis, c, "closed-form", "+x", jacobians=False)
        np.testing.assert_allclose((plus - minus) / (2 * h), Xp[:, :, k], atol=1e-4 * np.abs(Xp).max())
    for k in range(0, c.size, 7):
        d = np.zeros(c.size)
        d[k] = 1e-7
        plus, _ = sample_terms(frames, LEVERS, turns, basis, c + d.reshape(c.shape), "closed-form", "+x",
                               jacobians=False)
        minus, _ = sample_terms(frames, LEVERS, turns, basis, c - d.reshape(c.shape), "closed-form", "+x",
                                jacobians=False)
        np.testing.assert_allclose((plus - minus) / 2e-7, Xc[:, :, k], atol=1e-4 * np.abs(Xc).max())


@pytest.mark.parametrize("solver", ["closed-form", "least-squares"])
def test_adjustment_recovers_the_wand_poses_the_cube_field_got_wrong(solver):
    c, turns, truth, anchors = _room()
    if solver != "closed-form":  # the same room seen through the other tracker solver
        r = truth.position[:, None] + np.einsum("fij,nj->fni", truth.rotation, LEVERS)
        G = np.einsum("nki,kj->nij", basis(r.reshape(-1, 3)), c)
        v, C = distortion(r.reshape(-1, 3), G, solver=solver)
        T = truth.rotation[:, None] @ turns[None]
        truth = WandFrames(truth.position, truth.rotation, v.reshape(truth.reported_position.shape),
                           C.reshape(T.shape) @ T, truth.use)
        va, Ca = distortion(anchors.position, np.einsum("nki,kj->nij", basis(anchors.position), c), solver=solver)
        anchors = PosePairs(anchors.position, anchors.rotation, va, Ca @ anchors.rotation, anchors.frame,
                            anchors.sensor)
    rng = np.random.default_rng(1)
    start = _displaced(truth, rng)
    # the field the displaced poses imply (what the pose-only fit makes of them) is off too
    r = start.position[:, None] + np.einsum("fij,nj->fni", start.rotation, LEVERS)
    T = start.rotation[:, None] @ turns[None]
    n = r.shape[0] * r.shape[1]
    pairs = PosePairs(r.reshape(n, 3), T.reshape(n, 3, 3), start.reported_position.reshape(n, 3),
                      start.reported_rotation.reshape(n, 3, 3), np.repeat(np.arange(len(r)), 4),
                      np.tile(np.arange(4), len(r)))
    first, _ = fit_through_tracker(pairs, basis, {DEGREE: harmonics.count(DEGREE)}, solver, "+x", DEGREE, 1)
    before = np.linalg.norm(start.position - truth.position, axis=1)
    # solving the frames in the wrong field alone does not find them
    alone, _ = solve_frames(start, LEVERS, turns, basis, first, solver)
    fitted, frames, report = adjust(start, LEVERS, turns, basis, first, anchors, np.full(8, 10.0), solver)
    after = np.linalg.norm(frames.position - truth.position, axis=1)
    angle = rotations.angle_between_matrices(frames.rotation, truth.rotation)
    assert np.median(before) > 1e-3
    assert np.median(np.linalg.norm(alone.position - truth.position, axis=1)) > 0.3 * np.median(before)
    assert np.max(after) < 1e-6 and np.max(angle) < 1e-5
    np.testing.assert_allclose(fitted, c, atol=1e-6 * np.abs(c).max())
    assert report["rms_mm_by_iteration"][-1] < 1e-4 < report["rms_mm_by_iteration"][0]
