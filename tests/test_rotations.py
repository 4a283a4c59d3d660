import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ivc import rotations as R


def test_to_matrix_matches_scipy_scalar_first(rng):
    q = R.random(1000, rng)
    np.testing.assert_allclose(R.to_matrix(q), R.to_scipy(q).as_matrix(), atol=1e-14)
    # the one conversion place round-trips
    np.testing.assert_allclose(R.from_scipy(R.to_scipy(q)), q, atol=1e-14)


def test_matrix_columns_are_sensor_axes():
    # 90 degrees about z: sensor x axis points along source y
    q = R.from_rotvec([0.0, 0.0, np.pi / 2])
    T = R.to_matrix(q)
    np.testing.assert_allclose(T[:, 0], [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(R.rotate(q, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-15)


def test_quaternion_matrix_round_trip(rng):
    q = R.random((50, 20), rng)
    assert np.all(q[..., 0] >= 0)
    np.testing.assert_allclose(R.from_matrix(R.to_matrix(q)), q, atol=1e-14)
    T = Rotation.random(1000, random_state=1).as_matrix()
    np.testing.assert_allclose(R.to_matrix(R.from_matrix(T)), T, atol=1e-14)


def test_round_trip_near_pi_rotations(rng):
    axes = rng.standard_normal((200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for angle in (np.pi, np.pi - 1e-9, 1e-12, 0.0):
        q = R.canonical(R.from_rotvec(axes * angle))
        np.testing.assert_allclose(R.to_matrix(R.from_matrix(R.to_matrix(q))), R.to_matrix(q), atol=1e-14)


def test_composition_is_hamilton_product(rng):
    p, q = R.random(1000, rng), R.random(1000, rng)
    np.testing.assert_allclose(R.to_matrix(R.multiply(p, q)), R.to_matrix(p) @ R.to_matrix(q), atol=1e-14)
    # conjugate is the inverse
    np.testing.assert_allclose(R.canonical(R.multiply(q, R.conjugate(q))), np.tile(R.IDENTITY, (1000, 1)), atol=1e-15)


def test_angle_accurate_near_zero_and_pi(rng):
    axes = rng.standard_normal((100, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    base = R.random(100, rng)
    for theta in (1e-8, np.pi - 1e-8, 0.3):
        delta = R.from_rotvec(axes * theta)
        moved = R.multiply(delta, base)
        np.testing.assert_allclose(R.angle_between(moved, base), theta, rtol=0, atol=1e-15 + 1e-8 * 1e-6)
        np.testing.assert_allclose(
            R.angle_between_matrices(R.to_matrix(moved), R.to_matrix(base)), theta, rtol=0, atol=1e-14
        )


def test_angle_error_well_below_1e8_at_pi_minus_1e8():
    # the naive arccos((tr-1)/2) would give an error near 1e-8 here
    q = R.from_rotvec([0.0, 0.0, np.pi - 1e-8])
    assert abs(R.angle_between_matrices(R.to_matrix(q), np.eye(3)) - (np.pi - 1e-8)) < 1e-13
    q = R.from_rotvec([1e-8, 0.0, 0.0])
    assert abs(R.angle_between_matrices(R.to_matrix(q), np.eye(3)) - 1e-8) < 1e-20


def test_rotvec_round_trip(rng):
    v = rng.standard_normal((1000, 3))
    v *= (rng.uniform(0, np.pi, 1000) / np.linalg.norm(v, axis=1))[:, None]
    np.testing.assert_allclose(R.to_rotvec(R.from_rotvec(v)), v, atol=1e-12)
    np.testing.assert_allclose(R.from_rotvec(np.zeros(3)), R.IDENTITY)
    np.testing.assert_allclose(R.to_rotvec(R.IDENTITY), np.zeros(3))


def test_mean_recovers_orientation_of_spread_cloud(rng):
    # 1,000 orientations spread up to 0.1 rad about a mean, in +/- pairs so that the
    # set's mean is exactly `truth` (a random set's own mean wanders ~2 mrad from it)
    truth = R.random(1, rng)[0]
    axes = rng.standard_normal((500, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rotvecs = axes * rng.uniform(0, 0.1, (500, 1))
    samples = R.multiply(R.from_rotvec(np.concatenate([rotvecs, -rotvecs])), truth)
    samples[::2] *= -1  # the sign of a quaternion must not matter
    assert R.angle_between(R.mean(samples), truth) < 1e-3
    # an Euler-angle average, as Himberg 2010 did, is biased by the spread
    euler = R.to_scipy(samples).as_euler("xyz").mean(axis=0)
    naive = R.from_scipy(Rotation.from_euler("xyz", euler))
    assert R.angle_between(naive, truth) > R.angle_between(R.mean(samples), truth)


def test_mean_agrees_with_scipy_mean(rng):
    truth = R.random(1, rng)[0]
    samples = R.multiply(R.from_rotvec(0.2 * rng.standard_normal((1000, 3))), truth)
    w = rng.uniform(0.1, 1.0, 1000)
    reference = R.from_scipy(R.to_scipy(samples).mean(weights=w))
    assert R.angle_between(R.mean(samples, weights=w), reference) < 1e-12


def test_mean_batched_and_weighted(rng):
    q = R.random((3, 5), rng)
    # a weight of zero removes a sample; axis selects what is averaged
    w = np.ones((3, 5))
    w[:, 1:] = 0.0
    np.testing.assert_allclose(R.mean(q, weights=w, axis=1), q[:, 0], atol=1e-12)
    assert R.mean(q, axis=0).shape == (5, 4)


def test_random_is_uniform(rng):
    q = R.random(200_000, rng)
    # uniform rotations: the rotated x axis is uniform on the sphere, mean ~ 0
    x = R.to_matrix(q)[:, :, 0]
    assert np.all(np.abs(x.mean(axis=0)) < 0.01)
    # rotation angle density is (1 - cos t)/pi: mean angle pi/2 + 2/pi
    assert abs(R.angle(q).mean() - (np.pi / 2 + 2 / np.pi)) < 0.01


def test_nearest_rotation(rng):
    T = R.to_matrix(R.random(100, rng))
    noisy = T + 1e-3 * rng.standard_normal(T.shape)
    P = R.nearest_rotation(noisy)
    np.testing.assert_allclose(P @ np.swapaxes(P, -1, -2), np.broadcast_to(np.eye(3), P.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(P), 1.0)
    assert np.all(R.angle_between_matrices(P, T) < 5e-3)
    # a reflection is turned into the nearest proper rotation
    assert np.linalg.det(R.nearest_rotation(np.diag([1.0, 1.0, -1.0]))) == pytest.approx(1.0)


quaternion_components = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda v: np.linalg.norm(v) > 1e-3
)


@settings(max_examples=300, deadline=None)
@given(quaternion_components, quaternion_components)
def test_property_round_trip_and_composition(a, b):
    p, q = R.canonical(a), R.canonical(b)
    np.testing.assert_allclose(R.from_matrix(R.to_matrix(q)), q, atol=1e-12)
    np.testing.assert_allclose(R.to_matrix(R.multiply(p, q)), R.to_matrix(p) @ R.to_matrix(q), atol=1e-12)
    assert abs(R.angle_between(p, q) - R.angle_between_matrices(R.to_matrix(p), R.to_matrix(q))) < 1e-7
