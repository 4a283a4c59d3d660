import magpylib
import numpy as np
import pytest

from ivc import dipole
from ivc import rotations as R
from tests.helpers import random_positions


def reference_field(r):
    """Plain NumPy f_D, written independently of the compiled kernel."""
    r = np.asarray(r, float)
    rho = np.linalg.norm(r, axis=-1)[..., None, None]
    rhat = r / rho[..., 0]
    return (3 * rhat[..., :, None] * rhat[..., None, :] - np.eye(3)) / rho**3


def relative_error(A, B):
    """Per-sample ‖A − B‖_F / ‖B‖_F: entries that cancel to ~0 make elementwise rtol meaningless."""
    return np.linalg.norm(A - B, axis=(-2, -1)) / np.linalg.norm(B, axis=(-2, -1))


def test_field_identities(rng):
    r = random_positions(rng, 20_000)
    F = dipole.field(r)
    rho = np.linalg.norm(r, axis=1)
    rhat = r / rho[:, None]
    np.testing.assert_allclose(F, np.swapaxes(F, 1, 2), rtol=0, atol=0)
    scale = rho[:, None, None] ** -3
    assert np.all(np.abs(np.trace(F, axis1=1, axis2=2)) < 1e-13 * scale[:, 0, 0])
    np.testing.assert_array_equal(dipole.field(-r), F)
    F2 = (3 * rhat[:, :, None] * rhat[:, None, :] + np.eye(3)) / rho[:, None, None] ** 6
    assert np.all(relative_error(F @ F, F2) < 1e-13)
    np.testing.assert_allclose(np.sum(F**2, axis=(1, 2)), 6 / rho**6, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.det(F), 2 / rho**9, rtol=1e-12)
    assert np.all(relative_error(F, reference_field(r)) < 1e-13)


def test_field_matches_magpylib_up_to_its_constant(rng):
    r = random_positions(rng, 5000)
    F = dipole.field(r)
    for j, moment in enumerate(np.eye(3)):
        H = magpylib.core.dipole_Hfield(r, np.tile(moment, (len(r), 1)))
        # magpylib's H of moment m is f_D m / (4 pi)
        error = np.linalg.norm(4 * np.pi * H - F[:, :, j], axis=1) / np.linalg.norm(F[:, :, j], axis=1)
        assert error.max() < 1e-12


def test_field_batched_shapes():
    assert dipole.field(np.ones((2, 5, 3))).shape == (2, 5, 3, 3)
    assert dipole.field([0.0, 0.0, 1.0]).shape == (3, 3)
    with pytest.raises(ValueError, match="shape"):
        dipole.field(np.ones((4, 2)))


def test_jacobian_against_central_differences(rng):
    r = random_positions(rng, 2000, 0.05, 2.0)
    J = dipole.field_jacobian(r)
    rho = np.linalg.norm(r, axis=1)
    for k in range(3):
        h = (1e-5 * rho)[:, None] * np.eye(3)[k]
        numeric = (dipole.field(r + h) - dipole.field(r - h)) / (2 * h[:, k])[:, None, None]
        scale = np.abs(J).max(axis=(1, 2, 3))[:, None, None]
        assert np.all(np.abs(J[..., k] - numeric) <= 1e-6 * scale)


def test_signal_model_is_rotated_field(rng):
    r = random_positions(rng, 1000)
    T = R.to_matrix(R.random(1000, rng))
    G = 0.01 * rng.standard_normal((1000, 3, 3))
    S = dipole.signal(r, T, G)
    np.testing.assert_allclose(S, np.swapaxes(T, 1, 2) @ (reference_field(r) + G), rtol=1e-12, atol=1e-12)
    # broadcasting: one sensor orientation over many positions
    S1 = dipole.signal(r[:10], T[0])
    np.testing.assert_allclose(S1, T[0].T @ reference_field(r[:10]), rtol=1e-12)


def test_closed_form_pose_free_space_100k(rng):
    h = dipole.hemisphere_vector("+x")
    r = random_positions(rng, 100_000, 0.05, 2.0, hemisphere=h)
    q = R.random(100_000, rng)
    S = dipole.signal(r, R.to_matrix(q))
    r_est, T_est = dipole.closed_form_pose(S, "+x")
    assert np.abs(np.linalg.norm(r_est - r, axis=1)).max() < 1e-9
    assert R.angle_between_matrices(T_est, R.to_matrix(q)).max() < 1e-9
    assert R.angle_between(R.from_matrix(T_est), q).max() < 1e-9


@pytest.mark.parametrize("hemisphere", ["-x", "+y", "-y", "+z", "-z"])
def test_closed_form_pose_each_hemisphere(rng, hemisphere):
    h = dipole.hemisphere_vector(hemisphere)
    r = random_positions(rng, 2000, 0.05, 2.0, hemisphere=h)
    T = R.to_matrix(R.random(2000, rng))
    r_est, T_est = dipole.closed_form_pose(dipole.signal(r, T), hemisphere)
    assert np.abs(r_est - r).max() < 1e-9
    assert R.angle_between_matrices(T_est, T).max() < 1e-9


def test_other_hemisphere_returns_mirrored_position(rng):
    r = random_positions(rng, 500, 0.1, 1.0, hemisphere=np.array([-1.0, 0, 0]))
    T = R.to_matrix(R.random(500, rng))
    r_est, T_est = dipole.closed_form_pose(dipole.signal(r, T), "+x")
    np.testing.assert_allclose(r_est, -r, atol=1e-12)
    assert R.angle_between_matrices(T_est, T).max() < 1e-9


def test_closed_form_pose_is_least_squares_rotation_under_noise(rng):
    r = random_positions(rng, 300, 0.2, 1.0, hemisphere=np.array([1.0, 0, 0]))
    T = R.to_matrix(R.random(300, rng))
    S = dipole.signal(r, T)
    S_noisy = S + 0.02 * np.abs(S).mean() * rng.standard_normal(S.shape)
    r_est, T_est = dipole.closed_form_pose(S_noisy, "+x")
    assert np.allclose(np.linalg.det(T_est), 1.0)
    F = dipole.field(r_est)
    cost = np.sum((S_noisy - np.swapaxes(T_est, 1, 2) @ F) ** 2, axis=(1, 2))
    # no nearby rotation fits better: perturb by small rotations
    for _ in range(5):
        d = R.to_matrix(R.from_rotvec(1e-3 * rng.standard_normal((300, 3))))
        other = np.sum((S_noisy - np.swapaxes(d @ T_est, 1, 2) @ F) ** 2, axis=(1, 2))
        assert np.all(other >= cost - 1e-12 * cost)


def test_closed_form_pose_handles_reflected_input():
    # det(K) < 0 takes the SVD branch: the result is still a proper rotation
    S = dipole.signal([0.5, 0.1, 0.0], np.eye(3)) @ np.diag([1.0, 1.0, -1.0])
    _, T = dipole.closed_form_pose(S, "+x")
    assert np.linalg.det(T) == pytest.approx(1.0)


def test_closed_form_pose_non_finite_gives_nan():
    S = np.full((2, 3, 3), np.nan)
    S[1] = dipole.signal([0.5, 0.0, 0.0], np.eye(3))
    r, T = dipole.closed_form_pose(S)
    assert np.all(np.isnan(r[0])) and np.all(np.isnan(T[0]))
    np.testing.assert_allclose(r[1], [0.5, 0.0, 0.0], atol=1e-12)


def test_signal_from_pose_round_trip(rng):
    r = random_positions(rng, 1000, 0.05, 2.0, hemisphere=np.array([0, 0, 1.0]))
    q = R.random(1000, rng)
    r_est, T_est = dipole.closed_form_pose(dipole.signal_from_pose(r, q), "+z")
    np.testing.assert_allclose(r_est, r, atol=1e-12)
    assert R.angle_between(R.from_matrix(T_est), q).max() < 1e-9


def test_bad_hemisphere():
    with pytest.raises(ValueError, match="hemisphere"):
        dipole.hemisphere_vector("x")
