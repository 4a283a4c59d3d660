"""The tracker's own coil model: signal model, Jacobians, pose solve, calibration, file, simulator."""

import copy
import json

import numpy as np
import pytest

from ivc import dipole, rotations
from ivc.dipole.tracker import Tracker, load_tracker, model, save_tracker
from ivc.errors import TrackerError
from ivc.pose.calibrate import (
    Fixtures,
    ParameterLayout,
    calibrate,
    calibration_jacobian,
    canonical_gauge,
    pose_errors,
    predicted_signal,
    rigid_transform,
)
from ivc.pose.tracker import tracker_pose
from ivc.sim.stage import stage_pattern, stage_recording
from tests.helpers import imperfect_tracker, rig_fixtures


def _central(fn, h=1e-6):
    return (fn(h) - fn(-h)) / (2 * h)


# --- model ---------------------------------------------------------------------------------------


def test_model_jacobians_match_finite_differences(rng):
    tr = imperfect_tracker(rng)
    R = rotations.to_matrix(rotations.random(5, rng))
    t = 0.2 * rng.standard_normal((5, 3)) + np.array([0.3, 0.0, 0.0])
    S, d = model(R, t, tr, parts=True)
    scale = np.abs(S).max()
    for m in range(3):
        e = np.eye(3)[m]
        fd = _central(lambda s, e=e: model(R, t + s * e, tr)[0])
        np.testing.assert_allclose(d.d_t[..., m], fd, atol=1e-7 * scale / 1e-1)
        fd = _central(lambda s, e=e: model(R @ rotations.to_matrix(rotations.from_rotvec(s * e)), t, tr)[0])
        np.testing.assert_allclose(d.d_w[..., m], fd, atol=1e-7 * scale)
        fd = _central(lambda s, e=e: model(R, t + s * (R @ e), tr)[0])
        np.testing.assert_allclose(d.d_v[..., m], fd, atol=1e-6 * scale)
    for a in range(3):
        for b in range(3):
            for name, sl, part in (("source_moments", (slice(None), slice(None), b), d.d_A[:, :, b, a]),
                                   ("sensor_moments", (slice(None), b, slice(None)), d.d_B[:, b, :, a]),
                                   ("source_offsets", (slice(None), slice(None), a), d.d_p[:, :, a, b]),
                                   ("sensor_offsets", (slice(None), a, slice(None)), d.d_q[:, a, :, b])):
                def moved(s, name=name, a=a, b=b):
                    other = copy.deepcopy(tr)
                    getattr(other, name)[a, b] += s
                    return model(R, t, other)[0]

                fd = _central(moved)
                np.testing.assert_allclose(part, fd[sl], atol=1e-6 * scale / 1e-2)
                rest = np.delete(fd, sl[2] if sl[1] == slice(None) else sl[1],
                                 axis=2 if sl[1] == slice(None) else 1)
                assert np.abs(rest).max() < 1e-6 * scale  # no other coil moves


def test_concentric_model_is_gains_around_the_ideal_signal(rng):
    tr = imperfect_tracker(rng, offsets=False)
    r = np.array([[0.3, 0.1, -0.05], [0.2, -0.1, 0.1]])
    T = rotations.to_matrix(rotations.random(2, rng))
    S = tr.signal(r, T)
    np.testing.assert_allclose(S, tr.sensor_moments.T @ dipole.signal(r, T) @ tr.source_moments, rtol=1e-13)
    np.testing.assert_allclose(tr.corrected(S), dipole.signal(r, T), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(model(T, r, tr)[0], S, rtol=1e-12)
    offset = imperfect_tracker(rng)
    np.testing.assert_allclose(offset.signal(r, T), model(T, r, offset)[0], rtol=1e-13)


def test_ideal_tracker_is_the_dipole_model_bit_for_bit(rng):
    r = 0.5 * rng.standard_normal((50, 3)) + np.array([0.6, 0, 0])
    T = rotations.to_matrix(rotations.random(50, rng))
    ideal = Tracker.ideal()
    assert ideal.is_ideal and ideal.is_concentric
    assert np.array_equal(ideal.signal(r, T), dipole.signal(r, T))
    S = dipole.signal(r, T)
    solution = tracker_pose(S, None, "+x")
    r0, T0 = dipole.closed_form_pose(S, "+x")
    assert np.array_equal(solution.position, r0) and np.array_equal(solution.rotation, T0)


def test_ideal_tracker_leaves_the_simulator_unchanged():
    from ivc.sim import Simulator
    from ivc.sim.scene import scene_from_dict

    scene = scene_from_dict({"conductor": [{"shape": "plate", "size": [1.0, 1.0], "position": [0.5, 0, -0.35],
                                            "material": "aluminium", "resolution_mm": 120}]})
    scene.tabulate = False
    plain, _ = Simulator(scene, seed=3).step("check", 200)
    ideal, _ = Simulator(scene, seed=3, tracker=Tracker.ideal()).step("check", 200)
    for name in ("signal", "position", "quaternion", "valid"):
        assert np.array_equal(getattr(plain, name), getattr(ideal, name), equal_nan=True)
    skewed, _ = Simulator(scene, seed=3, tracker=imperfect_tracker(np.random.default_rng(1))).step("check", 200)
    ok = plain.valid & skewed.valid
    assert not np.allclose(plain.signal[ok], skewed.signal[ok])


# --- pose ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("offsets", [False, True])
def test_pose_solve_with_the_model_is_exact_without_noise(rng, offsets):
    tr = imperfect_tracker(rng, offsets=offsets)
    d = rng.standard_normal((200, 3))
    d[:, 0] = np.abs(d[:, 0]) + 0.3
    r = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.15, 0.6, (200, 1))
    T = rotations.to_matrix(rotations.random(200, rng))
    S = tr.signal(r, T)
    solution = tracker_pose(S, tr, "+x")
    assert solution.converged.all()
    assert np.abs(solution.position - r).max() < 1e-9
    assert rotations.angle_between_matrices(solution.rotation, T).max() < 1e-8
    # the ideal model on the same signals is off by the coil errors: millimetres at least
    naive = tracker_pose(S, None, "+x")
    assert np.sqrt(np.mean(np.sum((naive.position - r) ** 2, axis=1))) > 1e-3


def test_pose_solve_marks_bad_frames():
    S = np.full((2, 3, 3), np.nan)
    S[1] = dipole.signal([0.3, 0, 0], np.eye(3))
    solution = tracker_pose(S, imperfect_tracker(np.random.default_rng(0)), "+x")
    assert np.isnan(solution.position[0]).all() and not solution.converged[0]


# --- calibration -----------------------------------------------------------------------------------


@pytest.mark.parametrize("source_fixture", [False, True])
def test_calibration_jacobian_matches_finite_differences(rng, source_fixture):
    tr = imperfect_tracker(rng)
    tr.bias = 1e-3 * rng.standard_normal((3, 3))
    fixtures = rig_fixtures(rng)
    fixtures.source = rigid_transform(rotations.to_matrix(rotations.from_rotvec(0.02 * rng.standard_normal(3))),
                                 0.003 * rng.standard_normal(3))
    J_so, J_st = stage_pattern(xyz_mm=(-40.0, 40.0), rz_deg=(-60.0, 30.0), sensor_fixtures=("YoutZup", "ZinYup"))
    if source_fixture:
        J_so[::2, :3, :3] = rotations.to_matrix(rotations.from_rotvec([0.0, 0.0, np.pi / 2]))
    layout = ParameterLayout(True, source_fixture, bias=True)
    _, J = calibration_jacobian(layout, tr, fixtures, J_so, J_st)
    for k in range(layout.size):
        e = np.zeros(layout.size)
        e[k] = 1.0

        def moved(s, e=e):
            return predicted_signal(*layout.apply(tr, fixtures, s * e), J_so, J_st).reshape(len(J_st), 9)

        fd = _central(moved, 1e-7)
        np.testing.assert_allclose(J[:, :, k], fd, atol=1e-5 * np.abs(fd).max() + 1e-9, err_msg=f"parameter {k}")


def test_canonical_gauge_keeps_every_prediction(rng):
    tr, fixtures = imperfect_tracker(rng), rig_fixtures(rng)
    J_so, J_st = stage_pattern(xyz_mm=(-50.0, 50.0), rz_deg=(0.0, 90.0))
    for free in (False, True):
        clean_tr, clean_fix = canonical_gauge(tr, fixtures, J_so[0], free)
        np.testing.assert_allclose(predicted_signal(clean_tr, clean_fix, J_so, J_st),
                                   predicted_signal(tr, fixtures, J_so, J_st), rtol=1e-10, atol=1e-12)
        assert np.allclose(np.tril(clean_tr.source_moments, -1), 0)
        assert np.allclose(np.tril(clean_tr.sensor_moments, -1), 0)
        assert clean_tr.sensor_moments[2, 2] == pytest.approx(1.0)
        assert np.allclose(clean_tr.source_offsets.mean(axis=0), 0)
        assert np.allclose(clean_tr.sensor_offsets.mean(axis=0), 0)


def test_calibration_recovers_a_simulated_tracker_to_the_noise(rng):
    truth, fixtures = imperfect_tracker(rng), rig_fixtures(rng)
    J_so, J_st = stage_pattern()
    noise = 2e-4
    S = stage_recording(truth, fixtures, J_so, J_st, noise_relative=noise, rng=rng)
    result = calibrate(S, J_so, J_st, offsets=True, output_correction=False)
    assert result.converged
    # the residue is the noise: sqrt(9) entries x noise per entry
    assert np.sqrt(np.mean(result.residue**2)) == pytest.approx(3 * noise, rel=0.1)
    want, _ = canonical_gauge(truth, fixtures, J_so[0], False)
    got = result.tracker
    sigma = result.parameter_sigma
    errors = []
    for a, b in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
        errors.append((got.source_moments[a, b] - want.source_moments[a, b]) / sigma[f"A[{a},{b}]"])
    for a, b in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2)):
        errors.append((got.sensor_moments[a, b] - want.sensor_moments[a, b]) / sigma[f"B[{a},{b}]"])
    for i in range(2):
        for m in range(3):
            errors.append((got.source_offsets[i, m] - want.source_offsets[i, m]) / sigma[f"p[{i},{m}]"])
            errors.append((got.sensor_offsets[i, m] - want.sensor_offsets[i, m]) / sigma[f"q[{i},{m}]"])
    errors = np.array(errors)
    assert np.abs(errors).max() < 5.0  # every parameter within 5 standard errors
    assert 0.4 < np.sqrt(np.mean(errors**2)) < 2.0  # and the errors are the noise's, not a bias
    # poses solved with the recovered model match truth as well as with the true model
    held_so, held_st = stage_pattern(xyz_mm=(-45.0, -15.0, 15.0, 45.0), rz_deg=(-70.0, 20.0))
    S_held = stage_recording(truth, fixtures, held_so, held_st, noise_relative=noise, rng=rng)
    # (the fit reports poses in its own gauge's frames, so each is scored against its own chain)
    err_fit, ang_fit = pose_errors(got, result.fixtures, S_held, held_so, held_st)
    err_truth, ang_truth = pose_errors(truth, fixtures, S_held, held_so, held_st)
    assert np.sqrt(np.mean(err_fit**2)) < 1.5 * np.sqrt(np.mean(err_truth**2))
    assert np.sqrt(np.mean(ang_fit**2)) < 1.5 * np.sqrt(np.mean(ang_truth**2))
    assert np.sqrt(np.mean(err_truth**2)) < 1e-3  # and that is the noise's sub-millimetre error


def test_calibration_without_noise_is_exact(rng):
    truth, fixtures = imperfect_tracker(rng, offsets=False), rig_fixtures(rng)
    J_so, J_st = stage_pattern(rz_deg=(-90.0, 0.0, 90.0))
    S = stage_recording(truth, fixtures, J_so, J_st)
    result = calibrate(S, J_so, J_st, offsets=False)
    assert np.sqrt(np.mean(result.residue**2)) < 1e-9
    want, want_fix = canonical_gauge(truth, fixtures, J_so[0], False)
    np.testing.assert_allclose(result.tracker.source_moments, want.source_moments, atol=1e-9)
    np.testing.assert_allclose(result.tracker.sensor_moments, want.sensor_moments, atol=1e-9)
    position, angle = pose_errors(result.tracker, result.fixtures, S, J_so, J_st)
    assert position.max() < 1e-8 and angle.max() < 1e-8
    assert np.abs(result.tracker.position_correction).max() < 1e-8


def test_calibration_refuses_bad_input(rng):
    J_so, J_st = stage_pattern(xyz_mm=(0.0,), rz_deg=(0.0,), sensor_fixtures=("YoutZup",))
    with pytest.raises(TrackerError, match="at least 12"):
        calibrate(np.ones((1, 3, 3)), J_so, J_st)
    J_so, J_st = stage_pattern()
    S = stage_recording(Tracker.ideal(), rig_fixtures(rng), J_so, J_st)
    S[3, 0, 0] = np.nan
    with pytest.raises(TrackerError, match="finite"):
        calibrate(S, J_so, J_st)
    with pytest.raises(TrackerError, match="same N"):
        calibrate(S[:-1], J_so, J_st)


# --- file ----------------------------------------------------------------------------------------


def test_tracker_file_round_trip_and_errors(tmp_path, rng):
    tr = imperfect_tracker(rng)
    tr.position_correction = 1e-3 * rng.standard_normal((3, 4))
    tr.calibration = {"model": "per-coil offsets", "value": np.float64(1.5), "nan": float("nan")}
    path = tmp_path / "t.json"
    save_tracker(tr, path)
    back = load_tracker(path)
    for name in ("source_moments", "sensor_moments", "source_offsets", "sensor_offsets", "bias",
                 "position_correction", "rotation_correction"):
        assert np.array_equal(getattr(back, name), getattr(tr, name)), name
    assert back.calibration["value"] == 1.5 and back.calibration["nan"] is None
    data = json.loads(path.read_text())
    data["version"] = 99
    path.write_text(json.dumps(data))
    with pytest.raises(TrackerError, match="version 99"):
        load_tracker(path)
    path.write_text("{")
    with pytest.raises(TrackerError, match="not a JSON tracker file"):
        load_tracker(path)
    path.write_text(json.dumps({"format": "ivc-tracker", "version": 1, "source_moments": [[1, 0], [0, 1]],
                                "sensor_moments": np.eye(3).tolist()}))
    with pytest.raises(TrackerError, match="source_moments must be a 3x3"):
        load_tracker(path)
    with pytest.raises(TrackerError, match="singular"):
        Tracker(np.zeros((3, 3)))


def test_calibration_start_finds_a_rig_along_another_axis(rng):
    truth = imperfect_tracker(rng, offsets=False)
    fixtures = Fixtures(stage=rigid_transform(t=np.array([0.0, 0.01, 0.3])))  # the stage out along source z
    J_so, J_st = stage_pattern(rz_deg=(-90.0, 0.0, 90.0))
    S = stage_recording(truth, fixtures, J_so, J_st)
    result = calibrate(S, J_so, J_st, offsets=False, output_correction=False)
    assert np.sqrt(np.mean(result.residue**2)) < 1e-9


def test_nominal_source_motions_get_their_own_errors(rng):
    """A source fixture's 90-degree turn that is really 90.5 degrees: ``source_motions="free"`` fits it."""
    truth, fixtures = imperfect_tracker(rng, offsets=False), rig_fixtures(rng)
    J_so, J_st = stage_pattern(rz_deg=(-90.0, 0.0, 90.0))
    turn = rotations.to_matrix(rotations.from_rotvec([0.0, 0.0, np.pi / 2]))
    J_so[len(J_so) // 2 :, :3, :3] = turn
    actual = J_so.copy()
    error = rigid_transform(rotations.to_matrix(rotations.from_rotvec(np.radians([0.2, -0.3, 0.5]))),
                       np.array([0.001, -0.002, 0.0005]))
    actual[len(J_so) // 2 :] = actual[len(J_so) // 2 :] @ error
    S = stage_recording(truth, fixtures, actual, J_st)
    exact = calibrate(S, J_so, J_st, offsets=False, output_correction=False)
    free = calibrate(S, J_so, J_st, offsets=False, output_correction=False, source_motions="free")
    assert np.sqrt(np.mean(exact.residue**2)) > 1e-3  # the nominal turn does not fit
    assert np.sqrt(np.mean(free.residue**2)) < 1e-9
    assert len(free.fixtures.motions) == 2 and np.allclose(free.fixtures.motion_errors[0], np.eye(4), atol=1e-12)
    back = Fixtures.from_dict(json.loads(json.dumps(free.fixtures.to_dict())))
    np.testing.assert_allclose(predicted_signal(free.tracker, back, J_so, J_st),
                               predicted_signal(free.tracker, free.fixtures, J_so, J_st), rtol=1e-12)
    other = J_so.copy()
    other[:3, :3, :3] = turn.T
    with pytest.raises(TrackerError, match="none of the calibration's"):
        predicted_signal(free.tracker, free.fixtures, other, J_st)


def test_calibration_jacobian_with_free_source_motions(rng):
    tr, fixtures = imperfect_tracker(rng), rig_fixtures(rng)
    J_so, J_st = stage_pattern(xyz_mm=(-40.0, 40.0), rz_deg=(-60.0, 30.0), sensor_fixtures=("YoutZup", "ZinYup"))
    J_so[1::3, :3, :3] = rotations.to_matrix(rotations.from_rotvec([0.0, 0.0, np.pi / 2]))
    J_so[2::3, :3, :3] = rotations.to_matrix(rotations.from_rotvec([np.pi, 0.0, 0.0]))
    from ivc.pose.calibrate import distinct_source_motions

    motions = distinct_source_motions(J_so)
    fixtures.motions = motions
    fixtures.motion_errors = [np.eye(4)] + [
        rigid_transform(rotations.to_matrix(rotations.from_rotvec(0.01 * rng.standard_normal(3))),
                   0.002 * rng.standard_normal(3)) for _ in motions[1:]]
    layout = ParameterLayout(True, False, motion_groups=len(motions))
    _, J = calibration_jacobian(layout, tr, fixtures, J_so, J_st)
    for k in range(layout.fix, layout.size):
        e = np.zeros(layout.size)
        e[k] = 1.0

        def moved(s, e=e):
            return predicted_signal(*layout.apply(tr, fixtures, s * e), J_so, J_st).reshape(len(J_st), 9)

        fd = _central(moved, 1e-7)
        np.testing.assert_allclose(J[:, :, k], fd, atol=1e-5 * np.abs(fd).max() + 1e-9, err_msg=f"parameter {k}")
    # the gauge moves every motion's points together
    clean_tr, clean_fix = canonical_gauge(tr, fixtures, J_so[0], False)
    np.testing.assert_allclose(predicted_signal(clean_tr, clean_fix, J_so, J_st),
                               predicted_signal(tr, fixtures, J_so, J_st), rtol=1e-10, atol=1e-12)
