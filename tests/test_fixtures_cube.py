"""Cube calibration and placement (eq. 78-90, 108) against rigid-body simulations."""

import numpy as np
import pytest

from ivc import rotations as R
from ivc.fixtures import CUBE_BITS, CubeCalibration, CubePlacement, fit_cube, fixture_frame
from ivc.session import Step
from ivc.sim import Scene, Simulator
from ivc.sim.scene import NoiseSpec, scene_from_dict
from tests.helpers import static_capture


@pytest.fixture
def simulator():
    return Simulator(Scene(noise=NoiseSpec.none()), seed=11)


def test_calibration_is_independent_of_where_the_cube_was(simulator, rng):
    # rigid-body simulation: the same cube captured at two random poses must calibrate identically;
    # eq. 84 without the transpose (or a wrong X axis, eq. 80 as printed) makes the result pose dependent
    calibrations = []
    for _ in range(2):
        position = np.array([0.45, 0.0, 0.0]) + 0.1 * rng.standard_normal(3)
        step = static_capture(simulator.cube, position, R.random(1, rng)[0])
        calibrations.append(CubeCalibration.from_step(step))
    a, b = calibrations
    np.testing.assert_allclose(a.relative_positions, b.relative_positions, atol=1e-12)
    assert R.angle_between(a.relative_quaternions, b.relative_quaternions).max() < 1e-11
    # and equal to the cube's geometry in its own fixture frame
    origin, T_body = fixture_frame(simulator.cube.body_positions)
    np.testing.assert_allclose(a.relative_positions, (simulator.cube.body_positions - origin) @ T_body, atol=1e-12)
    expected_q = R.multiply(R.conjugate(R.from_matrix(T_body)), simulator.cube.body_quaternions)
    assert R.angle_between(a.relative_quaternions, expected_q).max() < 1e-11
    # fixture-frame conventions: sensor 0 at the origin, sensor 4 on +x, sensor 2 in the x-y plane
    np.testing.assert_allclose(a.relative_positions[0], 0, atol=1e-15)
    np.testing.assert_allclose(a.relative_positions[4, 1:], 0, atol=1e-12)
    assert a.relative_positions[4, 0] > 0 and abs(a.relative_positions[2, 2]) < 1e-12 and a.relative_positions[2, 1] > 0


def test_fixture_frame_is_a_rotation(rng):
    positions = 0.05 * CUBE_BITS + 0.003 * rng.standard_normal((8, 3))
    _, T = fixture_frame(positions)
    np.testing.assert_allclose(T.T @ T, np.eye(3), atol=1e-15)
    assert np.linalg.det(T) == pytest.approx(1.0)


def test_fit_cube_recovers_a_perfect_cube(rng):
    edge, offset, q = 0.0471, np.array([0.002, -0.001, 0.003]), R.random(1, rng)[0]
    vertices = (offset + edge * CUBE_BITS) @ R.to_matrix(q).T
    fit = fit_cube(vertices)
    assert fit.edge == pytest.approx(edge, rel=1e-12)
    np.testing.assert_allclose(fit.offset, offset, atol=1e-14)
    assert R.angle_between(fit.quaternion, q) < 1e-12
    np.testing.assert_allclose(fit.residuals, 0, atol=1e-14)
    # a perturbed cube: the residuals are what the fit could not explain, and sum to zero
    noisy = vertices + 0.001 * rng.standard_normal((8, 3))
    fit = fit_cube(noisy)
    np.testing.assert_allclose(fit.residuals.sum(axis=0), 0, atol=1e-14)
    assert np.sum(fit.residuals**2) <= np.sum((noisy - vertices) ** 2)


def test_placement_recovers_sensor_poses_and_zero_field_in_free_space(simulator):
    calibration = CubeCalibration.from_step(simulator.step("cube_calibration", 50)[0])
    survey, truth = simulator.step("cube_survey", 50)
    r0, T_I = simulator.true_cube_frame()
    survey.attrs.update(declared_position=r0, declared_quaternion=R.from_matrix(T_I))
    placement = CubePlacement.from_survey(calibration, survey)
    np.testing.assert_allclose(placement.positions, truth.position[0], atol=1e-12)
    assert R.angle_between(placement.quaternions, truth.quaternion[0]).max() < 1e-11
    np.testing.assert_allclose(placement.fields, 0, atol=1e-9)


def test_placement_measures_the_true_secondary_field():
    scene = scene_from_dict({"conductor": [{"shape": "plate", "size": [1.0, 1.0], "position": [0.5, 0, -0.3],
                                            "material": "perfect", "resolution_mm": 80}]})
    scene.noise = NoiseSpec.none()
    simulator = Simulator(scene, seed=5)
    calibration = CubeCalibration.from_step(simulator.step("cube_calibration", 20)[0])
    survey, truth = simulator.step("cube_survey", 20)
    r0, T_I = simulator.true_cube_frame()
    survey.attrs.update(declared_position=r0, declared_quaternion=R.from_matrix(T_I))
    placement = CubePlacement.from_survey(calibration, survey)
    expected = simulator.secondary(truth.position[0])
    assert np.abs(expected).max() > 1e-2  # the plate matters
    np.testing.assert_allclose(placement.fields, expected, atol=1e-9)
    np.testing.assert_allclose(placement.field_errors, 0, atol=1e-12)


def test_placement_errors_reflect_noise_and_dropouts():
    simulator = Simulator(Scene(noise=NoiseSpec(dropout_rate=0.05)), seed=2)
    calibration = CubeCalibration.from_step(simulator.step("cube_calibration", 400)[0])
    survey, _ = simulator.step("cube_survey", 400)
    assert not survey.valid.all()
    placement = CubePlacement.from_survey(calibration, survey)
    assert np.all(np.isfinite(placement.fields)) and np.all(placement.field_errors > 0)
    # standard error of a mean of ~380 frames of noise sigma: sigma / sqrt(380), within a factor 2
    from ivc.sim.tracker import noise_sigma

    expected = noise_sigma(simulator.scene.noise) / np.sqrt(380)
    assert 0.5 * expected < np.median(placement.field_errors) < 2 * expected


def test_vertex_choices(simulator):
    calibration = CubeCalibration.from_step(simulator.step("cube_calibration", 20)[0])
    np.testing.assert_array_equal(calibration.vertices("averaged"), calibration.relative_positions)
    np.testing.assert_array_equal(calibration.vertices("optimised"), calibration.fit.vertices)
    np.testing.assert_allclose(calibration.vertices("ideal"), 0.0508 * CUBE_BITS)
    assert calibration.fit.edge == pytest.approx(0.0508, abs=0.003)
    with pytest.raises(ValueError, match="vertex choice"):
        calibration.vertices("best")


def test_averaging_skips_invalid_frames():
    frames = 10
    position = np.tile([0.5, 0.0, 0.0], (frames, 8, 1)) + 0.05 * CUBE_BITS
    position[3, 2] = np.nan
    quaternion = np.tile([1.0, 0, 0, 0], (frames, 8, 1))
    quaternion[3, 2] = np.nan
    valid = np.ones((frames, 8), bool)
    valid[3, 2] = False
    calibration = CubeCalibration.from_step(Step(time=np.arange(frames) / 240.0, position=position,
                                                 quaternion=quaternion, valid=valid))
    np.testing.assert_allclose(calibration.relative_positions, 0.05 * CUBE_BITS, atol=1e-15)
    assert calibration.frames[2] == frames - 1
