import numpy as np
import pytest

from ivc import dipole
from ivc import rotations as R
from ivc.fixtures import CUBE_BITS
from ivc.fixtures.interpolant import TrilinearField
from ivc.pose import dipole_plus, solve_pose


def cube_vertices(rng):
    return np.array([0.475, -0.025, -0.025]) + 0.0508 * CUBE_BITS + 0.0015 * rng.standard_normal((8, 3))


def points_in_cube(field, n, rng):
    from ivc.fixtures.interpolant import trilinear_weights

    uvw = rng.uniform(0.02, 0.98, (n, 3))
    return np.einsum("fn,ni->fi", trilinear_weights(uvw)[0], field.vertices)


@pytest.mark.parametrize("method", ["joint", "two-stage"])
def test_free_space_recovers_exact_pose(rng, method):
    field = TrilinearField(cube_vertices(rng), np.zeros((8, 3, 3)))
    r = points_in_cube(field, 2000, rng)
    T = R.to_matrix(R.random(2000, rng))
    S = dipole.signal(r, T)
    solution = solve_pose(S, dipole_plus(field.value_and_jacobian), r + 0.005 * rng.standard_normal(r.shape),
                          method=method)
    assert solution.converged.all()
    assert np.abs(solution.position - r).max() < 1e-9
    assert R.angle_between_matrices(solution.rotation, T).max() < 1e-9
    assert solution.residual.max() < 1e-9


@pytest.mark.parametrize("method", ["joint", "two-stage"])
def test_exactly_trilinear_distortion_is_recovered(rng, method):
    # a secondary field that is exactly trilinear in the cube, known at the (actual) vertices: a 10 %
    # offset of the primary field (as in the default scene) varying by 2 % across the cube
    vertices = cube_vertices(rng)
    scale = np.abs(dipole.field(vertices.mean(axis=0))).max()
    fields = scale * (0.1 * rng.standard_normal((3, 3)) + 0.02 * rng.standard_normal((8, 3, 3)))
    field = TrilinearField(vertices, fields)
    r = points_in_cube(field, 2000, rng)
    T = R.to_matrix(R.random(2000, rng))
    S = dipole.signal(r, T, field(r))
    dipole_solution, _ = dipole.closed_form_pose(S, "+x")
    assert np.median(np.linalg.norm(dipole_solution - r, axis=1)) > 5e-3  # the distortion matters
    seed = np.tile(vertices.mean(axis=0), (len(r), 1))  # sensor 0 is inside the cube: start at its centre
    solution = solve_pose(S, dipole_plus(field.value_and_jacobian), seed, method=method)
    assert solution.converged.all()
    assert np.abs(solution.position - r).max() < 1e-9
    assert R.angle_between_matrices(solution.rotation, T).max() < 1e-9


def test_non_finite_frames_are_flagged(rng):
    field = TrilinearField(cube_vertices(rng), np.zeros((8, 3, 3)))
    r = points_in_cube(field, 5, rng)
    S = dipole.signal(r, np.eye(3))
    S[2] = np.nan
    solution = solve_pose(S, dipole_plus(field.value_and_jacobian), r)
    assert not solution.converged[2] and np.all(np.isnan(solution.position[2]))
    assert solution.converged[[0, 1, 3, 4]].all()


def test_residual_measures_model_mismatch(rng):
    field = TrilinearField(cube_vertices(rng), np.zeros((8, 3, 3)))
    r = points_in_cube(field, 300, rng)
    S = dipole.signal(r, R.to_matrix(R.random(300, rng)))
    noisy = S + 1e-3 * np.sqrt(np.mean(S**2)) * rng.standard_normal(S.shape)
    solution = solve_pose(noisy, dipole_plus(field.value_and_jacobian), r)
    assert solution.converged.all()
    # rms(Λ)/rms(S) is the unexplained noise: below the injected 1e-3, of its order
    assert 3e-4 < np.median(solution.residual) < 1.5e-3


def test_unknown_method():
    with pytest.raises(ValueError, match="method"):
        solve_pose(np.eye(3)[None], dipole_plus(None), np.ones((1, 3)), method="newton")


def test_procrustes_cost_is_the_cost_at_the_procrustes_rotation(rng):
    from ivc.pose.solver import procrustes, procrustes_cost

    M, S = rng.standard_normal((500, 3, 3)), rng.standard_normal((500, 3, 3))
    M[:3], S[:3] = np.eye(3), R.to_matrix(R.random(3, rng))  # equal singular values; a turned identity
    M[3] = np.diag([1.0, 1.0, 0.0])  # rank two
    T = procrustes(M, S)
    reference = np.sum((S - np.swapaxes(T, -1, -2) @ M) ** 2, axis=(1, 2))
    assert np.any(np.linalg.det(M @ np.swapaxes(S, -1, -2)) < 0)  # the reflection case is among them
    np.testing.assert_allclose(procrustes_cost(M, S), reference, atol=1e-7 * np.max(reference))
    np.testing.assert_allclose(procrustes_cost(M[:3], S[:3]), 0.0, atol=1e-12)
