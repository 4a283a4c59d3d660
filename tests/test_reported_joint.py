"""The whole-volume map from reported poses alone (ivc.lut.reported_joint): field samples from pose pairs,
the coupled fit against a dense solve, and the wand's pose from its agreeing corrected sensors."""

from __future__ import annotations

import numpy as np
import pytest

from ivc import dipole, rotations
from ivc.fixtures.wand import WandCalibration
from ivc.lut.fit_sources import design_rows
from ivc.lut.reported_joint import coupled_solve, field_samples, wand_from_sensors
from ivc.lut.samples import FieldSamples
from ivc.pose.reported_fit import PosePairs
from ivc.pose.tracker_solver import distortion

RNG = np.random.default_rng(7)


def _points(n: int) -> np.ndarray:
    """Random points (n, 3) 0.3-0.5 m from the source, in the +x hemisphere."""
    direction = RNG.normal(size=(n, 3))
    direction[:, 0] = np.abs(direction[:, 0]) + 0.5
    return direction / np.linalg.norm(direction, axis=1, keepdims=True) * RNG.uniform(0.3, 0.5, (n, 1))


def _pairs(r: np.ndarray, G: np.ndarray) -> PosePairs:
    """Pose pairs at true positions r (n, 3), random orientations, under the secondary field G (n, 3, 3)."""
    n = len(r)
    T = rotations.to_matrix(rotations.random(n, RNG))
    v, C = distortion(r, G, solver="closed-form", hemisphere="+x")
    return PosePairs(r, T, v, C @ T, np.arange(n), np.zeros(n, int))


def _secondary(r: np.ndarray) -> np.ndarray:
    """A smooth secondary field a quarter of the primary's size: the field of a dipole 0.4 m beyond the points."""
    return 0.25 * np.einsum("nia,aj->nij", dipole.field(r - np.array([0.9, 0.2, -0.1])) * 0.7**3,
                            np.array([[1.0, 0.2, 0.0], [0.1, 0.8, 0.3], [0.0, 0.2, 1.1]]))


def test_field_samples_reproduce_the_reported_pose_with_the_least_change():
    n = 200
    r = _points(n)
    G_true = _secondary(r)
    pairs = _pairs(r, G_true)
    prior = G_true + 0.005 * RNG.normal(size=(n, 3, 3)) * np.abs(G_true).max()
    G, ok, P = field_samples(pairs, prior, "closed-form", "+x")
    assert ok.all()
    v, C = distortion(pairs.position, G, solver="closed-form", hemisphere="+x")
    assert np.abs(v - pairs.reported_position).max() < 1e-6
    assert np.abs(C @ pairs.rotation - pairs.reported_rotation).max() < 1e-5
    # the projector: symmetric, idempotent, rank 6; the change from the prior lies in what the pose sees
    assert np.allclose(P, np.swapaxes(P, 1, 2), atol=1e-9) and np.allclose(P @ P, P, atol=1e-8)
    assert np.allclose(np.trace(P, axis1=1, axis2=2), 6.0, atol=1e-8)
    change = (G - prior).reshape(n, 9, 1)
    unseen = change - P @ change
    # (to first order: the constraint surface is curved, the projector is the solution's)
    assert np.all(np.linalg.norm(unseen, axis=(1, 2)) < 0.01 * np.linalg.norm(change, axis=(1, 2)))
    # and the true field differs from the sample only in what the pose does not see (to the linearisation)
    seen_error = P @ (G - G_true).reshape(n, 9, 1)
    assert np.linalg.norm(seen_error, axis=(1, 2)).max() < 0.05 * np.linalg.norm(change, axis=(1, 2)).max()


def test_coupled_solve_equals_the_dense_normal_equations():
    n, sources = 300, np.array([[1.0, 0.5, 0.3], [1.0, -0.5, 0.2], [0.9, 0.0, -0.6], [-0.5, 0.4, 0.5]])
    r = _points(n)
    fields = RNG.normal(size=(n, 3, 3))
    A = RNG.normal(size=(n, 6, 9))
    P = np.swapaxes(A, 1, 2) @ np.linalg.solve(A @ np.swapaxes(A, 1, 2), A)
    samples = FieldSamples(r, fields, RNG.uniform(1e-5, 1e-4, n), np.arange(n), np.zeros(n, int))
    damping, floor = 1e-6, 2e-5
    c, iterations, relative = coupled_solve(samples, P, sources, damping, floor)
    assert relative <= 1e-5 and iterations > 0
    # independent: the dense normal equations in vec(c) (row-major), Kronecker products written out
    X = design_rows(r, sources)  # (n, 3, 3K)
    w = samples.weights(floor)
    K3 = X.shape[2]
    B = np.einsum("nia,jb->nijab", X, np.eye(3)).reshape(n, 9, K3 * 3)  # vec(X c) = B vec(c)
    H = np.einsum("n,nkp,nkl,nlq->pq", w, B, P, B)
    d = np.einsum("n,nia,nia->a", w, X, X)  # the separable Gram's diagonal, per moment row
    H += np.diag(np.repeat(damping * d, 3))
    g = np.einsum("n,nkp,nkl,nl->p", w, B, P, fields.reshape(n, 9))
    dense = np.linalg.solve(H, g).reshape(K3, 3)
    assert np.allclose(c, dense, rtol=1e-4, atol=1e-4 * np.abs(dense).max())


@pytest.fixture()
def wand():
    positions = np.array([[0.0, 0, 0], [0, 0.05, 0], [0, 0.10, 0], [0, 0.15, 0], [0.01, 0.20, 0]])
    turns = rotations.to_matrix(rotations.from_rotvec(0.1 * RNG.normal(size=(5, 3))))
    turns[0] = np.eye(3)
    return WandCalibration(positions, turns, np.ones(5, int))


def test_the_wand_pose_is_the_agreeing_sensors_mean(wand):
    F = 4
    r0 = RNG.uniform(0.3, 0.5, (F, 3))
    T0 = rotations.to_matrix(rotations.random(F, RNG))
    positions, rots = wand.propagate(r0, T0)
    quaternion = rotations.from_matrix(rots)
    trusted = np.ones((F, 5), dtype=bool)
    positions = positions.copy()
    positions[0, 4] += [0.1, 0.05, 0.0]  # frame 0: one sensor on the map's other branch
    trusted[1, 1:] = False  # frame 1: one trusted sensor only
    trusted[2, 2:] = False
    positions[2, 1] += [0.0, 0.0, 0.01]  # frame 2: two trusted sensors that disagree by 10 mm
    precision = np.full((F, 5), 1e-4)
    turn = np.full((F, 5), 2e-4)
    p0, R0, kept, sigma, angle = wand_from_sensors(positions, quaternion, trusted, precision, turn, wand)
    assert kept.tolist() == [True, False, False, True]
    assert np.abs(p0[[0, 3]] - r0[[0, 3]]).max() < 1e-12
    assert np.abs(R0[[0, 3]] - T0[[0, 3]]).max() < 1e-12
    assert np.allclose(sigma[0], 1e-4 / 2) and np.allclose(sigma[3], 1e-4 / np.sqrt(5))  # 4 and 5 members
    assert np.isnan(p0[1]).all() and np.isnan(R0[2]).all()


@pytest.mark.slow
def test_extension_sweeps_of_reported_poses_map_the_box(monkeypatch):
    from dataclasses import replace
    from functools import partial

    from ivc import lut
    from ivc.correct import PoseCorrector
    from ivc.correct.evaluate import check_errors
    from ivc.lut import FitOptions, reported_joint
    from ivc.lut.joint import JointOptions, mapped_litres
    from ivc.lut.reported_build import fit_pose_lut
    from ivc.session import Session
    from ivc.sim import Simulator
    from ivc.sim.scene import scene_from_dict

    plate = {"shape": "plate", "size": [1.0, 1.0], "position": [0.55, 0, -0.4], "material": "aluminium",
             "resolution_mm": 80}
    scene = scene_from_dict({"conductor": [plate], "cube": {"center": [0.55, 0, 0]},
                             "volume": {"center": [0.55, 0, 0], "size": [0.6, 0.5, 0.4]},
                             "extension": {"sweeps": 2, "frames": 3000}})
    scene.tabulate = False
    frames = {"cube_calibration": 1000, "cube_survey": 200, "wand_calibration": 200, "wand_sweep": 3000,
              "check": 400}
    signals = Simulator(scene, seed=5).protocol(frames)
    session = Session(signals.hemisphere, {k: replace(s, signal=None) for k, s in signals.steps.items()},
                      signals.truth, signals.attrs)
    # one round, sources 0.1 m apart and 8,000 samples: the cockpit benchmark runs the defaults. fit_lut takes the
    # pose-only joint solve for a pose-only session with extension sweeps
    monkeypatch.setattr(reported_joint, "JointOptions", partial(JointOptions, max_iterations=1,
                                                                max_extension_frames=1500, source_spacing=0.1,
                                                                max_samples=8000))
    table = lut.fit_lut(session, FitOptions())
    cube = fit_pose_lut(session, FitOptions(refine=False))  # the joint map starts from the traced cube map
    rounds = table.fit["rounds"]
    assert [r["iteration"] for r in rounds] == [0, 1]
    assert rounds[0]["mapped_litres"] == pytest.approx(mapped_litres(cube.grid, cube.valid))
    assert mapped_litres(table.grid, table.valid) > 1.5 * rounds[0]["mapped_litres"]
    assert all(n > 0 for n in rounds[-1]["frames_solved"].values())
    assert table.fit["pairs_reproduced"] > 0.99
    report = table.report
    assert report.method == "equivalent sources, joint" and report.input == "reported poses"
    assert report.model_text().startswith(f"{report.sources} dipoles, damping ")
    assert table.map_error is not None and table.map_error[0] < 2e-4  # the map's own error, < 0.2 mm
    whole, around = check_errors(PoseCorrector(table), session), check_errors(PoseCorrector(cube), session)
    # the check poses fill the box, of which the cube's map holds a twentieth: twice as many of them trusted
    assert whole.ok.sum() >= 2 * around.ok.sum() > 0
    assert np.median(whole.ivc_position_mm[whole.ok]) < 0.2
    assert whole.ivc_position_mm[whole.ok].max() < 2.0
