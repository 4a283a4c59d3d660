"""The simulated tracker, fixtures and motions."""

import numpy as np
import pytest

from ivc import dipole
from ivc import rotations as R
from ivc.fixtures import CUBE_BITS, fixture_frame
from ivc.sim import Scene, Simulator, rig
from ivc.sim.scene import NoiseSpec, SceneError, scene_from_dict
from ivc.sim.tracker import measure


@pytest.fixture(scope="module")
def free_space():
    return Simulator(Scene(noise=NoiseSpec.none()), seed=7)


def test_free_space_without_noise_is_exactly_the_dipole_model(free_space):
    for name in ("cube_calibration", "wand_sweep", "check"):
        step, truth = free_space.step(name, 300)
        expected = dipole.signal(truth.position, R.to_matrix(truth.quaternion))
        np.testing.assert_array_equal(step.signal, expected)
        assert np.all(step.valid)
        assert np.abs(step.position - truth.position).max() < 1e-9
        assert R.angle_between(step.quaternion, truth.quaternion).max() < 1e-9


def test_same_seed_same_data_and_steps_are_independent():
    a = Simulator(Scene(), seed=3)
    b = Simulator(Scene(), seed=3)
    sweep_a, _ = a.step("wand_sweep", 500)
    b.step("cube_calibration", 100)  # simulating another step first changes nothing
    sweep_b, _ = b.step("wand_sweep", 500)
    np.testing.assert_array_equal(sweep_a.signal, sweep_b.signal)
    np.testing.assert_array_equal(a.wand.body_positions, b.wand.body_positions)
    other, _ = Simulator(Scene(), seed=4).step("wand_sweep", 500)
    assert not np.array_equal(other.signal, sweep_a.signal)


def test_cube_geometry_numbering_and_fixture_frame(free_space):
    cube = free_space.cube
    spec = free_space.scene.cube
    nominal = spec.edge * CUBE_BITS
    offsets = np.linalg.norm(cube.body_positions - nominal, axis=1)
    assert np.all(offsets < 6 * spec.mounting_sigma) and np.any(offsets > 0)
    # n = 4x + 2y + z: sensor 4 along X from sensor 0, 2 along Y, 1 along Z
    np.testing.assert_array_equal(CUBE_BITS[[4, 2, 1]], np.eye(3))
    origin, T_I = fixture_frame(cube.body_positions)
    np.testing.assert_allclose(T_I.T @ T_I, np.eye(3), atol=1e-15)
    assert np.linalg.det(T_I) == pytest.approx(1.0)
    along_x = T_I.T @ (cube.body_positions[4] - origin)
    assert along_x[1] == pytest.approx(0, abs=1e-15) and along_x[2] == pytest.approx(0, abs=1e-15)


def test_declared_pose_carries_a_placement_error(free_space):
    r0, T_I = free_space.true_cube_frame()
    position, quaternion = free_space.declared_cube_pose()
    error_mm = 1000 * np.linalg.norm(position - r0)
    error_mrad = 1000 * R.angle_between(quaternion, R.from_matrix(T_I))
    assert 0.1 < error_mm < 10 and 0.1 < error_mrad < 15
    survey, truth = free_space.step("cube_survey", 20)
    np.testing.assert_array_equal(survey.attrs["declared_position"], position)
    # the survey's truth is the true cube: sensor 0 at r0
    np.testing.assert_allclose(truth.position[0, 0], r0, atol=1e-15)


@pytest.mark.slow
def test_sweep_keeps_sensor0_in_the_cube_and_covers_the_sphere():
    scene = Scene()
    sim = Simulator(scene, seed=1)
    _, truth = sim.step("wand_sweep", 100_000)
    p0 = truth.position[:, 0]
    local = (p0 - scene.cube.center) @ R.to_matrix(scene.cube.quaternion)
    assert np.abs(local).max() <= 0.3 * scene.cube.edge + 1e-12
    # the wand's direction (sensor 7 minus sensor 0) covers the sphere evenly
    direction = truth.position[:, -1] - p0
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    z_band = np.digitize(direction[:, 2], np.linspace(-1, 1, 11))  # equal-area bands
    counts = np.bincount(z_band, minlength=12)[1:11]
    assert counts.min() > 0.7 * counts.mean()
    # smooth motion at about 0.3 rad/s
    q = R.to_scipy(truth.quaternion[:, 0])
    rate = R.angle_between(truth.quaternion[1:, 0], truth.quaternion[:-1, 0]) * scene.sweep_rate_hz
    assert 0.25 < np.median(rate) < 0.4 and rate.max() < 0.6
    assert len(q) == 100_000


def test_check_poses_fill_the_mapped_ball():
    scene = Scene()
    positions, quaternions = rig.check_poses(scene, 20_000, np.random.default_rng(0))
    radius = np.linalg.norm(positions[:, 0] - scene.cube.center, axis=1)
    assert radius.max() <= scene.check_radius
    # uniform in the ball: a quarter of the volume lies within 0.63 R
    assert np.mean(radius < 0.63 * scene.check_radius) == pytest.approx(0.25, abs=0.02)


def test_noise_gives_realistic_static_jitter():
    noise = NoiseSpec(dropout_rate=0.0)
    truth_p = np.tile([[0.5, 0.05, -0.03]], (4000, 1, 1))
    truth_q = np.tile(R.random(1, 0)[None], (4000, 1, 1))
    step = measure(truth_p, truth_q, secondary=None, noise=noise, rate_hz=240, hemisphere="+x",
                   rng=np.random.default_rng(0))
    jitter_mm = 1000 * np.linalg.norm(step.position[:, 0].std(axis=0))
    jitter_mrad = 1000 * np.sqrt(np.mean(R.angle_between(step.quaternion[:, 0], truth_q[:, 0]) ** 2))
    assert 0.01 < jitter_mm < 0.1
    assert 0.03 < jitter_mrad < 0.5


def test_dropouts_and_saturation_are_flagged():
    noise = NoiseSpec(dropout_rate=0.05, saturation_range=0.1)
    positions = np.zeros((2000, 2, 3))
    positions[:, 0] = [0.5, 0.0, 0.0]
    positions[:, 1] = [0.05, 0.0, 0.0]  # too close to the source
    quaternions = np.tile(R.IDENTITY, (2000, 2, 1))
    step = measure(positions, quaternions, secondary=None, noise=noise, rate_hz=240, hemisphere="+x",
                   rng=np.random.default_rng(0))
    assert not step.valid[:, 1].any()
    assert step.valid[:, 0].mean() == pytest.approx(0.95, abs=0.02)
    assert np.all(np.isnan(step.signal[~step.valid])) and np.all(np.isfinite(step.signal[step.valid]))
    assert np.all(np.isnan(step.position[~step.valid]))


def test_tracker_reports_its_own_dipole_solution():
    sim = Simulator(Scene(), seed=2)
    step, _ = sim.step("check", 200)
    ok = step.valid[:, 0]
    position, T = dipole.closed_form_pose(step.signal[ok], "+x")
    np.testing.assert_array_equal(position, step.position[ok])


def test_distorted_scene_bends_the_dipole_solution():
    scene = scene_from_dict({"conductor": [{"shape": "plate", "size": [1.0, 1.0], "position": [0.5, 0, -0.3],
                                            "material": "perfect", "resolution_mm": 80}]})
    scene.noise = NoiseSpec.none()
    sim = Simulator(scene, seed=0)
    step, truth = sim.step("check", 300)
    error = np.linalg.norm(step.position - truth.position, axis=-1)
    assert np.median(error) > 0.005
    free, free_truth = Simulator(Scene(noise=NoiseSpec.none()), seed=0).step("cube_survey", 10)
    assert np.abs(free.position - free_truth.position).max() < 1e-9


def test_scene_errors_name_the_entry():
    with pytest.raises(SceneError, match=r"conductor\[0\].shape"):
        scene_from_dict({"conductor": [{"shape": "blob", "position": [0, 0, 0]}]}, "room")
    with pytest.raises(SceneError, match=r"conductor\[0\]: missing 'position'"):
        scene_from_dict({"conductor": [{"shape": "plate", "size": [1, 1]}]}, "room")
    with pytest.raises(SceneError, match="material"):
        scene_from_dict({"conductor": [{"shape": "plate", "size": [1, 1], "position": [0, 0, 0],
                                        "material": "cheese"}]}, "room")
    with pytest.raises(SceneError, match="hemisphere"):
        scene_from_dict({"hemisphere": "up"}, "room")
