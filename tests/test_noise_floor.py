"""The single-frame noise floor (Cramér-Rao bound) against Monte Carlo solves of noisy signals."""

import numpy as np
import pytest

from ivc import dipole, rotations
from ivc.errors import InputError
from ivc.lut.fit_sources import SourceModel
from ivc.pose import solve_pose
from ivc.pose.solver import dipole_plus
from ivc.sim.noise_floor import finite_difference_jacobian, pose_noise_floor
from ivc.sim.scene import NoiseSpec
from ivc.sim.tracker import noise_sigma


@pytest.mark.parametrize("with_field", [False, True])
def test_bound_matches_the_spread_of_least_squares_solves(with_field):
    rng = np.random.default_rng(5)
    r = np.array([0.8, 0.2, -0.1])
    q = rotations.random(1, rng)[0]
    field = SourceModel(np.array([[1.0, 0.3, 0.0]]), 1e-3 * rng.standard_normal((1, 3, 3))) if with_field else None
    secondary = field.value_and_jacobian if field else None
    sigma = noise_sigma(NoiseSpec())
    position_floor, angle_floor = pose_noise_floor(r[None], q[None], sigma, secondary)
    T = rotations.to_matrix(q)
    M = dipole.field(r) + (field(r) if field else 0.0)
    trials = 2000
    S = T.T @ M + sigma * rng.standard_normal((trials, 3, 3))
    solution = solve_pose(S, dipole_plus(secondary), np.tile(r, (trials, 1)))
    assert solution.converged.all()
    position_rms = np.sqrt(np.mean(np.sum((solution.position - r) ** 2, axis=1)))
    dR = np.swapaxes(np.broadcast_to(T, solution.rotation.shape), -1, -2) @ solution.rotation
    angle_rms = np.sqrt(np.mean(rotations.angle_between(rotations.from_matrix(dR), rotations.IDENTITY) ** 2))
    assert position_rms == pytest.approx(position_floor[0], rel=0.08)
    assert angle_rms == pytest.approx(angle_floor[0], rel=0.08)


def test_floor_grows_with_range_and_fd_jacobian_is_exact_enough():
    q = rotations.IDENTITY[None].repeat(2, 0)
    near, far = pose_noise_floor(np.array([[0.5, 0, 0], [1.0, 0, 0]]), q, 1e-6)[0]
    assert far / near == pytest.approx(16, rel=0.05)  # r⁴ under absolute noise
    model = SourceModel(np.array([[1.2, 0.1, 0.0]]), np.full((1, 3, 3), 1e-3))
    points = np.array([[0.6, 0.1, 0.05]])
    G, dG = finite_difference_jacobian(model)(points)
    np.testing.assert_allclose(dG, model.value_and_jacobian(points)[1], rtol=1e-6, atol=1e-12)
    with pytest.raises(InputError):
        pose_noise_floor(points, q[:1], 0.0)
