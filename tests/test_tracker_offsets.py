"""Tracker calibration on any coil geometry: sources whose coils sit tens of millimetres off-centre, the
residual gate that decides convergence, and coil signs from the data (issue 39)."""

from dataclasses import replace

import numpy as np
import pytest

from ivc import dipole, rotations
from ivc.dipole.tracker import Tracker, load_tracker, save_tracker
from ivc.errors import InputError, TrackerError
from ivc.pose.calibrate import calibrate, chain, fit_output_correction, solve_chain_poses
from ivc.pose.coil_signs import find_sign_flips
from ivc.pose.tracker import ideal_signals, noise_gain, to_ideal, tracker_pose
from ivc.sim.coil_trackers import offset_tracker, ring_offsets
from ivc.sim.stage import stage_pattern, stage_recording
from tests.helpers import rig_fixtures

NOISE = 2e-4


def _truth_started(S, tracker, P):
    """The floor: the same model's solve started at the true pose (no start problem to solve)."""
    solution = tracker_pose(S, tracker, P[:, :3, 3], correct=False, retry=False, step_tolerance=1e-12,
                            start=(P[:, :3, 3], P[:, :3, :3]))
    return solution.position, solution.rotation


def _pose_differences(signal, r, T, step=1e-6):
    """Central differences (F, 9, 6) of ``signal(r, T)`` in ``r ← r + δr``, ``T ← T exp([ω]×)``."""
    columns = []
    for k in range(6):
        d = step * np.eye(6)[k]
        turn = rotations.to_matrix(rotations.from_rotvec(np.array([d[3:], -d[3:]])))
        plus, minus = signal(r + d[:3], T @ turn[0]), signal(r - d[:3], T @ turn[1])
        columns.append((plus - minus).reshape(len(r), 9) / (2 * step))
    return np.stack(columns, axis=2)


def _gain(J_device, J_ideal, B_inv_t, A_inv):
    """‖J_ideal J⁺ + C (I − J J⁺)‖_F / ‖C‖_F, J = J_device, C the gains' map, written out."""
    C = np.kron(B_inv_t, A_inv.T)
    pinv = np.linalg.pinv(J_device)
    L = J_ideal @ pinv + C @ (np.eye(9) - J_device @ pinv)
    return np.linalg.norm(L, axis=(1, 2)) / np.linalg.norm(C)


@pytest.fixture(scope="module")
def offset_rig():
    """A source with coils 45 mm off-centre, calibrated on a simulated stage; held-out points nearer and farther."""
    rng = np.random.default_rng(45)
    device, fixtures = offset_tracker(0.045, rng=rng), rig_fixtures(rng)
    J_so, J_st = stage_pattern()
    S = stage_recording(device, fixtures, J_so, J_st, noise_relative=NOISE, rng=rng)
    result = calibrate(S, J_so, J_st)
    held_so, held_st = stage_pattern(xyz_mm=(-60.0, -30.0, 0.0, 30.0, 60.0), rz_deg=(-80.0, -20.0, 40.0, 100.0))
    S_held = stage_recording(device, fixtures, held_so, held_st, noise_relative=NOISE, rng=rng)
    return device, fixtures, result, (S_held, held_so, held_st)


def test_offset_tracker_factory(rng):
    p = ring_offsets(0.045, rng)
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 0.045, rtol=1e-12)
    np.testing.assert_allclose(p.mean(axis=0), 0.0, atol=1e-15)
    device = offset_tracker(0.045, sensor_offset=0.003, rng=rng)
    np.testing.assert_allclose(np.linalg.norm(device.sensor_offsets, axis=1), 0.003, rtol=1e-12)
    # gains and cross-talk of a few percent, axes turned against the frame
    assert np.abs(np.linalg.norm(device.source_moments, axis=0) - 1).max() < 0.2
    assert not np.allclose(np.tril(device.source_moments, -1), 0, atol=1e-3)
    with pytest.raises(InputError, match="gain"):
        offset_tracker(gain=0.5)


def test_every_pose_of_a_45_mm_source_from_the_calibrations_own_start(offset_rig):
    device, fixtures, result, (S, J_so, J_st) = offset_rig
    model = result.tracker
    # the coil model holds: the residue is the noise's (3 x NOISE), the start finds every pose
    assert np.sqrt(np.mean(result.residue**2)) < 1.2 * 3 * NOISE
    assert model.residual_gate is not None and model.hemisphere is not None
    solution, P = solve_chain_poses(model, fixtures=result.fixtures, S=S, J_so=J_so, J_st=J_st, correct=False)
    r_floor, T_floor = _truth_started(S, replace(model, position_correction=np.zeros((3, 4)),
                                                 rotation_correction=np.zeros((3, 4))), P)
    assert solution.converged.all()
    # each pose is the minimum the true-pose start finds: recovered to the noise, no wrong minimum
    assert np.abs(solution.position - r_floor).max() < 1e-7
    assert rotations.angle_between_matrices(solution.rotation, T_floor).max() < 1e-6
    error = np.linalg.norm(solution.position - P[:, :3, 3], axis=1)
    assert error.max() < 5e-3 and np.sqrt(np.mean(error**2)) < 1e-3
    # the old start (closed form of the gain-corrected signal, no retry) puts some of them in wrong minima,
    # and the gate flags every one of those
    plain = tracker_pose(S, model, correct=False, retry=False)
    wrong = np.linalg.norm(plain.position - P[:, :3, 3], axis=1) > 0.01
    assert wrong.sum() > 0 and not np.any(plain.converged[wrong])
    assert plain.residual[wrong].min() > 10 * solution.residual.max()


def test_to_ideal_within_the_noise_for_every_sample(offset_rig):
    device, fixtures, _, (_, J_so, J_st) = offset_rig
    rng = np.random.default_rng(3)
    P = chain(fixtures, J_so, J_st)
    r, T = P[:, :3, 3], P[:, :3, :3]
    clean = device.signal(r, T)
    scale = np.linalg.norm(clean, ord=2, axis=(1, 2))
    noisy = clean + NOISE * scale[:, None, None] * rng.standard_normal(clean.shape)
    side = P[:, :3, 3].mean(axis=0)
    ideal = dipole.signal(r, T)
    # without noise: exact
    exact = to_ideal(clean, device, side)
    assert np.abs(exact - ideal).max() / np.abs(ideal).max() < 1e-9
    converted = ideal_signals(noisy, device, side, noise_relative=NOISE)
    assert converted.passed.all()
    # with noise: each sample's error is its own noise carried through the gains, plus what that noise does to
    # the pose the coil offsets' share is taken at. To first order (finite differences of the device's and the
    # ideal signal at the true pose, an independent check): nothing left from the start, the tolerance, the gate
    noise = noisy - clean
    A_inv, B_inv_t = np.linalg.inv(device.source_moments), np.linalg.inv(device.sensor_moments).T
    J_device, J_ideal = _pose_differences(device.signal, r, T), _pose_differences(dipole.signal, r, T)
    delta = np.linalg.solve(np.swapaxes(J_device, 1, 2) @ J_device,
                            np.swapaxes(J_device, 1, 2) @ noise.reshape(-1, 9, 1))  # the pose error (F, 6, 1)
    left = (noise.reshape(-1, 9, 1) - J_device @ delta).reshape(-1, 3, 3)
    predicted = (J_ideal @ delta).reshape(-1, 3, 3) + B_inv_t @ left @ A_inv
    error = converted.signal - ideal
    off = np.linalg.norm(error - predicted, axis=(1, 2)) / np.linalg.norm(predicted, axis=(1, 2))
    assert np.median(off) < 0.01 and off.max() < 0.2  # the largest where the pose is weakest (second order)
    # and within the noise its propagation predicts (noise_gain: the first-order factor over what the gains
    # alone carry), for every sample, though up to 6x what the gains alone carry near the coils
    carried = np.linalg.norm(B_inv_t @ noise @ A_inv, axis=(1, 2))
    np.testing.assert_allclose(noise_gain(device, r, T), _gain(J_device, J_ideal, B_inv_t, A_inv), rtol=1e-6)
    ratio = np.linalg.norm(error, axis=(1, 2)) / (converted.noise_gain * carried)
    assert ratio.max() < 3 and 0.7 < np.median(ratio) < 1.3
    assert converted.noise_gain.min() >= 1.0 and converted.noise_gain.max() > 2
    # while the raw signal is tens of percent off the ideal one near this source
    raw = np.linalg.norm(device.corrected(clean) - ideal, axis=(1, 2)) / np.linalg.norm(ideal, axis=(1, 2))
    assert np.median(raw) > 0.05


def test_a_wrong_minimum_is_flagged_and_the_output_correction_ignores_it(offset_rig):
    _, _, result, (S, J_so, J_st) = offset_rig
    model = replace(result.tracker, position_correction=np.zeros((3, 4)), rotation_correction=np.zeros((3, 4)))
    right, P = solve_chain_poses(model, result.fixtures, S, J_so, J_st, correct=False)
    plain = tracker_pose(S, model, correct=False, retry=False)
    wrong = np.flatnonzero(np.linalg.norm(plain.position - P[:, :3, 3], axis=1) > 0.01)
    assert len(wrong) and not plain.converged[wrong].any()
    k = wrong[0]
    forced = replace(right, position=right.position.copy(), rotation=right.rotation.copy(),
                     converged=right.converged.copy(), residual=right.residual.copy())
    forced.position[k], forced.rotation[k] = plain.position[k], plain.rotation[k]
    forced.converged[k], forced.residual[k] = plain.converged[k], plain.residual[k]
    with_forced = fit_output_correction(model, result.fixtures, S, J_so, J_st, solution=forced)
    keep = np.arange(len(S)) != k
    without = fit_output_correction(model, result.fixtures, S[keep], J_so[keep], J_st[keep])
    np.testing.assert_allclose(with_forced.position_correction, without.position_correction, atol=1e-12)
    np.testing.assert_allclose(with_forced.rotation_correction, without.rotation_correction, atol=1e-12)
    # had it been taken as converged, it would have moved the correction
    forced.converged[k] = True
    taken = fit_output_correction(model, result.fixtures, S, J_so, J_st, solution=forced)
    assert np.abs(taken.position_correction - without.position_correction).max() > 1e-4


def test_gate_scales_with_the_model_and_the_noise(tmp_path, offset_rig):
    _, _, result, _ = offset_rig
    model = result.tracker
    assert model.pose_gate() == pytest.approx(model.residual_gate)
    assert model.pose_gate(1e-3) > model.pose_gate() and model.pose_gate(1e-3) > 3e-3
    assert Tracker().pose_gate() == pytest.approx(0.01)  # a model without a calibrated gate
    path = tmp_path / "t.json"
    save_tracker(model, path)
    back = load_tracker(path)
    assert back.residual_gate == model.residual_gate and np.array_equal(back.hemisphere, model.hemisphere)
    with pytest.raises(TrackerError, match="residual_gate"):
        Tracker(residual_gate=-1.0)
    with pytest.raises(TrackerError, match="hemisphere"):
        Tracker(hemisphere=[0.0, 0.0, 0.0])
    with pytest.raises(TrackerError, match="noise_relative"):
        model.pose_gate(-1.0)


def test_hemisphere_comes_from_the_calibration_not_plus_x(rng):
    """A rig along the source's -y: the calibration's hemisphere is -y in its frame; the default +x would fail."""
    from ivc.pose.calibrate import Fixtures, rigid_transform

    device = offset_tracker(0.02, rng=rng)
    fixtures = Fixtures(stage=rigid_transform(rotations.to_matrix(rotations.from_rotvec([0, 0, np.pi])),
                                              np.array([0.0, -0.25, 0.0])))
    J_so, J_st = stage_pattern(rz_deg=(-90.0, 0.0, 90.0))
    S = stage_recording(device, fixtures, J_so, J_st, noise_relative=NOISE, rng=rng)
    result = calibrate(S, J_so, J_st, output_correction=False)
    P = chain(result.fixtures, J_so, J_st)
    assert np.all(P[:, :3, 3] @ result.tracker.hemisphere > 0)
    solution = tracker_pose(S, result.tracker, correct=False)  # no hemisphere given: the calibration's
    assert solution.converged.all() and np.linalg.norm(solution.position - P[:, :3, 3], axis=1).max() < 3e-3


def test_a_flipped_coil_in_a_simulated_recording_is_detected(rng):
    device, fixtures = offset_tracker(0.01, rng=rng), rig_fixtures(rng)
    parts = [stage_pattern(xyz_mm=(-40.0, 0.0, 40.0), rz_deg=(-90.0, 0.0, 90.0), sensor_fixtures=(code,))
             for code in ("YoutZup", "ZinYup", "ZinXdown")]
    J_so = np.concatenate([p[0] for p in parts])
    J_st = np.concatenate([p[1] for p in parts])
    group = np.repeat(np.arange(3), [len(p[1]) for p in parts])
    S = stage_recording(device, fixtures, J_so, J_st, noise_relative=NOISE, rng=rng)
    assert find_sign_flips(S, J_so, J_st, group) == []  # consistent recordings: nothing to say
    flipped = S.copy()
    flipped[group == 2, :, 1] *= -1  # source coil y of the third recording negated
    found = find_sign_flips(flipped, J_so, J_st, group)
    assert len(found) == 1 and found[0].group == 2
    np.testing.assert_array_equal(found[0].signs, [1, -1, 1])
    assert found[0].flipped < found[0].joint / 10


def test_a_frame_failing_by_a_room_s_field_keeps_its_pose_without_the_retry(offset_rig):
    """Next to metal every frame fails the gate by what the room adds, not by a wrong minimum: where its first
    pass is the search's best start and the coils are far enough, no other start is tried (the iterations are
    the first pass's), the pose is the one the true pose leads to. (That the wrong minima at the calibration's
    range are still retried: test_every_pose_of_a_45_mm_source_from_the_calibrations_own_start.)"""
    _, _, result, (_, J_so, J_st) = offset_rig
    model = replace(result.tracker, position_correction=np.zeros((3, 4)), rotation_correction=np.zeros((3, 4)))
    P = chain(result.fixtures, J_so, J_st)[::3]
    r, T = 2.0 * P[:, :3, 3], P[:, :3, :3]  # twice as far: coils 45 mm off-centre at 0.35-0.6 m
    clean = model.signal(r, T)
    rng = np.random.default_rng(8)
    room = 0.02 * np.linalg.norm(clean, ord=2, axis=(1, 2))[:, None, None] * rng.standard_normal(clean.shape)
    first = tracker_pose(clean + room, model, correct=False, retry=False)
    solved = tracker_pose(clean + room, model, correct=False)
    assert np.mean(first.converged) < 0.01  # 2 % of the signal: (nearly) every frame fails the gate
    assert np.array_equal(solved.iterations, first.iterations)  # and none was retried
    np.testing.assert_array_equal(solved.position, first.position)
    truth = P.copy()
    truth[:, :3, 3] = r
    floor_r, floor_T = _truth_started(clean + room, model, truth)  # the minimum the true pose leads to
    assert np.abs(solved.position - floor_r).max() < 1e-6
    assert rotations.angle_between_matrices(solved.rotation, floor_T).max() < 1e-5
